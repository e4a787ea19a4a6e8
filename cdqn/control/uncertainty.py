"""Output-multiplicative uncertainty covers: the job of MATLAB's ``ucover``.

The sampled learning plants ``P_i`` (inputs ``[u, r]``, outputs ``[Q1, Q2]``,
:func:`cdqn.control.plant.io_plant`) are covered by the nominal plant ``P_0`` with an
output-multiplicative perturbation (paper Sec. 3, Part 3 "Parametric uncertainty"):

.. math::  P_i = (I + w(s)\\,\\Delta)\\,P_0,\\qquad \\|\\Delta\\|_\\infty \\le 1,
           \\qquad |w(j\\omega)| \\ge \\max_i\\,\\bar\\sigma\\big(E_i(j\\omega)\\big),
           \\quad E_i = (P_i - P_0)\\,P_0^{-1},

for every ω of a grid over a band ``[ω_lo, ω_hi]``.  ``w`` is a stable, minimum-phase
weight of low order,

.. math::  w(s) = k \\prod_{j=1}^{n} \\frac{s/z_j + 1}{s/p_j + 1},\\qquad z_j, p_j > 0,

whose real poles and zeros make stability and minimum phase hold by construction; the
shape ``(z, p)`` minimises the mean log-gap ``mean_ω log(|w|/max_i σ̄(E_i))`` and ``k`` is then
the smallest value that overbounds every grid point.

The corners are free (``z_j, p_j ∈ [e^-50, e^50]``) unless ``corners`` limits them to
``[ω_lo/c, c·ω_hi]``.  A free fit can put a pole at about 1e-9 rad/s, far below the band, to
follow a bound that grows toward ω_lo; such a pole is numerically on the imaginary axis, and
the H∞ plant then violates SB10AD's assumption A3 (``[A − jωI, B2; C1, D12]`` of full column
rank). :mod:`cdqn.control.synthesis` refits with ``corners`` when that happens.

Why a band: with γ = 1 every plant has a pole at γΘ2 − Θ1 (and the paper's plant a second one
at s = 0), so a plant of the box with Θ2 ≈ Θ1/γ has a pole at (paper: a double pole at) 0
while ``P_0`` has none (a single one), and ``σ̄(E)`` grows like 1/ω below ``|γΘ2 − Θ1|``: no
finite weight covers the box down to ω = 0.
The band's lower edge is therefore a design choice (``synthesis.band``); learning signals
live at ``ω ≳ 1/T`` for a training of learning time ``T = α·steps``, and the upper edge is
around the Nyquist frequency ``π/α`` of the SGD steps.

The measurement-noise block (paper: Q1 ± 0.2, Q2 ± 0.5) is a static family
``diag(1 + δ1, 1 + δ2)``, ``|δ1| ≤ 0.2``, ``|δ2| ≤ 0.5``; its exact output-multiplicative
cover is the constant ``diag(0.2, 0.5)`` (an order-0 fit: the research code's order-1
``ucover`` of the same family is constant in effect).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.optimize

from cdqn.control.errors import DesignError
from cdqn.control.plant import DEFAULT_PLANT, io_freqresp
from cdqn.control.weights import SisoWeight

COVER_SAFETY = 1.001
"""Factor on the fitted gain ``k`` so that the cover lies strictly above the bound."""


def relative_errors(
    points: np.ndarray,
    nominal: tuple[float, float],
    discount: float,
    omega: np.ndarray,
    plant: str = DEFAULT_PLANT,
) -> np.ndarray:
    """``σ̄(E_i(jω))`` of each sample (rows of ``points``) on ``omega``: shape (P, W).

    Paper plant: ``E_i = (P_i − P_0) P_0⁻¹``.  Gradient-flow plant: ``P = g [1, 1]`` with
    ``g = b/(s − cᵀb)`` has rank one, and the smallest ``E_i`` with ``P_i = (I + E_i) P_0`` is
    ``(g_i − g_0) g_0ᴴ/‖g_0‖²``, of norm ``‖g_i − g_0‖/‖g_0‖``."""
    P = io_freqresp(points, discount, omega, plant)
    P0 = io_freqresp(np.asarray([nominal]), discount, omega, plant)[0]
    if plant == "gradient_flow":
        g, g0 = P[..., 0], P0[None, ..., 0]
        return np.linalg.norm(g - g0, axis=-1) / np.linalg.norm(g0, axis=-1)
    E = P @ np.linalg.inv(P0)[None] - np.eye(2)
    return np.linalg.svd(E, compute_uv=False)[..., 0]


@dataclass
class CoverFit:
    """A fitted output-multiplicative cover and the data it covers."""

    weight: SisoWeight
    """The cover ``w(s)`` (stable, minimum phase)."""
    omega: np.ndarray
    """Grid over the band, rad/s of learning time."""
    bound: np.ndarray
    """``max_i σ̄(E_i(jω))`` on ``omega``."""
    band: tuple[float, float]
    """``[ω_lo, ω_hi]`` of the fit."""
    order: int
    """Number of pole/zero pairs of ``w``."""
    sample_errors: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, 0)))
    """``σ̄(E_i(jω))`` per sample, shape (P, W), for plots."""

    @property
    def margin(self) -> float:
        """``min_ω |w(jω)| / bound(ω)``: ≥ 1 when the cover overbounds every grid point."""
        return float(np.min(self.weight.mag(self.omega) / self.bound))


FREE = (-50.0, 50.0)
"""Limits of the log-corners ``ln z_j, ln p_j`` of a free fit."""


def _shape(
    x: np.ndarray, order: int, s: np.ndarray, limits: tuple[float, float] = FREE
) -> np.ndarray:
    z, p = np.exp(np.clip(x[:order], *limits)), np.exp(np.clip(x[order:], *limits))
    out = np.ones_like(s)
    for zj, pj in zip(z, p, strict=True):
        out = out * (s / zj + 1) / (s / pj + 1)
    return out


def _weight_from(
    x: np.ndarray, order: int, k: float, limits: tuple[float, float] = FREE
) -> SisoWeight:
    num, den = np.array([k]), np.array([1.0])
    z, p = np.exp(np.clip(x[:order], *limits)), np.exp(np.clip(x[order:], *limits))
    for zj, pj in zip(z, p, strict=True):
        num = np.polymul(num, [1.0 / zj, 1.0])
        den = np.polymul(den, [1.0 / pj, 1.0])
    return SisoWeight(tuple(float(c) for c in num), tuple(float(c) for c in den), "w_cover")


def fit_overbound(
    omega: np.ndarray, bound: np.ndarray, order: int, corners: float | None = None
) -> SisoWeight:
    """Lowest-mean-log-gap weight of ``order`` pole/zero pairs with ``|w| ≥ bound`` on
    ``omega`` (module docstring); ``corners=c`` keeps every pole and zero within
    ``[ω_lo/c, c·ω_hi]``."""
    if order < 0:
        raise DesignError(f"cover order {order}: must be >= 0")
    if not np.all(np.isfinite(bound)):
        raise DesignError(
            "uncertainty cover: the sampled relative error is not finite in the band "
            "(a sample plant shares a pole with the grid); raise synthesis.band's lower edge"
        )
    log_b = np.log(bound)
    s = 1j * omega
    if order == 0:
        return SisoWeight((float(bound.max() * COVER_SAFETY),), (1.0,), "w_cover")

    lo, hi = np.log(omega[0]), np.log(omega[-1])
    limits = FREE if corners is None else (lo - np.log(corners), hi + np.log(corners))

    def gain_and_gap(x: np.ndarray) -> tuple[float, float]:
        log_shape = np.log(np.abs(_shape(x, order, s, limits)))
        log_k = float(np.max(log_b - log_shape))
        return log_k, float(np.mean(log_k + log_shape - log_b))

    starts = []
    for a in (0.2, 0.5, 0.8):
        for b in (0.2, 0.5, 0.8):
            zj = lo + a * (hi - lo) + np.linspace(0, 1, order)
            pj = lo + b * (hi - lo) + np.linspace(0, 1, order)
            starts.append(np.concatenate([zj, pj]))
    best_x, best_gap = starts[0], np.inf
    for x0 in starts:
        res = scipy.optimize.minimize(
            lambda x: gain_and_gap(x)[1],
            x0,
            method="Nelder-Mead",
            options={"xatol": 1e-4, "fatol": 1e-6, "maxiter": 400 * order},
        )
        if res.fun < best_gap:
            best_x, best_gap = res.x, float(res.fun)
    log_k, _ = gain_and_gap(best_x)
    return _weight_from(best_x, order, float(np.exp(log_k)) * COVER_SAFETY, limits)


def fit_cover(
    points: np.ndarray,
    nominal: tuple[float, float],
    discount: float,
    band: tuple[float, float],
    order: int,
    n_omega: int = 200,
    plant: str = DEFAULT_PLANT,
    corners: float | None = None,
) -> CoverFit:
    """Fit the output-multiplicative cover of the sampled plants of ``plant`` over ``band``
    (``corners``: :func:`fit_overbound`)."""
    lo, hi = float(band[0]), float(band[1])
    if not 0 < lo < hi:
        raise DesignError(f"synthesis.band={[lo, hi]}: need 0 < lower < upper (rad/s)")
    omega = np.logspace(np.log10(lo), np.log10(hi), n_omega)
    errors = relative_errors(points, nominal, discount, omega, plant)
    bound = errors.max(axis=0)
    weight = fit_overbound(omega, bound, order, corners)
    return CoverFit(weight, omega, bound, (lo, hi), order, errors)


def noise_cover(levels: tuple[float, float]) -> tuple[SisoWeight, SisoWeight]:
    """Exact (constant) covers of the relative measurement errors ``|δ1| ≤ levels[0]``,
    ``|δ2| ≤ levels[1]`` on Q1 and Q2."""
    if len(levels) != 2 or min(levels) < 0:
        raise DesignError(f"synthesis.noise={list(levels)}: need two non-negative levels")
    return SisoWeight.constant(levels[0], "w_n1"), SisoWeight.constant(levels[1], "w_n2")
