"""Per-step controller arithmetic, compiled (numba), shared by single runs and populations.

The runtime controllers of :mod:`cdqn.control.runtime` and the batched population step
(:mod:`cdqn.agents.controlled_population`) call these same functions, so a member of a population
computes the control reward of the single run of its seed bit for bit.  All of them use
strict IEEE arithmetic (no fast-math), in the order the formulas are written.

Control convention (:mod:`cdqn.control.plant`): ``Q̇1 = Θ1 (r + γ Q̂2 − Q1 + u)``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

H2_SOLVED = 0
H2_UNCONTROLLABLE = 1
"""Θ1·γ·Θ2 = 0, w3 ≤ 0 or W_c ≤ 0: the integrator state is not controllable or not weighted."""
H2_NOT_HURWITZ = 2
"""The closed form's polynomial is not Hurwitz (no stabilising LQR)."""

_NEWTON_ITERATIONS = 100
"""Cap on Newton steps; they converge in two or three, and stop when they stop moving."""


@njit(cache=True)
def static_gain_u(k1: float, k2: float, k3: float, x_e: float, q1: float, q2: float) -> float:
    """``u = −k1 Q1 − k2 Q2 + k3 x_e`` (paper Sec. 4.3)."""
    return -k1 * q1 - k2 * q2 + k3 * x_e


@njit(cache=True)
def state_space_step(Ad, Bd, C, D, x, x_e, q1, q2):
    """One step of the discrete-time controller, ``v = [x_e, Q1, Q2]``:
    ``u = C x + D v``, then ``x ← A_d x + B_d v`` (in place).  Sums run in index order."""
    n = x.shape[0]
    v0, v1, v2 = x_e, q1, q2
    u = 0.0
    for i in range(n):
        u += C[i] * x[i]
    u += D[0] * v0 + D[1] * v1 + D[2] * v2
    new = np.empty(n)
    for i in range(n):
        acc = 0.0
        for j in range(n):
            acc += Ad[i, j] * x[j]
        new[i] = acc + (Bd[i, 0] * v0 + Bd[i, 1] * v1 + Bd[i, 2] * v2)
    for i in range(n):
        x[i] = new[i]
    return u


@njit(cache=True)
def h2_closed_form(a, b, g, w1, w2, w3, wc):
    """``(k1, k2, k3, status)`` of the LQR of the augmented model at ``(Θ1, Θ2) = (a, b)``
    with the paper's ``B_u`` (closed form of :mod:`cdqn.control.h2`, whose docstring
    derives it); ``status`` is :data:`H2_SOLVED` or the reason there is no solution."""
    agb = a * g * b
    if agb == 0.0 or w3 <= 0.0 or wc <= 0.0:
        return 0.0, 0.0, 0.0, H2_UNCONTROLLABLE
    c = a - g * b
    s = a * a / wc
    p1 = c * c + s * w1
    p2 = s * ((w1 * g * g + w2) * b * b + w3)
    e3 = math.sqrt(s * w3) * abs(g * b)
    e = 3.0 * math.sqrt(2.0 * max(abs(p1), math.sqrt(abs(p2)), (0.5 * e3 * e3) ** (1 / 3)))
    for _ in range(2):  # fixed-point steps of f(e) = √(p1 + 2√(p2 + 2 e3 e)) from above
        e = math.sqrt(p1 + 2.0 * math.sqrt(p2 + 2.0 * e3 * e))
    for _ in range(_NEWTON_ITERATIONS):  # Newton on the quartic, monotone from above
        y = e * e - p1
        new = e - (0.25 * y * y - 2.0 * e3 * e - p2) / (e * y - 2.0 * e3)
        if not new < e:
            break
        e = new
    e1 = e
    e2 = 0.5 * (e1 * e1 - p1)
    if not (e1 > 0.0 and e2 > 0.0 and e1 * e2 > e3 and e3 > 0.0):
        return 0.0, 0.0, 0.0, H2_NOT_HURWITZ
    k1 = (e1 - c) / a
    k3 = e3 / agb
    k2 = -(e2 + agb * k1 + a * k3) / (a * b)
    return k1, k2, -k3, H2_SOLVED


@njit(cache=True)
def project_target(k1, k2, g, target, rho):
    """(k1, k2) moved into the learning target ``target = [γ_eff lo, γ_eff hi, 1 + k1 lo,
    1 + k1 hi, cap]`` (:mod:`cdqn.control.target`): ``1 + k1`` and ``γ_eff = (γ − k2)/(1 + k1)``
    clipped to their ranges (``γ_eff`` taken at the range's centre where ``1 + k1 ≤ 0``).
    With ``cap > 0`` and ``ρ = Θ2/Θ1 > 0`` (a scheduled controller), ``γ_eff`` is further
    capped at ``cap/ρ``, so that ``γ_eff ρ ≤ cap < 1`` keeps the step's loop stable."""
    scale = 1.0 + k1
    g_eff = (g - k2) / scale if scale > 0.0 else 0.5 * (target[0] + target[1])
    s = min(max(scale, target[2]), target[3])
    g_hi = target[1]
    if target[4] > 0.0 and rho > 0.0:
        g_hi = min(g_hi, target[4] / rho)
    g_eff = min(max(g_eff, target[0]), g_hi)
    return s - 1.0, g - g_eff * s


@njit(cache=True)
def scheduled_lqr_step(theta1, theta2, g, w_x, wc, research, target, gains, x_e, q1, q2):
    """One step of the gain-scheduled H2 controller (paper Sec. 4.1): the gains of
    :func:`h2_closed_form` at this step's (Θ1, Θ2), mapped by the paper
    (``(k1, k2, k3)``) or the research code (``(k3, −k2, k1)``, ``research``), then (k1, k2)
    moved into the learning ``target`` (:func:`project_target`; an empty array: none); where
    no LQR exists the previous gains (``gains``, updated in place) are kept.  Returns
    ``(u, 1/(1 + k1), solved)``."""
    k1, k2, k3, status = h2_closed_form(theta1, theta2, g, w_x[0], w_x[1], w_x[2], wc)
    solved = status == H2_SOLVED
    if solved:
        if research:
            k1, k2, k3 = k3, -k2, k1
        if target.shape[0] == 5:
            k1, k2 = project_target(k1, k2, g, target, theta2 / theta1 if theta1 > 0 else 0.0)
        gains[0], gains[1], gains[2] = k1, k2, k3
    else:
        k1, k2, k3 = gains[0], gains[1], gains[2]
    return static_gain_u(k1, k2, k3, x_e, q1, q2), 1.0 / (1.0 + gains[0]), solved
