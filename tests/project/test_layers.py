"""The layers of vservo.core, checked on the import graph of the installed package.

core/ holds one folder per layer, lowest first (core/__init__.py): a module imports only
its own layer and the layers before it (terminal/ lies under them all and imports no
layer), so perception, servo and robot never see the simulator and production never
depends on the study; nothing under core imports the app; and there is no import cycle
anywhere in vservo. Every import counts: at module level, inside a function, and under
TYPE_CHECKING (a cycle of type hints is still a cycle).
"""

from __future__ import annotations

import ast
from pathlib import Path

import vservo.app
import vservo.core
import vservo.robot_models
import vservo.static

LAYERS = ("geometry", "cell", "perception", "robot", "servo", "sim", "calibration", "production", "study")
Graph = dict[str, set[str]]


def package_modules() -> dict[str, Path]:
    """Every module of the installed vservo packages, by dotted name."""
    modules = {}
    for package in (vservo.app, vservo.core, vservo.robot_models, vservo.static):
        root = Path(package.__file__).parent
        for path in root.rglob("*.py"):
            parts = [package.__name__, *path.relative_to(root).with_suffix("").parts]
            if parts[-1] == "__init__":
                parts.pop()
            modules[".".join(parts)] = path
    return modules


def import_graph(modules: dict[str, Path]) -> Graph:
    """module -> the vservo modules it imports (a name imported from a package that is a
    module of its own counts as that module)."""
    graph: Graph = {}
    for name, path in modules.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom):
                assert node.level == 0, f"{name}: relative import (vservo imports absolutely)"
                for alias in node.names:
                    submodule = f"{node.module}.{alias.name}"
                    targets.add(submodule if submodule in modules else node.module)
        graph[name] = {target for target in targets if target in modules and target != name}
    return graph


def layer_of(module: str) -> int | None:
    """The rank of a module of vservo.core: its layer's place in LAYERS, -1 for the core
    package itself, its error root and terminal/ (the base every layer may use); None elsewhere."""
    parts = module.split(".")
    if module in ("vservo.core", "vservo.core.errors") or parts[:3] == ["vservo", "core", "terminal"]:
        return -1
    if parts[:2] != ["vservo", "core"] or len(parts) < 3 or parts[2] not in LAYERS:
        return None
    return LAYERS.index(parts[2])


def layer_violations(graph: Graph) -> list[str]:
    """Imports that break the layer rules, one line each."""
    found = []
    for module, targets in sorted(graph.items()):
        if not module.startswith("vservo.core"):
            continue
        for target in sorted(targets):
            if target.startswith("vservo.app"):
                found.append(f"{module} imports {target}: nothing under core imports the app")
            elif (rank := layer_of(module)) is not None and (target_rank := layer_of(target)) is not None and target_rank > rank:
                importer = LAYERS[rank] if rank >= 0 else "terminal"
                found.append(f"{module} imports {target}: {importer} may not import {LAYERS[target_rank]}")
    return found


def import_cycles(graph: Graph) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        on_stack.add(module)
        for target in graph.get(module, ()):
            if target not in index:
                visit(target)
                low[module] = min(low[module], low[target])
            elif target in on_stack:
                low[module] = min(low[module], index[target])
        if low[module] == index[module]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == module:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return cycles


def test_the_checks_catch_what_they_are_for():
    broken = {
        "vservo.core.servo.loop": {"vservo.core.sim.plant", "vservo.core.geometry.spatial"},
        "vservo.core.robot.jrc": {"vservo.core.sim.pseudo_terminal"},
        "vservo.core.production.assembly": {"vservo.core.study.run"},
        "vservo.core.cell.config": {"vservo.app.server"},
        "vservo.core.geometry.spatial": set(),
        "vservo.core.terminal.progress": {"vservo.core.geometry.spatial"},
        "vservo.app.server": {"vservo.app.teach_panel"},
        "vservo.app.teach_panel": {"vservo.app.server"},
    }
    lines = layer_violations(broken)
    assert any("servo.loop imports vservo.core.sim.plant" in line for line in lines)
    assert any("robot.jrc imports vservo.core.sim" in line for line in lines)
    assert any("production.assembly imports vservo.core.study.run" in line for line in lines)
    assert any("core.cell.config imports vservo.app.server" in line for line in lines)
    assert any("terminal.progress imports vservo.core.geometry.spatial" in line for line in lines)
    assert len(lines) == 5
    assert import_cycles(broken) == [["vservo.app.server", "vservo.app.teach_panel"]]


def test_every_module_of_core_sits_in_a_layer():
    assert [m for m in package_modules() if m.startswith("vservo.core") and layer_of(m) is None] == []


def test_layers_import_only_the_layers_below_them():
    assert layer_violations(import_graph(package_modules())) == []


def test_no_import_cycles():
    assert import_cycles(import_graph(package_modules())) == []


def test_every_package_folder_is_installed():
    """A package folder missing from pyproject.toml's list would be absent from a wheel."""
    import tomllib

    root = Path(__file__).resolve().parents[2]
    listed = set(tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    folders = {m for m, path in package_modules().items() if path.name == "__init__.py"}
    assert folders == listed
