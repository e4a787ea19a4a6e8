"""Stability certificate of a design over its NTK box.

A controller ``K`` (inputs ``[x_e, Q1, Q2]``, output ``u``; for a static gain
``D = [k3, −k1, −k2]``) closes the augmented learning model (paper Eq. ext_statespace,
:func:`cdqn.control.plant.augmented_plant`, with ``B_u`` of ``controller.synthesis.plant``)
at every point (Θ1, Θ2) of the plant samples and of a denser validation grid with the box's
corners:

.. math::  A_{cl} = \\begin{bmatrix} A_a + B_u D_K C_y & B_u C_K \\\\ B_K C_y & A_K
           \\end{bmatrix},\\qquad C_y x_a = [x_e, Q_1, Q_2]^\\top .

Continuous-time check: ``max Re λ < −margin`` at every point, on the minimal part of the
loop.  On the gradient-flow plant every closed loop has the structural eigenvalue 0 of the
conserved quantity ``Θ2 Q1 − Θ1 Q2`` (:mod:`cdqn.control.plant`): unreachable from every
input, it neither grows nor can be moved by any controller; it is the line of equilibria of the
TD error.  The certificate therefore tests the loop restricted to the invariant complement of
that direction, ``Nᵀ A_cl N`` (:func:`cdqn.control.plant.reduction_basis`), whose spectrum is
that of ``A_cl`` less exactly this one zero.  Restricting (rather than discarding eigenvalues
near 0) removes the structural mode by construction, never a mode a controller left
marginal: a double zero (e.g. ``k3 = 0``) leaves a zero in the restriction and fails.  On the
paper's plant the restriction is the identity.  Stability is checked on the eigenvalues, never
through a norm (``norm(sys, 'inf')`` returns an L∞ value for unstable systems without
complaint).

Discrete-time check at ``Δt = α`` (what training runs): one SGD step is an explicit-Euler step
of the learning model, the integrator is updated before the controller reads it
(:class:`cdqn.agents.controlled.ControlledAgent`), and the controller runs discretised as in
:class:`cdqn.control.runtime.StateSpace`:

.. math::  x_e^+ = x_e - \\alpha Q_1,\\quad v = [x_e^+, Q_1, Q_2],\\quad
           u = C_d x_c + D v,\\quad Q^+ = Q + \\alpha(A_Q Q + B_u u),\\quad
           x_c^+ = A_d x_c + B_d v,

stable when every eigenvalue of the same restriction has modulus < 1 (on the gradient-flow
plant ``ℓ Q^+ = ℓ Q`` holds exactly step by step, so the removed eigenvalue is exactly 1).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cdqn.control.box import NTKBox
from cdqn.control.plant import (
    DEFAULT_PLANT,
    check_plant,
    control_input_batch,
    reduce_batch,
    reduction_basis,
)
from cdqn.control.runtime import discretize


@dataclass
class ControllerMatrices:
    """Continuous-time ``ẋ_c = A x_c + B v``, ``u = C x_c + D v``, ``v = [x_e, Q1, Q2]``."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray

    @classmethod
    def static(cls, k1: float, k2: float, k3: float) -> ControllerMatrices:
        """``u = −k1 Q1 − k2 Q2 + k3 x_e``."""
        return cls(np.zeros((0, 0)), np.zeros((0, 3)), np.zeros((1, 0)), np.array([[k3, -k1, -k2]]))

    @property
    def nstates(self) -> int:
        return int(self.A.shape[0])


def closed_loop_batch(
    points: np.ndarray,
    discount: float,
    K: ControllerMatrices,
    plant: str = DEFAULT_PLANT,
    reduce: bool = True,
) -> np.ndarray:
    """Continuous-time ``A_cl`` (module docstring) for each row (Θ1, Θ2): (P, 3+n, 3+n), or
    with ``reduce`` its restriction to the minimal part, (P, 3+n−k, 3+n−k)."""
    pts = np.atleast_2d(points)
    t1, t2 = pts[:, 0], pts[:, 1]
    bu = control_input_batch(pts, plant)
    nk = K.nstates
    P = len(pts)
    A = np.zeros((P, 3 + nk, 3 + nk))
    A[:, 0, 0], A[:, 0, 1] = -t1, discount * t1
    A[:, 1, 0], A[:, 1, 1] = -t2, discount * t2
    A[:, 2, 0] = -1.0
    Cy = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    D = K.D.reshape(1, 3)
    A[:, :2, :3] += bu[:, :, None] * (D @ Cy)[0][None, None, :]
    if nk:
        A[:, :2, 3:] += bu[:, :, None] * K.C.reshape(1, 1, nk)
        A[:, 3:, :3] = K.B @ Cy
        A[:, 3:, 3:] = K.A
    if reduce:
        A = reduce_batch(A, reduction_basis(pts, 3 + nk, plant))
    return A


def discrete_loop_batch(
    points: np.ndarray,
    discount: float,
    K: ControllerMatrices,
    lr: float,
    method: str,
    plant: str = DEFAULT_PLANT,
    reduce: bool = True,
) -> np.ndarray:
    """Discrete-time closed loop at ``Δt = α`` (module docstring): (P, 3+n, 3+n), or with
    ``reduce`` its restriction to the minimal part."""
    pts = np.atleast_2d(points)
    t1, t2 = pts[:, 0], pts[:, 1]
    nk = K.nstates
    P = len(pts)
    if nk:
        Ad, Bd = discretize(K.A, K.B, lr, method)
    # v = M [Q1, Q2, x_e]
    M = np.array([[-lr, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    D = K.D.reshape(1, 3)
    Phi = np.zeros((P, 3 + nk, 3 + nk))
    Aq = np.zeros((P, 2, 3))
    Aq[:, 0, 0], Aq[:, 0, 1] = -t1, discount * t1
    Aq[:, 1, 0], Aq[:, 1, 1] = -t2, discount * t2
    Bu = control_input_batch(pts, plant)[:, :, None]
    Phi[:, :2, :3] = np.eye(2, 3) + lr * (Aq + Bu @ (D @ M)[None])
    Phi[:, 2, :3] = [-lr, 0.0, 1.0]
    if nk:
        Phi[:, :2, 3:] = lr * Bu @ K.C.reshape(1, nk)[None]
        Phi[:, 3:, :3] = Bd @ M
        Phi[:, 3:, 3:] = Ad
    if reduce:
        Phi = reduce_batch(Phi, reduction_basis(pts, 3 + nk, plant))
    return Phi


@dataclass
class Certificate:
    """Result of :func:`certify`."""

    passed: bool
    """Every sample and grid point stable in continuous time (and at Δt = α if checked)."""
    n_points: int
    """Samples + validation-grid points checked."""
    share_stable: float
    """Share of the checked points whose closed loop is stable (continuous time)."""
    share_stable_grid: float
    """Share of the validation grid (a uniform cover of the box) that is stable."""
    worst_pole: float
    """Largest real part of a closed-loop pole over all points (continuous time)."""
    worst_point: tuple[float, float]
    """(Θ1, Θ2) where ``worst_pole`` occurs."""
    margin: float
    """Required ``max Re λ < −margin``."""
    plant: str = DEFAULT_PLANT
    """Learning plant checked (:data:`cdqn.control.plant.PLANTS`); on ``gradient_flow`` the
    poles are those of the minimal part (the structural zero removed, module docstring)."""
    discrete_checked: bool = False
    """Whether the Δt = α check ran (it needs the learning rate)."""
    worst_discrete_modulus: float = float("nan")
    """Largest |λ| of the discrete-time loop over all points."""
    worst_discrete_point: tuple[float, float] = (float("nan"), float("nan"))
    """(Θ1, Θ2) where ``worst_discrete_modulus`` occurs."""
    unstable_points: list[list[float]] = field(default_factory=list)
    """Up to 20 points (Θ1, Θ2) left unstable (continuous or discrete)."""

    def reason(self) -> str:
        """Why the certificate failed ('' when it passed)."""
        if self.passed:
            return ""
        parts = []
        if self.share_stable < 1.0 or self.worst_pole >= -self.margin:
            parts.append(
                f"closed loop unstable on {100 * (1 - self.share_stable):.1f}% of the checked "
                f"points ({100 * self.share_stable_grid:.1f}% of the box's grid stable); worst "
                f"pole Re λ = {self.worst_pole:.4g} at (Θ1, Θ2) = "
                f"({self.worst_point[0]:.4g}, {self.worst_point[1]:.4g})"
            )
        if self.discrete_checked and self.worst_discrete_modulus >= 1.0:
            parts.append(
                f"discrete-time loop at Δt = α unstable: |λ| = {self.worst_discrete_modulus:.6g} "
                f"at (Θ1, Θ2) = ({self.worst_discrete_point[0]:.4g}, "
                f"{self.worst_discrete_point[1]:.4g})"
            )
        return "; ".join(parts)

    def to_dict(self) -> dict[str, Any]:
        return {
            "passed": self.passed,
            "n_points": self.n_points,
            "share_stable": self.share_stable,
            "share_stable_grid": self.share_stable_grid,
            "worst_pole": self.worst_pole,
            "worst_point": list(self.worst_point),
            "margin": self.margin,
            "plant": self.plant,
            "discrete_checked": self.discrete_checked,
            "worst_discrete_modulus": self.worst_discrete_modulus,
            "worst_discrete_point": list(self.worst_discrete_point),
            "unstable_points": self.unstable_points,
            "reason": self.reason(),
        }


def max_real_poles(
    points: np.ndarray, discount: float, K: ControllerMatrices, plant: str = DEFAULT_PLANT
) -> np.ndarray:
    """``max Re λ`` of the minimal part of ``A_cl`` at each point (module docstring)."""
    return np.linalg.eigvals(closed_loop_batch(points, discount, K, plant)).real.max(axis=1)


def max_discrete_modulus(
    points: np.ndarray,
    discount: float,
    K: ControllerMatrices,
    lr: float,
    method: str = "zoh",
    plant: str = DEFAULT_PLANT,
) -> np.ndarray:
    """``max |λ|`` of the minimal part of the loop at ``Δt = α`` at each point."""
    Phi = discrete_loop_batch(points, discount, K, lr, method, plant)
    return np.abs(np.linalg.eigvals(Phi)).max(axis=1)


def certify(
    K: ControllerMatrices,
    box: NTKBox,
    samples: np.ndarray,
    grid: tuple[int, int],
    discount: float,
    margin: float = 1e-6,
    lr: float | None = None,
    method: str = "zoh",
    plant: str = DEFAULT_PLANT,
) -> Certificate:
    """Check ``K`` on the samples and on a ``grid[0] × grid[1]`` grid of ``box`` (corners
    included), on the learning plant ``plant``: module docstring."""
    check_plant(plant)
    grid_pts = box.grid(*grid)
    pts = np.vstack([samples, grid_pts])
    re = max_real_poles(pts, discount, K, plant)
    stable = re < -margin
    worst = int(np.argmax(re))
    cert = Certificate(
        passed=bool(stable.all()),
        n_points=len(pts),
        share_stable=float(stable.mean()),
        share_stable_grid=float(stable[len(samples) :].mean()),
        worst_pole=float(re[worst]),
        worst_point=(float(pts[worst, 0]), float(pts[worst, 1])),
        margin=margin,
        plant=plant,
    )
    bad = ~stable
    if lr is not None:
        mod = max_discrete_modulus(pts, discount, K, lr, method, plant)
        worst_d = int(np.argmax(mod))
        cert.discrete_checked = True
        cert.worst_discrete_modulus = float(mod[worst_d])
        cert.worst_discrete_point = (float(pts[worst_d, 0]), float(pts[worst_d, 1]))
        bad |= mod >= 1.0
        cert.passed = cert.passed and bool((mod < 1.0).all())
    cert.unstable_points = pts[bad][:20].tolist()
    return cert
