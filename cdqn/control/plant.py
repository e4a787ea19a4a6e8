"""Learning dynamics of deep Q-learning as a linear system (paper Sec. 3-4).

Sign convention, stated once for all of cdqn: the control reward ``u`` enters the
learning dynamics as

.. math::  \\dot Q_1 = \\Theta_1\\,(r + \\gamma \\hat Q_2 - Q_1 + u),

which is the gradient flow of the loss ``½ (r + γ max Q(s') − Q(s,a) + u)²`` with the
target, ``u`` and ``x_e`` held constant w.r.t. θ (paper Eq. loss_Hinf).  The static
controller ``u = −k1 Q1 − k2 Q2 + k3 x_e`` turns it into the paper's Eq. Q_change_LQ.

Nominal plant (paper Eq. q_learning_uncontrolled_state_space_nominal and controlled_Q),
states ``[Q1, Q2]``:

.. math::  \\dot Q = \\begin{bmatrix} -\\Theta_1 & \\gamma\\Theta_1 \\\\
           -\\Theta_2 & \\gamma\\Theta_2 \\end{bmatrix} Q
           + \\begin{bmatrix}\\Theta_1\\\\ \\Theta_2\\end{bmatrix} r
           + \\begin{bmatrix}\\Theta_1\\\\ 0\\end{bmatrix} u.

One eigenvalue is 0, the other ``γΘ2 − Θ1``: nominally stable iff ``Θ1 > γΘ2``.

Augmented plant (paper Eq. ext_statespace), states ``x_a = [Q1, Q2, x_e]`` with
``ẋ_e = e = r + γ Q̂2 − Q1`` and ``Q̂2`` an exogenous input:

.. math::  \\dot x_a = \\begin{bmatrix} -\\Theta_1 & \\gamma\\Theta_1 & 0 \\\\
           -\\Theta_2 & \\gamma\\Theta_2 & 0 \\\\ -1 & 0 & 0 \\end{bmatrix} x_a
           + \\begin{bmatrix}\\Theta_1\\\\ \\Theta_2\\\\ 1\\end{bmatrix} r
           + \\begin{bmatrix}0\\\\ 0\\\\ \\gamma\\end{bmatrix} \\hat Q_2
           + \\begin{bmatrix}\\Theta_1\\\\ 0\\\\ 0\\end{bmatrix} u.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class LinearPlant(NamedTuple):
    """Continuous-time ``ẋ = A x + B_r r + B_u u (+ B_q Q̂2)``."""

    A: np.ndarray
    B_r: np.ndarray
    B_u: np.ndarray
    B_q: np.ndarray


def nominal_plant(theta1: float, theta2: float, discount: float) -> LinearPlant:
    """States [Q1, Q2] (module docstring)."""
    A = np.array([[-theta1, discount * theta1], [-theta2, discount * theta2]])
    return LinearPlant(
        A=A,
        B_r=np.array([theta1, theta2]),
        B_u=np.array([theta1, 0.0]),
        B_q=np.zeros(2),
    )


def augmented_plant(theta1: float, theta2: float, discount: float) -> LinearPlant:
    """States [Q1, Q2, x_e] (module docstring, paper Eq. ext_statespace)."""
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
        B_u=np.array([theta1, 0.0, 0.0]),
        B_q=np.array([0.0, 0.0, discount]),
    )


def static_closed_loop(
    theta1: float, theta2: float, discount: float, gains: tuple[float, float, float]
) -> np.ndarray:
    """State matrix of the augmented plant under ``u = −k1 Q1 − k2 Q2 + k3 x_e``.

    .. math::  A_{cl} = \\begin{bmatrix} -\\Theta_1(1+k_1) & (\\gamma-k_2)\\Theta_1 &
               \\Theta_1 k_3 \\\\ -\\Theta_2 & \\gamma\\Theta_2 & 0 \\\\ -1 & 0 & 0
               \\end{bmatrix}  \\quad\\text{(paper Sec. 4.1)}.
    """
    k1, k2, k3 = gains
    plant = augmented_plant(theta1, theta2, discount)
    return plant.A + np.outer(plant.B_u, [-k1, -k2, k3])
