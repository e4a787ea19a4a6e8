"""Controller synthesis end to end: NTK box → plant samples → cover → H∞ design →
reduction → certificate → artefacts, cached by the hash of the design inputs.

Flow (``kind`` = ``hinf`` or ``hinf_f``)::

    NTK box (config or measured) ──► plant samples (corners + uniform in Θ1, Θ2/Θ1)
        │                                  │
        │                    ┌─────────────┴───────────────┐
        ▼                    ▼                             ▼
    nominal plant     cover w(s) over band          fixed structure (hinf_f):
        │            (uncertainty.fit_cover)        multi-start tuning of (k1, k2, k3)
        ▼                    │                      over the samples (structured.py)
    generalized plant ◄──────┘                             │
    γ-bisection with SB10AD (hinf.py)                      │
    balanced reduction (reduction.py) ─────────────────────┤
                                                           ▼
                               certificate over samples + validation grid (certificate.py)
                                                           │
                                 DesignError with the reason, or ControllerDesign

The continuous-time controller is stored with inputs ``[x_e, Q1, Q2]`` and output ``u`` in
cdqn's convention ``Q̇1 = Θ1 (r + γQ̂2 − Q1 + u)``; a static controller has empty ``A``,
``B``, ``C`` and ``D = [[k3, −k1, −k2]]``.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from cdqn.config import ControllerConfig, HinfWeights, SynthesisConfig, ThetaBounds, WeightsConfig
from cdqn.control.box import NTKBox
from cdqn.control.certificate import Certificate, ControllerMatrices, certify
from cdqn.control.errors import DesignError
from cdqn.control.h2 import LQRError, h2_gains_plant
from cdqn.control.hinf import (
    HinfWeightSet,
    Regularisation,
    StateSpaceMatrices,
    generalized_plant,
    hinf_bisection,
    lft_closed_loop,
    sigma,
)
from cdqn.control.plant import check_plant
from cdqn.control.reduction import hankel, truncate
from cdqn.control.runtime import StateSpace, StaticGain
from cdqn.control.setup import ControllerSetup
from cdqn.control.structured import (
    FixedStructureWeights,
    PerformanceLoops,
    default_starts,
    tune_fixed_structure,
)
from cdqn.control.target import TargetBox, check_target, dc_gain, learning_target
from cdqn.control.uncertainty import CoverFit, fit_cover
from cdqn.control.weights import SisoWeight

DESIGN_VERSION = 7
"""Bumped whenever the synthesis changes its results; part of the cache key."""
KINDS = ("hinf", "hinf_f")
"""Controllers that are synthesised (h2 is solved per step)."""


def box_from_config(tb: ThetaBounds) -> NTKBox:
    """The config box; ``nominal=None`` puts the nominal at (√(Θ1_lo·Θ1_hi), mid ratio)."""
    t1 = (float(tb.theta1[0]), float(tb.theta1[1]))
    rho = (float(tb.ratio[0]), float(tb.ratio[1]))
    if tb.nominal is None:
        if t1[0] <= 0:
            return NTKBox(t1, rho, (0.0, 0.0))  # raises the box's own error
        t_nom = float(np.sqrt(t1[0] * t1[1]))
        nominal = (t_nom, t_nom * 0.5 * (rho[0] + rho[1]))
    else:
        nominal = (float(tb.nominal[0]), float(tb.nominal[1]))
    return NTKBox(t1, rho, nominal)


@dataclass
class DesignInputs:
    """Everything a design depends on; its hash names the cache entry."""

    kind: str
    """``hinf`` (dynamic) or ``hinf_f`` (fixed structure)."""
    box: NTKBox
    discount: float
    """γ, discount factor."""
    lr: float
    """α: the discrete-time check runs at Δt = α."""
    weights: dict[str, Any]
    """The kind's weights (``weights.hinf`` or ``weights.hinf_f`` as a dict)."""
    h2: dict[str, Any]
    """H2 weights (the fixed-structure design's default first start)."""
    synthesis: dict[str, Any]
    """Synthesis settings that affect the result."""
    discretization: str = "zoh"
    """Runtime discretisation of a dynamic controller (checked at Δt = α)."""
    target: TargetBox | None = None
    """Learning target (γ_eff and 1 + k1 ranges) the design keeps (:mod:`cdqn.control.target`)."""

    def key(self) -> str:
        payload = {
            "version": DESIGN_VERSION,
            "kind": self.kind,
            "box": self.box.to_dict() | {"source": None},
            "discount": self.discount,
            "lr": self.lr,
            "weights": self.weights,
            "h2": self.h2 if self.kind == "hinf_f" else None,
            "synthesis": self.synthesis,
            "discretization": self.discretization,
            "target": None if self.target is None else self.target.to_dict(),
        }
        text = json.dumps(payload, sort_keys=True, default=float)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


_NOT_DESIGN_FIELDS = (
    "cache",
    "cache_dir",
    "ntk_bounds",
    "quantiles",
    "ratio_floor",
    "rollout_steps",
)


def design_inputs(
    cfg: ControllerConfig,
    weights: WeightsConfig,
    discount: float,
    lr: float,
    box: NTKBox | None = None,
) -> DesignInputs:
    """Collect the inputs of a design from the run's configs (``box`` overrides the config
    box, e.g. a measured one)."""
    if cfg.name not in KINDS:
        raise DesignError(f"controller.name={cfg.name!r}: synthesis designs {', '.join(KINDS)}")
    w: HinfWeights = getattr(weights, cfg.name)
    syn = {k: v for k, v in asdict(cfg.synthesis).items() if k not in _NOT_DESIGN_FIELDS}
    return DesignInputs(
        kind=cfg.name,
        box=box if box is not None else box_from_config(weights.theta_bounds),
        discount=float(discount),
        lr=float(lr),
        weights=asdict(w),
        h2=asdict(weights.h2),
        synthesis=syn,
        discretization=cfg.discretization,
        target=TargetBox.of_controller(weights, cfg.name),
    )


@dataclass
class ControllerDesign:
    """A synthesised, certified controller (continuous time)."""

    kind: str
    controller: ControllerMatrices
    """Inputs [x_e, Q1, Q2], output u (cdqn's convention)."""
    gamma: float
    """hinf: achieved H∞ bound of the full-order closed loop; hinf_f: worst-case H∞ norm
    over the plant samples."""
    box: NTKBox
    discount: float
    certificate: Certificate
    samples: np.ndarray
    """Plant samples, rows (Θ1, Θ2)."""
    gains: tuple[float, float, float] | None = None
    """(k1, k2, k3) of a static controller."""
    cover: CoverFit | None = None
    """Output-multiplicative cover of the samples (hinf uses it; hinf_f reports it)."""
    details: dict[str, Any] = field(default_factory=dict)
    """Design-specific numbers: orders, Hankel singular values, regularisation, starts."""
    sigma_omega: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """Frequency grid of ``sigma``."""
    sigma: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    """Largest and smallest closed-loop singular value at the nominal point."""
    weights: list[SisoWeight] = field(default_factory=list)
    """The weights used, for plots."""
    seconds: float = 0.0
    """Wall time of the synthesis (without plots)."""
    key: str = ""
    """Hash of the design inputs."""
    learning: dict[str, Any] = field(default_factory=dict)
    """The learning target the controller keeps at DC (:func:`cdqn.control.target.learning_target`)
    and the target it was asked to keep."""

    def to_json(self) -> dict[str, Any]:
        K = self.controller
        static = K.nstates == 0
        out: dict[str, Any] = {
            "kind": self.kind,
            "A": [] if static else K.A.tolist(),
            "B": [] if static else K.B.tolist(),
            "C": [] if static else K.C.tolist(),
            "D": K.D.tolist(),
            "theta_bounds": {"theta1": list(self.box.theta1), "ratio": list(self.box.ratio)},
            "discount": self.discount,
            "gamma": self.gamma,
            "inputs": ["x_e", "Q1", "Q2"],
            "convention": "dQ1/dt = Theta1 (r + gamma Q2hat - Q1 + u)",
            "source": "synthesized",
            "nominal": list(self.box.nominal),
            "box_source": self.box.source,
            "plant": self.certificate.plant,
            "certificate": self.certificate.to_dict(),
            "seconds": self.seconds,
            "key": self.key,
            "details": self.details,
            "learning_target": self.learning,
        }
        if self.gains is not None:
            out["gains"] = list(self.gains)
        if self.cover is not None:
            out["cover"] = {
                **self.cover.weight.to_dict(),
                "band": list(self.cover.band),
                "order": self.cover.order,
                "margin": self.cover.margin,
            }
        return out


def _weight_set(w: dict[str, Any], prefix: str) -> dict[str, SisoWeight]:
    return {
        name: SisoWeight.make(w[name]["num"], w[name]["den"], f"{prefix}{name}")
        for name in ("w_p", "w_u", "w_r", "w_qhat")
    }


def _reg(syn: dict[str, Any]) -> Regularisation:
    return Regularisation(
        integrator=float(syn["reg_integrator"]),
        control=float(syn["reg_control"]),
        sensor=float(syn["reg_sensor"]),
        process=float(syn["reg_process"]),
    )


def _certify(K: ControllerMatrices, inputs: DesignInputs, samples: np.ndarray) -> Certificate:
    syn = inputs.synthesis
    return certify(
        K,
        inputs.box,
        samples,
        (int(syn["grid"][0]), int(syn["grid"][1])),
        inputs.discount,
        margin=float(syn["margin"]),
        lr=inputs.lr,
        method=inputs.discretization if inputs.discretization != "euler" else "euler",
        plant=syn["plant"],
    )


def _hinf_weight_set(inputs: DesignInputs, cover: CoverFit) -> HinfWeightSet:
    """The dynamic design's weights: the kind's W_p, W_u, W_r, W_Q̂, the cover scaled by W_Δ
    and the measurement-noise levels."""
    syn = inputs.synthesis
    ws = _weight_set(inputs.weights, "")
    return HinfWeightSet(
        ws["w_p"],
        ws["w_u"],
        ws["w_r"],
        ws["w_qhat"],
        cover.weight.scaled(float(inputs.weights["w_delta"])),
        (float(syn["noise"][0]), float(syn["noise"][1])),
    )


class _Reduced(NamedTuple):
    """The controller :func:`_reduce_on_target` keeps and what it tried."""

    K: ControllerMatrices
    certificate: Certificate
    share: float
    """λ of the kept candidate (:func:`_dc_on_target`); nan when none passed its certificate."""
    tried: list[dict[str, Any]]
    """Each order and candidate tried, with its outcome."""


def _reduce_on_target(
    K_full: ControllerMatrices, order0: int, inputs: DesignInputs, samples: np.ndarray
) -> _Reduced:
    """Balanced truncation of ``K_full`` to the lowest order from ``order0`` up at which a
    candidate that keeps the learning target (:func:`_dc_on_target`) passes its certificate;
    when none passes, the last candidate certified (its certificate says why).  Raises
    :class:`DesignError` when every candidate's instantaneous gain is off the target or
    unstable on the box."""
    tried: list[dict[str, Any]] = []
    last: tuple[ControllerMatrices, Certificate] | None = None
    for order in range(order0, K_full.nstates + 1):
        try:
            K_order = truncate(K_full, order)
        except Exception as err:  # SLICOT refuses an order: try the next one
            tried.append({"order": order, "error": str(err)})
            continue
        for K, lam in _dc_on_target(K_order, inputs):
            if inputs.target is not None and not _instantaneous_gain_stable(K, inputs, samples):
                reason = "instantaneous gain D off the target or not a stabilising static gain"
                tried.append({"order": order, "dynamic_share": lam, "reason": reason})
                continue
            cert = _certify(K, inputs, samples)
            tried.append({"order": order, "dynamic_share": lam, "passed": cert.passed,
                          "worst_pole": cert.worst_pole})  # fmt: skip
            if cert.passed:
                return _Reduced(K, cert, lam, tried)
            last = (K, cert)
    if last is None:
        key = "weights.target" if inputs.target is None else inputs.target.key("gamma_eff")
        key = key.rsplit(".", 1)[0]
        raise DesignError(
            f"hinf design for the box Θ1 ∈ {list(inputs.box.theta1)}, Θ2/Θ1 ∈ "
            f"{list(inputs.box.ratio)} failed its certificate: with the learning target "
            f"{inputs.target.to_dict() if inputs.target else None}, every instantaneous "
            f"gain left by the shares λ in {list(DYNAMIC_SHARES)} of the synthesised "
            f"dynamics (and {list(INTEGRAL_SHARES)} of its integral gain) is off the target "
            f"or unstable on the box; widen {key} or narrow the box"
        )
    return _Reduced(*last, float("nan"), tried)


def _design_hinf(inputs: DesignInputs, samples: np.ndarray, cover: CoverFit) -> ControllerDesign:
    """The dynamic H∞ design (paper Sec. 4.2): the generalized plant at the box's nominal
    (:func:`cdqn.control.hinf.generalized_plant`), the γ-bisection
    ``min_K γ s.t. ‖F_l(P, K)‖_∞ < γ``, balanced reduction to the lowest order whose
    candidate on the learning target passes the certificate (:func:`_reduce_on_target`)."""
    syn = inputs.synthesis
    weights = _hinf_weight_set(inputs, cover)
    reg = _reg(syn)
    P = generalized_plant(*inputs.box.nominal, inputs.discount, weights, reg, plant=syn["plant"])
    res = hinf_bisection(P, rel_tol=float(syn["gamma_tol"]))
    K_full = ControllerMatrices(
        res.controller.A, res.controller.B, res.controller.C, res.controller.D
    )
    red = hankel(K_full)
    threshold = float(syn["hsv_threshold"])
    order0 = min(max(red.order_for(threshold), red.n_unstable), K_full.nstates)
    kept = _reduce_on_target(K_full, order0, inputs, samples)
    K = kept.K
    omega = np.logspace(-3, 6, 300)
    sv = sigma(lft_closed_loop(P, StateSpaceMatrices(K.A, K.B, K.C, K.D)), omega)
    details = {
        "full_order": K_full.nstates,
        "order": K.nstates,
        "hsv": red.hsv.tolist(),
        "hsv_threshold": threshold,
        "orders_tried": kept.tried,
        "dynamic_share": kept.share,
        "gamma_full_order": res.gamma,
        "gamma_reduced_grid": float(sv[:, 0].max()),
        "sb10ad_calls": res.iterations,
        "plant": syn["plant"],
        "plant_states": P.sys.nstates,
        "regularisation": asdict(reg),
        "w_delta": float(inputs.weights["w_delta"]),
        "controller_poles": [[float(z.real), float(z.imag)] for z in np.linalg.eigvals(K.A)]
        if K.nstates
        else [],
    }
    cover_w = weights.w_cover
    return ControllerDesign(
        kind="hinf",
        controller=K,
        gamma=res.gamma,
        box=inputs.box,
        discount=inputs.discount,
        certificate=kept.certificate,
        samples=samples,
        cover=cover,
        details=details,
        sigma_omega=omega,
        sigma=np.column_stack([sv[:, 0], sv[:, -1]]),
        weights=[
            weights.w_p,
            weights.w_u,
            weights.w_r,
            weights.w_qhat,
            SisoWeight(cover_w.num, cover_w.den, "W_Δ·w_cover"),
        ],
    )


DYNAMIC_SHARES = (1.0, 0.5, 0.25, 0.1, 0.05, 0.02, 0.01, 0.005, 0.002, 0.001, 1e-4, 0.0)
"""Shares λ of the synthesised dynamics tried, largest first (:func:`_dc_on_target`); at 0
the controller is the static gain of the target's centre with the synthesised integral gain."""
INTEGRAL_SHARES = (1.0, 0.1, 0.01, 0.001)
"""Shares of the synthesised DC integral gain tried, largest first (:func:`_dc_on_target`)."""


def _dc_on_target(
    K: ControllerMatrices, inputs: DesignInputs
) -> list[tuple[ControllerMatrices, float]]:
    """Candidates ``(K_λ, λ)`` that keep the learning target (:mod:`cdqn.control.target`):

    .. math::  K_\lambda(s) = K_t + \lambda\,(K(s) - K(0)),

    with ``K_t`` the static gain of the target's centre (its integral gain on ``x_e``, which
    the target leaves free, ``K(0)``'s scaled by a share in :data:`INTEGRAL_SHARES`, largest
    first): its DC gain is ``K_t`` exactly, and ``λ`` scales the synthesised dynamics around
    it (``A`` and ``B`` unchanged, ``C_λ = λC``, ``D_λ = K_t + λ(D − K(0))``).  A training step
    applies the controller's instantaneous gain ``K_λ(∞) = D_λ`` while Θ1, Θ2 change from step
    to step, so a candidate is kept only when ``D_λ`` keeps the learning target too and is itself a
    stabilising static gain over the box (continuous time and at Δt = α), besides the
    certificate of ``K_λ``; λ runs over :data:`DYNAMIC_SHARES`.  (Measured: with only the DC
    gain on target, the CartPole designs' instantaneous gains had 1 + k1 < 0 or γ_eff ≈ −13
    and diverged within 60 episodes on every seed, certificate or not.)  Without a target:
    ``[(K, 1)]``."""
    if inputs.target is None:
        return [(K, 1.0)]
    dc = dc_gain(K)
    if not np.all(np.isfinite(dc)):
        raise DesignError(
            "hinf design: the controller has an integrator (singular A), so its DC gain cannot "
            f"be placed in the learning target {inputs.target.to_dict()}"
        )
    k1, k2 = inputs.target.gains(*inputs.target.centre(), inputs.discount)
    D = np.asarray(K.D, float).reshape(3)
    out = []
    for integral in INTEGRAL_SHARES:
        K_t = np.array([integral * dc[0], -k1, -k2])
        for lam in DYNAMIC_SHARES:
            D_lam = (K_t + lam * (D - dc)).reshape(1, 3)
            out.append((ControllerMatrices(K.A, K.B, lam * K.C, D_lam), lam))
    return out


def _instantaneous_gain_stable(
    K: ControllerMatrices, inputs: DesignInputs, samples: np.ndarray
) -> bool:
    """Whether ``K(∞) = D`` alone, as the static gain ``u = D [x_e, Q1, Q2]``, keeps the
    learning target and is stable over the box (:func:`_dc_on_target`)."""
    k3, mk1, mk2 = np.asarray(K.D, float).reshape(3)
    if -mk1 <= -1.0 or inputs.target is None:
        return False
    if inputs.target.distance(-mk1, -mk2, inputs.discount) > 1e-9:
        return False
    return _certify(ControllerMatrices.static(-mk1, -mk2, k3), inputs, samples).passed


def _design_hinf_f(inputs: DesignInputs, samples: np.ndarray, cover: CoverFit) -> ControllerDesign:
    syn = inputs.synthesis
    ws = _weight_set(inputs.weights, "")
    noise = (float(syn["noise"][0]), float(syn["noise"][1]))
    weights = FixedStructureWeights(ws["w_p"], ws["w_u"], ws["w_r"], ws["w_qhat"], noise)
    if syn.get("start") is not None:
        first = tuple(float(v) for v in syn["start"])
        start_source = "synthesis.start"
    else:
        try:
            first = h2_gains_plant(
                *inputs.box.nominal,
                inputs.discount,
                np.asarray(inputs.h2["w_x"]),
                float(inputs.h2["w_c"]),
                syn["plant"],
            )
        except LQRError as err:
            raise DesignError(f"fixed-structure design: no H2 start at the nominal: {err}") from err
        start_source = "H2 gains at the nominal"
    starts = default_starts(
        inputs.box.ratio[1],
        inputs.discount,
        first,
        int(syn["restarts"]),
        int(syn["seed"]),
        syn["plant"],
        inputs.target,
    )
    res = tune_fixed_structure(
        samples,
        inputs.discount,
        weights,
        starts,
        margin=float(syn["decay"]),
        lr=inputs.lr,
        plant=syn["plant"],
        target=inputs.target,
    )
    K = ControllerMatrices.static(*res.gains)
    cert = _certify(K, inputs, samples)
    omega = np.logspace(-3, 6, 300)
    nominal = PerformanceLoops(
        np.asarray([inputs.box.nominal]), inputs.discount, weights, omega, syn["plant"]
    )
    A, B, C, D = nominal.matrices(res.gains)
    sv = sigma(StateSpaceMatrices(A[0], B[0], C[0], D), omega)
    details = {
        "start": [float(v) for v in res.start],
        "start_source": start_source,
        "start_objective": res.start_objective,
        "objective": res.objective,
        "starts_tried": res.starts_tried,
        "decay": float(syn["decay"]),
        "noise": list(noise),
        "plant": syn["plant"],
    }
    return ControllerDesign(
        kind="hinf_f",
        controller=K,
        gamma=res.worst_hinf,
        box=inputs.box,
        discount=inputs.discount,
        certificate=cert,
        samples=samples,
        gains=res.gains,
        cover=cover,
        details=details,
        sigma_omega=omega,
        sigma=np.column_stack([sv[:, 0], sv[:, -1]]),
        weights=[ws["w_p"], ws["w_u"], ws["w_r"], ws["w_qhat"]],
    )


def design_controller(inputs: DesignInputs) -> ControllerDesign:
    """Synthesise and certify (module docstring); raises :class:`DesignError` with the
    reason when no certified controller results."""
    t0 = time.perf_counter()
    syn = inputs.synthesis
    if inputs.kind not in KINDS:
        raise DesignError(f"design kind {inputs.kind!r}: allowed {', '.join(KINDS)}")
    check_plant(syn["plant"])
    _check_discrete_feasible(inputs)
    if inputs.target is not None:
        check_target(inputs.target, inputs.box)
    samples = inputs.box.sample(int(syn["samples"]), int(syn["seed"]))
    cover = fit_cover(
        samples,
        inputs.box.nominal,
        inputs.discount,
        (float(syn["band"][0]), float(syn["band"][1])),
        int(syn["cover_order"]),
        plant=syn["plant"],
    )
    if inputs.kind == "hinf":
        design = _design_hinf(inputs, samples, cover)
    else:
        design = _design_hinf_f(inputs, samples, cover)
    design.seconds = time.perf_counter() - t0
    design.key = inputs.key()
    design.learning = learning_target(design.controller, inputs.discount, inputs.box, inputs.lr)
    design.learning["target"] = None if inputs.target is None else inputs.target.to_dict()
    if not design.certificate.passed:
        raise DesignError(
            f"{inputs.kind} design for the box Θ1 ∈ {list(inputs.box.theta1)}, Θ2/Θ1 ∈ "
            f"{list(inputs.box.ratio)} failed its certificate: {design.certificate.reason()}"
        )
    return design


def _check_discrete_feasible(inputs: DesignInputs) -> None:
    """A box no controller can stabilise at Δt = α, on the paper's plant: the fast Q1 mode of
    any loop that is stable in continuous time has ``Θ1(1+k1) > γΘ2``, i.e.
    ``α Θ1 (1+k1) ≥ α γ ρ Θ1``; an explicit-Euler step is stable only when this is < 2 at
    every point.  The gradient-flow plant has no such bound: its fast mode
    ``−(1+k1)Θ1 + (γ−k2)Θ2`` can be made small over the whole box (e.g. ``k2 = γ``)."""
    if inputs.synthesis["plant"] != "paper":
        return
    t1_hi, r_hi = inputs.box.theta1[1], inputs.box.ratio[1]
    bound = inputs.lr * inputs.discount * r_hi * t1_hi
    if bound >= 2.0:
        raise DesignError(
            f"infeasible NTK box: α·γ·ρ_max·Θ1_max = {bound:.3g} >= 2, so no controller keeps "
            f"the SGD steps (explicit Euler at Δt = α = {inputs.lr:g}) stable at Θ1 = {t1_hi:g},"
            f" Θ2/Θ1 = {r_hi:g}; lower the learning rate or narrow the box"
        )


# ----------------------------------------------------------------------------- artefacts


def report(design: ControllerDesign) -> str:
    """Human-readable design report."""
    c = design.certificate
    plant = c.plant
    lines = [
        f"controller: {design.kind} (key {design.key})",
        f"learning plant: {plant} (B_u = "
        + (
            "[Θ1, Θ2]: u moves Q1 and Q2 as the training step does)"
            if plant == "gradient_flow"
            else "[Θ1, 0]: the paper's Eq. controlled_Q)"
        ),
        f"NTK box ({design.box.source}): Θ1 ∈ {list(design.box.theta1)}, Θ2/Θ1 ∈ "
        f"{list(design.box.ratio)}, nominal (Θ1, Θ2) = "
        f"({design.box.nominal[0]:.4g}, {design.box.nominal[1]:.4g}), γ_discount = "
        f"{design.discount}",
    ]
    for w in design.weights:
        lines.append(f"  weight {w.name}: num {list(w.num)} / den {list(w.den)}")
    if design.cover is not None:
        cw = design.cover.weight
        lines.append(
            f"cover (band {list(design.cover.band)} rad/s, order {design.cover.order}): "
            f"num {[float(f'{v:.6g}') for v in cw.num]} / den "
            f"{[float(f'{v:.6g}') for v in cw.den]}, min |w|/bound = {design.cover.margin:.4f}"
        )
    if design.kind == "hinf":
        det = design.details
        lines.append(
            f"achieved γ = {design.gamma:.6g} (full order {det['full_order']}, "
            f"{det['sb10ad_calls']} SB10AD calls); reduced to order {det['order']} "
            f"(HSV threshold {det['hsv_threshold']:g}); grid sup of the reduced loop "
            f"{det['gamma_reduced_grid']:.6g}"
        )
        lines.append(f"  A = {np.array2string(design.controller.A, precision=5)}")
        lines.append(f"  B = {np.array2string(design.controller.B, precision=5)}")
        lines.append(f"  C = {np.array2string(design.controller.C, precision=5)}")
        lines.append(f"  D = {np.array2string(design.controller.D, precision=5)}")
    else:
        k1, k2, k3 = design.gains or (0.0, 0.0, 0.0)
        lines.append(
            f"gains (k1, k2, k3) = ({k1:.6g}, {k2:.6g}, {k3:.6g}); worst-case H∞ over samples "
            f"= {design.gamma:.6g} (start {design.details['start_source']}: "
            f"{[round(v, 6) for v in design.details['start']]})"
        )
    lt = design.learning
    if lt:
        lines.append(
            f"learning target kept{' at DC' if design.kind == 'hinf' else ''}: γ_eff = "
            f"{lt['gamma_eff']:.6g}, 1 + k1 = {lt['step_scale']:.6g} (target {lt.get('target')}); "
            f"largest α(1 + k1)Θ1 over the box = {lt['max_step_gain']:.4g}"
        )
    lines.append(
        f"certificate: {'PASSED' if c.passed else 'FAILED'} on {c.n_points} points; stable share "
        f"{100 * c.share_stable:.1f}% (grid {100 * c.share_stable_grid:.1f}%); worst pole Re λ = "
        f"{c.worst_pole:.6g} at ({c.worst_point[0]:.4g}, {c.worst_point[1]:.4g}); "
        f"Δt = α loop max |λ| = {c.worst_discrete_modulus:.9f}"
        + (
            " (minimal part: the structural zero of Θ2·Q1 − Θ1·Q2 removed)"
            if plant == "gradient_flow"
            else ""
        )
    )
    lines.append(f"time: {design.seconds:.2f} s")
    return "\n".join(lines)


def write_artifacts(design: ControllerDesign, folder: Path) -> None:
    """controller.json, report.txt, closed_loop_sv.csv and the PNG plots into ``folder``."""
    from cdqn.control import plots

    folder.mkdir(parents=True, exist_ok=True)
    (folder / "controller.json").write_text(json.dumps(design.to_json(), indent=2))
    (folder / "report.txt").write_text(report(design) + "\n")
    rows = np.column_stack([design.sigma_omega, design.sigma])
    np.savetxt(
        folder / "closed_loop_sv.csv",
        rows,
        delimiter=",",
        header="omega,sigma_max,sigma_min",
        comments="",
    )
    omega = np.logspace(-3, 6, 300)
    plots.plot_weights(design.weights, omega, folder / "weights_bode.png")
    if design.cover is not None:
        cv = design.cover
        plots.plot_cover(cv.omega, cv.sample_errors, cv.weight, cv.band, folder / "cover.png")
    plots.plot_sigma(
        design.sigma_omega,
        design.sigma,
        design.gamma,
        f"Closed loop at the nominal point ({design.kind})",
        folder / "closed_loop_sv.png",
    )
    unstable = np.asarray(design.certificate.unstable_points).reshape(-1, 2)
    plots.plot_box(design.box, design.samples, folder / "ntk_box.png", unstable=unstable)


def cache_root(cfg: SynthesisConfig) -> Path:
    return Path(cfg.cache_dir).expanduser()


def load_or_design(
    inputs: DesignInputs, cache_dir: Path | None
) -> tuple[dict[str, Any], Path, ControllerDesign | None]:
    """The design record and its artefact folder, from the cache when present.

    Returns ``(controller.json as dict, folder, design or None when it came from cache)``.
    Only certified designs are cached.
    """
    key = inputs.key()
    if cache_dir is not None:
        entry = cache_dir / key
        record = entry / "controller.json"
        if record.is_file():
            return json.loads(record.read_text()), entry, None
    design = design_controller(inputs)
    if cache_dir is not None:
        cache_dir.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{key}-", dir=cache_dir))
        write_artifacts(design, tmp)
        entry = cache_dir / key
        try:
            tmp.rename(entry)
        except OSError:  # written meanwhile by a parallel run: keep theirs
            shutil.rmtree(tmp, ignore_errors=True)
        return json.loads((entry / "controller.json").read_text()), entry, design
    tmp = Path(tempfile.mkdtemp(prefix=f"cdqn-design-{key}-"))
    write_artifacts(design, tmp)
    return design.to_json(), tmp, design


def runtime_from_record(record: dict[str, Any], lr: float, cfg: ControllerConfig):
    """The runtime controller of a controller.json record."""
    D = np.asarray(record["D"], float).reshape(1, 3)
    if not record["A"]:
        k3, mk1, mk2 = D[0]
        return StaticGain(-mk1, -mk2, k3)
    return StateSpace(
        np.asarray(record["A"], float),
        np.asarray(record["B"], float),
        np.asarray(record["C"], float),
        D,
        lr,
        cfg.discretization,
        cfg.reset_state,
    )


def synthesized_controller(
    cfg: ControllerConfig,
    weights: WeightsConfig,
    discount: float,
    lr: float,
    box: NTKBox | None = None,
) -> ControllerSetup:
    """The certified synthesised controller of a run (``controller.design=synthesize``);
    ``box`` overrides the config box (a measured one)."""
    inputs = design_inputs(cfg, weights, discount, lr, box)
    cache_dir = cache_root(cfg.synthesis) if cfg.synthesis.cache else None
    record, folder, _ = load_or_design(inputs, cache_dir)
    ctrl = runtime_from_record(record, lr, cfg)
    return ControllerSetup(ctrl, source="synthesized", design=record, artifacts=folder)
