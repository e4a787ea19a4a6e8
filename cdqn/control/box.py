"""The NTK box a robust design covers, its plant samples and its validation grid.

The parametric uncertainty of the learning model (paper Sec. 3, Remark "Boundedness of the
parametric uncertainty", Fig. NTK_range) is described by a box in (Θ1, Θ2/Θ1):

.. math::  \\Theta_1 \\in [\\underline\\Theta_1, \\overline\\Theta_1],\\qquad
           \\Theta_2 = \\rho\\,\\Theta_1,\\quad \\rho \\in [\\underline\\rho, \\overline\\rho],

which keeps the correlation of Θ1 and Θ2 the paper points out (the paper's CartPole box:
200 < Θ1 < 500, 0.8 < ρ < 1.2).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from cdqn.control.errors import DesignError

Box = tuple[tuple[float, float], tuple[float, float]]
"""An NTK box as plain bounds ``((Θ1 lower, Θ1 upper), (ρ lower, ρ upper))``, ρ = Θ2/Θ1:
what a design record keeps (``theta_bounds``) and what compiled training code reads."""


@dataclass(frozen=True)
class NTKBox:
    """Box of NTK values; points are returned as rows ``(Θ1, Θ2)``."""

    theta1: tuple[float, float]
    """[lower, upper] of Θ1."""
    ratio: tuple[float, float]
    """[lower, upper] of ρ = Θ2/Θ1."""
    nominal: tuple[float, float]
    """Nominal (Θ1, Θ2) of the design plant."""
    source: str = "config"
    """``config`` (given), ``measured`` (from a rollout of the initial network) or
    ``measured on <env>, seed <n>`` (a tuning study's, written into the configuration)."""

    def __post_init__(self) -> None:
        t1, rho, nom = self.theta1, self.ratio, self.nominal
        if len(t1) != 2 or not 0 < t1[0] <= t1[1] or not np.all(np.isfinite(t1)):
            raise DesignError(
                f"infeasible NTK box: theta1={list(t1)} must be [lower, upper] with "
                "0 < lower <= upper (u acts through Θ1, so Θ1 > 0 is needed to control it)"
            )
        if len(rho) != 2 or not 0 < rho[0] <= rho[1] or not np.all(np.isfinite(rho)):
            raise DesignError(
                f"infeasible NTK box: ratio={list(rho)} must be [lower, upper] with "
                "0 < lower <= upper"
            )
        if len(nom) != 2 or not (t1[0] <= nom[0] <= t1[1]):
            raise DesignError(
                f"NTK box: nominal Θ1={nom[0] if nom else None} lies outside theta1={list(t1)}"
            )
        r_nom = nom[1] / nom[0]
        if not rho[0] <= r_nom <= rho[1]:
            raise DesignError(f"NTK box: nominal Θ2/Θ1={r_nom:.4g} lies outside ratio={list(rho)}")

    def corners(self) -> np.ndarray:
        """The four corners, rows (Θ1, Θ2)."""
        t1 = np.array([self.theta1[0], self.theta1[0], self.theta1[1], self.theta1[1]])
        rho = np.array([self.ratio[0], self.ratio[1], self.ratio[0], self.ratio[1]])
        return np.column_stack([t1, rho * t1])

    def sample(self, n: int, seed: int) -> np.ndarray:
        """``n`` plant samples: the corners, then points uniform in (Θ1, ρ)."""
        rng = np.random.default_rng(seed)
        m = max(n - 4, 0)
        t1 = rng.uniform(*self.theta1, size=m)
        rho = rng.uniform(*self.ratio, size=m)
        return np.vstack([self.corners(), np.column_stack([t1, rho * t1])])[:n]

    def grid(self, n_theta1: int, n_ratio: int) -> np.ndarray:
        """Regular ``n_theta1 × n_ratio`` grid over the box, corners included."""
        t1 = np.linspace(*self.theta1, max(n_theta1, 2))
        rho = np.linspace(*self.ratio, max(n_ratio, 2))
        T, R = np.meshgrid(t1, rho, indexing="ij")
        return np.column_stack([T.ravel(), (R * T).ravel()])

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Boolean mask of the rows (Θ1, Θ2) that lie in the box."""
        t1, t2 = points[:, 0], points[:, 1]
        rho = t2 / t1
        return (
            (t1 >= self.theta1[0])
            & (t1 <= self.theta1[1])
            & (rho >= self.ratio[0])
            & (rho <= self.ratio[1])
        )

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}
