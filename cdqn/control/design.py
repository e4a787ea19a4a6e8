"""A controller design as cdqn keeps it: its inputs (:class:`DesignInputs`, hashed into the
cache key), the certified result (:class:`ControllerDesign`), its report and artefacts, the
cache of designs by key and the runtime controller of a stored record.  The synthesis
itself is :mod:`cdqn.control.synthesis`, loaded only when the cache has no design.

The continuous-time controller is stored with inputs ``[x_e, Q1, Q2]`` and output ``u`` in
cdqn's convention ``Q̇1 = Θ1 (r + γQ̂2 − Q1 + u)``; a static controller has empty ``A``,
``B``, ``C`` and ``D = [[k3, −k1, −k2]]``.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from cdqn.config import ControllerConfig, HinfWeights, SynthesisConfig, ThetaBounds, WeightsConfig
from cdqn.control.box import NTKBox
from cdqn.control.errors import DesignError
from cdqn.control.runtime import StateSpace, StaticGain
from cdqn.control.target import TargetBox

if TYPE_CHECKING:
    from cdqn.control.certificate import Certificate, ControllerMatrices
    from cdqn.control.uncertainty import CoverFit
    from cdqn.control.weights import SisoWeight

DESIGN_VERSION = 8
"""Bumped whenever the synthesis changes its results or its artefacts; part of the cache key.
A cache entry holds nothing of the environment it was first designed for: the box's source
(:attr:`NTKBox.source`) is not a design input, so the record and report leave it to their
reader (:func:`with_box_source`)."""
KINDS = ("hinf", "hinf_f")
"""Controllers that are synthesised (h2 is solved per step)."""


def box_from_config(tb: ThetaBounds) -> NTKBox:
    """The config box; ``nominal=None`` puts the nominal at (√(Θ1_lo·Θ1_hi), mid ratio); its
    source says where a tuning study measured it (``theta_bounds.measured_on``)."""
    t1 = (float(tb.theta1[0]), float(tb.theta1[1]))
    rho = (float(tb.ratio[0]), float(tb.ratio[1]))
    if tb.nominal is None:
        if t1[0] <= 0:
            return NTKBox(t1, rho, (0.0, 0.0))  # raises the box's own error
        t_nom = float(np.sqrt(t1[0] * t1[1]))
        nominal = (t_nom, t_nom * 0.5 * (rho[0] + rho[1]))
    else:
        nominal = (float(tb.nominal[0]), float(tb.nominal[1]))
    return NTKBox(t1, rho, nominal, f"measured on {tb.measured_on}" if tb.measured_on else "config")


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


SIGMA_OMEGA = np.logspace(-3, 6, 300)
"""Frequencies (rad/s) of a design's closed-loop singular values and weight plots."""


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


# ----------------------------------------------------------------------------- artefacts


BOX_LINE = "NTK box:"
"""How the report's line of the box begins; :func:`with_box_source` names the source there."""


def with_box_source(report_text: str, source: str) -> str:
    """A cached design's report with the source of the box it serves now (``config``,
    ``measured``, ``measured on <label>, seed <n>``): the same design serves every box of the
    same numbers, whichever environment it was measured on."""
    return report_text.replace(BOX_LINE, f"NTK box ({source}):", 1)


def with_record_source(record: dict[str, Any], source: str) -> dict[str, Any]:
    """A cached design's record (``controller.json``) with the source of the box it serves
    now as ``box_source`` (:func:`with_box_source` does the same for the report)."""
    return {**record, "box_source": source}


def report(design: ControllerDesign) -> str:
    """Human-readable design report (the box's line without its source: :data:`BOX_LINE`)."""
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
        f"{BOX_LINE} Θ1 ∈ {list(design.box.theta1)}, Θ2/Θ1 ∈ "
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
    plots.plot_weights(design.weights, SIGMA_OMEGA, folder / "weights_bode.png")
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


def cached_design(
    inputs: DesignInputs, cache_dir: Path | None
) -> tuple[dict[str, Any], Path] | None:
    """The cached design record of ``inputs`` (``controller.json`` as a dict) and its artefact
    folder, or None when ``cache_dir`` does not hold it (or is None: no cache)."""
    if cache_dir is None:
        return None
    entry = cache_dir / inputs.key()
    record = entry / "controller.json"
    if not record.is_file():
        return None
    return json.loads(record.read_text()), entry


def runtime_from_record(
    record: dict[str, Any], lr: float, cfg: ControllerConfig
) -> StaticGain | StateSpace:
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
