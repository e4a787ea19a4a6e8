"""Synthesis end to end with real python-control/slycot: certified designs, caching, the
fixed-structure search, and every error path with its message."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from cdqn.config import Config
from cdqn.control.box import NTKBox
from cdqn.control.certificate import ControllerMatrices, certify, max_real_poles
from cdqn.control.design import box_from_config, design_inputs, with_box_source
from cdqn.control.errors import DesignError
from cdqn.control.factory import make_controller, synthesized_controller
from cdqn.control.hinf import (
    HinfInfeasible,
    HinfWeightSet,
    Regularisation,
    generalized_plant,
    hinf_bisection,
)
from cdqn.control.runtime import StateSpace, StaticGain
from cdqn.control.structured import (
    FixedStructureWeights,
    PerformanceLoops,
    default_starts,
    tune_fixed_structure,
)
from cdqn.control.synthesis import (
    BOUNDED_CORNERS,
    _cover,
    _design_hinf,
    design_controller,
    load_or_design,
)
from cdqn.control.weights import SisoWeight
from cdqn.ntk_bounds import summarise
from tests.conftest import compose_config

FAST = [
    "controller.synthesis.samples=40",
    "controller.synthesis.restarts=1",
    "controller.synthesis.grid=[9,9]",
]
"""Settings that keep a fixed-structure design to a few seconds."""


def _conf(env: str, kind: str, extra: list[str] | None = None) -> Config:
    cfg = compose_config([f"env={env}", f"controller={kind}", *(extra or [])])
    return OmegaConf.to_object(cfg)


@pytest.fixture(scope="session")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One design cache for the test session: each design is synthesised once."""
    return tmp_path_factory.mktemp("design-cache")


def _design(cache: Path, env: str, kind: str, extra: list[str] | None = None):
    conf = _conf(env, kind, extra)
    inputs = design_inputs(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
    return load_or_design(inputs, cache), inputs


def test_dynamic_design_passes_certificate_and_is_cached(cache: Path) -> None:
    (record, folder, design), inputs = _design(cache, "mountaincar", "hinf")
    assert record["certificate"]["passed"] and record["certificate"]["share_stable"] == 1.0
    assert record["kind"] == "hinf" and record["gamma"] > 0
    A, B, C = (np.asarray(record[k]) for k in "ABC")
    n = A.shape[0]
    assert n >= 1 and B.shape == (n, 3) and C.shape == (1, n)
    box = _conf("mountaincar", "hinf").weights.theta_bounds  # the configured box, recorded
    assert record["theta_bounds"] == {"theta1": list(box.theta1), "ratio": list(box.ratio)}
    assert record["details"]["order"] <= record["details"]["full_order"]
    for name in (
        "controller.json",
        "report.txt",
        "closed_loop_sv.csv",
        "weights_bode.png",
        "cover.png",
        "closed_loop_sv.png",
        "ntk_box.png",
    ):
        assert (folder / name).is_file(), name
    header = (folder / "closed_loop_sv.csv").read_text().splitlines()[0]
    assert header == "omega,sigma_max,sigma_min"
    # second call: from the cache, same record
    again, folder2, design2 = load_or_design(inputs, cache)
    assert design2 is None and folder2 == folder and again == record
    # the certificate holds for the stored matrices themselves
    K = ControllerMatrices(A, B, C, np.asarray(record["D"]))
    box = NTKBox(
        tuple(record["theta_bounds"]["theta1"]),
        tuple(record["theta_bounds"]["ratio"]),
        tuple(record["nominal"]),
    )
    assert certify(K, box, box.sample(50, 1), (11, 11), 1.0, lr=inputs.lr).passed
    # and over the Θ1 that training reaches: the kernel grows as the weights move, on
    # Mountain car from the box's [35, 55] to ~3000 (docs/synthesis.md, "The kernel during
    # training")
    grown = NTKBox((box.theta1[0], 3500.0), box.ratio, box.nominal)
    assert certify(K, grown, grown.sample(50, 1), (25, 11), 1.0, lr=inputs.lr).passed


def test_training_uses_the_synthesised_controller(cache: Path) -> None:
    conf = _conf(
        "mountaincar",
        "hinf",
        ["controller.design=synthesize", f"controller.synthesis.cache_dir={cache}"],
    )
    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
    assert setup.source == "synthesized" and isinstance(setup.controller, StateSpace)
    assert setup.design["certificate"]["passed"]
    assert setup.artifacts is not None and (setup.artifacts / "cover.png").is_file()
    u = [setup.controller.step(0.01, 1.0, 1.0, 300.0, 300.0) for _ in range(3)]
    assert all(np.isfinite(u)) and any(v != 0.0 for v in u)


def test_a_cached_design_names_the_box_of_the_run_it_serves(cache: Path) -> None:
    """The same box measured on two environments is one cache entry; each run's record and
    report name its own environment, and the cached files name none."""
    base = ["controller.design=synthesize", f"controller.synthesis.cache_dir={cache}"]
    texts = []
    for label in ("EnvA-v0", "EnvB-v0"):
        conf = _conf("mountaincar", "hinf", [*base, f"weights.theta_bounds.measured_on={label}"])
        setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
        assert setup.design["box_source"] == f"measured on {label}"
        cached = (setup.artifacts / "report.txt").read_text()
        assert "EnvA" not in cached and "EnvB" not in cached
        assert "EnvA" not in json.dumps(
            json.loads((setup.artifacts / "controller.json").read_text())
        )
        texts.append(with_box_source(cached, setup.design["box_source"]))
    assert "NTK box (measured on EnvB-v0): Θ1 ∈" in texts[1] and "EnvA" not in texts[1]


def test_fixed_structure_design_passes_certificate(cache: Path) -> None:
    (record, _, _), _ = _design(cache, "mountaincar", "hinf_f", FAST)
    assert record["certificate"]["passed"]
    assert record["A"] == [] and record["B"] == [] and record["C"] == []
    k1, k2, k3 = record["gains"]
    assert record["D"] == [[k3, -k1, -k2]]
    conf = _conf("mountaincar", "hinf_f", [*FAST, f"controller.synthesis.cache_dir={cache}"])
    setup = synthesized_controller(conf.controller, conf.weights, 1.0, conf.train.lr)
    assert isinstance(setup.controller, StaticGain)
    assert (setup.controller.k1, setup.controller.k2, setup.controller.k3) == (k1, k2, k3)


def _fs_weights() -> FixedStructureWeights:
    return FixedStructureWeights(
        SisoWeight.make([1e-5], [0.1, 1.0], "w_p"),
        SisoWeight.make([0.001, 0.0], [1e-4, 0.101, 1.0], "w_u"),
        SisoWeight.make([1.0, 0.0], [2e-4, 0.201, 1.0], "w_r"),
        SisoWeight.make([1.0, 0.0], [2e-4, 0.201, 1.0], "w_qhat"),
    )


STABILISING = {"gradient_flow": (-0.379, 2.82, 0.1937), "paper": (0.379, -2.82, -0.1937)}
"""The research gains as published stabilise the gradient-flow plant; negated, the paper's."""


@pytest.mark.parametrize("plant", ["gradient_flow", "paper"])
def test_fixed_structure_result_no_worse_than_its_start(plant: str) -> None:
    box = NTKBox((200.0, 500.0), (0.8, 1.2), (316.0, 316.0))
    pts = box.sample(30, 0)
    start = STABILISING[plant]
    res = tune_fixed_structure(
        pts, 1.0, _fs_weights(), [start], margin=0.05, lr=5e-5, max_iter=150, plant=plant
    )
    loops = PerformanceLoops(pts, 1.0, _fs_weights(), np.logspace(-3, 6, 50), plant)
    assert res.worst_hinf <= float(np.max(loops.exact_norms(start))) + 1e-12
    assert res.objective <= res.start_objective
    K = ControllerMatrices.static(*res.gains)
    assert certify(K, box, pts, (7, 7), 1.0, 0.05, lr=5e-5, plant=plant).passed


@pytest.mark.parametrize("plant", ["gradient_flow", "paper"])
def test_fixed_structure_from_unstable_start_reaches_stability(plant: str) -> None:
    box = NTKBox((200.0, 500.0), (0.8, 1.2), (316.0, 316.0))
    pts = box.sample(20, 0)
    other = STABILISING["paper" if plant == "gradient_flow" else "gradient_flow"]
    starts = default_starts(1.2, 1.0, other, 2, seed=0, plant=plant)
    res = tune_fixed_structure(
        pts, 1.0, _fs_weights(), starts, margin=0.05, lr=5e-5, max_iter=150, plant=plant
    )
    assert res.start_objective == np.inf
    K = ControllerMatrices.static(*res.gains)
    assert certify(K, box, pts, (7, 7), 1.0, 0.05, plant=plant).passed


def test_default_starts_lie_in_the_stabilising_region() -> None:
    box = NTKBox((100.0, 800.0), (0.8, 1.2), (282.8, 282.8))
    pts = box.sample(50, 0)
    for plant in ("gradient_flow", "paper"):
        starts = default_starts(1.2, 1.0, (0.0, 0.0, 0.0), 20, seed=3, plant=plant)[1:]
        for k in starts:
            re = max_real_poles(pts, 1.0, ControllerMatrices.static(*k), plant)
            assert re.max() < 0, (plant, k)


def test_performance_loops_reduce_to_the_minimal_part() -> None:
    """On the gradient-flow plant T_i drops the structural zero; the transfer function is that
    of the full (unreduced) loop."""
    pts = np.array([[300.0, 330.0], [150.0, 130.0]])
    omega = np.array([0.5, 20.0, 4e3])
    gains = (-0.379, 2.82, 0.1937)
    loops = PerformanceLoops(pts, 1.0, _fs_weights(), omega)
    A, B, C, D = loops.matrices(gains)
    assert np.all(np.linalg.eigvals(A).real < 0)
    n = A.shape[1] + 1  # full order
    for i, t2 in enumerate(pts[:, 1]):
        # rebuild the full loop from the paper-plant loop plus u into Q2 through Θ2
        full = PerformanceLoops(pts[i : i + 1], 1.0, _fs_weights(), omega, "paper")
        Af, Bf, Cf, _ = full.matrices(gains)
        Af, Bf, Cf = Af[0].copy(), Bf[0].copy(), Cf[0]
        F = np.zeros(n)
        F[:3] = -gains[0], -gains[1], gains[2]
        G = np.array([0.0, 0.0, -gains[0] * 0.2, -gains[1] * 0.5])
        Af[1] += t2 * F
        Bf[1] += t2 * G
        ev = np.linalg.eigvals(Af)
        assert np.min(np.abs(ev)) < 1e-8 * np.abs(Af).max()
        for w in omega:
            Hf = Cf @ np.linalg.solve(1j * w * np.eye(n) - Af, Bf)
            Hr = C[i] @ np.linalg.solve(1j * w * np.eye(n - 1) - A[i], B[i])
            np.testing.assert_allclose(Hr, Hf, rtol=1e-8, atol=1e-14)


# ------------------------------------------------------------------------------ errors


def test_error_infeasible_box_for_the_learning_rate() -> None:
    """On the paper's plant; the gradient-flow plant has no such bound (its fast mode can be
    slowed down by the gains over the whole box)."""
    conf = _conf(
        "cartpole",
        "hinf_f",
        ["weights.theta_bounds.theta1=[200.0,50000.0]", "controller.synthesis.plant=paper"],
    )
    inputs = design_inputs(conf.controller, conf.weights, 1.0, conf.train.lr)
    with pytest.raises(DesignError, match=r"infeasible NTK box: α·γ·ρ_max·Θ1_max = .* >= 2"):
        design_controller(inputs)


def test_error_invalid_box_from_config() -> None:
    conf = _conf("cartpole", "hinf", ["weights.theta_bounds.nominal=[900.0,900.0]"])
    with pytest.raises(DesignError, match="outside theta1"):
        box_from_config(conf.weights.theta_bounds)


def test_error_failing_certificate_never_a_zero_gain() -> None:
    """On the paper's plant the dynamic design for the wide measured CartPole box leaves part
    of it unstable."""
    conf = _conf(
        "cartpole", "hinf", ["controller.synthesis.cache=false", "controller.synthesis.plant=paper"]
    )
    inputs = design_inputs(conf.controller, conf.weights, 1.0, conf.train.lr)
    with pytest.raises(DesignError, match="failed its certificate: .*unstable"):
        design_controller(inputs)


def test_error_failing_synthesis() -> None:
    box = NTKBox((200.0, 500.0), (0.8, 1.2), (316.0, 316.0))
    ws = HinfWeightSet(
        SisoWeight.make([1.0], [0.1, 1.0], "w_p"),
        SisoWeight.make([0.01, 0.0], [1e-4, 0.101, 1.0], "w_u"),
        SisoWeight.constant(1.0, "w_r"),
        SisoWeight.constant(1.0, "w_qhat"),
        SisoWeight.constant(0.1, "w"),
        (0.2, 0.5),
    )
    P = generalized_plant(*box.nominal, 1.0, ws, Regularisation())
    with pytest.raises(DesignError, match=r"H∞ synthesis failed: SB10AD found no stabilising"):
        hinf_bisection(P, gamma_max=1e-3)


def test_dynamic_design_refits_a_cover_that_breaks_sb10ad() -> None:
    """A one-hot environment's measured box (FrozenLake-v1: Θ1 ∈ [51, 54], Θ2/Θ1 ∈ [0.58, 1],
    nominal ratio 0.8): the free cover puts a pole near 1e-7 rad/s, SB10AD refuses the plant
    (assumption A3), and the design is made with the cover's corners near the band."""
    conf = _conf("cartpole", "hinf", ["weights=generic", "controller.synthesis.cache=false"])
    box = NTKBox((51.0, 54.0), (0.58, 1.0), (52.0, 41.6))
    inputs = design_inputs(conf.controller, conf.weights, conf.train.discount, conf.train.lr, box)
    samples = box.sample(int(inputs.synthesis["samples"]), int(inputs.synthesis["seed"]))
    free, bounded = _cover(inputs, samples), _cover(inputs, samples, BOUNDED_CORNERS)
    band = inputs.synthesis["band"]
    assert min(np.abs(np.roots(free.weight.den))) < band[0] / 1e3
    assert min(np.abs(np.roots(bounded.weight.den))) >= band[0] / BOUNDED_CORNERS * 0.999
    assert bounded.margin >= 1.0  # still a cover: above the sampled error everywhere
    with pytest.raises(HinfInfeasible, match="SB10AD"):
        _design_hinf(inputs, samples, free)
    design = design_controller(inputs)
    assert design.certificate.passed and design.kind == "hinf"
    assert design.cover.weight == bounded.weight


def test_error_fixed_structure_no_feasible_start() -> None:
    box = NTKBox((200.0, 500.0), (0.8, 1.2), (316.0, 316.0))
    with pytest.raises(DesignError, match="fixed-structure design: none of 1 starts"):
        tune_fixed_structure(
            box.sample(8, 0), 1.0, _fs_weights(), [(0.4, -2.8, -0.2)], margin=1e4, max_iter=30
        )


def test_error_unknown_kind_and_measured_box() -> None:
    conf = _conf("cartpole", "h2")
    with pytest.raises(DesignError, match="synthesis designs hinf, hinf_f"):
        design_inputs(conf.controller, conf.weights, 1.0, 5e-5)
    conf = _conf("cartpole", "hinf_f", ["controller.synthesis.plant=exact"])
    inputs = design_inputs(conf.controller, conf.weights, 1.0, 5e-5)
    with pytest.raises(DesignError, match="synthesis.plant='exact': allowed gradient_flow, paper"):
        design_controller(inputs)
    samples = np.column_stack([np.linspace(100, 500, 50), np.linspace(-10, -1, 50)])
    with pytest.raises(DesignError, match="no transition has Θ2/Θ1"):
        summarise(samples, (0.02, 0.98))
    with pytest.raises(DesignError, match="synthesis.quantiles"):
        summarise(samples, (0.9, 0.1))
    with pytest.raises(DesignError, match="not a proper transfer function"):
        SisoWeight.make([1.0, 0.0, 0.0], [1.0, 1.0], "w_u")


def test_measured_box_summary() -> None:
    rng = np.random.default_rng(0)
    t1 = rng.uniform(150, 700, 2000)
    rho = np.where(rng.random(2000) < 0.4, 0.0, rng.uniform(0.85, 1.15, 2000))
    box = summarise(np.column_stack([t1, rho * t1]), (0.02, 0.98))
    assert box.source == "measured"
    assert box.theta1[0] <= np.quantile(t1, 0.02) and box.theta1[1] >= np.quantile(t1, 0.98)
    assert box.ratio[0] >= 0.8 and box.ratio[1] <= 1.2  # Θ2 ≈ 0 transitions left out
    # raw observations of ~1e18 (an integer Box at its full range) give Θ1 ~1e37: still a box
    huge = summarise(np.column_stack([t1 * 1e35, rho * t1 * 1e35]), (0.02, 0.98))
    assert huge.theta1[0] <= np.quantile(t1, 0.02) * 1e35 < 1e38 < huge.theta1[1] * 10


# ------------------------------------------------------------------------ all shipped envs


@pytest.mark.slow
@pytest.mark.parametrize(
    ("env", "kind"),
    [
        ("cartpole", "hinf_f"),
        ("acrobot", "hinf_f"),
        ("mountaincar", "hinf_f"),
        ("cartpole", "hinf"),
        ("acrobot", "hinf"),
        ("mountaincar", "hinf"),
        ("cartpole_pole", "hinf"),
    ],
)
def test_shipped_designs_pass_their_certificate(cache: Path, env: str, kind: str) -> None:
    (record, _, _), _ = _design(cache, env, kind)
    cert = record["certificate"]
    assert cert["passed"] and cert["share_stable"] == 1.0, cert["reason"]
    assert record["plant"] == cert["plant"] == "gradient_flow"
    assert json.loads(json.dumps(record)) == record
    if kind == "hinf_f":  # stable on the plant training realises: k3 > 0 and
        k1, k2, k3 = record["gains"]  # (1 + k1) > (γ − k2) Θ2/Θ1 over the box
        assert k3 > 0 and 1 + k1 > (1.0 - k2) * record["theta_bounds"]["ratio"][1]


@pytest.mark.slow
@pytest.mark.parametrize("env", ["cartpole", "mountaincar"])
def test_paper_plant_cannot_hold_a_learning_target(cache: Path, env: str) -> None:
    """On the paper's plant a static loop is stable only with 1 + k1 > γρ and k2 < −γk1, so
    γ_eff = (γ − k2)/(1 + k1) > 1 there: no target within |γ_eff| <= 1 is met, and the
    design says so by name."""
    with pytest.raises(DesignError, match="within the learning target"):
        _design(cache, env, "hinf_f", ["controller.synthesis.plant=paper"])


def test_measured_box_of_the_runs_network() -> None:
    import torch

    from cdqn.envs import env_sizes, make_env
    from cdqn.network import NetworkSpec, QNetwork
    from cdqn.ntk_bounds import measured_box

    conf = _conf(
        "mountaincar",
        "hinf_f",
        [
            "network=small",
            "controller.synthesis.ntk_bounds=measured",
            "controller.synthesis.rollout_steps=300",
        ],
    )
    env = make_env(conf.env)
    n_obs, n_actions = env_sizes(env)
    env.close()
    torch.manual_seed(0)
    net = QNetwork(NetworkSpec(n_obs, n_actions, conf.network.width, conf.network.dtype))
    before = [p.detach().clone() for p in net.parameters()]
    box = measured_box(conf, net)
    assert box is not None and box.source == "measured" and box.theta1[0] > 0
    assert all(torch.equal(a, b) for a, b in zip(before, net.parameters(), strict=True))
    conf.controller.synthesis.ntk_bounds = "guess"
    with pytest.raises(DesignError, match="ntk_bounds='guess': allowed config, measured"):
        measured_box(conf, net)
