"""The fast paths compute what the definitions say: stacked networks equal single ones bit
for bit, the closed-form H2 gain equals the Hamiltonian solution, the compiled controllers
follow their formulas, and Double DQN's hand-written minibatch step equals torch
autograd's."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from cdqn import bench
from cdqn.control.h2 import LQRError, h2_gains, h2_gains_batch, h2_gains_reference
from cdqn.control.runtime import ScheduledLQR, StateSpace
from cdqn.network import (
    FastTwoLayer,
    NetworkSpec,
    QNetwork,
    StackedTwoLayer,
    gradient_step,
    load_network,
    save_network,
)


def _nets(k: int, n_obs: int = 4, width: int = 300) -> list[QNetwork]:
    nets = []
    for seed in range(k):
        torch.manual_seed(seed)
        nets.append(QNetwork(NetworkSpec(n_obs, 2, width)))
    return nets


def test_the_gradient_step_is_torch_sgds_step_bit_for_bit() -> None:
    """``gradient_step`` (the autograd path's θ ← θ − α ∂L/∂θ) moves every parameter exactly
    as ``torch.optim.SGD`` (no momentum, no decay) does, over several steps."""
    ours, theirs = _nets(1)[0], copy.deepcopy(_nets(1)[0])
    sgd = torch.optim.SGD(theirs.parameters(), lr=3e-3)
    x = torch.linspace(-1.0, 1.0, 4, dtype=torch.float64)
    for step in range(3):
        loss = 0.5 * (ours(x + step)[1] - 1.0) ** 2
        gradient_step(ours, loss, 3e-3)
        sgd.zero_grad(set_to_none=True)
        (0.5 * (theirs(x + step)[1] - 1.0) ** 2).backward()
        sgd.step()
    for a, b in zip(ours.parameters(), theirs.parameters(), strict=True):
        assert torch.equal(a, b)
        assert a.grad is None
    assert not torch.equal(ours.out.weight, _nets(1)[0].out.weight)  # it moved


def test_stacked_members_compute_bit_identically_to_single_networks() -> None:
    """Every member's forward, Θ1/Θ2 and SGD step equal a FastTwoLayer on its own network,
    exactly, whatever the population size: the basis of population-equals-single-run."""
    nets = _nets(4)
    stack = StackedTwoLayer.from_networks(nets)
    singles = [FastTwoLayer(n) for n in copy.deepcopy(nets)]
    gen = np.random.default_rng(0)
    x = gen.normal(size=(4, 4))
    nexts = []
    for _ in range(25):
        y = x + 0.1 * gen.normal(size=(4, 4))
        f1, f2 = stack.forward(x), stack.forward(y)
        a = gen.integers(2, size=4)
        b = np.argmax(f2.q, axis=1)
        td = stack.td_terms(f1, a, f2, b)
        scale = 1e-3 * gen.normal(size=4)
        for k, fast in enumerate(singles):
            g1, g2 = fast.forward(x[k]), fast.forward(y[k])
            assert np.array_equal(g1.q, f1.q[k]) and np.array_equal(g2.p, f2.p[k])
            theta1, theta2, grad = fast.td_terms(g1, int(a[k]), g2, int(b[k]))
            assert theta1 == td.theta1[k] and theta2 == td.theta2[k]
            assert np.array_equal(grad[0], td.grad_b1[k])
            nxt = fast.sgd_step(g1, int(a[k]), float(scale[k]), grad, g2)
            assert np.array_equal(nxt.q, fast.forward(y[k], reuse=nxt).q)
            np.testing.assert_allclose(nxt.q, fast.forward(y[k]).q, rtol=1e-12)  # fresh pass
            nexts.append(nxt)
        f_next = stack.sgd_step(f1, a, scale, td.grad_b1, f2)
        for k, nxt in enumerate(nexts):
            assert np.array_equal(nxt.p, f_next.p[k]) and np.array_equal(nxt.q, f_next.q[k])
        nexts = []
        x = y
    for k, fast in enumerate(singles):
        assert np.array_equal(fast.stack.w1t[0], stack.w1t[k])
        assert np.array_equal(fast.w2, stack.w2[k]) and np.array_equal(fast.b1, stack.b1[k])
    stack.select(np.array([2, 0]))  # leaving members does not change the others' numbers
    f = stack.forward(x[[2, 0]])
    assert np.array_equal(f.q[0], singles[2].forward(x[2]).q)


def test_td_terms_equal_the_ntk_definition() -> None:
    (net,) = _nets(1, n_obs=3, width=200)
    fast = FastTwoLayer(net)
    gen = np.random.default_rng(1)
    x, y = gen.normal(size=3), gen.normal(size=3)
    fx, fy = fast.forward(x), fast.forward(y)
    for a, b in ((0, 0), (0, 1), (1, 0)):
        theta1, theta2, _ = fast.td_terms(fx, a, fy, b)
        assert theta1 == pytest.approx(fast.ntk(fx, a, fx, a), rel=1e-13)
        assert theta2 == pytest.approx(fast.ntk(fx, a, fy, b), rel=1e-13)


def test_hidden_weight_is_input_major_and_round_trips(tmp_path: Path) -> None:
    (net,) = _nets(1)
    assert net.hidden.weight.stride() == (1, 300)  # W1ᵀ contiguous, shared with NumPy
    fast = FastTwoLayer(net)
    assert np.shares_memory(net.hidden.weight.detach().numpy(), fast.w1)
    before = [p.detach().clone() for p in net.parameters()]
    f = fast.forward(np.ones(4))
    _, _, grad = fast.td_terms(f, 1, f, 1)
    fast.sgd_step(f, 1, 0.01, grad, f)  # the module sees the step, without copies
    assert all(not torch.equal(b, p) for b, p in zip(before, net.parameters(), strict=True))
    save_network(net, tmp_path)
    loaded = load_network(tmp_path)
    for p, q in zip(net.parameters(), loaded.parameters(), strict=True):
        assert torch.equal(p, q)


def _h2_cases():
    gen = np.random.default_rng(7)
    for i in range(300):
        a = float(gen.uniform(1.0, 2000.0))
        b = a * float(gen.uniform(-1.5, 1.5)) if i % 3 else float(gen.uniform(-3000, 3000))
        gamma = float(gen.choice([1.0, 0.99, 0.5]))
        w_x = [float(gen.choice([0, 1, 10])), float(gen.choice([0, 1, 100, 3e4])), 10.0]
        yield a, b, gamma, w_x, float(gen.choice([1.0, 30.0, 2e4]))
    for w_x, w_c in (([1, 3e4, 10], 2e4), ([1, 100, 80], 30), ([1, 10, 100], 1e3)):  # paper
        for theta1 in (200.0, 220.0, 350.0, 500.0):
            for ratio in (0.8, 1.0, 1.2):
                yield theta1, ratio * theta1, 1.0, w_x, w_c


def test_h2_closed_form_equals_the_hamiltonian_solution() -> None:
    for theta1, theta2, gamma, w_x, w_c in _h2_cases():
        try:
            ref = h2_gains_reference(theta1, theta2, gamma, np.array(w_x), w_c)
        except LQRError:
            with pytest.raises(LQRError):
                h2_gains(theta1, theta2, gamma, np.array(w_x), w_c)
            continue
        got = h2_gains(theta1, theta2, gamma, np.array(w_x), w_c)
        np.testing.assert_allclose(got, ref, rtol=1e-8, atol=1e-12)


def test_h2_batch_equals_scalar_bit_for_bit() -> None:
    gen = np.random.default_rng(3)
    theta1 = gen.uniform(200, 500, size=50)
    theta2 = theta1 * gen.uniform(0.8, 1.2, size=50)
    w_x = np.array([1.0, 3e4, 10.0])
    batch = h2_gains_batch(theta1, theta2, 1.0, w_x, 2e4)
    scalar = [h2_gains(t1, t2, 1.0, w_x, 2e4) for t1, t2 in zip(theta1, theta2, strict=True)]
    assert np.array_equal(batch, np.array(scalar))


def test_compiled_state_space_step_is_the_matrix_recursion() -> None:
    """``u = C x + D v``, ``x ← A_d x + B_d v`` with ``v = [x_e, Q1, Q2]``."""
    gen = np.random.default_rng(0)
    A = gen.normal(size=(4, 4)) - 5 * np.eye(4)
    B, C, D = gen.normal(size=(4, 3)), gen.normal(size=4), gen.normal(size=3)
    ctrl = StateSpace(A, B, C, D, 1e-2, "tustin", reset_state=True)
    x = np.zeros(4)
    for _ in range(50):
        v = gen.normal(size=3)
        u = ctrl.step(*v, 300.0, 310.0)
        np.testing.assert_allclose(u, C @ x + D @ v, rtol=1e-12, atol=1e-12)
        x = ctrl.Ad @ x + ctrl.Bd @ v
        np.testing.assert_allclose(ctrl.x, x, rtol=1e-12, atol=1e-12)
    assert np.abs(x).sum() > 0
    ctrl.reset()
    assert not ctrl.x.any()


def test_scheduled_lqr_keeps_its_last_gains_where_no_lqr_exists() -> None:
    ctrl = ScheduledLQR(1.0, [1.0, 3e4, 10.0], 2e4, "research")
    ctrl.step(0.1, 2.0, 2.1, 300.0, 310.0)
    solved = ctrl.gains
    k1, k2, k3 = h2_gains(300.0, 310.0, 1.0, np.array([1.0, 3e4, 10.0]), 2e4)
    assert solved == (k3, -k2, k1)  # the research code's assignment
    assert ctrl.loss_weight == 1.0 / (1.0 + solved[0])
    u = ctrl.step(0.3, 1.0, 1.5, 300.0, 0.0)  # Θ2 = 0: no stabilising LQR
    assert ctrl.unsolved_steps == 1 and ctrl.gains == solved
    assert u == -solved[0] * 1.0 - solved[1] * 1.5 + solved[2] * 0.3


def test_h2_without_integrator_weight_has_no_stabilising_solution() -> None:
    for solve in (h2_gains, h2_gains_reference):
        with pytest.raises(LQRError):
            solve(220.0, 222.0, 1.0, np.array([1.0, 3e4, 0.0]), 2e4)


def test_benchmark_reports_the_documented_fields(capsys: pytest.CaptureFixture[str]) -> None:
    """``python -m cdqn.bench --json`` on a tiny budget (its numbers are not checked)."""
    bench.main(
        ["--width", "16", "--steps", "60", "--warmup", "20", "--repeats", "1",
         "--population", "2", "--controllers", "none,hinf_f,ddqn", "--no-estimate", "--json"]
    )  # fmt: skip
    out = json.loads(capsys.readouterr().out)
    assert out["floor"]["steps_per_s"] > 0
    assert set(out["controllers"]) == {"none", "hinf_f", "ddqn"}
    for entry in out["controllers"].values():
        assert entry["steps_per_s"] > 0 and entry["ratio_to_floor"] > 0
    assert out["population"]["k"] == 2 and out["population"]["speedup"] > 0
    assert set(out["population"]["by_controller"]) == {"none", "hinf_f", "ddqn"}
    assert out["population"]["by_controller"]["ddqn"]["speedup"] > 0
    assert bench.makespan([3.0, 1.0, 1.0, 1.0], 2) == 3.0


def test_the_sweep_estimate_starts_jobs_in_the_order_of_the_paper_sweep() -> None:
    """``bench.SWEEP_ORDER`` is the job order of ``sweeps/paper.yaml`` (Hydra's product of
    its parameters in the order written), so the estimated makespan is the sweep's."""
    import itertools

    import yaml

    from tests.conftest import CONF_DIR

    sweep = yaml.safe_load((CONF_DIR.parent / "sweeps" / "paper.yaml").read_text())
    params = sweep["hydra"]["sweeper"]["params"]
    values = {k: str(v).split(",") for k, v in params.items()}
    jobs = [dict(zip(values, combo, strict=True)) for combo in itertools.product(*values.values())]
    assert [(j["env"], j["controller"]) for j in jobs] == list(bench.SWEEP_ORDER)
    assert {c for _, c in bench.SWEEP_ORDER} == set(bench.PAPER_CONTROLLERS)
    assert {e for e, _ in bench.SWEEP_ORDER} == set(bench.PAPER_ENVS)
