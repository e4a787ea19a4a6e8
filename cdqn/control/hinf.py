"""Dynamic H∞ controller: the Δ-P-K generalized plant, γ-bisection around SLICOT's
fixed-γ H∞ routine, balanced reduction (paper Sec. 4.2).

Generalized plant (all blocks SISO unless marked; ``Q = [Q1, Q2]`` the learning plant's
outputs, ``G`` the minimal realisation of the learning plant of ``synthesis.plant``,
:func:`cdqn.control.plant.minimal_io_plant`: the paper's two-state plant as it is, the
gradient-flow plant as the first-order ``ẏ = (γΘ2 − Θ1) y + ‖b‖(u + r)``, ``Q = b̂ y``)::

             d (2) ──► W_Δ ─────────────┐                              z_d = Q   (to Δ)
             n (2) ──► W_n ───────────┐ │                              z_n = Q   (to Δ_n)
      r ──► W_r ── r_w ─┬─────────────│─│──────────┐
                        │   ┌──────┐  ▼ ▼          │
      u ───────────────┬│──►│  G   ├──Q──(+)── Q̃ ──│───────────┬─────► y2,3 = Q̃
                       ││   └──────┘     ▲         │           │
       w_q (ε_q) ──────││───process noise┘         ▼           │
                       ││         Q̂2 ──► γW_Q̂ ──► (+) ◄── −Q̃1 ┘
                       ││                           │ e
                       ││              ┌────────────┼──────────┐
                       ││              ▼                       │
                       ││        1/(s+ε_i) ── x_i ──► W_p ──► z_p
                       ││              │                       │
                       ││   w_s (ε_s) ─(+)──────────────────────┴──► y1 ≈ x_e = ∫e
                       │└──► W_u ──► z_u,  ε_u ──► z_ε
                       └──── u = K(s) [y1, y2, y3]

with ``Q̃ = Q + W_Δ d + W_n n`` (output-multiplicative uncertainty and measurement noise),
``z_p = W_p x_i`` on the integrated error ``x_i`` (``track_integral=False``: ``W_p e`` as the
paper writes it; with the paper's small ``W_p`` on ``e`` no integral action results),
``e = W_r r + γ W_Q̂ Q̂2 − Q̃1`` the tracking error (paper Sec. 4.2, the interconnection of
the paper's Fig. hinfsyn_DPK with the integrated error as first measurement), and

.. math::  \\min_K \\gamma \\quad\\text{s.t.}\\quad
           \\|\\mathcal F_l(\\mathcal P, K)\\|_\\infty < \\gamma .

The controller's inputs are ``[x_e, Q1, Q2]`` and its output is ``u`` in cdqn's
convention ``Q̇1 = Θ1 (r + γQ̂2 − Q1 + u)``; SLICOT closes ``u = +K y``, the same sign.

Regularisation (each needed by SB10AD's assumptions A1–A4; sizes from
:class:`cdqn.config.SynthesisConfig`):

* ``ε_i``: the integrator ``1/s`` becomes ``1/(s+ε_i)`` (A3: a pure integrator on a state
  that ``z`` does not see is an invariant zero on the imaginary axis).
* ``ε_u``: a performance output ``ε_u·u`` (A2: ``W_u`` is strictly proper, so ``D12 = 0``
  without it).
* ``ε_s``: sensor noise ``ε_s·w_s`` on the integrated error (A2: ``D21`` full row rank).
* ``ε_q``: process noise ``ε_q·w_q`` into Q1 and Q2 (A4: with γ = 1 the paper plant's mode
  at s = 0 has left eigenvector ``[Θ2, −Θ1]``, orthogonal to the reward input
  ``[Θ1, Θ2]``, so it is unreachable from every exogenous input).  On the gradient-flow
  plant that mode is unreachable from ``u`` as well (``B_u = [Θ1, Θ2]``): ``(A, B_2)`` is not
  stabilisable and SB10AD would refuse, so the plant enters in its minimal realisation,
  which drops exactly this mode (it changes no transfer function from ``[w, u]`` to
  ``[z, y]``; the certificate treats the mode as the marginal line of equilibria it is,
  :mod:`cdqn.control.certificate`); ``ε_q w_q`` then enters along ``b̂``.

``D11 = 0`` by construction: SB10AD refuses problems (INFO=6) when ``D11`` couples inputs
that also feed the measurements.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import slycot

from cdqn.control.errors import DesignError
from cdqn.control.plant import DEFAULT_PLANT, minimal_io_plant
from cdqn.control.weights import SisoWeight

EXOGENOUS = ("d1", "d2", "n1", "n2", "r", "qhat", "w_s", "w_q1", "w_q2")
"""Exogenous inputs of the generalized plant, in order."""
PERFORMANCE = ("z_d1", "z_d2", "z_n1", "z_n2", "z_p", "z_u", "z_eps")
"""Performance outputs of the generalized plant, in order."""
MEASUREMENTS = ("x_e", "Q1", "Q2")
"""Measurements (controller inputs), in order."""


@dataclass(frozen=True)
class Regularisation:
    """Sizes of the regularisations of the generalized plant (module docstring)."""

    integrator: float = 1e-3
    """ε_i, integrator 1/s → 1/(s+ε_i), rad/s."""
    control: float = 1e-2
    """ε_u, extra performance output ε_u·u."""
    sensor: float = 1e-4
    """ε_s, sensor noise on the integrated error."""
    process: float = 1e-2
    """ε_q, process noise into the Q states."""


@dataclass(frozen=True)
class HinfWeightSet:
    """Weights of the dynamic design (paper Sec. 4.2)."""

    w_p: SisoWeight
    w_u: SisoWeight
    w_r: SisoWeight
    w_qhat: SisoWeight
    w_cover: SisoWeight
    """Output-multiplicative cover of the sampled plants, already scaled by W_Δ."""
    w_noise: tuple[float, float]
    """Relative measurement-noise levels on Q1, Q2."""


@dataclass
class StateSpaceMatrices:
    """``ẋ = A x + B v``, ``y = C x + D v``."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray

    @property
    def nstates(self) -> int:
        return int(self.A.shape[0])


@dataclass
class GeneralizedPlant:
    """``P`` with inputs ``[w; u]`` (``w`` = :data:`EXOGENOUS`) and outputs ``[z; y]``."""

    sys: StateSpaceMatrices
    n_exogenous: int
    n_performance: int
    n_measurements: int = 3
    n_controls: int = 1


@dataclass
class HinfResult:
    """A synthesised controller and its closed loop."""

    controller: StateSpaceMatrices
    """``K``: inputs [x_e, Q1, Q2], output u."""
    gamma: float
    """Achieved closed-loop H∞ norm bound γ of ``F_l(P, K)``."""
    closed_loop: StateSpaceMatrices
    """``F_l(P, K)`` from ``w`` to ``z``."""
    iterations: int
    """SB10AD calls made by the bisection."""


class _Signals:
    """The generalized plant's states and its signals as linear maps of ``[x; w; u]``.

    A signal is one row ``[c_x, d_w, d_u]`` with ``signal = c_x x + d_w w + d_u u``; the
    states ``x`` are, in order, the learning plant's ``x_Q``, the integrator ``x_i`` and each
    weight's own states (``r``: W_r, ``q``: W_Q̂, ``c1``/``c2``: the cover on Q1/Q2, ``p``: W_p,
    ``u``: W_u)."""

    def __init__(self, n_q: int, blocks: Mapping[str, tuple[np.ndarray, ...]]) -> None:
        self.blocks = blocks
        sizes = {"Q": n_q, "i": 1} | {k: v[0].shape[0] for k, v in blocks.items()}
        self.idx: dict[str, slice] = {}
        n = 0
        for k, size in sizes.items():
            self.idx[k] = slice(n, n + size)
            n += size
        self.n, self.nw = n, len(EXOGENOUS)

    def zero(self) -> np.ndarray:
        return np.zeros(self.n + self.nw + 1)

    def w(self, name: str) -> np.ndarray:
        """The exogenous input ``name`` of :data:`EXOGENOUS`."""
        out = self.zero()
        out[self.n + EXOGENOUS.index(name)] = 1.0
        return out

    def u(self) -> np.ndarray:
        """The control input."""
        out = self.zero()
        out[-1] = 1.0
        return out

    def state(self, i: int) -> np.ndarray:
        out = self.zero()
        out[i] = 1.0
        return out

    def weighted(self, key: str, inp: np.ndarray, k: float = 1.0) -> np.ndarray:
        """``k W(s) inp``: the output ``C x_W + D inp`` of weight ``key`` fed ``inp``."""
        _, _, c, d = self.blocks[key]
        out = d[0, 0] * inp
        out[self.idx[key]] += c[0]
        return k * out

    def add(self, *terms: tuple[float, np.ndarray]) -> np.ndarray:
        """``Σ coef · signal``."""
        out = self.zero()
        for coef, t in terms:
            out = out + coef * t
        return out


class _Loop(NamedTuple):
    """The interconnection's signals (module docstring)."""

    u: np.ndarray
    """Control input u."""
    rw: np.ndarray
    """``r_w = W_r r``."""
    qhat: np.ndarray
    """``γ W_Q̂ Q̂2``."""
    Q: list[np.ndarray]
    """``Q = C_Q x_Q``, the learning plant's outputs [Q1, Q2]."""
    Qm: list[np.ndarray]
    """``Q̃ = Q + W_Δ d + W_n n``, the measured Q1, Q2."""
    e: np.ndarray
    """``e = r_w + γ W_Q̂ Q̂2 − Q̃1``, the tracking error."""
    tracked: np.ndarray
    """What W_p weighs: the integrated error ``x_i`` (or ``e``, ``track_integral=False``)."""


def _loop(
    sig: _Signals, C_Q: np.ndarray, discount: float, noise: tuple[float, float], track: bool
) -> _Loop:
    """The signals of the interconnection (paper Sec. 4.2, Fig. hinfsyn_DPK)."""
    q0 = sig.idx["Q"].start
    Q = [sig.add(*((C_Q[j, k], sig.state(q0 + k)) for k in range(C_Q.shape[1]))) for j in range(2)]
    dq = [sig.weighted("c1", sig.w("d1")), sig.weighted("c2", sig.w("d2"))]
    Qm = [sig.add((1.0, Q[j]), (1.0, dq[j]), (noise[j], sig.w(f"n{j + 1}"))) for j in range(2)]
    rw = sig.weighted("r", sig.w("r"))
    qhat = sig.weighted("q", sig.w("qhat"), discount)
    e = sig.add((1.0, rw), (1.0, qhat), (-1.0, Qm[0]))
    tracked = sig.state(sig.idx["i"].start) if track else e
    return _Loop(sig.u(), rw, qhat, Q, Qm, e, tracked)


def _state_equations(
    sig: _Signals, A_Q: np.ndarray, B_Q: np.ndarray, C_Q: np.ndarray, s: _Loop, reg: Regularisation
) -> tuple[np.ndarray, np.ndarray]:
    """``ẋ = A x + B [w; u]``:

    .. math::  \\dot x_Q = A_Q x_Q + B_u u + B_r r_w + \\varepsilon_q C_Q^T w_q, \\qquad
               \\dot x_i = -\\varepsilon_i x_i + e, \\qquad
               \\dot x_W = A_W x_W + B_W v_W

    for each weight ``W`` and its input ``v_W`` (``r``, ``Q̂2``, ``d1``, ``d2``, the tracked
    error, ``u``)."""
    n = sig.n
    A, B = np.zeros((n, n)), np.zeros((n, sig.nw + 1))
    q0 = sig.idx["Q"].start
    A[q0 : q0 + A_Q.shape[0], q0 : q0 + A_Q.shape[0]] = A_Q
    for k in range(A_Q.shape[0]):
        noise = [(reg.process * C_Q[j, k], sig.w(f"w_q{j + 1}")) for j in range(2)]
        lin = sig.add((B_Q[k, 0], s.u), (B_Q[k, 1], s.rw), *noise)
        A[q0 + k] += lin[:n]
        B[q0 + k] += lin[n:]
    i0 = sig.idx["i"].start
    A[i0, i0] -= reg.integrator
    A[i0] += s.e[:n]
    B[i0] += s.e[n:]
    inputs = {"r": sig.w("r"), "q": sig.w("qhat"), "c1": sig.w("d1"), "c2": sig.w("d2")}
    for key, inp in (inputs | {"p": s.tracked, "u": s.u}).items():
        a, b, _, _ = sig.blocks[key]
        sl = sig.idx[key]
        A[sl, sl] += a
        A[sl] += np.outer(b[:, 0], inp[:n])
        B[sl] += np.outer(b[:, 0], inp[n:])
    return A, B


def _output_equations(
    sig: _Signals, s: _Loop, reg: Regularisation
) -> tuple[np.ndarray, np.ndarray]:
    """``[z; y] = C x + D [w; u]``: ``z = [Q (to Δ), Q (to Δ_n), W_p x_i, W_u u, ε_u u]``
    (:data:`PERFORMANCE`), ``y = [x_i + ε_s w_s, Q̃1, Q̃2]`` (:data:`MEASUREMENTS`)."""
    i0 = sig.idx["i"].start
    outs = [
        *s.Q,
        *s.Q,
        sig.weighted("p", s.tracked),
        sig.weighted("u", s.u),
        sig.add((reg.control, s.u)),
        sig.add((1.0, sig.state(i0)), (reg.sensor, sig.w("w_s"))),
        *s.Qm,
    ]
    rows = np.vstack(outs)
    return rows[:, : sig.n], rows[:, sig.n :]


def generalized_plant(
    theta1: float,
    theta2: float,
    discount: float,
    weights: HinfWeightSet,
    reg: Regularisation,
    track_integral: bool = True,
    plant: str = DEFAULT_PLANT,
) -> GeneralizedPlant:
    """Assemble the generalized plant of the module docstring at nominal (Θ1, Θ2), with the
    minimal realisation of the learning plant ``plant``
    (:func:`cdqn.control.plant.minimal_io_plant`): its states, then its state
    (:func:`_state_equations`) and output (:func:`_output_equations`) equations."""
    A_Q, B_Q, C_Q = minimal_io_plant(theta1, theta2, discount, plant)
    blocks = {
        "r": weights.w_r.ss(),
        "q": weights.w_qhat.ss(),
        "c1": weights.w_cover.ss(),
        "c2": weights.w_cover.ss(),
        "p": weights.w_p.ss(),
        "u": weights.w_u.ss(),
    }
    sig = _Signals(A_Q.shape[0], blocks)
    loop = _loop(sig, C_Q, discount, weights.w_noise, track_integral)
    A, B = _state_equations(sig, A_Q, B_Q, C_Q, loop, reg)
    C, D = _output_equations(sig, loop, reg)
    return GeneralizedPlant(StateSpaceMatrices(A, B, C, D), sig.nw, len(PERFORMANCE))


def _sb10ad(P: GeneralizedPlant, gamma: float) -> tuple[Any, ...]:
    """SLICOT SB10AD at ``gamma``: its outputs (``out[5]`` is the closed loop's ``A``)."""
    s = P.sys
    return slycot.sb10ad(
        s.nstates,
        P.n_exogenous + P.n_controls,
        P.n_performance + P.n_measurements,
        P.n_controls,
        P.n_measurements,
        gamma,
        s.A,
        s.B,
        s.C,
        s.D,
        job=4,
    )


class HinfInfeasible(DesignError):
    """No γ up to the bisection's limit gives a stabilising SB10AD solution."""


def hinf_bisection(
    P: GeneralizedPlant, rel_tol: float = 1e-3, gamma_max: float = 1e8
) -> HinfResult:
    """Smallest γ (to ``rel_tol``) for which SB10AD's fixed-γ solution exists and its
    closed loop is stable; bisection in log γ between a feasible and an infeasible value.

    Raises :class:`DesignError` when no γ ≤ ``gamma_max`` is feasible.
    """
    calls = 0
    last_error = ""

    def attempt(g: float) -> tuple[Any, ...] | None:
        nonlocal calls, last_error
        calls += 1
        try:
            out = _sb10ad(P, g)
        except (slycot.exceptions.SlycotArithmeticError, ValueError) as err:
            last_error = str(err).strip().splitlines()[0] if str(err).strip() else repr(err)
            return None
        Ac = out[5]
        if Ac.size and np.max(np.linalg.eigvals(Ac).real) >= 0:
            last_error = f"closed loop unstable at γ={g:.4g}"
            return None
        return out

    hi, best = 1.0, None
    while hi <= gamma_max:
        best = attempt(hi)
        if best is not None:
            break
        hi *= 10.0
    if best is None:
        raise HinfInfeasible(
            f"H∞ synthesis failed: SB10AD found no stabilising controller for γ ≤ {gamma_max:g} "
            f"(last: {last_error})"
        )
    lo = 0.0 if hi == 1.0 else hi / 10.0
    if hi == 1.0:
        # search downward for an infeasible lower end
        lo = hi
        while lo > 1e-6:
            lo /= 10.0
            out = attempt(lo)
            if out is None:
                break
            hi, best = lo, out
        else:
            lo = 0.0
    while hi - lo > rel_tol * hi:
        mid = np.sqrt(lo * hi) if lo > 0 else hi / 2
        out = attempt(mid)
        if out is None:
            lo = mid
        else:
            hi, best = mid, out
    _, Ak, Bk, Ck, Dk, Ac, Bc, Cc, Dc, _ = best
    return HinfResult(
        StateSpaceMatrices(Ak, Bk, Ck, Dk),
        float(hi),
        StateSpaceMatrices(Ac, Bc, Cc, Dc),
        calls,
    )


def lft_closed_loop(P: GeneralizedPlant, K: StateSpaceMatrices) -> StateSpaceMatrices:
    """``F_l(P, K)`` for ``D22 = 0`` and ``u = K y`` (SLICOT's sign)."""
    s = P.sys
    nw, nz = P.n_exogenous, P.n_performance
    B1, B2 = s.B[:, :nw], s.B[:, nw:]
    C1, C2 = s.C[:nz], s.C[nz:]
    D11, D12 = s.D[:nz, :nw], s.D[:nz, nw:]
    D21 = s.D[nz:, :nw]
    Ak, Bk, Ck, Dk = K.A, K.B, K.C, K.D
    A = np.block([[s.A + B2 @ Dk @ C2, B2 @ Ck], [Bk @ C2, Ak]])
    B = np.vstack([B1 + B2 @ Dk @ D21, Bk @ D21])
    C = np.hstack([C1 + D12 @ Dk @ C2, D12 @ Ck])
    D = D11 + D12 @ Dk @ D21
    return StateSpaceMatrices(A, B, C, D)


def sigma(sys: StateSpaceMatrices, omega: np.ndarray) -> np.ndarray:
    """Singular values of ``C (jω − A)^{-1} B + D`` on ``omega``: shape (W, min(p, m))."""
    n = sys.nstates
    s = 1j * np.asarray(omega)[:, None, None]
    X = np.linalg.solve(
        s * np.eye(n) - sys.A[None],
        np.broadcast_to(sys.B, (len(omega),) + sys.B.shape).astype(complex),
    )
    H = sys.C[None] @ X + sys.D[None]
    return np.linalg.svd(H, compute_uv=False)
