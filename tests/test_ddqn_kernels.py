"""Double DQN's compiled minibatch step (:mod:`cdqn.ddqn_kernels`): equal to torch autograd
in either dtype and for any number of inputs and actions, written out or through BLAS; its
arithmetic as the benchmark counts it."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from cdqn.agents.ddqn import DDQNAgent
from cdqn.bench import agent_products
from cdqn.config import Config, ControllerConfig, TrainConfig
from cdqn.ddqn_kernels import DENSE_INPUTS, minibatch_macs
from cdqn.network import NetworkSpec, QNetwork

TOLERANCE = {"float64": (1e-9, 1e-10, 1e-12), "float32": (2e-4, 2e-4, 2e-6)}
"""(relative, on the loss; relative and absolute, on the parameters) per dtype: float32's
epsilon is 1.2e-7, and the sums over samples and hidden units run in another order than
torch's."""


def fast_and_autograd_agents(
    n_obs: int, n_actions: int, dtype: str, lr: float
) -> tuple[QNetwork, list[DDQNAgent]]:
    """A width-120 network and two Double DQN agents on copies of it: the fast path, then
    autograd."""
    torch.manual_seed(1)
    base = QNetwork(NetworkSpec(n_obs, n_actions, 120, dtype))
    cfg = ControllerConfig(
        name="ddqn", batch_size=8, buffer_size=500, learning_starts=10, target_update=15
    )
    agents = []
    for fast in (True, False):
        train = TrainConfig(lr=lr, fast_path=fast, eps_start=0.0, eps_end=0.0)
        agents.append(DDQNAgent(copy.deepcopy(base), cfg, train, np.random.default_rng(5)))
    return base, agents


@pytest.mark.parametrize(
    ("dtype", "n_obs", "n_actions"),
    [("float64", 4, 2), ("float32", 4, 2), ("float64", 6, 3), ("float32", 3, 1),
     ("float64", DENSE_INPUTS, 3), ("float32", 36, 3)],  # the last two: products through BLAS
)  # fmt: skip
def test_minibatch_step_equals_autograd(dtype: str, n_obs: int, n_actions: int) -> None:
    """Double DQN with the fast path and with torch autograd take the same steps (losses,
    networks after 60 updates with minibatch steps and target copies), in the network's
    dtype."""
    base, agents = fast_and_autograd_agents(n_obs, n_actions, dtype, lr=1e-3)
    rel_loss, rtol, atol = TOLERANCE[dtype]
    gen = np.random.default_rng(2)
    obs = gen.normal(size=n_obs)
    for t in range(60):
        nxt = obs + 0.1 * gen.normal(size=n_obs)
        done = t % 17 == 16
        recs = [agent.update(obs, t % n_actions, 1.0, nxt, done) for agent in agents]
        assert recs[0].loss == pytest.approx(recs[1].loss, rel=rel_loss, nan_ok=True)
        obs = gen.normal(size=n_obs) if done else nxt
    assert agents[0].steps >= 50 and np.isfinite(agents[0].last_loss)
    for p_fast, p_auto in zip(agents[0].net.parameters(), agents[1].net.parameters(), strict=True):
        assert p_fast.dtype == getattr(torch, dtype)
        torch.testing.assert_close(p_fast, p_auto, rtol=rtol, atol=atol)
    pairs = zip(agents[0].net.parameters(), base.parameters(), strict=True)
    assert all(not torch.equal(a, b) for a, b in pairs)  # every parameter learned


def test_benchmark_counts_the_minibatch_arithmetic() -> None:
    """The benchmark's products of a Double DQN step hold the minibatch step's multiply-adds
    (every ``train_freq`` steps) and two passes: CartPole at width 2500 is 0.56 M per step."""
    conf = Config()
    conf.controller = ControllerConfig(name="ddqn", batch_size=32, train_freq=4)
    conf.network.width = 2500
    per_step = sum(p.macs for p in agent_products(conf, 4, 2))
    minibatch = minibatch_macs(32, 4, 2, 2500)
    assert minibatch == 32 * 2500 * (3 * 6 + 4 + 4)
    assert per_step == pytest.approx(minibatch / 4 + 2 * 2500 * 6 + 4 * 2500)
    assert 0.55e6 < per_step < 0.57e6
