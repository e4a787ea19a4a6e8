"""One sign convention: the training loss's gradient step gives Q̇1 = Θ1 (r + γQ2 − Q1 + u)."""

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


@pytest.mark.parametrize("fast_path", [True, False])
@pytest.mark.parametrize(
    "controller",
    [
        StaticGain(0.4, -0.7, -0.3),
        StateSpace(
            np.array([[-50.0]]),
            np.array([[1.0, 2.0, -1.0]]),
            np.array([[3.0]]),
            np.array([[0.5, -0.2, 0.1]]),
            1e-6,
        ),
    ],
    ids=["static", "dynamic"],
)
def test_one_sgd_step_moves_q1_by_alpha_theta1_delta(controller, fast_path: bool) -> None:
    lr = 1e-6
    agent = _agent(controller, fast_path, lr)
    obs = np.array([0.1, -0.2, 0.3, 0.05])
    nxt = np.array([0.12, -0.1, 0.25, 0.0])
    action, reward = 1, 1.0
    before = agent.fast.forward(obs).q[action]
    rec = agent.update(obs, action, reward, nxt, False)
    after = agent.fast.forward(obs).q[action]
    delta = reward + 0.9 * rec.q2 - rec.q1 + rec.u
    assert rec.u != 0.0
    assert after - before == pytest.approx(lr * rec.theta1 * delta, rel=1e-4)
