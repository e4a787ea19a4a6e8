"""Learning dynamics of deep Q-learning as a linear system (paper Sec. 3-4), in two variants.

Sign convention, stated once for all of cdqn: the control reward ``u`` enters the training
loss like the reward,

.. math::  \\mathcal L = \\tfrac12\\,\\delta^2,\\qquad
           \\delta = r + \\gamma \\max_{a'} Q(s',a') - Q(s,a) + u

(paper Eq. loss_Hinf; the static-gain loss Eq. loss_LQ has the same gradient), with the
target, ``u`` and ``x_e`` held constant w.r.t. θ.  The static controller
``u = −k1 Q1 − k2 Q2 + k3 x_e`` turns ``δ`` into the bracket of the paper's Eq. Q_change_LQ.

Which plant that loss realises
------------------------------

One SGD step of cdqn (:class:`cdqn.agents.controlled.ControlledAgent`) is
``Δθ = α δ ∂Q(s,a)/∂θ``.  To first order in α *every* Q-value moves, by
``ΔQ(x) = ∂Q(x)/∂θ · Δθ = α δ Θ(x, (s,a))`` (paper Eq. Q_change_self and Q_change_other).
For ``Q1 = Q(s,a)`` and ``Q2 = Q(s',a')`` with ``Θ1 = Θ((s,a),(s,a))``,
``Θ2 = Θ((s,a),(s',a'))``, and one step lasting ``Δt = α``:

.. math::  \\dot Q_1 = \\Theta_1\\,\\delta,\\qquad \\dot Q_2 = \\Theta_2\\,\\delta,\\qquad
           \\delta = -Q_1 + \\gamma Q_2 + r + u .

So ``u`` reaches ``Q2`` through ``Θ2`` exactly as ``r`` does:
``B_u = B_r = b = [Θ1, Θ2]ᵀ``.  This is ``plant="gradient_flow"``, what cdqn's training
step actually does (``tests/test_control_sign.py`` checks both ``ΔQ1 = αΘ1δ`` and
``ΔQ2 = αΘ2δ`` on a real network).

The paper's Eq. controlled_Q and Eq. ext_statespace instead take ``B_u = [Θ1, 0]ᵀ`` ("the
control input only affects dQ1/dt directly"): ``plant="paper"``, kept to reproduce the paper's
designs.  Both variants share

.. math::  \\dot Q = A Q + b\\,r + B_u u,\\qquad A = b\\,c^\\top,\\quad
           b = \\begin{bmatrix}\\Theta_1\\\\ \\Theta_2\\end{bmatrix},\\quad
           c = \\begin{bmatrix}-1\\\\ \\gamma\\end{bmatrix},\\qquad
           B_u = \\begin{cases} b & \\text{gradient\\_flow}\\\\
           [\\Theta_1, 0]^\\top & \\text{paper}\\end{cases}

(paper Eq. q_learning_uncontrolled_state_space_nominal).  ``A`` has rank one: eigenvalues 0
and ``cᵀb = γΘ2 − Θ1``.

Augmented plant (paper Eq. ext_statespace), states ``x_a = [Q1, Q2, x_e]`` with
``ẋ_e = e = r + γ Q̂2 − Q1`` and ``Q̂2`` an exogenous input:

.. math::  \\dot x_a = \\begin{bmatrix} b c^\\top & 0 \\\\ -1\\;\\;0 & 0\\end{bmatrix} x_a
           + \\begin{bmatrix} b\\\\ 1\\end{bmatrix} r
           + \\begin{bmatrix}0\\\\ 0\\\\ \\gamma\\end{bmatrix} \\hat Q_2
           + \\begin{bmatrix} B_u\\\\ 0\\end{bmatrix} u.

The structural zero of the gradient-flow plant
----------------------------------------------

With ``ℓ = [Θ2, −Θ1]`` (``ℓ b = 0``) the quantity ``w = ℓ Q = Θ2 Q1 − Θ1 Q2`` obeys
``ẇ = ℓ b (δ) = 0`` whatever ``r``, ``Q̂2`` and ``u`` are: on the gradient-flow plant
``[ℓ, 0]`` is a left eigenvector, at eigenvalue 0, of every closed loop of any controller that
reads ``[x_e, Q1, Q2]``, and the mode is unreachable from every input.  No controller moves
it, and it does not grow: it is the line of equilibria along which the learning step is zero
(``δ = 0`` and ``e = 0``), shifted by the initial value of ``w``.  The rest of the dynamics
lives on the invariant hyperplane ``ker ℓ = span(b) × R`` (``A`` maps everything into it);
in the coordinate ``y`` along ``b̂ = b/‖b‖`` (``Q = b̂ y``) the minimal learning plant is first
order:

.. math::  \\dot y = (\\gamma\\Theta_2 - \\Theta_1)\\,y + \\|b\\|\\,(r + u),\\qquad
           Q = \\hat b\\, y,

the exact transfer function ``Q(s) = b (r + u)/(s − cᵀb)`` of the full plant.  Designs and
certificates work on this minimal part (:func:`reduction_basis`): the certified loop is the
closed loop restricted to ``ker ℓ`` (``Nᵀ A_cl N`` with an orthonormal basis ``N``), whose
eigenvalues are those of ``A_cl`` less the one structural zero.  A loop whose restriction is
stable has bounded trajectories that converge to a point of the line of equilibria; if the
zero were double (e.g. ``k3 = 0``: ``x_e`` then drifts), the restriction keeps a zero and
fails the certificate.  On the paper's plant ``ℓ B_u = Θ1Θ2 ≠ 0``: nothing is removed.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import NamedTuple

import numpy as np

from cdqn.control.errors import DesignError

PLANTS = ("gradient_flow", "paper")
"""``gradient_flow``: ``B_u = [Θ1, Θ2]`` (what training does); ``paper``: ``B_u = [Θ1, 0]``
(the paper's Eq. controlled_Q)."""
DEFAULT_PLANT = "gradient_flow"


def check_plant(plant: str) -> str:
    """``plant`` if it is one of :data:`PLANTS`, else :class:`DesignError`."""
    if plant not in PLANTS:
        raise DesignError(f"controller.synthesis.plant={plant!r}: allowed {', '.join(PLANTS)}")
    return plant


def gain_triple(values: Iterable[float]) -> tuple[float, float, float]:
    """The static gains ``(k1, k2, k3)`` of ``values`` (three numbers) as floats."""
    k1, k2, k3 = (float(v) for v in values)
    return k1, k2, k3


class LinearPlant(NamedTuple):
    """Continuous-time ``ẋ = A x + B_r r + B_u u (+ B_q Q̂2)``."""

    A: np.ndarray
    B_r: np.ndarray
    B_u: np.ndarray
    B_q: np.ndarray


def control_input(theta1: float, theta2: float, plant: str = DEFAULT_PLANT) -> np.ndarray:
    """``B_u`` on ``[Q1, Q2]`` (module docstring): ``[Θ1, Θ2]`` or the paper's ``[Θ1, 0]``."""
    check_plant(plant)
    return np.array([theta1, theta2 if plant == "gradient_flow" else 0.0], dtype=float)


def control_input_batch(points: np.ndarray, plant: str = DEFAULT_PLANT) -> np.ndarray:
    """:func:`control_input` for rows (Θ1, Θ2) of ``points``: shape (P, 2)."""
    check_plant(plant)
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    out = pts[:, :2].copy()
    if plant == "paper":
        out[:, 1] = 0.0
    return out


def nominal_plant(
    theta1: float, theta2: float, discount: float, plant: str = DEFAULT_PLANT
) -> LinearPlant:
    """States [Q1, Q2] (module docstring)."""
    A = np.array([[-theta1, discount * theta1], [-theta2, discount * theta2]])
    return LinearPlant(
        A=A,
        B_r=np.array([theta1, theta2]),
        B_u=control_input(theta1, theta2, plant),
        B_q=np.zeros(2),
    )


def augmented_plant(
    theta1: float, theta2: float, discount: float, plant: str = DEFAULT_PLANT
) -> LinearPlant:
    """States [Q1, Q2, x_e] (module docstring, paper Eq. ext_statespace with ``B_u`` of
    ``plant``)."""
    A = np.array(
        [
            [-theta1, discount * theta1, 0.0],
            [-theta2, discount * theta2, 0.0],
            [-1.0, 0.0, 0.0],
        ]
    )
    return LinearPlant(
        A=A,
        B_r=np.array([theta1, theta2, 1.0]),
        B_u=np.append(control_input(theta1, theta2, plant), 0.0),
        B_q=np.array([0.0, 0.0, discount]),
    )


def static_closed_loop(
    theta1: float,
    theta2: float,
    discount: float,
    gains: tuple[float, float, float],
    plant: str = DEFAULT_PLANT,
) -> np.ndarray:
    """State matrix of the augmented plant under ``u = −k1 Q1 − k2 Q2 + k3 x_e``.

    Paper plant (paper Sec. 4.1):

    .. math::  A_{cl} = \\begin{bmatrix} -\\Theta_1(1+k_1) & (\\gamma-k_2)\\Theta_1 &
               \\Theta_1 k_3 \\\\ -\\Theta_2 & \\gamma\\Theta_2 & 0 \\\\ -1 & 0 & 0
               \\end{bmatrix}.

    Gradient-flow plant: both Q rows are ``Θ_i·[−(1+k1), γ−k2, k3]``; besides the structural
    zero, the eigenvalues are the roots of ``s² − μ s + k3 Θ1`` with
    ``μ = −(1+k1)Θ1 + (γ−k2)Θ2``: stable iff ``(1+k1)Θ1 > (γ−k2)Θ2`` and ``k3 > 0``.
    """
    k1, k2, k3 = gains
    p = augmented_plant(theta1, theta2, discount, plant)
    return p.A + np.outer(p.B_u, [-k1, -k2, k3])


def conserved_direction(
    theta1: float, theta2: float, plant: str = DEFAULT_PLANT
) -> np.ndarray | None:
    """``ℓ = [Θ2, −Θ1]`` on ``[Q1, Q2]`` for the gradient-flow plant (``ℓ Q`` is constant on
    every closed loop), ``None`` for the paper's plant (module docstring)."""
    check_plant(plant)
    return np.array([theta2, -theta1], dtype=float) if plant == "gradient_flow" else None


def reduction_basis(points: np.ndarray, n_states: int, plant: str = DEFAULT_PLANT) -> np.ndarray:
    """Orthonormal bases ``N`` (shape ``(P, n, n − k)``) of the minimal part of a loop whose
    first two states are ``[Q1, Q2]`` and whose other ``n − 2`` states (``x_e``, controller,
    weights) are kept.

    Gradient-flow plant: ``[Q1, Q2] = b̂ y`` (``k = 1``, module docstring); paper plant:
    the identity (``k = 0``).  A loop ``(A, B, C)`` reduces to ``(NᵀAN, NᵀB, CN)``; this is
    exact (same transfer function, the eigenvalues less the structural zero) because
    ``ker ℓ = range N`` is invariant and contains the columns of ``B``.
    """
    check_plant(plant)
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    P = len(pts)
    if plant == "paper":
        return np.broadcast_to(np.eye(n_states), (P, n_states, n_states)).copy()
    b = pts[:, :2] / np.linalg.norm(pts[:, :2], axis=1, keepdims=True)
    N = np.zeros((P, n_states, n_states - 1))
    N[:, 0, 0], N[:, 1, 0] = b[:, 0], b[:, 1]
    N[:, 2:, 1:] = np.eye(n_states - 2)
    return N


def reduce_batch(A: np.ndarray, N: np.ndarray) -> np.ndarray:
    """``Nᵀ A N`` for stacks ``A`` (P, n, n) and ``N`` (P, n, m)."""
    return np.swapaxes(N, -1, -2) @ A @ N


def io_plant(
    theta1: float, theta2: float, discount: float, plant: str = DEFAULT_PLANT
) -> tuple[np.ndarray, np.ndarray]:
    """``(A, B)`` of the nominal plant with inputs ``[u, r]`` and outputs ``C = I``.

    .. math::  B = [B_u,\\; b] = \\begin{bmatrix}\\Theta_1 & \\Theta_1\\\\ \\Theta_2 &
               \\Theta_2\\end{bmatrix}\\ \\text{(gradient flow)},\\qquad
               \\begin{bmatrix}\\Theta_1 & \\Theta_1\\\\ 0 & \\Theta_2\\end{bmatrix}
               \\ \\text{(paper Eq. controlled_Q)}.

    This is the plant whose sampled variation the output-multiplicative cover bounds.
    """
    p = nominal_plant(theta1, theta2, discount, plant)
    return p.A, np.column_stack([p.B_u, p.B_r])


def minimal_io_plant(
    theta1: float, theta2: float, discount: float, plant: str = DEFAULT_PLANT
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Minimal realisation ``(A, B, C)`` of :func:`io_plant` (inputs ``[u, r]``, outputs
    ``[Q1, Q2]``): the paper's plant as it is (``C = I``); the gradient-flow plant in the
    coordinate ``y`` along ``b̂`` (module docstring): ``A = [[γΘ2 − Θ1]]``,
    ``B = ‖b‖·[1, 1]``, ``C = b̂``."""
    A, B = io_plant(theta1, theta2, discount, plant)
    N = reduction_basis(np.array([[theta1, theta2]]), 2, plant)[0]
    return N.T @ A @ N, N.T @ B, N


def io_freqresp(
    points: np.ndarray, discount: float, omega: np.ndarray, plant: str = DEFAULT_PLANT
) -> np.ndarray:
    """Frequency responses ``P(jω)`` of :func:`io_plant` at rows ``(Θ1, Θ2)`` of ``points``.

    Returns an array of shape ``(len(points), len(omega), 2, 2)``.  The gradient-flow plant is
    evaluated in closed form, ``P = b [1, 1]/(jω − cᵀb)`` (its mode at 0 is uncontrollable);
    it has rank one.
    """
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    t1, t2 = pts[:, 0], pts[:, 1]
    s = 1j * np.asarray(omega, dtype=float)[None, :, None, None]
    if check_plant(plant) == "gradient_flow":
        lam = (discount * t2 - t1)[:, None, None, None]
        b = np.stack([t1, t2], axis=1)[:, None, :, None]
        return np.broadcast_to(b / (s - lam), (len(pts), s.shape[1], 2, 2)).astype(complex)
    A = np.zeros((len(pts), 2, 2))
    A[:, 0, 0], A[:, 0, 1] = -t1, discount * t1
    A[:, 1, 0], A[:, 1, 1] = -t2, discount * t2
    B = np.zeros((len(pts), 2, 2))
    B[:, 0, 0], B[:, 0, 1], B[:, 1, 1] = t1, t1, t2
    M = s * np.eye(2) - A[:, None]
    return np.linalg.solve(M, np.broadcast_to(B[:, None], M.shape).astype(complex))
