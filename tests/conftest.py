"""Shared fixtures: paths to the team's real data (skipped when absent) and small generated scans."""
from __future__ import annotations

from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
LIDAR = SHARED / "lidar"


def shared_file(relative: str) -> Path:
    """A file under ../shared/data/lidar, or skip the test with the reason."""
    path = LIDAR / relative
    if not path.exists():
        pytest.skip(f"shared data not present: {path} (tests on generated data still run)")
    return path


def simulated_street(tmp_path_factory: pytest.TempPathFactory, folder: str, n_points: int, seed: int) -> Path:
    """A simulated street scan (LAZ) of `n_points` from the project's own simulator, in a fresh folder."""
    from pipeline.simulate import write_street_scan

    path = tmp_path_factory.mktemp(folder) / "street.laz"
    write_street_scan(path, n_points=n_points, seed=seed)
    return path


@pytest.fixture(scope="session")
def street_scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 60k-point simulated street scan, made once per session."""
    return simulated_street(tmp_path_factory, "street", 60_000, 3)
