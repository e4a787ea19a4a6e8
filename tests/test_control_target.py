"""The learning target (effective discount γ_eff, step scale 1 + k1) as a design input: every
synthesised controller keeps it, a target the box cannot hold is refused by name."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from cdqn.config import Config
from cdqn.control.certificate import ControllerMatrices
from cdqn.control.design import box_from_config, design_inputs
from cdqn.control.errors import DesignError
from cdqn.control.factory import make_controller
from cdqn.control.h2 import scheduled_gains
from cdqn.control.synthesis import load_or_design
from cdqn.control.target import TargetBox, dc_gain
from tests.conftest import compose_config

FAST = [
    "controller.synthesis.samples=40",
    "controller.synthesis.restarts=1",
    "controller.synthesis.grid=[9,9]",
]
TARGET = ["weights.target.gamma_eff=[-0.9,-0.5]", "weights.target.step_scale=[0.5,0.9]"]
"""A target unlike every shipped one, so that keeping it is the design's doing."""


def _conf(kind: str, extra: list[str]) -> Config:
    cfg = compose_config(["env=cartpole", f"controller={kind}", *FAST, *TARGET, *extra])
    return OmegaConf.to_object(cfg)


def _inside(k1: float, k2: float, discount: float = 1.0) -> bool:
    scale = 1.0 + k1
    g_eff = (discount - k2) / scale
    return -0.9 - 1e-9 <= g_eff <= -0.5 + 1e-9 and 0.5 - 1e-9 <= scale <= 0.9 + 1e-9


def test_projection_moves_gains_into_the_target_and_keeps_those_inside() -> None:
    target = TargetBox((-0.9, -0.5), (0.5, 0.9))
    assert target.project(-0.3, 1.49, 1.0) == pytest.approx((-0.3, 1.49))  # inside: kept
    for k1, k2 in [(49.0, 0.998), (0.0, 0.0), (-0.95, 5.0), (-3.0, 1.0), (2.0, -7.0)]:
        p1, p2 = target.project(k1, k2, 1.0)
        assert _inside(p1, p2)
        assert target.distance(p1, p2, 1.0) == pytest.approx(0.0, abs=1e-12)
    assert target.distance(49.0, 0.998, 1.0) > 0


@pytest.mark.parametrize("kind", ["hinf_f", "hinf"])
def test_synthesised_designs_keep_the_learning_target(kind: str, tmp_path: Path) -> None:
    conf = _conf(kind, [])
    inputs = design_inputs(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
    record, folder, _ = load_or_design(inputs, tmp_path)
    assert record["certificate"]["passed"]
    lt = record["learning_target"]
    assert lt["target"] == {"gamma_eff": [-0.9, -0.5], "step_scale": [0.5, 0.9]}
    n = len(record["A"])
    K = ControllerMatrices(
        np.asarray(record["A"], float).reshape(n, n),
        np.asarray(record["B"], float).reshape(n, 3),
        np.asarray(record["C"], float).reshape(1, n),
        np.asarray(record["D"], float).reshape(1, 3),
    )
    k3, mk1, mk2 = dc_gain(K)
    assert _inside(-mk1, -mk2)
    assert lt["gamma_eff"] == pytest.approx((1.0 + mk2) / (1.0 - mk1))
    assert lt["step_scale"] == pytest.approx(1.0 - mk1)
    assert lt["max_step_gain"] == pytest.approx(conf.train.lr * (1.0 - mk1) * 800.0)
    report = (folder / "report.txt").read_text()
    assert "learning target kept" in report and "largest α(1 + k1)Θ1" in report


def test_gain_scheduled_h2_keeps_the_target_at_every_point_and_is_certified() -> None:
    conf = _conf("h2", [])
    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
    assert setup.design["certificate"]["passed"]
    box = box_from_config(conf.weights.theta_bounds)
    pts = box.grid(7, 7)
    gains = scheduled_gains(
        pts, 1.0, np.asarray(conf.weights.h2.w_x), conf.weights.h2.w_c, True,
        TargetBox.of(conf.weights.target).array(),
    )  # fmt: skip
    assert all(_inside(k1, k2) for k1, k2, _ in gains)
    lo, hi = setup.design["learning_target"]["gamma_eff"]
    assert -0.9 - 1e-9 <= lo <= hi <= -0.5 + 1e-9
    # the runtime controller applies the same gains
    ctrl = setup.controller
    ctrl.step(0.0, 0.0, 0.0, *pts[3])
    assert ctrl.gains == pytest.approx(tuple(gains[3]))


@pytest.mark.parametrize("kind", ["hinf_f", "hinf", "h2"])
def test_an_expansive_effective_discount_is_refused(kind: str) -> None:
    """|γ_eff| > 1: the effective Bellman operator is no contraction."""
    conf = _conf(kind, ["weights.target.gamma_eff=[-3.0,-2.5]", "controller.synthesis.cache=false"])
    with pytest.raises(DesignError, match=r"weights\.target\.gamma_eff=\[-3\.0, -2\.5\]: need -1"):
        make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)


@pytest.mark.parametrize("kind", ["hinf_f", "hinf", "h2"])
def test_a_target_the_box_cannot_hold_is_refused_by_name(kind: str) -> None:
    """CartPole's box has Θ2/Θ1 up to 1.2: no loop with γ_eff ≥ 1/1.2 is stable on it."""
    conf = _conf(kind, ["weights.target.gamma_eff=[0.9,0.99]", "controller.synthesis.cache=false"])
    with pytest.raises(DesignError, match=r"weights\.target\.gamma_eff=\[0\.9, 0\.99\]"):
        make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)


OWN = ["weights.controller_target.hinf_f.gamma_eff=[-0.8,-0.6]"]
"""``hinf_f``'s own effective-discount range; its step-scale range stays ``TARGET``'s."""


def test_a_controller_keeps_its_own_target_and_the_others_the_shared_one(tmp_path: Path) -> None:
    conf = _conf("hinf_f", OWN)
    own = TargetBox.of_controller(conf.weights, "hinf_f")
    assert (own.gamma_eff, own.step_scale) == ((-0.8, -0.6), (0.5, 0.9))
    for other in ("h2", "hinf"):
        shared = TargetBox.of_controller(conf.weights, other)
        assert (shared.gamma_eff, shared.step_scale) == ((-0.9, -0.5), (0.5, 0.9))
    inputs = design_inputs(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
    record, _, _ = load_or_design(inputs, tmp_path)
    assert record["certificate"]["passed"]
    lt = record["learning_target"]
    assert lt["target"] == {"gamma_eff": [-0.8, -0.6], "step_scale": [0.5, 0.9]}
    assert -0.8 - 1e-9 <= lt["gamma_eff"] <= -0.6 + 1e-9
    assert 0.5 - 1e-9 <= lt["step_scale"] <= 0.9 + 1e-9


@pytest.mark.parametrize("kind", ["hinf_f", "h2"])
def test_an_own_target_that_cannot_hold_is_refused_by_its_own_key(kind: str) -> None:
    conf = _conf(kind, [f"weights.controller_target.{kind}.gamma_eff=[-3.0,-2.5]",
                        "controller.synthesis.cache=false"])  # fmt: skip
    key = rf"weights\.controller_target\.{kind}\.gamma_eff=\[-3\.0, -2\.5\]: need -1"
    with pytest.raises(DesignError, match=key):
        make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)


def test_dynamic_design_instantaneous_gain_keeps_the_target(tmp_path: Path) -> None:
    """A step applies the controller's D while Θ changes every step: D keeps the target too."""
    conf = _conf("hinf", [])
    inputs = design_inputs(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
    record, _, _ = load_or_design(inputs, tmp_path)
    k3, mk1, mk2 = np.asarray(record["D"], float).reshape(3)
    assert _inside(-mk1, -mk2)
    assert 0.0 <= record["details"]["dynamic_share"] <= 1.0


def test_scheduled_h2_rho_cap_lowers_the_discount_only_where_the_ratio_is_large() -> None:
    """Acrobot's raw-observation box (Θ2/Θ1 up to 1.5) cannot hold γ_eff = 0.99 with static
    gains; the scheduled H2 caps γ_eff·ρ at 0.98 step by step and is certified."""
    extra = [
        "weights.target.gamma_eff=[0.99,0.99]",
        "weights.target.step_scale=[0.2,0.2]",
        "weights.theta_bounds.theta1=[200.0,3200.0]",
        "weights.theta_bounds.ratio=[0.55,1.5]",
    ]
    conf = OmegaConf.to_object(compose_config(["env=acrobot", "controller=h2", *FAST, *extra]))
    with pytest.raises(DesignError, match="weights.target.gamma_eff"):
        make_controller(conf.controller, conf.weights, 1.0, 5e-5)
    conf.weights.target.rho_cap = 0.98
    setup = make_controller(conf.controller, conf.weights, 1.0, 5e-5)
    assert setup.design["certificate"]["passed"]
    box = box_from_config(conf.weights.theta_bounds)
    pts = box.grid(9, 9)
    gains = scheduled_gains(pts, 1.0, np.asarray(conf.weights.h2.w_x), conf.weights.h2.w_c,
                            True, TargetBox.of(conf.weights.target).array())  # fmt: skip
    g_eff = (1.0 - gains[:, 1]) / (1.0 + gains[:, 0])
    rho = pts[:, 1] / pts[:, 0]
    assert np.all(g_eff * rho <= 0.98 + 1e-9)
    assert np.allclose(g_eff[rho <= 0.98 / 0.99], 0.99)


def test_scheduled_h2_keeps_one_learning_target_whatever_the_transition() -> None:
    """The scheduled H2's (γ_eff, 1 + k1) is one point of the target range, the same at a
    transition whose next greedy action repeats the action (ρ ≈ 1) and at one whose does not
    (ρ ≈ 0.3, outside the box): only k3 follows (Θ1, Θ2).  Projected per step, the LQR gains
    gave γ_eff = −1 at the first and −0.95 at the second."""
    conf = OmegaConf.to_object(compose_config(["env=cartpole", "controller=h2", *FAST]))
    conf.weights.target.gamma_eff = [-1.0, -0.95]
    setup = make_controller(conf.controller, conf.weights, 1.0, 5e-5)
    ctrl = setup.controller
    seen = []
    for theta1, rho in ((300.0, 1.0), (300.0, 0.3), (120.0, 1.15), (700.0, -0.2)):
        ctrl.step(0.01, 0.5, 0.4, theta1, rho * theta1)
        seen.append(ctrl.gains)
    k1, k2, k3 = np.array(seen).T
    assert np.ptp(k1) == 0.0 and np.ptp(k2) == 0.0
    assert np.ptp(k3) > 0.1
    lt = setup.design["learning_target"]
    assert lt["pinned"]["gamma_eff"][0] == lt["pinned"]["gamma_eff"][1]
    assert -1.0 <= (1.0 - k2[0]) / (1.0 + k1[0]) <= -0.95


def test_every_run_records_what_its_design_keeps(tracking_uri: str) -> None:
    from mlflow.tracking import MlflowClient

    from cdqn.training.run import run

    cfg = compose_config(["controller=hinf_f", *FAST, *TARGET, "network.width=16",
                          "train.episodes=1", "train.progress=false", "tracking.log_model=false",
                          f"tracking.uri={tracking_uri}"])  # fmt: skip
    result = run(cfg, progress=False)
    tags = MlflowClient(tracking_uri).get_run(result.run_id).data.tags
    assert -0.9 <= float(tags["design_gamma_eff"]) <= -0.5
    assert 0.5 <= float(tags["design_step_scale"]) <= 0.9
    assert float(tags["design_worst_pole"]) < 0
    assert 0 < float(tags["design_max_step_gain"]) < 2
