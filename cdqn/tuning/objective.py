"""The study's objective: the area under a population's learning curves.

    J = (1/K) Σ_k (1/N) Σ_{e=1..N} MA100_k(e),   MA100_k(e) = mean(R_k[max(1, e−99) .. e]),

the average moving-average return over training: it rewards learning fast (early episodes
count) and well (late ones too).  A member that diverges keeps its lowest return for its
missing episodes.  J_n, the same over the first n episodes, is the intermediate value the
pruner compares (:mod:`cdqn.tuning.pruner`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

WINDOW = 100
"""Episodes of the moving average MA100, and of the final score."""


def ma100(returns: list[float]) -> np.ndarray:
    """MA100(e) = mean of the returns of episodes max(1, e−99) … e."""
    r = np.asarray(returns, float)
    c = np.concatenate([[0.0], np.cumsum(r)])
    e = np.arange(1, len(r) + 1)
    lo = np.maximum(0, e - WINDOW)
    return (c[e] - c[lo]) / (e - lo)


def final(returns: list[float]) -> float:
    """The final score: the mean return of the last :data:`WINDOW` episodes (NaN for none)."""
    return float(np.mean(returns[-WINDOW:])) if len(returns) else math.nan


def padded(returns: list[float], n: int, failed: bool) -> list[float] | None:
    """The first ``n`` returns of a member; a member that failed keeps its lowest return for
    its missing episodes; None while a running member has not reached ``n``."""
    if len(returns) >= n:
        return list(returns[:n])
    if failed and returns:
        return list(returns) + [min(returns)] * (n - len(returns))
    return None


def area(curves: list[list[float]]) -> float:
    """Mean over members of the mean of MA100 over the episodes given (module docstring)."""
    return float(np.mean([ma100(r).mean() for r in curves]))


def decimals(*values: float) -> int:
    """Decimal places that show returns at the scale of ``values``: one from 10 on
    (CartPole's 416.9 ± 106.7), two from 0.1 (FrozenLake's 0.43 ± 0.27), three below
    (FrozenLake8x8's 0.020 ± 0.024)."""
    finite = [abs(v) for v in values if np.isfinite(v)]
    top = max(finite, default=0.0)
    return 1 if top >= 10 else 2 if top >= 0.1 or top == 0 else 3


def score_text(*values: float) -> str:
    """Returns as the printed summaries show them (``mean`` or ``mean ± std``), with the
    :func:`decimals` of their scale."""
    places = decimals(*values)
    return " ± ".join(f"{v:.{places}f}" for v in values)


class Progress:
    """Returns of a population's members as they arrive, and its intermediate values."""

    def __init__(self, seeds: list[int]) -> None:
        self.returns: dict[int, list[float]] = {s: [] for s in seeds}
        self.failed: set[int] = set()

    def observe(self, member: Any) -> None:
        self.returns[member.seed] = member.returns

    def value_at(self, n: int) -> float | None:
        """J over the first ``n`` episodes once every member has them (or has failed)."""
        found = [padded(r, n, s in self.failed) for s, r in self.returns.items()]
        curves = [c for c in found if c is not None]
        if len(curves) < len(found):
            return None
        return area(curves)
