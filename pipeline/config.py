"""Run settings: shipped defaults, then a preset or TOML file, then explicit flags (flags win)."""
from __future__ import annotations

import math
import numbers
import re
import tomllib
from dataclasses import dataclass, fields, replace
from functools import cached_property
from pathlib import Path
from typing import Any, Sequence

import configs
from model.methods import Method
from model.registry import METHODS, changed_parameters, get_simplifier, method_name
from pipeline.errors import PipelineError

_SIZE = re.compile(r"^\s*([0-9]*\.?[0-9]+)\s*([KMGT]i?B|B)?\s*$", re.IGNORECASE)
MIN_MEMORY_LIMIT = 256 * 2**20  # a worker process takes ~90 MiB at rest (270 with torch): below, Dask restarts it forever
_UNITS = {"b": 1, "kb": 10**3, "mb": 10**6, "gb": 10**9, "tb": 10**12,
          "kib": 2**10, "mib": 2**20, "gib": 2**30, "tib": 2**40}


@dataclass(frozen=True)
class RunConfig:
    """Everything one `pipeline run` needs besides its inputs and output path."""

    ratio: float = 0.1
    method: str = "learned"
    tile_size: float = 50.0
    overlap: float = 2.0
    max_tile_points: int = 200_000
    merge_tile_points: int = 50_000  # sparse nominal tiles merge (2x2, 4x4 of them) while within this many points
                                     # (at most max_tile_points: see merge_limit); 0: off
    seam_tolerance: float = 0.01
    workers: int = 2
    memory_limit: str = "2GB"
    cache_memory: str = "32MB"  # each process's cache of stored row chunks (tiles re-read their neighbours')
    chunk_points: int = 500_000  # points per bucketing piece: one piece per worker in memory at a time
    in_process_points: int = 3_000_000  # scans up to this size run on threads of this process: see README
    seed: int = 0
    allow_geographic: bool = False  # run on coordinates in degrees (tile sizes and distances become degrees)
    levels: tuple[float, ...] = ()  # nested outputs at these ratios from one simplification (the first is `ratio`)
    keep_classes: tuple[int, ...] = ()  # classification codes kept whole; the ratio applies to the rest
    thin_classes: tuple[int, ...] = ()  # the only codes thinned; every other point is kept whole
    method_parameters: tuple[tuple[str, Any], ...] = ()  # (name, value) replacing the method's defaults

    @cached_property
    def simplifier(self) -> Method:
        """The method with its parameters, as the run's tiles call it (made once per settings object)."""
        return get_simplifier(self.method, **dict(self.method_parameters))

    @property
    def merge_limit(self) -> int:
        """The points a merged tile may hold: --merge-tile-points, but never more than --max-tile-points (so a
        smaller --max-tile-points, given for memory, bounds merged tiles too, without naming both), and 0 (no
        merging) for a method whose picks depend on a tile's extent (the paper's network)."""
        if self.simplifier.sees_tile_extent:
            return 0
        return min(int(self.merge_tile_points), int(self.max_tile_points))

    def in_unit(self, metres_per_unit: float) -> "RunConfig":
        """The same settings with the lengths (tile size, overlap, seam tolerance: metres) in a scan unit."""
        return replace(self, tile_size=self.tile_size / metres_per_unit, overlap=self.overlap / metres_per_unit,
                       seam_tolerance=self.seam_tolerance / metres_per_unit)

    def validated(self) -> "RunConfig":
        """Return self after checking every value, raising PipelineError naming the bad one."""
        if not (isinstance(self.ratio, (int, float)) and math.isfinite(self.ratio) and 0 < self.ratio <= 1):
            raise PipelineError(f"--ratio must be in (0, 1], got {self.ratio!r}")
        if self.method not in METHODS:
            raise PipelineError(f"--method must be one of {', '.join(METHODS)}, got {self.method!r}")
        try:
            self.simplifier
        except ValueError as exc:
            raise PipelineError(f"--method {self.method}: {exc}") from None
        for name in ("tile_size", "overlap", "seam_tolerance"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0) or (name == "tile_size" and value <= 0):
                least = "a positive number of" if name == "tile_size" else "0 or more"
                raise PipelineError(f"--{name.replace('_', '-')} must be {least} metres, got {value!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, numbers.Integral) or self.seed < 0:
            raise PipelineError(f"--seed must be a whole number, 0 or more, got {self.seed!r}")
        if int(self.in_process_points) < 0:
            raise PipelineError(f"in-process-points must be 0 (never) or more, got {self.in_process_points!r}")
        for name in ("max_tile_points", "workers", "chunk_points"):
            if int(getattr(self, name)) < 1:
                raise PipelineError(f"{name.replace('_', '-')} must be at least 1, got {getattr(self, name)!r}")
        if int(self.merge_tile_points) < 0:
            raise PipelineError(f"--merge-tile-points must be 0 (off) or more, got {self.merge_tile_points!r}")
        if parse_size(self.memory_limit, "--memory-limit") < MIN_MEMORY_LIMIT:
            raise PipelineError(f"--memory-limit {self.memory_limit} is below the {MIN_MEMORY_LIMIT // 2**20} MiB a "
                                "worker needs (one takes about 100 MB at rest, its tile the rest): give it 256MiB "
                                "or more, 2GB for the default method")
        check_levels(self.levels, self.ratio)
        check_classes(self.keep_classes, self.thin_classes)
        if parse_size(self.cache_memory, "cache-memory") >= parse_size(self.memory_limit, "--memory-limit"):
            raise PipelineError(f"cache-memory must be below --memory-limit, got {self.cache_memory!r} "
                                f"with {self.memory_limit!r}")
        return self


def check_levels(levels: tuple[float, ...], ratio: float) -> None:
    """Levels are ratios in (0, 1], strictly decreasing, the first being the run's ratio."""
    if not levels:
        return
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and 0 < v <= 1
               for v in levels):
        raise PipelineError(f"--levels must be ratios in (0, 1], got {','.join(map(str, levels))}")
    if any(later >= earlier for earlier, later in zip(levels, levels[1:])):
        raise PipelineError(f"--levels must decrease (each level a subset of the one before), got "
                            f"{','.join(map(str, levels))}")
    if levels[0] != ratio:
        raise PipelineError(f"--ratio {ratio} disagrees with --levels {','.join(map(str, levels))}, whose first "
                            "level is the ratio: give one of them")


def check_classes(keep: tuple[int, ...], thin: tuple[int, ...]) -> None:
    """Class codes are whole numbers 0-255, and a run either keeps some classes whole or thins only some."""
    for option, codes in (("--keep-class", keep), ("--thin-class", thin)):
        if not all(isinstance(c, int) and not isinstance(c, bool) and 0 <= c <= 255 for c in codes):
            raise PipelineError(f"{option} takes LAS classification codes 0-255, got {','.join(map(str, codes))}")
    if keep and thin:
        raise PipelineError("give --keep-class or --thin-class, not both (one names what the other leaves)")


def parse_list(text: str | None, option: str, kind: type) -> tuple | None:
    """'6,14,15' as a tuple of `kind` (None stays None: the option was not given); one line if malformed."""
    if text is None:
        return None
    try:
        return tuple(kind(part) for part in text.split(",") if part.strip())
    except ValueError:
        raise PipelineError(f"{option} takes comma-separated {'whole numbers' if kind is int else 'numbers'}, "
                            f"got {text!r}") from None


def parse_parameters(texts: Sequence[str]) -> dict[str, Any]:
    """`--param NAME=VALUE` flags as a dict, each value read as TOML (0.05, true, "a b") or else kept as text
    (a path); one line if one has no `=`."""
    parameters = {}
    for text in texts:
        name, equals, value = text.partition("=")
        if not equals or not name.strip():
            raise PipelineError(f"--param takes NAME=VALUE, got {text!r}")
        try:
            parameters[name.strip()] = tomllib.loads(f"value = {value.strip()}")["value"]
        except tomllib.TOMLDecodeError:
            parameters[name.strip()] = value.strip()
    return parameters


def parse_size(text: str, option: str = "--memory-limit") -> int:
    """Bytes in a size such as '2GB', '512MiB' or '1500000000' (what Dask's memory_limit accepts)."""
    match = _SIZE.match(str(text))
    if not match:
        raise PipelineError(f"{option} must look like 2GB or 512MiB, got {text!r}")
    return int(float(match.group(1)) * _UNITS[(match.group(2) or "b").lower()])


def load_settings(config: str | None) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    """The [run] table of a preset name (`default`, `toronto3d`, `airborne`) or a TOML file path, and its
    [method.<name>] tables: each method's parameters, used when the run uses that method."""
    if config is None:
        config = "default"
    path = configs.preset_path(config) or Path(config)
    if not path.is_file():
        raise PipelineError(f"{config}: no such config file or preset (presets: {', '.join(configs.preset_names())})")
    try:
        document = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise PipelineError(f"{path}: not a valid TOML config ({exc})") from None
    stray = sorted(set(document) - {"run", "method"})
    if stray:  # read as nothing, a setting above [run] would leave the run on its default without a word
        raise PipelineError(f"{path}: {stray[0]!r} is outside [run]: settings go under [run], a method's parameters "
                            "under [method.<name>]")
    table, methods = document.get("run", {}), document.get("method", {})
    if not isinstance(table, dict):
        raise PipelineError(f"{path}: [run] must be a table of settings, got {type(table).__name__} {table!r}")
    if not isinstance(methods, dict) or not all(isinstance(v, dict) for v in methods.values()):
        raise PipelineError(f"{path}: [method] must hold one table per method, e.g. [method.voxel] slack = 0.05")
    unknown = sorted(set(methods) - set(METHODS))
    if unknown:
        raise PipelineError(f"{path}: [method.{unknown[0]}]: unknown method (known: {', '.join(METHODS)})")
    for name, parameters in methods.items():  # every table, the run's method or not: a typo fails here
        try:
            get_simplifier(name, **parameters)
        except ValueError as exc:
            raise PipelineError(f"{path}: [method.{name}]: {exc}") from None
    return checked_settings(table, f"{path}: [run]"), methods


SETTING_TYPES = {f.name: f.type for f in fields(RunConfig)  # "float", "int", "str", "bool" (postponed annotations)
                 if f.name != "method_parameters"}  # a file gives those in [method.<name>] tables
SIZE_SETTINGS = ("memory_limit", "cache_memory")  # "2GB" or a number of bytes
TYPE_WORDS = {"float": "a number", "int": "a whole number", "str": "a string", "bool": "true or false",
              "tuple[float, ...]": "a list of numbers", "tuple[int, ...]": "a list of whole numbers"}


def checked_settings(settings: dict[str, Any], where: str) -> dict[str, Any]:
    """Settings from a file, each a known name with a value of its type (an int where a float goes is
    fine, a bool is no number); else one line naming `where` (file and table) and the key."""
    unknown = sorted(set(settings) - set(SETTING_TYPES))
    if unknown:
        raise PipelineError(f"{where}: unknown setting(s) {', '.join(unknown)} (known: {', '.join(SETTING_TYPES)})")
    for key, value in settings.items():
        kind = SETTING_TYPES[key]
        ok = {"float": isinstance(value, (int, float)) and not isinstance(value, bool),
              "int": isinstance(value, int) and not isinstance(value, bool),
              "str": isinstance(value, str) or (key in SIZE_SETTINGS and isinstance(value, int)
                                                and not isinstance(value, bool)),
              "bool": isinstance(value, bool),
              "tuple[float, ...]": isinstance(value, list) and all(isinstance(v, (int, float))
                                                                   and not isinstance(v, bool) for v in value),
              "tuple[int, ...]": isinstance(value, list) and all(isinstance(v, int)
                                                                 and not isinstance(v, bool) for v in value)}[kind]
        if not ok:
            raise PipelineError(f"{where}: {key} must be {TYPE_WORDS[kind]}, got {value!r}")
    return settings


def plain_numbers(value: Any) -> Any:
    """A numpy scalar or array (np.float32(0.1), an array of levels) as Python numbers, as the user wrote them
    (a float32 by its shortest decimal, 0.1, not 0.10000000149); anything else unchanged. The checks and the
    count round(ratio * N) then treat it as they treat Python's own."""
    dtype = getattr(value, "dtype", None)
    if dtype is None or isinstance(value, (str, bytes)):
        return value
    if getattr(value, "ndim", 0):
        return tuple(plain_numbers(each) for each in value)
    return float(str(value)) if dtype.kind == "f" and dtype.itemsize < 8 else value.item()


def build_config(config: str | None = None, *, method: str | Method | None = None,
                 method_parameters: dict[str, Any] | None = None, **overrides: Any) -> RunConfig:
    """Defaults, then the preset or file, then the non-None overrides; validated. `method` is a name or a
    simplifier object (model.methods: its parameters are kept); the method's parameters are its
    defaults, then the file's [method.<name>] table, then the object's, then `method_parameters`."""
    base = RunConfig()
    settings, method_tables = load_settings(config)
    given = {k: plain_numbers(v) for k, v in overrides.items() if v is not None}
    checked_settings({k: list(v) if isinstance(v, tuple) else v for k, v in given.items()}, "keyword argument")
    if method_parameters is not None and not isinstance(method_parameters, dict):
        raise PipelineError(f"method_parameters must be a dict of name: value, got {method_parameters!r}")
    settings.update(given)
    settings = {k: tuple(v) if isinstance(v, list) else v for k, v in settings.items()}
    changed: dict[str, Any] = {}
    if isinstance(method, Method):
        settings["method"] = method_name(method)
        changed = changed_parameters(settings["method"], method)
    elif method is not None:
        settings["method"] = method
    name = settings.get("method", base.method)
    parameters = {**method_tables.get(name, {}), **changed, **(method_parameters or {})}
    settings["method_parameters"] = tuple(sorted(parameters.items()))
    if settings.get("levels") and "ratio" not in settings:  # the first level is the ratio the run simplifies to
        settings["ratio"] = settings["levels"][0]
    try:
        return replace(base, **settings).validated()
    except TypeError as exc:
        raise PipelineError(f"bad setting: {exc}") from None
