"""The math in the docstrings reads as written: no docstring of ``cdqn/``, ``analysis/`` or
``hydra_plugins/`` holds a control character other than a newline.

A LaTeX command in a docstring that is not raw needs its backslash doubled: ``\\rm``,
``\\frac`` or ``\\beta`` written with one backslash become a carriage return, a form feed or
a backspace, and the equation is silently cut (``\\,`` or ``\\quad`` with one backslash are
refused by Python itself)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FILES = sorted(
    p for folder in ("cdqn", "analysis", "hydra_plugins") for p in (ROOT / folder).rglob("*.py")
)
ALLOWED = {"\n"}


def _docstrings(path: Path) -> list[tuple[int, str]]:
    """(line, text) of the module's, each class's and each function's docstring."""
    tree = ast.parse(path.read_text(), str(path))
    nodes = [tree, *(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef | ast.FunctionDef
                                                          | ast.AsyncFunctionDef))]  # fmt: skip
    out = []
    for node in nodes:
        text = ast.get_docstring(node, clean=False)
        if text is not None:
            out.append((node.body[0].lineno, text))
    return out


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_docstrings_hold_no_control_character(path: Path) -> None:
    bad = [(line, repr(c)) for line, text in _docstrings(path) for c in set(text)
           if (ord(c) < 32 or ord(c) == 127) and c not in ALLOWED]  # fmt: skip
    assert bad == [], f"{path.relative_to(ROOT)}: docstring at line(s) {bad}"


def test_the_check_finds_a_single_backslash() -> None:
    tree = 'def f():\n    """.. math::  F_{\\rm all}"""\n'
    text = ast.get_docstring(ast.parse(tree).body[0], clean=False)
    assert text is not None and "\r" in text
