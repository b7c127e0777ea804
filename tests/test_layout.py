"""The code's layout: imports point down the data flow (model < tiling < pipeline's foundation < io <
engine and simulate < apps < the API), tiling takes only model.rules from model, no module imports itself
back through others (not even under TYPE_CHECKING or inside a function), and mesh mode runs without Dask."""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("model", "tiling", "pipeline")
FOUNDATION = ("pipeline.errors", "pipeline.progress", "pipeline.config", "pipeline.version")
LAYERS = {  # a module may import its own layer's modules and those of lower layers
    "model": 0, "tiling": 1, "foundation": 2, "pipeline.io": 3, "pipeline.engine": 4, "pipeline.simulate": 4,
    "pipeline.apps": 5, "pipeline": 6,
}
APART = {("pipeline.engine", "pipeline.simulate"), ("pipeline.simulate", "pipeline.engine")}  # same layer, unrelated


def module_name(path: Path) -> str:
    """`pipeline/io/scan.py` -> `pipeline.io.scan`; a package's `__init__.py` is the package."""
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def project_modules() -> dict[str, Path]:
    """Every module of the project's packages, by dotted name."""
    return {module_name(path): path for package in PACKAGES for path in sorted((REPO / package).rglob("*.py"))}


def imported(path: Path, modules: dict[str, Path]) -> set[str]:
    """The project modules `path` imports anywhere in its text (top level, functions, TYPE_CHECKING blocks);
    `from package import name` counts as the module `package.name` when that is a module, else `package`."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [f"{node.module}.{alias.name}" if f"{node.module}.{alias.name}" in modules else node.module
                     for alias in node.names]
        else:
            continue
        found.update(name for name in names if name in modules)
    return found


def layer(module: str) -> str:
    """The layer a module belongs to (the longest LAYERS key that is a prefix of it)."""
    if module in FOUNDATION:
        return "foundation"
    return max((key for key in LAYERS if module == key or module.startswith(key + ".")), key=len)


def test_imports_point_down_the_data_flow():
    modules = project_modules()
    upward = []
    for name, path in modules.items():
        for target in imported(path, modules):
            source_layer, target_layer = layer(name), layer(target)
            if LAYERS[target_layer] > LAYERS[source_layer] or (source_layer, target_layer) in APART:
                upward.append(f"{name} ({source_layer}) imports {target} ({target_layer})")
    assert not upward, "\n".join(upward)


def test_tiling_takes_only_the_shared_rules_from_model():
    """tiling receives simplifiers as callables; of model it shares only the rules (model.rules)."""
    modules = project_modules()
    reached = {(name, target) for name, path in modules.items() if layer(name) == "tiling"
               for target in imported(path, modules) if layer(target) == "model" and target != "model.rules"}
    assert not reached, sorted(reached)


def test_no_import_cycle():
    modules = project_modules()
    graph = {name: imported(path, modules) - {name} for name, path in modules.items()}
    state: dict[str, int] = {}  # 1: on the current path, 2: finished
    cycles = []

    def visit(name: str, path: list[str]) -> None:
        state[name] = 1
        for target in sorted(graph[name]):
            if state.get(target) == 1:
                cycles.append(" -> ".join(path[path.index(target):] + [target]))
            elif target not in state:
                visit(target, path + [target])
        state[name] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name, [name])
    # a package's __init__ that imports its own modules lazily (pipeline's API) is no cycle of modules
    cycles = [cycle for cycle in cycles if not cycle.startswith("pipeline -> ")]
    assert not cycles, "\n".join(cycles)


def test_the_checks_see_an_upward_import():
    """The walker finds imports inside functions and TYPE_CHECKING blocks (else both tests above could not fail)."""
    modules = project_modules()
    assert "pipeline.engine.runner" in imported(REPO / "pipeline" / "__init__.py", modules)  # inside a function
    assert "pipeline.engine.tasks" in imported(REPO / "pipeline" / "engine" / "worker_setup.py", modules)
    assert layer("pipeline.apps.visual.view3d") == "pipeline.apps" and layer("pipeline.config") == "foundation"


@pytest.mark.parametrize("module", ["pipeline.apps.mesh_mode", "pipeline.apps.cli", "pipeline"])
def test_no_dask_until_a_cluster_is_needed(module):
    code = f"import sys, {module}; print(sorted({{m.split('.')[0] for m in sys.modules}} & {{'dask', 'distributed'}}))"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True)
    assert result.stdout.strip() == "[]"
