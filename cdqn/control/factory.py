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
