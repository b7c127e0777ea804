"""Checks before any worker starts: one CRS in metres, every file's first points decode, and room on disk
for the work folder and the outputs."""
from __future__ import annotations

import shutil
from pathlib import Path

from pipeline.errors import PipelineError
from pipeline.io.crs import crs_label, degrees_reason, same_crs
from pipeline.io.scan import Scan
from pipeline.progress import Progress
from tiling.store import TAIL

PROBE_POINTS = 1_000      # points of each file decoded before any worker starts
SURVEY_BYTES = 6          # per scan point, a stratified method's survey: a float32 loss per core+halo point
RESULT_XYZ_BYTES = 24     # per kept point, beside its record in the tile results: xyz as 3 float64
SCRATCH_SLACK = 1.10      # piece records, the store's chunk files and the file system's whole blocks for the many
                          # small results: the 100M-point runs used 4 % over the sum, a 1M street's learned 8 % (55.7
                          # MiB on a tmpfs where 1.05 estimated 54.2 and let the run start, to fail in its simplify)
REPROJECT_ADVICE = ("tile size, overlap and neighbourhoods are in metres: reproject to a projected CRS first "
                    "(e.g. pdal translate IN OUT reprojection --filters.reprojection.out_srs=EPSG:<UTM zone>) "
                    "or pass --allow-geographic to run in degrees anyway")


def check_run(scan: Scan, allow_degrees: bool, scratch: Path, kept: int = 0, surveyed: bool = False,
              progress: Progress = Progress(), held: int = 0) -> None:
    """Before any worker starts: every input in one CRS, none in degrees (unless allowed), the first points of every file decode,
    and the scratch folder has room for the work folder: the bucketed scan (every record, uncompressed,
    with its index), the per-point survey of a stratified method and the tile results (`kept` points,
    seam reserve included: each one's record and xyz)
    (100M-point street, bench/scale.py, when results held an 8-byte row: 47.4 bytes per point for fps,
    53.5 for learned, record 34), less the `held` bytes an earlier attempt's work folder already holds (a run
    resumed after its scratch disk filled was refused, where it had room to finish)."""
    first = scan.sources[0]
    for source in scan.sources[1:]:
        if not same_crs(first.header, source.header):
            raise PipelineError(f"{source.path}: its CRS, {crs_label(source.header)}, differs from {first.path}'s, "
                                f"{crs_label(first.header)}: reproject the inputs to one CRS before merging them")
    for source in scan.sources:
        reason = degrees_reason(source.header)
        if reason and not allow_degrees:
            raise PipelineError(f"{source.path}: {reason}; {REPROJECT_ADVICE}")
    with progress.phase("validate", len(scan.sources), unit="file") as phase:
        scan.probe(PROBE_POINTS, on_file=phase.update)
    if not scratch.is_dir():
        raise PipelineError(f"{scratch}: scratch folder does not exist")
    need = SCRATCH_SLACK * (scan.point_count * (scan.dtype.itemsize + TAIL + (SURVEY_BYTES if surveyed else 0))
                            + kept * (scan.dtype.itemsize + RESULT_XYZ_BYTES)) - held
    check_room(scratch, need, "the scratch tiles", "pass --scratch a folder on a larger disk")


def check_room(folder: Path, need: float, what: str, advice: str) -> None:
    """Refuse, before any work, a folder whose disk has less than `need` bytes free for `what`."""
    free = shutil.disk_usage(folder).free
    if free < need:
        raise PipelineError(f"{folder}: not enough space left for {what} ({free / 2**20:.1f} MiB free, "
                            f"about {need / 2**20:.1f} MiB needed): {advice}")
