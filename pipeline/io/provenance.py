"""What an output says about how it was made: `lidar-simplify <version>` and the date in the LAS header,
and a JSON record (method, ratio, model weights, settings, sources) in a VLR and in zarr attributes."""
from __future__ import annotations

import copy
import datetime
import hashlib
import json
from functools import lru_cache
from pathlib import Path
from typing import Any

import laspy

from pipeline.io.output_meta import OutputMeta
from pipeline.version import __version__

SOFTWARE = "lidar-simplify"
PROVENANCE_USER_ID = "lidar-simplify"  # 16 bytes at most in a VLR
PROVENANCE_RECORD_ID = 1


def software_name() -> str:
    """`lidar-simplify <version>`, what the header's generating-software field holds (32 bytes at most)."""
    return f"{SOFTWARE} {__version__}"[:32]


def weights_digest(path: Path | None) -> str | None:
    """`<file name>:<the first 16 hex digits of its SHA-256>` of a method's trained weights (None: it has none);
    read again once the file changes (its size or modification time), as weights retrained in place do."""
    if path is None:
        return None
    stat = path.stat()
    return file_digest(path, stat.st_size, stat.st_mtime_ns)


@lru_cache(maxsize=None)
def file_digest(path: Path, size: int, mtime_ns: int) -> str:
    """weights_digest of the file at `path` as it is at that size and time (each version read once)."""
    return f"{path.name}:{hashlib.sha256(path.read_bytes()).hexdigest()[:16]}"


def run_record(meta: OutputMeta) -> dict[str, Any]:
    """The JSON-able provenance of one output: software, date, method, ratio, model weights, settings, sources."""
    return {"software": SOFTWARE, "version": __version__, "created": datetime.date.today().isoformat(),
            "method": meta.method, "ratio": meta.ratio, "model_weights": weights_digest(meta.trained_weights),
            "settings": meta.settings, "sources": meta.sources}


def provenance_vlr(meta: OutputMeta) -> laspy.VLR:
    """A VLR whose record data is the run record as UTF-8 JSON."""
    payload = json.dumps(run_record(meta), sort_keys=True).encode()
    return laspy.VLR(PROVENANCE_USER_ID, PROVENANCE_RECORD_ID, "simplification settings (JSON)", payload)


def read_provenance(header: laspy.LasHeader) -> dict[str, Any] | None:
    """The run record a lidar-simplify output carries, or None for any other file."""
    for vlr in header.vlrs:
        if vlr.user_id == PROVENANCE_USER_ID and vlr.record_id == PROVENANCE_RECORD_ID:
            return json.loads(bytes(vlr.record_data).rstrip(b"\0"))
    return None


def stamped_header(header: laspy.LasHeader, meta: OutputMeta) -> laspy.LasHeader:
    """A copy of the input's header that names this software and today, and carries the run record
    (replacing the record of an earlier simplification of the same points)."""
    stamped = copy.deepcopy(header)
    stamped.generating_software = software_name()
    stamped.creation_date = datetime.date.today()
    stamped.vlrs[:] = [v for v in stamped.vlrs if v.user_id != PROVENANCE_USER_ID]  # in place: a new list makes
    stamped.vlrs.append(provenance_vlr(meta))  # laspy regenerate the extra-bytes VLRs (two of them became one)
    return stamped
