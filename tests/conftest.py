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


@pytest.fixture(scope="session")
def street_scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 60k-point simulated street scan (LAZ), made once per session by the project's own simulator."""
    from pipeline.simulate import write_street_scan

    path = tmp_path_factory.mktemp("street") / "street.laz"
    write_street_scan(path, n_points=60_000, seed=3)
    return path
