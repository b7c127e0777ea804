"""Run presets shipped as TOML files beside this module (`default`, `toronto3d`, `airborne`)."""
from importlib import resources
from pathlib import Path


def preset_names() -> list[str]:
    """Names of the shipped presets, for `--config NAME` and the CLI help."""
    return sorted(p.name.removesuffix(".toml") for p in resources.files(__name__).iterdir() if p.name.endswith(".toml"))


def preset_path(name: str) -> Path | None:
    """The TOML file of a shipped preset, or None when `name` is not one."""
    candidate = resources.files(__name__) / f"{name}.toml"
    return Path(str(candidate)) if candidate.is_file() else None
