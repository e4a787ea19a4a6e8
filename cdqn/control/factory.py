"""Build the runtime controller of a run from its controller and weights configs."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cdqn.config import CONTROLLERS, ConfigError, ControllerConfig, WeightsConfig
from cdqn.control.runtime import (
    NoControl,
    RuntimeController,
    ScheduledLQR,
    StateSpace,
    StaticGain,
)


@dataclass
class ControllerSetup:
    """The runtime controller and the record of where its design came from."""

    controller: RuntimeController
    source: str
    """``paper`` (research-code values), ``synthesized`` or ``scheduled`` (per-step LQR)."""
    design: dict[str, Any] = field(default_factory=dict)
    """Design record, logged as ``design/controller.json`` (gains or matrices, bounds,
    certificate)."""
    artifacts: Path | None = None
    """A folder of further design artefacts (plots, tables), logged under ``design/``."""

    def tags(self) -> dict[str, str]:
        """What the design keeps, as run tags: ``design_gamma_eff`` and ``design_step_scale``
        (γ_eff and 1 + k1; DC values for ``hinf``; ``lo..hi`` over the box for ``h2``),
        ``design_max_step_gain`` (largest α(1 + k1)Θ1 over the box) and
        ``design_worst_pole`` (certificate); empty for designs without a learning target."""
        lt = self.design.get("learning_target")
        if not lt:
            return {}

        def fmt(v: Any) -> str:
            if isinstance(v, list | tuple):
                return f"{v[0]:.6g}..{v[1]:.6g}"
            return f"{v:.6g}"

        cert = self.design.get("certificate", {})
        out = {
            "design_gamma_eff": fmt(lt["gamma_eff"]),
            "design_step_scale": fmt(lt["step_scale"]),
            "design_max_step_gain": fmt(lt["max_step_gain"]),
        }
        if "worst_pole" in cert:
            out["design_worst_pole"] = fmt(cert["worst_pole"])
        return out


def make_controller(
    cfg: ControllerConfig,
    weights: WeightsConfig,
    discount: float,
    lr: float,
    box: Any = None,
) -> ControllerSetup:
    """Controller for ``cfg.name``; ``ddqn`` and ``none`` get :class:`NoControl`.

    ``box`` (a :class:`cdqn.control.box.NTKBox`, e.g. measured on the run's network) replaces
    ``weights.theta_bounds`` in a synthesised design."""
    name = cfg.name
    if name in ("none", "ddqn"):
        return ControllerSetup(NoControl(), source="none")
    if name == "h2":
        if cfg.design == "synthesize":
            return _scheduled_h2(cfg, weights, discount, lr, box)
        w_x, w_c = list(weights.h2.w_x), weights.h2.w_c
        ctrl = ScheduledLQR(discount, w_x, w_c, cfg.h2_gain_map)
        design = {"kind": "h2", "w_x": w_x, "w_c": w_c, "gain_map": cfg.h2_gain_map}
        return ControllerSetup(ctrl, source="scheduled", design=design)
    if cfg.design == "paper":
        return _paper_controller(cfg, weights, lr)
    if cfg.design == "synthesize":
        from cdqn.control.design import synthesized_controller  # noqa: PLC0415

        return synthesized_controller(cfg, weights, discount, lr, box)
    raise ConfigError(f"controller.design={cfg.design!r}: allowed paper, synthesize")


def _scheduled_h2(
    cfg: ControllerConfig, weights: WeightsConfig, discount: float, lr: float, box: Any
) -> ControllerSetup:
    """The gain-scheduled H2 with the learning target of ``weights.target``, certified over
    the NTK box frozen at every sample and grid point (:func:`cdqn.control.h2.certify_scheduled`);
    :class:`DesignError` when the certificate fails."""
    from cdqn.control.design import box_from_config  # noqa: PLC0415
    from cdqn.control.errors import DesignError  # noqa: PLC0415
    from cdqn.control.h2 import certify_scheduled  # noqa: PLC0415
    from cdqn.control.target import TargetBox, check_target  # noqa: PLC0415

    w_x, w_c = list(weights.h2.w_x), weights.h2.w_c
    target = TargetBox.of(weights.target)
    ntk_box = box if box is not None else box_from_config(weights.theta_bounds)
    check_target(target, ntk_box, scheduled=True)
    syn = cfg.synthesis
    research = cfg.h2_gain_map == "research"
    cert, rows = certify_scheduled(
        ntk_box, discount, np.asarray(w_x), w_c, research, target.array(), lr, syn.samples,
        (int(syn.grid[0]), int(syn.grid[1])), syn.seed, syn.margin, syn.plant,
    )  # fmt: skip
    if not cert.passed:
        raise DesignError(
            f"h2 design with the learning target {target.to_dict()} over the box Θ1 ∈ "
            f"{list(ntk_box.theta1)}, Θ2/Θ1 ∈ {list(ntk_box.ratio)} failed its certificate: "
            f"{cert.reason()}"
        )
    k1, k2, k3 = rows[:, 2], rows[:, 3], rows[:, 4]
    scale = 1.0 + k1
    g_eff = (discount - k2) / scale
    learning = {
        "gamma_eff": [float(g_eff.min()), float(g_eff.max())],
        "step_scale": [float(scale.min()), float(scale.max())],
        "k3": [float(k3.min()), float(k3.max())],
        "max_step_gain": float(np.max(lr * scale * rows[:, 0])),
        "target": target.to_dict(),
    }
    design = {
        "kind": "h2",
        "w_x": w_x,
        "w_c": w_c,
        "gain_map": cfg.h2_gain_map,
        "theta_bounds": {"theta1": list(ntk_box.theta1), "ratio": list(ntk_box.ratio)},
        "box_source": ntk_box.source,
        "discount": discount,
        "certificate": cert.to_dict(),
        "learning_target": learning,
        "source": "synthesized",
    }
    ctrl = ScheduledLQR(discount, w_x, w_c, cfg.h2_gain_map, target.array())
    return ControllerSetup(ctrl, source="scheduled", design=design)


def _paper_controller(cfg: ControllerConfig, weights: WeightsConfig, lr: float) -> ControllerSetup:
    paper = weights.paper
    if cfg.name == "hinf_f":
        if paper.hinf_f is None:
            raise ConfigError(
                f"controller.design=paper: weights={weights.name!r} has no research-code "
                "fixed-structure gains (weights.paper.hinf_f); use controller.design=synthesize"
            )
        k1, k2, k3 = (float(k) for k in paper.hinf_f)
        design = {"kind": "hinf_f", "gains": [k1, k2, k3]}
        return ControllerSetup(StaticGain(k1, k2, k3), source="paper", design=design)
    if cfg.name == "hinf":
        if paper.hinf_A is None or paper.hinf_B is None or paper.hinf_C is None:
            raise ConfigError(
                f"controller.design=paper: weights={weights.name!r} has no research-code "
                "dynamic controller (weights.paper.hinf_A/B/C); use controller.design=synthesize"
            )
        A, B, C = (np.asarray(m, dtype=float) for m in (paper.hinf_A, paper.hinf_B, paper.hinf_C))
        ctrl = StateSpace(A, B, C, None, lr, cfg.discretization, cfg.reset_state)
        design = {"kind": "hinf", "A": A.tolist(), "B": B.tolist(), "C": C.tolist(), "D": []}
        return ControllerSetup(ctrl, source="paper", design=design)
    raise ConfigError(f"controller.name={cfg.name!r}: allowed {', '.join(CONTROLLERS)}")
