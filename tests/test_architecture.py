"""The flow is one way (ARCHITECTURE.md): every import, lazy ones included, goes to a lower
layer, or stays inside its own package without a cycle."""

from __future__ import annotations

import ast
import functools
from pathlib import Path

from conftest import ROOT

#: The layers of ARCHITECTURE.md, lowest first; a package stands for all its modules.
LAYERS: list[list[str]] = [
    ["symcal.base"],
    ["symcal.language"],
    ["symcal.problem"],
    ["symcal.simulation"],
    ["symcal.data"],
    ["symcal.solvers"],
    ["symcal.analysis"],
    ["symcal.calibrate"],
    ["symcal.experiment"],
    ["symcal.revise"],
    ["symcal.export"],
    ["symcal.report"],
    ["symcal.cli"],
    ["symcal", "symcal.__main__"],
]
#: Every folder of symcal/ is one layer: its modules may import each other (no cycle).
PACKAGES = tuple(layer[0] for layer in LAYERS[:-1])


def _modules() -> dict[str, Path]:
    out = {}
    for path in (ROOT / "symcal").rglob("*.py"):
        parts = path.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _target(name: str, modules: dict[str, Path]) -> str:
    while name not in modules and "." in name:
        name = name.rsplit(".", 1)[0]
    return name


def _imports(path: Path, modules: dict[str, Path]) -> set[str]:
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("symcal"):
            for alias in node.names:
                full = f"{node.module}.{alias.name}"
                found.add(full if full in modules else _target(node.module, modules))
        elif isinstance(node, ast.Import):
            found |= {_target(a.name, modules) for a in node.names if a.name.startswith("symcal")}
    return found


@functools.cache
def _graph() -> dict[str, frozenset[str]]:
    """Every module's symcal imports, itself left out (parsed once per test process: the
    tests below read the same graph)."""
    modules = _modules()
    return {n: frozenset(_imports(p, modules) - {n}) for n, p in modules.items()}


def _layer(name: str) -> int:
    for i, layer in enumerate(LAYERS):
        for unit in layer:
            if name == unit or (unit in PACKAGES and name.startswith(unit + ".")):
                return i
    raise AssertionError(f"{name} is in no layer of ARCHITECTURE.md: add it to LAYERS")


def _package(name: str) -> str | None:
    return next((p for p in PACKAGES if name == p or name.startswith(p + ".")), None)


def test_every_import_goes_down_the_layers() -> None:
    wrong = []
    for name, deps in _graph().items():
        for dep in deps:
            same_package = _package(name) is not None and _package(name) == _package(dep)
            if not same_package and _layer(dep) >= _layer(name):
                wrong.append(f"{name} imports {dep}")
    assert wrong == []


def test_no_import_cycle() -> None:
    graph = _graph()
    state: dict[str, int] = {}

    def visit(node: str, path: list[str]) -> list[str] | None:
        state[node] = 1
        for dep in sorted(graph.get(node, ())):
            if state.get(dep) == 1:
                return [*path, node, dep]
            if dep not in state:
                cycle = visit(dep, [*path, node])
                if cycle:
                    return cycle
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state:
            cycle = visit(start, [])
            assert cycle is None, " -> ".join(cycle)


def test_objects_never_import_their_presenters() -> None:
    for name, deps in _graph().items():
        if _layer(name) < _layer("symcal.report"):
            presenters = {d for d in deps if _package(d) == "symcal.report"}
            assert not presenters, name


def test_the_architecture_document_lists_every_module() -> None:
    text = (ROOT / "ARCHITECTURE.md").read_text(encoding="utf-8")
    missing = [name for name, path in _modules().items() if path.name != "__init__.py"
               and f"`{path.relative_to(ROOT / 'symcal')}`" not in text]
    assert missing == []


def test_solvers_never_read_yaml() -> None:
    """Solvers read SolveOptions (base/options.py), never the YAML language."""
    modules = _modules()
    wrong = [f"{name} imports {dep}" for name, path in modules.items()
             if _package(name) == "symcal.solvers"
             for dep in _imports(path, modules) if _package(dep) == "symcal.language"]
    assert wrong == []


def test_a_report_simulates_nothing() -> None:
    """Reports are functions of the Result (issue 21 item 5): nothing in symcal/report/
    imports the simulator (floors are found at solve time and stored in the Result)."""
    modules = _modules()
    found = {name: sorted(d for d in _imports(path, modules)
                         if _package(d) == "symcal.simulation")
             for name, path in modules.items() if _package(name) == "symcal.report"}
    assert {k: v for k, v in found.items() if v} == {}
