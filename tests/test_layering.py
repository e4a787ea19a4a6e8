"""The package's imports run one way: the lower layers (configuration, environments,
network, agents, control) never import the training side, the training side's modules
import only from lower layers of it (``cdqn.training.LAYERS``), entry points are imported
by nobody, and no two cdqn modules import each other, directly or around a loop.

Every ``import`` statement counts, including those inside functions; only imports under
``if TYPE_CHECKING:`` (never executed) are left out."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import cdqn
from cdqn.training import LAYERS

ROOT = Path(cdqn.__file__).resolve().parent
ENTRY_POINTS = {"cdqn.train", "cdqn.synthesize", "cdqn.tune", "cdqn.bench", "cdqn.evaluate",
                "cdqn.profile"}  # fmt: skip
TRAINING = "cdqn.training"
TUNING = "cdqn.tuning"
"""Above the training side: studies run populations; only the ``cdqn.tune`` entry point
imports it."""


def _modules(root: Path) -> dict[str, Path]:
    """Dotted name -> file of every module under ``root`` (packages by their ``__init__``)."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _executed(tree: ast.AST) -> list[ast.AST]:
    """The nodes of ``tree`` outside ``if TYPE_CHECKING:`` blocks."""
    out: list[ast.AST] = []
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            stack.extend(node.orelse)
            continue
        out.append(node)
        stack.extend(ast.iter_child_nodes(node))
    return out


def import_graph(root: Path) -> dict[str, set[str]]:
    """Module -> the modules of the same package it imports."""
    modules = _modules(root)
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        deps: set[str] = set()
        for node in _executed(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            else:
                continue
            for target in targets:
                while target and target not in modules:
                    target = target.rpartition(".")[0]
                if target and target != name and target != root.name:
                    deps.add(target)
        graph[name] = deps
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One import loop per strongly connected component with more than one module
    (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return import_graph(ROOT)


def test_no_import_cycles(graph: dict[str, set[str]]) -> None:
    assert cycles(graph) == []


def test_lower_layers_never_import_training_or_entry_points(
    graph: dict[str, set[str]],
) -> None:
    lower = [m for m in graph if not m.startswith((TRAINING, TUNING)) and m not in ENTRY_POINTS]
    assert {
        "cdqn.config",
        "cdqn.envs",
        "cdqn.network",
        "cdqn.agents",
        "cdqn.control.design",
    } <= set(lower)
    wrong = {
        m: sorted(d for d in graph[m] if d.startswith((TRAINING, TUNING)) or d in ENTRY_POINTS)
        for m in lower
    }
    assert {m: d for m, d in wrong.items() if d} == {}


def test_only_the_tune_entry_point_imports_the_tuning_side(graph: dict[str, set[str]]) -> None:
    users = {m for m, deps in graph.items() if any(d.startswith(TUNING) for d in deps)}
    assert {m for m in users if not m.startswith(TUNING)} == {"cdqn.tune"}


def test_training_modules_import_only_lower_layers(graph: dict[str, set[str]]) -> None:
    layer = {f"{TRAINING}.{name}": i for i, names in enumerate(LAYERS) for name in names}
    modules = {m for m in graph if m.startswith(f"{TRAINING}.")}
    assert modules == set(layer), "every module of cdqn.training has its place in LAYERS"
    wrong = {
        m: sorted(d for d in graph[m] if d in ENTRY_POINTS or layer.get(d, -1) >= layer[m])
        for m in modules
    }
    assert {m: d for m, d in wrong.items() if d} == {}


def test_the_checks_catch_a_cycle_and_an_upward_import(tmp_path: Path) -> None:
    pkg = tmp_path / "pkg"
    (pkg / "training").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "training" / "__init__.py").write_text("")
    (pkg / "config.py").write_text(
        "def f():\n    from pkg.training.run import go\n    return go\n"
    )  # a lower layer reaching up, inside a function
    (pkg / "training" / "run.py").write_text("from pkg.training import single\nimport pkg.config\n")
    (pkg / "training" / "single.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.training.run import x\n"
        "from pkg.training.run import go\n"
    )
    found = import_graph(pkg)
    assert found["pkg.config"] == {"pkg.training.run"}
    assert found["pkg.training.single"] == {"pkg.training.run"}
    assert cycles(found) == [["pkg.config", "pkg.training.run", "pkg.training.single"]]
