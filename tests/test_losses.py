"""Each controlled loss has the gradient of the paper's parameter update, and the
hand-derived fast path takes exactly the autograd step."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from cdqn.agents.controlled import ControlledAgent, control_reward_loss, static_gain_loss
from cdqn.config import TrainConfig
from cdqn.control.runtime import NoControl, ScheduledLQR, StateSpace, StaticGain
from cdqn.network import NetworkSpec, QNetwork


def _grad(net: QNetwork, loss: torch.Tensor) -> list[torch.Tensor]:
    net.zero_grad()
    loss.backward()
    return [p.grad.clone() for p in net.parameters()]


def _q_grad(net: QNetwork, x: torch.Tensor, a: int) -> list[torch.Tensor]:
    return _grad(net, net(x)[a])


@pytest.fixture
def net() -> QNetwork:
    torch.manual_seed(3)
    return QNetwork(NetworkSpec(3, 2, 50, "float64"))


def test_static_gain_loss_gradient_is_eq_theta_change_lq(net: QNetwork) -> None:
    """-dL/dθ = (r + (γ-k2) Q2 - (1+k1) Q1 + k3 x_e) ∂Q(s,a)/∂θ  (paper Eq. theta_change_LQ)."""
    x = torch.randn(3, dtype=torch.float64)
    r, q2, x_e, gamma = 1.0, 2.5, 0.7, 0.99
    for gains in ((0.4, -1.3, 0.2), (-0.379, 2.82, 0.1937), (1.58, -2.8, -0.02)):
        k1, k2, k3 = gains
        grad_loss = _grad(net, static_gain_loss(net(x)[1], q2, r, x_e, gains, gamma))
        q1 = float(net(x)[1].detach())
        factor = r + (gamma - k2) * q2 - (1 + k1) * q1 + k3 * x_e
        for g, gq in zip(grad_loss, _q_grad(net, x, 1), strict=True):
            torch.testing.assert_close(-g, factor * gq, rtol=1e-12, atol=1e-14)


def test_control_reward_loss_gradient_is_the_hinf_update(net: QNetwork) -> None:
    """-dL/dθ = (r + γ Q2 - Q1 + u) ∂Q(s,a)/∂θ  (paper Eq. loss_Hinf)."""
    x = torch.randn(3, dtype=torch.float64)
    r, q2, u, gamma = -1.0, 0.3, 4.2, 1.0
    grad_loss = _grad(net, control_reward_loss(net(x)[0], q2, r, u, gamma))
    factor = r + gamma * q2 - float(net(x)[0].detach()) + u
    for g, gq in zip(grad_loss, _q_grad(net, x, 0), strict=True):
        torch.testing.assert_close(-g, factor * gq, rtol=1e-12, atol=1e-14)


def _controllers():
    yield "none", NoControl
    yield "hinf_f", lambda: StaticGain(0.379, -2.82, -0.1937)
    yield "h2", lambda: ScheduledLQR(1.0, [1.0, 30000.0, 10.0], 20000.0)
    A = np.array([[-20470.0, 13550.0], [-13130.0, -2.394]])
    B = np.array([[155.7, 53.97, 55.91], [-1.744, -0.6808, 0.179]])
    yield "hinf", lambda: StateSpace(A, B, np.array([-174.1, 1.881]), None, 5e-3, "zoh")


@pytest.mark.parametrize(
    ("name", "make"), list(_controllers()), ids=lambda v: v if isinstance(v, str) else ""
)
def test_fast_path_takes_the_autograd_step(name: str, make) -> None:
    torch.manual_seed(0)
    base = QNetwork(NetworkSpec(4, 2, 40, "float64"))
    agents = []
    for fast in (True, False):
        cfg = TrainConfig(lr=5e-3, fast_path=fast, eps_start=0.0, eps_end=0.0)
        agents.append(
            ControlledAgent(copy.deepcopy(base), make(), cfg, True, np.random.default_rng(1))
        )
    gen = np.random.default_rng(7)
    obs = gen.normal(size=4)
    for t in range(30):
        nxt = obs + 0.1 * gen.normal(size=4)
        actions = [agent.act(obs) for agent in agents]
        assert actions[0] == actions[1]
        recs = [agent.update(obs, actions[0], 1.0, nxt, t == 29) for agent in agents]
        assert recs[0].loss == pytest.approx(recs[1].loss, rel=1e-9, abs=1e-12)
        assert recs[0].u == pytest.approx(recs[1].u, rel=1e-9, abs=1e-12)
        obs = nxt
    for p_fast, p_auto in zip(agents[0].net.parameters(), agents[1].net.parameters(), strict=True):
        torch.testing.assert_close(p_fast, p_auto, rtol=1e-10, atol=1e-12)


def test_one_step_moves_q1_as_the_learning_model_predicts() -> None:
    """ΔQ1 ≈ α Θ1 (r + γ Q2 - Q1 + u): the loss's gradient flow is the plant of cdqn.control."""
    torch.manual_seed(1)
    net = QNetwork(NetworkSpec(4, 2, 500, "float64"))
    cfg = TrainConfig(lr=1e-6, eps_start=0.0, eps_end=0.0, discount=1.0)
    agent = ControlledAgent(net, StaticGain(0.3, -0.5, 0.2), cfg, True, np.random.default_rng(0))
    obs, nxt = np.array([0.1, -0.2, 0.05, 0.3]), np.array([0.12, -0.1, 0.04, 0.2])
    a = agent.act(obs)
    rec = agent.update(obs, a, 1.0, nxt, False)
    q1_after = float(net(torch.as_tensor(obs))[a].detach())
    predicted = cfg.lr * rec.theta1 * (1.0 + rec.q2 - rec.q1 + rec.u)
    assert q1_after - rec.q1 == pytest.approx(predicted, rel=1e-6)
