"""Names, orders and colours shared by the table and every figure (no plotting imports).

A controller keeps one colour in every figure: the known controllers have fixed entries of
seaborn's colour-blind palette, any other controller the next free entry in name order.
"""

from __future__ import annotations

from collections.abc import Iterable

CONTROLLER_ORDER = ("h2", "hinf_f", "hinf", "ddqn", "none")
"""Row order of the paper's table, then the uncontrolled baseline."""
ENV_ORDER = ("cartpole", "acrobot", "mountaincar")
"""Column order of the paper's table."""

CONTROLLER_TEXT = {
    "h2": "H2",
    "hinf_f": "H∞ fixed-structure",
    "hinf": "H∞ dynamic",
    "ddqn": "DDQN",
    "none": "no control",
}
"""Plain-text (Markdown, CSV) names, as in the paper's table."""
CONTROLLER_LATEX = {
    "h2": r"$\mathcal{H}_2$",
    "hinf_f": r"$\mathcal{H}_\infty$ fixed-structure",
    "hinf": r"$\mathcal{H}_\infty$ dynamic",
    "ddqn": "DDQN",
    "none": "no control",
}
"""LaTeX names for the table."""
CONTROLLER_MATH = {
    "h2": r"$\mathcal{H}_2$",
    "hinf_f": r"$\mathcal{H}_{\infty,f}$",
    "hinf": r"$\mathcal{H}_\infty$",
    "ddqn": "DDQN",
    "none": "no control",
}
"""Legend names in figures (matplotlib mathtext), as in the paper's plots."""
ENV_TEXT = {"cartpole": "Cartpole", "acrobot": "Acrobot", "mountaincar": "Mountain car"}

PALETTE = (
    "#0173b2",
    "#de8f05",
    "#029e73",
    "#d55e00",
    "#cc78bc",
    "#ca9161",
    "#fbafe4",
    "#949494",
    "#ece133",
    "#56b4e9",
)
"""seaborn's colour-blind palette."""
FIXED_COLOR = {"hinf": 0, "hinf_f": 1, "h2": 2, "ddqn": 3, "none": 7}
"""Palette index of the known controllers."""


def ordered(names: Iterable[str], order: Iterable[str]) -> list[str]:
    """``names`` in the given order first, the others after it alphabetically."""
    present = set(names)
    known = [n for n in order if n in present]
    return known + sorted(present - set(known))


def controller_text(name: str) -> str:
    return CONTROLLER_TEXT.get(name, name)


def controller_latex(name: str) -> str:
    return CONTROLLER_LATEX.get(name, name.replace("_", r"\_"))


def controller_label(name: str) -> str:
    return CONTROLLER_MATH.get(name, name)


def env_text(name: str) -> str:
    if name in ENV_TEXT or "-v" not in name:
        return ENV_TEXT.get(name, name.replace("_", " ").capitalize())
    return name  # a gymnasium id (env.id=<id> runs), as registered


def env_file_prefix(name: str) -> str:
    """File-name prefix of an environment, as in the paper's labels (``Cartpole``)."""
    return name[:1].upper() + name[1:]


def controller_colors(names: Iterable[str]) -> dict[str, str]:
    """Colour per controller: fixed for the known ones, free colours in name order for others.

    Pass every controller of the store, so that all figures agree.
    """
    names = set(names)
    free = [i for i in range(len(PALETTE)) if i not in FIXED_COLOR.values()]
    colors = {n: PALETTE[FIXED_COLOR[n]] for n in names if n in FIXED_COLOR}
    for i, name in enumerate(sorted(names - set(FIXED_COLOR))):
        colors[name] = PALETTE[free[i % len(free)]]
    return colors
