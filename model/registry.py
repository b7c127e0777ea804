"""Method names to simplifiers with their default parameters: the one switch behind `--method`, a config
file's `[method.<name>]` table and the API's `method_parameters`."""
from __future__ import annotations

from dataclasses import fields, replace
from pathlib import Path
from typing import Any

from model.methods import Fill, Fps, Learned, MeasuredDetail, Method, Paper, Random, TopCurvature, Voxel

REGISTERED: dict[str, Method] = {
    "fps": Fps(),
    "voxel": Voxel(),
    "random": Random(),
    "tcp": TopCurvature(),
    "stratified": Fill(),
    "stratified-detail": MeasuredDetail(),
    "learned": Learned(),
    "paper": Paper(),
    "paper-refined": Paper(refine=True),
}
METHODS = tuple(REGISTERED)
PARAMETER_KINDS = {bool: "true or false", int: "a whole number", float: "a number", Path: "a file path"}


def get_simplifier(method: str, **parameters: Any) -> Method:
    """The simplifier registered under `method`, with `parameters` replacing its defaults (ValueError names
    the known methods, an unknown parameter or a value of the wrong kind)."""
    try:
        default = REGISTERED[method]
    except KeyError:
        raise ValueError(f"unknown method {method!r}; known: {', '.join(METHODS)}") from None
    known = {f.name: Path if isinstance(getattr(default, f.name), Path) else type(getattr(default, f.name))
             for f in fields(default)}
    unknown = sorted(set(parameters) - set(known))
    if unknown:
        takes = ", ".join(known) or "no parameters"
        raise ValueError(f"method {method!r} has no parameter {', '.join(map(repr, unknown))} (it takes: {takes})")
    return replace(default, **{name: typed(name, value, known[name]) for name, value in parameters.items()})


def typed(name: str, value: Any, kind: type) -> Any:
    """`value` as the parameter's kind (an int where a float goes, a string where a path goes)."""
    if kind is Path and isinstance(value, (str, Path)):
        return Path(value)
    if kind is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, kind) and (kind is bool or not isinstance(value, bool)):
        return value
    raise ValueError(f"parameter {name!r} must be {PARAMETER_KINDS.get(kind, kind.__name__)}, got {value!r}")


def method_name(method: Method) -> str:
    """The name a simplifier object runs under: the first registered name of its class (its parameters
    then say how it differs from that name's defaults)."""
    for name, default in REGISTERED.items():
        if type(default) is type(method):
            return name
    raise ValueError(f"{type(method).__name__} is not a registered method (known: {', '.join(METHODS)})")


def changed_parameters(name: str, method: Method) -> dict[str, Any]:
    """The parameters of `method` that differ from those registered under `name`, JSON-able."""
    defaults = REGISTERED[name].parameters()
    return {key: value for key, value in method.parameters().items() if defaults[key] != value}
