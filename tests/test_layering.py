"""The import graph: core/ is the engine (no ROS, nothing from the layers above it), its stages import
only from the stages before them, and no module-level import cycles anywhere in the package."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("monovoc_ros", "msg_adapters")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, *, top_level_only: bool, modules: frozenset[str] = frozenset()) -> set[str]:
    """What ``path`` imports; ``from pkg import sub`` of a submodule counts as importing ``pkg.sub`` only."""
    tree = ast.parse(path.read_text())
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    found = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            subs = {f"{node.module}.{a.name}" for a in node.names} & modules
            found |= subs
            if len(subs) < len(node.names):
                found.add(node.module)
    return {m for m in found if m.split(".")[0] in (*PACKAGES, "rclpy")}


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py")}


def test_core_imports_only_core():
    for name, path in _modules().items():
        if name.startswith("monovoc_ros.core"):
            above = {m for m in _imports(path, top_level_only=False) if not m.startswith("monovoc_ros.core")}
            assert not above, f"{name} imports {sorted(above)}"


# core's stages in import order (monovoc_ros/core/__init__.py). At core's root, thread_pools comes first and
# keyframe and sync right after map/ (every stage may take them); the rest of the root sits above every stage.
CORE_STAGES = ("thread_pools", "map", "keyframe", "sync", "raster", "evidence", "segments", "follow", "evaluation")


def _core_rank(name: str) -> int:
    part = name.split(".")[2]
    return CORE_STAGES.index(part) if part in CORE_STAGES else len(CORE_STAGES)


def test_core_stages_import_downward():
    modules = _modules()
    for name, path in modules.items():
        if name.startswith("monovoc_ros.core."):
            rank = _core_rank(name)
            found = _imports(path, top_level_only=False, modules=frozenset(modules))
            later = {m for m in found if m.startswith("monovoc_ros.core.")}
            later = {m for m in later if _core_rank(m) > rank}
            assert not later, f"{name} imports {sorted(later)} from a later stage"


def test_no_module_level_import_cycles():
    modules = _modules()
    graph = {
        name: {m for m in _imports(path, top_level_only=True, modules=frozenset(modules)) if m in modules and m != name}
        for name, path in modules.items()
    }
    state: dict[str, int] = {}

    def visit(node: str, stack: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycle = stack[stack.index(nxt) :] + [nxt] if nxt in stack else [node, nxt]
                raise AssertionError(f"import cycle: {' -> '.join(cycle)}")
            if nxt not in state:
                visit(nxt, [*stack, nxt])
        state[node] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name, [name])


def test_every_numba_kernel_releases_the_interpreter():
    """The executor's callbacks (the query service among them) run beside the worker and the planning thread:
    a kernel compiled without nogil holds the GIL for its whole run and stalls them."""
    import ast

    holding = []
    for name, path in _modules().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.FunctionDef):
                continue
            for deco in node.decorator_list:
                if isinstance(deco, ast.Call) and ast.unparse(deco.func) in ("njit", "numba.njit"):
                    nogil = [k for k in deco.keywords if k.arg == "nogil"]
                    if not nogil or not (isinstance(nogil[0].value, ast.Constant) and nogil[0].value.value is True):
                        holding.append(f"{name}.{node.name}")
                elif ast.unparse(deco) in ("njit", "numba.njit"):
                    holding.append(f"{name}.{node.name}")
    assert not holding, holding
