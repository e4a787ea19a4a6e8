"""One sign convention and one plant: the training step gives Q̇1 = Θ1 δ and Q̇2 = Θ2 δ with
δ = r + γQ2 − Q1 + u (the gradient-flow plant, B_u = [Θ1, Θ2])."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cdqn.agents.controlled import ControlledAgent
from cdqn.config import TrainConfig
from cdqn.control.runtime import StateSpace, StaticGain
from cdqn.network import NetworkSpec, QNetwork


def _agent(controller, fast_path: bool, lr: float) -> ControlledAgent:
    torch.manual_seed(0)
    net = QNetwork(NetworkSpec(4, 2, 16, "float64"))
    cfg = TrainConfig(lr=lr, discount=0.9, eps_start=0.0, eps_end=0.0, fast_path=fast_path)
    return ControlledAgent(net, controller, cfg, True, np.random.default_rng(0))


def _static() -> StaticGain:
    return StaticGain(0.4, -0.7, -0.3)


def _dynamic() -> StateSpace:
    A, B = np.array([[-50.0]]), np.array([[1.0, 2.0, -1.0]])
    return StateSpace(A, B, np.array([[3.0]]), np.array([[0.5, -0.2, 0.1]]), 1e-6)


each_controller = pytest.mark.parametrize("make", [_static, _dynamic], ids=["static", "dynamic"])
"""A fresh controller per test: the dynamic one carries state."""


@pytest.mark.parametrize("fast_path", [True, False])
@each_controller
def test_one_sgd_step_moves_q1_by_alpha_theta1_delta(make, fast_path: bool) -> None:
    lr = 1e-6
    agent = _agent(make(), fast_path, lr)
    obs = np.array([0.1, -0.2, 0.3, 0.05])
    nxt = np.array([0.12, -0.1, 0.25, 0.0])
    action, reward = 1, 1.0
    before = agent.fast.forward(obs).q[action]
    rec = agent.update(obs, action, reward, nxt, False)
    after = agent.fast.forward(obs).q[action]
    delta = reward + 0.9 * rec.q2 - rec.q1 + rec.u
    assert rec.u != 0.0
    assert after - before == pytest.approx(lr * rec.theta1 * delta, rel=1e-4)


@pytest.mark.parametrize("fast_path", [True, False])
@each_controller
def test_one_sgd_step_moves_q2_by_alpha_theta2_delta(make, fast_path: bool) -> None:
    """u reaches Q2 = Q(s', a') through Θ2 like the reward: the gradient-flow plant
    (B_u = [Θ1, Θ2]) is the one training realises, not the paper's B_u = [Θ1, 0]."""
    lr = 1e-6
    agent = _agent(make(), fast_path, lr)
    obs = np.array([0.1, -0.2, 0.3, 0.05])
    nxt = np.array([0.12, -0.1, 0.25, 0.0])
    action, reward = 1, 1.0
    q_next = agent.fast.forward(nxt).q
    a2 = int(np.argmax(q_next))
    rec = agent.update(obs, action, reward, nxt, False)
    assert rec.q2 == pytest.approx(q_next[a2], rel=1e-12)
    moved = agent.fast.forward(nxt).q[a2] - rec.q2
    delta = reward + 0.9 * rec.q2 - rec.q1 + rec.u
    assert rec.u != 0.0 and abs(rec.theta2) > 0.1 * abs(rec.theta1)
    assert moved == pytest.approx(lr * rec.theta2 * delta, rel=1e-4)
    # the paper's plant would move Q2 by α Θ2 (δ − u): off by α Θ2 u
    paper = lr * rec.theta2 * (delta - rec.u)
    assert abs(moved - paper) == pytest.approx(abs(lr * rec.theta2 * rec.u), rel=1e-3)


def test_linear_model_of_a_training_step_is_the_gradient_flow_plant() -> None:
    """One SGD step equals one explicit-Euler step of Q̇ = b (cᵀQ + r + u), b = [Θ1, Θ2], of
    :func:`cdqn.control.plant.nominal_plant` with ``plant="gradient_flow"``."""
    from cdqn.control.plant import nominal_plant

    lr = 1e-6
    agent = _agent(StaticGain(0.3, -0.5, 0.2), True, lr)
    obs = np.array([0.1, -0.2, 0.3, 0.05])
    nxt = np.array([0.12, -0.1, 0.25, 0.0])
    a2 = int(np.argmax(agent.fast.forward(nxt).q))
    rec = agent.update(obs, 0, 1.0, nxt, False)
    after = np.array([agent.fast.forward(obs).q[0], agent.fast.forward(nxt).q[a2]])
    for plant, close in (("gradient_flow", True), ("paper", False)):
        p = nominal_plant(rec.theta1, rec.theta2, 0.9, plant)
        q = np.array([rec.q1, rec.q2])
        predicted = q + lr * (p.A @ q + p.B_r * 1.0 + p.B_u * rec.u)
        err = np.abs(after - predicted).max() / (lr * abs(rec.theta2 * rec.u))
        assert bool(err < 1e-3) is close, plant
