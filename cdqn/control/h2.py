"""Gain-scheduled H2 (LQR) controller of the augmented learning model (paper Sec. 4.1).

For the step's NTK values (Θ1, Θ2) the LQR problem

.. math::  \\min_u \\tfrac12\\int_0^\\infty x_a^\\top W_x x_a + u^\\top W_c u\\,dt,
           \\qquad \\dot x_a = A(\\Theta)\\,x_a + B_u(\\Theta)\\,u

of the augmented plant (:func:`cdqn.control.plant.augmented_plant`) is solved through the
stable invariant subspace of the Hamiltonian

.. math::  H = \\begin{bmatrix} A & -B W_c^{-1} B^\\top \\\\ -W_x & -A^\\top\\end{bmatrix},
           \\qquad X = U_2 U_1^{-1},\\qquad K = W_c^{-1} B^\\top X,

which for this 3-state problem costs one 6×6 eigendecomposition (tens of microseconds).
The optimal control is ``u = −K x_a``; with the paper's gains ``u = −k1 Q1 − k2 Q2 + k3 x_e``
this is ``(k1, k2, k3) = (K_1, K_2, −K_3)``.
"""

from __future__ import annotations

import numpy as np

from cdqn.control.plant import augmented_plant


class LQRError(RuntimeError):
    """The LQR problem has no stabilising solution at this operating point."""


def lqr_gain(A: np.ndarray, B: np.ndarray, w_x: np.ndarray, w_c: float) -> np.ndarray:
    """Single-input LQR gain K (``u = −K x``) from the Hamiltonian's stable subspace."""
    n = A.shape[0]
    b = B.reshape(n, 1)
    H = np.block([[A, -(b @ b.T) / w_c], [-np.diag(w_x), -A.T]])
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
    """The paper's (k1, k2, k3) of the LQR on the augmented model at (Θ1, Θ2)."""
    plant = augmented_plant(theta1, theta2, discount)
    K = lqr_gain(plant.A, plant.B_u, np.asarray(w_x, dtype=float), float(w_c))
    return float(K[0]), float(K[1]), float(-K[2])
