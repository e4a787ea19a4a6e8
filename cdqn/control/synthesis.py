"""Controller synthesis end to end: NTK box → plant samples → cover → H∞ design →
reduction → certificate → artefacts, cached by the hash of the design inputs
(:func:`load_or_design`; the records and the cache: :mod:`cdqn.control.design`).

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
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from cdqn.control.certificate import Certificate, ControllerMatrices, certify
from cdqn.control.design import (
    KINDS,
    SIGMA_OMEGA,
    ControllerDesign,
    DesignInputs,
    cached_design,
    write_artifacts,
)
from cdqn.control.errors import DesignError
from cdqn.control.h2 import LQRError, h2_gains_plant
from cdqn.control.hinf import (
    HinfInfeasible,
    HinfWeightSet,
    Regularisation,
    StateSpaceMatrices,
    generalized_plant,
    hinf_bisection,
    lft_closed_loop,
    sigma,
)
from cdqn.control.plant import check_plant, gain_triple
from cdqn.control.reduction import hankel, truncate
from cdqn.control.structured import (
    FixedStructureWeights,
    PerformanceLoops,
    default_starts,
    tune_fixed_structure,
)
from cdqn.control.target import check_target, dc_gain, learning_target
from cdqn.control.uncertainty import CoverFit, fit_cover
from cdqn.control.weights import SisoWeight

BOUNDED_CORNERS = 100.0
"""Refit of a dynamic design whose free cover SB10AD refuses: the cover's poles and zeros
within two decades of ``synthesis.band``."""


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
    sv = sigma(lft_closed_loop(P, StateSpaceMatrices(K.A, K.B, K.C, K.D)), SIGMA_OMEGA)
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
    cover_w = SisoWeight(weights.w_cover.num, weights.w_cover.den, "W_Δ·w_cover")
    used = [weights.w_p, weights.w_u, weights.w_r, weights.w_qhat, cover_w]
    return _record("hinf", K, res.gamma, inputs, kept.certificate, samples, cover, details,
                   sv, used)  # fmt: skip


def _record(
    kind: str,
    K: ControllerMatrices,
    gamma: float,
    inputs: DesignInputs,
    certificate: Certificate,
    samples: np.ndarray,
    cover: CoverFit,
    details: dict[str, Any],
    sv: np.ndarray,
    weights: list[SisoWeight],
    gains: tuple[float, float, float] | None = None,
) -> ControllerDesign:
    """The record of a synthesised design; ``sv``: the singular values of its closed loop at
    the nominal point over :data:`SIGMA_OMEGA` (largest and smallest kept)."""
    return ControllerDesign(
        kind=kind,
        controller=K,
        gamma=gamma,
        box=inputs.box,
        discount=inputs.discount,
        certificate=certificate,
        samples=samples,
        gains=gains,
        cover=cover,
        details=details,
        sigma_omega=SIGMA_OMEGA.copy(),
        sigma=np.column_stack([sv[:, 0], sv[:, -1]]),
        weights=weights,
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
        first = gain_triple(syn["start"])
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
    nominal = PerformanceLoops(
        np.asarray([inputs.box.nominal]), inputs.discount, weights, SIGMA_OMEGA, syn["plant"]
    )
    A, B, C, D = nominal.matrices(res.gains)
    sv = sigma(StateSpaceMatrices(A[0], B[0], C[0], D), SIGMA_OMEGA)
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
    used = [ws["w_p"], ws["w_u"], ws["w_r"], ws["w_qhat"]]
    return _record("hinf_f", K, res.worst_hinf, inputs, cert, samples, cover, details, sv,
                   used, res.gains)  # fmt: skip


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
    cover = _cover(inputs, samples)
    if inputs.kind == "hinf":
        try:
            design = _design_hinf(inputs, samples, cover)
        except HinfInfeasible:
            # a free cover with a corner far below the band breaks SB10AD's assumption A3
            # (cdqn.control.uncertainty): refit within BOUNDED_CORNERS of the band
            design = _design_hinf(inputs, samples, _cover(inputs, samples, BOUNDED_CORNERS))
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


def _cover(inputs: DesignInputs, samples: np.ndarray, corners: float | None = None) -> CoverFit:
    """The uncertainty cover of the box's samples over ``synthesis.band``
    (:func:`cdqn.control.uncertainty.fit_cover`)."""
    syn = inputs.synthesis
    band = (float(syn["band"][0]), float(syn["band"][1]))
    return fit_cover(
        samples,
        inputs.box.nominal,
        inputs.discount,
        band,
        int(syn["cover_order"]),
        plant=syn["plant"],
        corners=corners,
    )


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


def load_or_design(
    inputs: DesignInputs, cache_dir: Path | None
) -> tuple[dict[str, Any], Path, ControllerDesign | None]:
    """The design record and its artefact folder, from the cache when present.

    Returns ``(controller.json as dict, folder, design or None when it came from cache)``.
    Only certified designs are cached.
    """
    key = inputs.key()
    found = cached_design(inputs, cache_dir)
    if found is not None:
        return found[0], found[1], None
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
