"""Build the runtime controller of a run from its controller and weights configs: the
research-code designs, the gain-scheduled H2, or a synthesised design
(:mod:`cdqn.control.design`, read from its cache or made by :mod:`cdqn.control.synthesis`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from cdqn.config import CONTROLLERS, ConfigError, ControllerConfig, WeightsConfig
from cdqn.control.errors import DesignError
from cdqn.control.runtime import NoControl, ScheduledLQR, StateSpace, StaticGain
from cdqn.control.setup import ControllerSetup
from cdqn.control.target import TargetBox, check_target


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
        return synthesized_controller(cfg, weights, discount, lr, box)
    raise ConfigError(f"controller.design={cfg.design!r}: allowed paper, synthesize")


def synthesized_controller(cfg: ControllerConfig, weights: WeightsConfig, discount: float,
                           lr: float, box: Any = None) -> ControllerSetup:  # fmt: skip
    """The certified synthesised controller of a run (``controller.design=synthesize``);
    ``box`` overrides the config box (a measured one).  A design the cache holds is read
    back; only a new one loads python-control and the synthesis (seconds to import)."""
    from cdqn.control.design import (
        cache_root,
        cached_design,
        design_inputs,
        runtime_from_record,
        with_record_source,
    )

    inputs = design_inputs(cfg, weights, discount, lr, box)
    cache_dir = cache_root(cfg.synthesis) if cfg.synthesis.cache else None
    found = cached_design(inputs, cache_dir)
    if found is None:
        from cdqn.control.synthesis import load_or_design

        record, folder, _ = load_or_design(inputs, cache_dir)
    else:
        record, folder = found
    record = with_record_source(record, inputs.box.source)  # this run's, not the cache's
    ctrl = runtime_from_record(record, lr, cfg)
    return ControllerSetup(ctrl, source="synthesized", design=record, artifacts=folder)


def _scheduled_h2(
    cfg: ControllerConfig, weights: WeightsConfig, discount: float, lr: float, box: Any
) -> ControllerSetup:
    """The gain-scheduled H2 with its learning target (:meth:`TargetBox.of_controller`),
    certified over the NTK box frozen at every sample and grid point
    (:func:`cdqn.control.h2.certify_scheduled`); :class:`DesignError` when the certificate fails."""
    from cdqn.control.design import box_from_config
    from cdqn.control.h2 import certify_scheduled

    w_x, w_c = list(weights.h2.w_x), weights.h2.w_c
    asked = TargetBox.of_controller(weights, cfg.name)
    ntk_box = box if box is not None else box_from_config(weights.theta_bounds)
    check_target(asked, ntk_box, scheduled=True)
    syn = cfg.synthesis
    research = cfg.h2_gain_map == "research"
    target = _pinned_target(asked, ntk_box, discount, np.asarray(w_x), w_c, research)
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
        "target": asked.to_dict(),
        "pinned": target.to_dict(),
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


def _pinned_target(
    target: TargetBox, box: Any, discount: float, w_x: np.ndarray, w_c: float, research: bool
) -> TargetBox:
    """The learning target of the gain-scheduled H2 pinned to one point: the LQR gains at the
    box's nominal (Θ1, Θ2), moved into ``target`` (:func:`cdqn.control.kernels.project_target`),
    give ``(γ_eff*, 1 + k1*)``; every step then uses them, and only ``k3`` (and the optional
    ``rho_cap``) follows the step's (Θ1, Θ2).

    Why a point: the LQR gains move with ρ = Θ2/Θ1, and ρ jumps between transitions whose next
    greedy action repeats the action (Θ2 holds the ``[a == b]`` term of the NTK) and those whose
    does not; a γ_eff projected per step then takes different values on the two kinds, so the
    Bellman equation being learned depends on the transition (docs/research/learning.md, "One
    learning target per design")."""
    from cdqn.control.h2 import scheduled_gains

    k1, k2, _ = scheduled_gains(
        np.array([box.nominal], dtype=float), discount, w_x, w_c, research, target.array()
    )[0]
    if not (np.isfinite(k1) and np.isfinite(k2)):
        raise DesignError(
            f"h2 design: no LQR gain at the nominal point (Θ1, Θ2) = {tuple(box.nominal)} "
            "to pin the learning target; change weights.h2 or weights.theta_bounds.nominal"
        )
    s = 1.0 + float(k1)
    g = (discount - float(k2)) / s
    return TargetBox((g, g), (s, s), target.rho_cap)


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
