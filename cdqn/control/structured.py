"""Fixed-structure H∞ controller: tune (k1, k2, k3) of ``u = −k1 Q1 − k2 Q2 + k3 x_e``
(paper Sec. 4.3) over sampled plants — the job of MATLAB's ``hinfstruct`` on a multi-model
problem.

For every plant sample ``i`` (Θ1, Θ2) the static gain closes the augmented learning model,
and the performance channel from the weighted reward and target to the weighted integrated
tracking error and control is

.. math::  T_i(s) : \\begin{bmatrix} r \\\\ \\hat Q_2 \\\\ n\\end{bmatrix} \\mapsto
           \\begin{bmatrix} W_p\\,x_e \\\\ W_u\\,u\\end{bmatrix},\\qquad
           \\dot x_e = W_r r + \\gamma W_{\\hat Q}\\hat Q_2 - Q_1,

(the reward enters the plant through ``W_r`` as well; the learning plant is
``synthesis.plant``, and on the gradient-flow plant, where ``u`` moves Q1 and Q2, ``T_i`` is
evaluated on its minimal part, :func:`cdqn.control.plant.reduction_basis`, which drops the
structural zero and keeps the transfer function) and the controller and the integrator
read ``Q̃ = Q + diag(0.2, 0.5)·n``, the measurement-noise block of the paper (the noise
channel is what penalises high gains: ``W_u`` alone rolls off before a high-gain loop's
bandwidth).  The tuning problem is

.. math::  \\min_{k_1,k_2,k_3}\\ \\max_i \\|T_i\\|_\\infty
           \\quad\\text{s.t.}\\quad \\max_i \\max\\mathrm{Re}\\,\\lambda(A_{cl,i}) < -m,

with ``m`` = ``synthesis.decay`` and, given the learning rate, the loops stable as SGD
steps at Δt = α as well (:func:`violation`); solved by Nelder–Mead from several starts (a
start from unstable gains can run away, so each start first minimises the worst closed-loop
pole until it is stable, then the norm).
The norm is the supremum over a logarithmic frequency grid during the search and the exact
``‖T_i‖∞`` (SLICOT AB13DD, after an explicit stability check) for the result.
"""

from __future__ import annotations

from dataclasses import dataclass

import control
import numpy as np
import scipy.optimize

from cdqn.control.certificate import ControllerMatrices, max_discrete_modulus, max_real_poles
from cdqn.control.errors import DesignError
from cdqn.control.plant import (
    DEFAULT_PLANT,
    check_plant,
    control_input_batch,
    gain_triple,
    reduce_batch,
    reduction_basis,
)
from cdqn.control.target import TargetBox
from cdqn.control.weights import SisoWeight


@dataclass(frozen=True)
class FixedStructureWeights:
    """Weights of the fixed-structure design (paper Sec. 4.3; research-code MATLAB)."""

    w_p: SisoWeight
    w_u: SisoWeight
    w_r: SisoWeight
    w_qhat: SisoWeight
    noise: tuple[float, float] = (0.2, 0.5)
    """Relative measurement-noise levels on Q1, Q2 (paper: ± 0.2, ± 0.5)."""


@dataclass
class FixedStructureResult:
    """Tuned gains and how they were found."""

    gains: tuple[float, float, float]
    """(k1, k2, k3) of ``u = −k1 Q1 − k2 Q2 + k3 x_e``."""
    worst_hinf: float
    """Exact ``max_i ‖T_i‖∞`` over the plant samples."""
    start: tuple[float, float, float]
    """The first start (the configured one)."""
    start_objective: float
    """Grid objective at ``start`` (``inf`` if it does not stabilise every sample)."""
    objective: float
    """Grid objective at ``gains``."""
    starts_tried: int
    """Number of starts."""


def _sigma_max_sq_2xm(H: np.ndarray) -> np.ndarray:
    """``σ̄(H)²`` of a stack of 2×m matrices, the largest eigenvalue of the 2×2 ``H H*``."""
    G = H @ np.conj(np.swapaxes(H, -1, -2))
    tr = (G[..., 0, 0] + G[..., 1, 1]).real
    det = (G[..., 0, 0] * G[..., 1, 1] - G[..., 0, 1] * G[..., 1, 0]).real
    return 0.5 * (tr + np.sqrt(np.maximum(tr * tr - 4.0 * det, 0.0)))


class PerformanceLoops:
    """The closed loops ``T_i`` of the module docstring, vectorised over samples."""

    def __init__(
        self,
        points: np.ndarray,
        discount: float,
        weights: FixedStructureWeights,
        omega: np.ndarray,
        plant: str = DEFAULT_PLANT,
    ) -> None:
        self.points = np.atleast_2d(points)
        self.discount = discount
        self.omega = omega
        self.blocks = [w.ss() for w in (weights.w_r, weights.w_qhat, weights.w_p, weights.w_u)]
        self.noise = weights.noise
        self.plant = check_plant(plant)

    def matrices(
        self, gains: tuple[float, float, float]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Batched ``(A, B, C, D)`` of ``T_i``, states [Q1, Q2, x_e, W_r, W_Q̂, W_p, W_u]; on the
        gradient-flow plant reduced to the minimal part (``[Q1, Q2] = b̂ y``,
        :func:`cdqn.control.plant.reduction_basis`), so ``C`` is batched too."""
        k1, k2, k3 = gains
        (ar, br, cr, dr), (aq, bq, cq, dq), (ap, bp, cp, dp), (au, bu, cu, du) = self.blocks
        nr, nq, npp, nu = (a.shape[0] for a in (ar, aq, ap, au))
        n = 3 + nr + nq + npp + nu
        ir, iq = 3, 3 + nr
        ip, iu = iq + nq, iq + nq + npp
        t1, t2 = self.points[:, 0], self.points[:, 1]
        g = self.discount
        P = len(t1)
        A = np.zeros((P, n, n))
        B = np.zeros((P, n, 4))
        # u = F x + G w : the controller reads Q̃ = Q + diag(noise) n
        F = np.zeros(n)
        F[0], F[1], F[2] = -k1, -k2, k3
        G = np.array([0.0, 0.0, -k1 * self.noise[0], -k2 * self.noise[1]])
        # r_w = cr x_r + dr r ; q_w = g (cq x_q + dq q̂)
        Rw = np.zeros(n)
        Rw[ir : ir + nr] = cr[0]
        Qw = np.zeros(n)
        Qw[iq : iq + nq] = g * cq[0]
        # Q1' = Θ1(−Q1 + γQ2 + r_w) + B_u1 u ; Q2' = Θ2(−Q1 + γQ2 + r_w) + B_u2 u
        b_u = control_input_batch(self.points, self.plant)
        base = np.zeros(n)
        base[0], base[1] = -1.0, g
        for j, t in enumerate((t1, t2)):
            A[:, j] = t[:, None] * (base + Rw)[None] + b_u[:, j, None] * F[None]
            B[:, j, 0] = t * dr[0, 0]
            B[:, j] += b_u[:, j, None] * G[None]
        # x_e' = r_w + q_w − Q̃1
        E = Rw + Qw
        E[0] -= 1.0
        A[:, 2] = E
        B[:, 2] = [dr[0, 0], g * dq[0, 0], -self.noise[0], 0.0]
        A[:, ir : ir + nr, ir : ir + nr] = ar
        B[:, ir : ir + nr, 0] = br[:, 0]
        A[:, iq : iq + nq, iq : iq + nq] = aq
        B[:, iq : iq + nq, 1] = bq[:, 0]
        # W_p on x_e, W_u on u
        A[:, ip : ip + npp, ip : ip + npp] = ap
        A[:, ip : ip + npp, 2] += bp[:, 0]
        A[:, iu : iu + nu, iu : iu + nu] = au
        A[:, iu : iu + nu] += np.outer(bu[:, 0], F)[None]
        B[:, iu : iu + nu] += np.outer(bu[:, 0], G)[None]
        C = np.zeros((2, n))
        C[0, ip : ip + npp] = cp[0]
        C[0, 2] += dp[0, 0]
        C[1, iu : iu + nu] = cu[0]
        C[1] += du[0, 0] * F
        D = np.zeros((2, 4))
        D[1] = du[0, 0] * G
        N = reduction_basis(self.points, n, self.plant)
        return reduce_batch(A, N), np.swapaxes(N, -1, -2) @ B, C[None] @ N, D

    def grid_norms(self, gains: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
        """(max Re λ, sup_ω σ̄(T_i(jω)) on the grid) per sample, from the modal form
        ``T(jω) = C V (jω − Λ)^{-1} V^{-1} B`` (falls back to linear solves when ``V`` is
        ill-conditioned)."""
        A, B, C, D = self.matrices(gains)
        lam, V = np.linalg.eig(A)
        re = lam.real.max(axis=1)
        s = 1j * self.omega
        if np.max(np.linalg.cond(V)) < 1e8:
            CV = C @ V
            VB = np.linalg.solve(V, B.astype(complex))
            R = 1.0 / (s[None, :, None] - lam[:, None, :])
            H = np.einsum("pik,pwk,pkj->pwij", CV, R, VB) + D
        else:
            n = A.shape[1]
            M = s[None, :, None, None] * np.eye(n) - A[:, None]
            X = np.linalg.solve(M, np.broadcast_to(B[:, None], M.shape[:3] + (4,)).astype(complex))
            H = C[:, None] @ X + D
        return re, np.sqrt(_sigma_max_sq_2xm(H)).max(axis=1)

    def exact_norms(self, gains: tuple[float, float, float]) -> np.ndarray:
        """Exact ``‖T_i‖∞`` (AB13DD) per sample; raises if a sample is unstable."""
        A, B, C, D = self.matrices(gains)
        out = np.empty(len(A))
        for i in range(len(A)):
            if np.max(np.linalg.eigvals(A[i]).real) >= 0:
                raise DesignError(f"fixed-structure loop unstable at sample {self.points[i]}")
            out[i] = float(control.norm(control.ss(A[i], B[i], C[i], D), p="inf"))
        return out


def violation(
    k: np.ndarray,
    points: np.ndarray,
    discount: float,
    margin: float,
    lr: float | None,
    plant: str = DEFAULT_PLANT,
    target: TargetBox | None = None,
) -> float:
    """Constraint value, < 0 when feasible: ``max Re λ + margin`` of the continuous-time loops
    and, with ``lr``, ``(max |λ_d| − 1)/α + margin`` of the loops at Δt = α (the same
    units: ``|λ_d| ≈ 1 + α Re λ``); both on the minimal part of the loop
    (:mod:`cdqn.control.certificate`).  With a learning ``target``
    (:mod:`cdqn.control.target`), gains outside it are infeasible: the value is then
    ``1e3`` times their distance from it (so that a search is led into it)."""
    if k[0] <= -1.0:
        return 1e6 * (1.0 - k[0])
    if target is not None:
        dist = target.distance(float(k[0]), float(k[1]), discount)
        if dist > 0.0:
            return 1e3 * (dist + 1e-3)
    K = ControllerMatrices.static(float(k[0]), float(k[1]), float(k[2]))
    v = float(np.max(max_real_poles(points, discount, K, plant))) + margin
    if lr is not None:
        mod = max_discrete_modulus(points, discount, K, lr, "zoh", plant)
        v = max(v, (float(mod.max()) - 1.0) / lr + margin)
    return v


def _search(
    loops: PerformanceLoops,
    starts: list[np.ndarray],
    margin: float,
    max_iter: int,
    lr: float | None,
    target: TargetBox | None = None,
) -> tuple[np.ndarray | None, float]:
    """Best (gains, grid objective) over ``starts`` on the samples of ``loops``."""
    points, discount, plant = loops.points, loops.discount, loops.plant

    def worst_pole(k: np.ndarray) -> float:
        return violation(k, points, discount, margin, lr, plant, target) - margin

    def objective(k: np.ndarray) -> float:
        if violation(k, points, discount, margin, lr, plant, target) >= 0:
            return np.inf
        _, norms = loops.grid_norms((float(k[0]), float(k[1]), float(k[2])))
        return float(np.max(norms))

    best_k: np.ndarray | None = None
    best_f = np.inf
    for k0 in starts:
        k = np.asarray(k0, float)
        if worst_pole(k) >= -margin:
            # phase 1: reach stability of every sample from an unstable start
            res = scipy.optimize.minimize(
                lambda x: max(worst_pole(x), -10.0 * max(margin, 1e-3)),
                k,
                method="Nelder-Mead",
                options={"maxiter": max_iter, "xatol": 1e-6, "fatol": 1e-9},
            )
            k = res.x
            if worst_pole(k) >= -margin:
                continue
        f0 = objective(k)
        if f0 < best_f:
            best_k, best_f = k, f0
        step = np.maximum(np.abs(k) * 0.2, 1e-3)
        simplex = np.vstack([k] + [k + np.eye(3)[j] * step[j] for j in range(3)])
        res = scipy.optimize.minimize(
            objective,
            k,
            method="Nelder-Mead",
            options={
                "maxiter": max_iter,
                "xatol": 1e-6,
                "fatol": 1e-6 * max(f0, 1e-12),
                "initial_simplex": simplex,
            },
        )
        if np.isfinite(res.fun) and res.fun < best_f:
            best_k, best_f = res.x, float(res.fun)
    return best_k, best_f


def tune_fixed_structure(
    points: np.ndarray,
    discount: float,
    weights: FixedStructureWeights,
    starts: list[tuple[float, float, float]],
    margin: float = 1e-6,
    n_omega: int = 80,
    band: tuple[float, float] = (1e-3, 1e6),
    max_iter: int = 200,
    n_active: int = 12,
    lr: float | None = None,
    plant: str = DEFAULT_PLANT,
    target: TargetBox | None = None,
) -> FixedStructureResult:
    """Multi-start Nelder–Mead tuning of (k1, k2, k3) (module docstring).

    The search runs on an active set of samples (the first ``n_active``: the box's corners
    come first); after each search every sample is checked, the violating or worst ones
    join the active set and the search resumes from the best gains, until the gains
    stabilise every sample and the active set holds the worst-case sample.  The result is
    never worse (exact norm) than the first start when that start stabilises every sample.
    With a learning ``target`` every gain the search accepts keeps it (:func:`violation`).

    Raises :class:`DesignError` when no start reaches gains that stabilise every sample.
    """
    if not starts:
        raise DesignError("fixed-structure design: no start gains given")
    pts = np.atleast_2d(points)
    omega = np.logspace(np.log10(band[0]), np.log10(band[1]), n_omega)
    all_loops = PerformanceLoops(pts, discount, weights, omega, plant)
    active = list(range(min(n_active, len(pts))))
    first = np.asarray(starts[0], float)
    start_ok = violation(first, pts, discount, margin, lr, plant, target) < 0
    start_obj = float(np.max(all_loops.grid_norms(tuple(first))[1])) if start_ok else np.inf
    candidates = [np.asarray(s, float) for s in starts]
    best_k: np.ndarray | None = None
    for _ in range(10):
        loops = PerformanceLoops(pts[active], discount, weights, omega, plant)
        k, _f = _search(loops, candidates, margin, max_iter, lr, target)
        if k is None:
            break
        _, norms = all_loops.grid_norms((float(k[0]), float(k[1]), float(k[2])))
        viol = np.array(
            [
                violation(k, pts[i : i + 1], discount, margin, lr, plant, target)
                for i in range(len(pts))
            ]
        )
        best_k = k
        bad = [int(i) for i in np.argsort(-viol) if viol[i] >= 0 and i not in active]
        largest = int(np.argmax(norms))
        if not bad and largest in active:
            break
        active += bad[:4] + ([largest] if largest not in active else [])
        candidates = [k]
    within = "" if target is None else f" within the learning target {target.to_dict()}"
    if best_k is None:
        raise DesignError(
            f"fixed-structure design: none of {len(starts)} starts reached gains{within} that "
            f"stabilise the plant samples ({len(pts)} samples, margin {margin:g})"
        )
    _, norms = all_loops.grid_norms(tuple(best_k))
    v = violation(best_k, pts, discount, margin, lr, plant, target)
    if v >= 0:
        raise DesignError(
            "fixed-structure design: the tuned gains "
            f"{tuple(round(float(x), 6) for x in best_k)} do not stabilise every plant sample "
            f"with decay rate {margin:g}{within} (constraint value {v:.4g})"
        )
    gains = (float(best_k[0]), float(best_k[1]), float(best_k[2]))
    worst = float(np.max(all_loops.exact_norms(gains)))
    objective = float(np.max(norms))
    if np.isfinite(start_obj):
        start_exact = float(np.max(all_loops.exact_norms(tuple(first))))
        if start_exact <= worst:
            gains, worst, objective = gain_triple(first), start_exact, start_obj
    start = (float(first[0]), float(first[1]), float(first[2]))
    return FixedStructureResult(gains, worst, start, start_obj, objective, len(starts))


def default_starts(
    ratio_max: float,
    discount: float,
    first: tuple[float, float, float],
    n_random: int,
    seed: int,
    plant: str = DEFAULT_PLANT,
    target: TargetBox | None = None,
) -> list[tuple[float, float, float]]:
    """``first``, then random gains in the stabilising region of the box (the Routh–Hurwitz
    conditions of :func:`cdqn.control.plant.static_closed_loop` for ρ > 0).

    Gradient-flow plant: ``(1 + k1) Θ1 > (γ − k2) Θ2`` at every sample, i.e. the effective
    discount ``(γ − k2)/(1 + k1) < 1/ρ_max``, and ``k3 > 0``; drawn as ``1 + k1`` in
    ``[0.5, 3]``, ``(γ − k2)/(1 + k1)`` in ``[−2, 0.95]/ρ_max`` and ``k3`` log-uniform in
    ``[1e-2, 1]``.  Paper plant: ``1 + k1 > γ·ρ_max``, ``k2 < −γ k1``, ``k3 < 0``.

    With a learning ``target``: ``first`` with its (k1, k2) projected into the target, then
    ``1 + k1`` and ``γ_eff`` uniform in the target's ranges (``γ_eff`` capped below
    ``1/ρ_max``) and ``k3`` as above."""
    check_plant(plant)
    rng = np.random.default_rng(seed)
    out = [gain_triple(first)]
    if target is not None:
        k1, k2 = target.project(first[0], first[1], discount)
        k3 = first[2] if first[2] > 0 else 0.1
        out = [(float(k1), float(k2), float(k3))]
        g_hi = min(target.gamma_eff[1], 0.99 / ratio_max)
        g_lo = min(target.gamma_eff[0], g_hi)
        for _ in range(n_random):
            k1, k2 = target.gains(
                rng.uniform(g_lo, g_hi), rng.uniform(*target.step_scale), discount
            )
            out.append((float(k1), float(k2), float(10.0 ** rng.uniform(-2, 0))))
        return out
    for _ in range(n_random):
        if plant == "gradient_flow":
            one_k1 = rng.uniform(0.5, 3.0)
            k2 = discount - one_k1 * rng.uniform(-2.0, 0.95) / ratio_max
            k3 = 10.0 ** rng.uniform(-2, 0)
            out.append((float(one_k1 - 1.0), float(k2), float(k3)))
            continue
        k1 = discount * ratio_max - 1.0 + rng.uniform(0.05, 2.0)
        k2 = -discount * k1 - rng.uniform(0.1, 3.0)
        k3 = -(10.0 ** rng.uniform(-2, 1))
        out.append((float(k1), float(k2), float(k3)))
    return out
