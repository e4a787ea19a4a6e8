"""Gain-scheduled H2 (LQR) controller of the augmented learning model (paper Sec. 4.1).

For the step's NTK values (Θ1, Θ2) the LQR problem

.. math::  \\min_u \\tfrac12\\int_0^\\infty x_a^\\top W_x x_a + u^\\top W_c u\\,dt,
           \\qquad \\dot x_a = A(\\Theta)\\,x_a + B_u(\\Theta)\\,u

of the augmented plant with the paper's ``B_u = [Θ1, 0, 0]ᵀ``
(:func:`cdqn.control.plant.augmented_plant` with ``plant="paper"``) is solved at every
training step, so it has to be cheap.  :func:`lqr_gain` solves any single-input LQR
problem through the stable invariant subspace of the Hamiltonian

.. math::  H = \\begin{bmatrix} A & -B W_c^{-1} B^\\top \\\\ -W_x & -A^\\top\\end{bmatrix},
           \\qquad X = U_2 U_1^{-1},\\qquad K = W_c^{-1} B^\\top X.

:func:`h2_gains` uses a closed form of the same solution for this plant (a few
microseconds instead of an eigendecomposition).  With ``a = Θ1``, ``b = Θ2``,
``c = Θ1 − γΘ2`` and ``W_x = diag(w1, w2, w3)``, the open loop has
``det(sI − A) = s²(s + c)`` and ``adj(sI − A) B = [a s(s − γb), −ab s, −a(s − γb)]``.
The return-difference (Chang–Letov) identity makes the closed-loop characteristic
polynomial ``p(s) = s³ + e1 s² + e2 s + e3`` the stable spectral factor of

.. math::  p(s)\\,p(-s) = -(z^3 - p_1 z^2 + p_2 z - p_3),\\qquad z = s^2,

.. math::  p_1 = c^2 + \\frac{a^2 w_1}{W_c},\\quad
           p_2 = \\frac{a^2}{W_c}\\big((w_1\\gamma^2 + w_2)\\,b^2 + w_3\\big),\\quad
           p_3 = \\frac{a^2 w_3 \\gamma^2 b^2}{W_c}.

With the roots ``z_i = r_i²`` (``Re r_i > 0``), ``e1 = Σ r_i``, ``e2 = Σ r_i r_j``,
``e3 = r1 r2 r3 = √p3``, and ``e2 = (e1² − p1)/2``; ``e1`` is the largest real root of the
quartic ``g(e) = (e² − p1)²/4 − 2 e3 e − p2`` (its four roots are the sign choices
``±r1 ± r2 ± r3`` with product ``+e3``).  It is the only fixed point of the increasing map
``f(e) = √(p1 + 2√(p2 + 2 e3 e))`` (from ``e1² = p1 + 2 e2``, ``e2² = p2 + 2 e1 e3``, both
``e``'s positive), so two steps of ``f`` from an upper bound (Fujiwara's bound on the
``z_i``) stay above it and nearly reach it; Newton's method on ``g``, which is convex and
increasing there, then decreases monotonically to it in two or three steps.
Matching ``det(sI − A + B K) = p(s)`` coefficient by coefficient gives the gain
``u = −K x_a``:

.. math::  K_1 = \\frac{e_1 - c}{a},\\qquad K_3 = \\frac{e_3}{a\\gamma b},\\qquad
           K_2 = -\\frac{e_2 + a\\gamma b K_1 + a K_3}{a b}.

With the paper's gains ``u = −k1 Q1 − k2 Q2 + k3 x_e`` this is
``(k1, k2, k3) = (K_1, K_2, −K_3)``.  :func:`h2_gains_batch` evaluates the same formulas
for arrays of operating points (one per member of a population).

Learning target (:mod:`cdqn.control.target`): the LQR weights say nothing about the fixed
point of learning, so every step's (k1, k2) is moved into ``weights.target``
(:func:`cdqn.control.kernels.project_target`); :func:`certify_scheduled` checks the scheduled
loop over the NTK box, frozen at each point.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from cdqn.control.box import NTKBox
from cdqn.control.certificate import (
    Certificate,
    ControllerMatrices,
    max_discrete_modulus,
    max_real_poles,
)
from cdqn.control.kernels import (
    H2_SOLVED,
    H2_UNCONTROLLABLE,
    h2_closed_form,
    scheduled_lqr_step,
)
from cdqn.control.plant import augmented_plant, check_plant, reduction_basis


class LQRError(RuntimeError):
    """The LQR problem has no stabilising solution at this operating point."""


def lqr_gain(A: np.ndarray, B: np.ndarray, w_x: np.ndarray, w_c: float) -> np.ndarray:
    """Single-input LQR gain K (``u = −K x``) from the Hamiltonian's stable subspace;
    ``w_x`` is the diagonal of the state weight or the full matrix."""
    n = A.shape[0]
    b = B.reshape(n, 1)
    W = np.diag(w_x) if np.ndim(w_x) == 1 else np.asarray(w_x, dtype=float)
    H = np.block([[A, -(b @ b.T) / w_c], [-W, -A.T]])
    eigval, eigvec = np.linalg.eig(H)
    stable = eigval.real < 0
    if int(stable.sum()) != n:
        raise LQRError(f"Hamiltonian has {int(stable.sum())} stable eigenvalues, expected {n}")
    u1, u2 = eigvec[:n, stable], eigvec[n:, stable]
    X = np.real(np.linalg.solve(u1.T, u2.T).T)
    return (b.T @ X).ravel() / w_c


def h2_gains(
    theta1: float, theta2: float, discount: float, w_x: np.ndarray, w_c: float
) -> tuple[float, float, float]:
    """The paper's (k1, k2, k3) of the LQR on the augmented model at (Θ1, Θ2), in closed
    form (module docstring, compiled in :func:`cdqn.control.kernels.h2_closed_form`);
    raises :class:`LQRError` where no stabilising LQR exists."""
    a, b, g = float(theta1), float(theta2), float(discount)
    w1, w2, w3 = np.asarray(w_x, dtype=float).tolist()
    k1, k2, k3, status = h2_closed_form(a, b, g, w1, w2, w3, float(w_c))
    if status == H2_UNCONTROLLABLE:
        raise LQRError(
            f"no stabilising LQR at Θ1={a}, Θ2={b}, γ={g}, w3={w3}: the integrator state "
            "x_e must be controllable through Θ1, Θ2 and weighted (w3 > 0)"
        )
    if status != H2_SOLVED:
        raise LQRError(f"no stabilising LQR at Θ1={a}, Θ2={b} (closed loop not Hurwitz)")
    return k1, k2, k3


@njit(cache=True)
def _h2_batch(a, b, g, w1, w2, w3, wc, out):
    worst = H2_SOLVED
    for i in range(a.shape[0]):
        out[i, 0], out[i, 1], out[i, 2], status = h2_closed_form(a[i], b[i], g, w1, w2, w3, wc)
        worst = max(worst, status)
    return worst


def h2_gains_batch(
    theta1: np.ndarray, theta2: np.ndarray, discount: float, w_x: np.ndarray, w_c: float
) -> np.ndarray:
    """:func:`h2_gains` for arrays of operating points; returns ``(n, 3)`` gains, equal to
    :func:`h2_gains` at each point."""
    a = np.ascontiguousarray(theta1, dtype=float).ravel()
    b = np.ascontiguousarray(theta2, dtype=float).ravel()
    w1, w2, w3 = np.asarray(w_x, dtype=float).tolist()
    out = np.empty((len(a), 3))
    if _h2_batch(a, b, float(discount), w1, w2, w3, float(w_c), out) != H2_SOLVED:
        raise LQRError("no stabilising LQR at some operating point")
    return out.reshape(np.shape(theta1) + (3,))


def h2_gains_reference(
    theta1: float, theta2: float, discount: float, w_x: np.ndarray, w_c: float
) -> tuple[float, float, float]:
    """(k1, k2, k3) through the Hamiltonian eigendecomposition (:func:`lqr_gain`); the
    reference the closed form is tested against."""
    plant = augmented_plant(theta1, theta2, discount, "paper")
    K = lqr_gain(plant.A, plant.B_u, np.asarray(w_x, dtype=float), float(w_c))
    return float(K[0]), float(K[1]), float(-K[2])


def h2_gains_plant(
    theta1: float, theta2: float, discount: float, w_x: np.ndarray, w_c: float, plant: str
) -> tuple[float, float, float]:
    """(k1, k2, k3) of the LQR at (Θ1, Θ2) on the learning plant ``plant``
    (:mod:`cdqn.control.plant`).

    ``paper``: :func:`h2_gains` (the paper's Sec. 4.1, closed form).  ``gradient_flow``: the
    conserved mode ``Θ2 Q1 − Θ1 Q2`` is uncontrollable at s = 0, so no LQR of the full
    augmented plant exists (the Hamiltonian has eigenvalues on the imaginary axis); the LQR
    is solved on the minimal part ``x = N x_r`` (``A_r = NᵀAN``, ``B_r = NᵀB_u``, state weight
    ``Nᵀ W_x N``) and applied as ``u = −K_r Nᵀ x``, which leaves the conserved mode alone and
    gives the minimal part the LQR's closed loop.
    """
    if check_plant(plant) == "paper":
        return h2_gains(theta1, theta2, discount, w_x, w_c)
    p = augmented_plant(theta1, theta2, discount, plant)
    N = reduction_basis(np.array([[theta1, theta2]]), 3, plant)[0]
    W = N.T @ np.diag(np.asarray(w_x, dtype=float)) @ N
    K = lqr_gain(N.T @ p.A @ N, N.T @ p.B_u, W, float(w_c)) @ N.T
    return float(K[0]), float(K[1]), float(-K[2])


def scheduled_gains(
    points: np.ndarray,
    discount: float,
    w_x: np.ndarray,
    w_c: float,
    research: bool,
    target: np.ndarray,
) -> np.ndarray:
    """``(P, 3)`` gains (k1, k2, k3) the gain-scheduled H2 applies at each (Θ1, Θ2), through
    the runtime kernel itself (:func:`cdqn.control.kernels.scheduled_lqr_step`: closed form,
    gain map, learning target); NaN rows where no LQR exists."""
    out = np.full((len(points), 3), np.nan)
    w = np.ascontiguousarray(w_x, dtype=float)
    for i, (t1, t2) in enumerate(np.atleast_2d(points)):
        gains = np.zeros(3)
        _, _, solved = scheduled_lqr_step(
            float(t1), float(t2), discount, w, float(w_c), research, target, gains, 0.0, 0.0, 0.0
        )
        if solved:
            out[i] = gains
    return out


def certify_scheduled(
    box: NTKBox,
    discount: float,
    w_x: np.ndarray,
    w_c: float,
    research: bool,
    target: np.ndarray,
    lr: float,
    samples: int,
    grid: tuple[int, int],
    seed: int,
    margin: float,
    plant: str,
) -> tuple[Certificate, np.ndarray]:
    """Frozen-parameter certificate of the gain-scheduled H2 over the NTK box: at every sample
    and grid point (Θ1, Θ2) the static loop with the gains scheduled there
    (:func:`scheduled_gains`) must be stable in continuous time and at Δt = α
    (:mod:`cdqn.control.certificate`).  Returns the certificate and ``(P, 5)`` rows
    (Θ1, Θ2, k1, k2, k3)."""
    pts = np.vstack([box.sample(samples, seed), box.grid(*grid)])
    gains = scheduled_gains(pts, discount, w_x, w_c, research, target)
    re = np.full(len(pts), np.inf)
    mod = np.full(len(pts), np.inf)
    for i, k in enumerate(gains):
        if np.all(np.isfinite(k)) and k[0] > -1.0:
            K = ControllerMatrices.static(*k)
            re[i] = max_real_poles(pts[i : i + 1], discount, K, plant)[0]
            mod[i] = max_discrete_modulus(pts[i : i + 1], discount, K, lr, "zoh", plant)[0]
    stable = re < -margin
    worst, worst_d = int(np.argmax(re)), int(np.argmax(mod))
    bad = ~stable | (mod >= 1.0)
    cert = Certificate(
        passed=bool(stable.all() and (mod < 1.0).all()),
        n_points=len(pts),
        share_stable=float(stable.mean()),
        share_stable_grid=float(stable[samples:].mean()),
        worst_pole=float(re[worst]),
        worst_point=(float(pts[worst, 0]), float(pts[worst, 1])),
        margin=margin,
        plant=plant,
        discrete_checked=True,
        worst_discrete_modulus=float(mod[worst_d]),
        worst_discrete_point=(float(pts[worst_d, 0]), float(pts[worst_d, 1])),
        unstable_points=pts[bad][:20].tolist(),
    )
    return cert, np.column_stack([pts, gains])
