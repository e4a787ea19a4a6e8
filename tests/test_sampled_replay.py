"""Sampled replay of the controlled agents (cdqn.agents.replay): after each step, transitions
drawn from the recent past pass through the same controlled update."""

from __future__ import annotations

import copy

import numpy as np
import torch

from cdqn.agents.controlled import ControlledAgent
from cdqn.config import TrainConfig
from cdqn.control.runtime import StaticGain
from cdqn.network import NetworkSpec, QNetwork


def _agents(sample: int, buffer: int) -> tuple[ControlledAgent, ControlledAgent]:
    """Two agents on one initial network and seed: one replays, the other replays by hand."""
    torch.manual_seed(0)
    net = QNetwork(NetworkSpec(4, 2, 32, "float64"))
    cfg = TrainConfig(lr=1e-2, discount=0.9, eps_start=0.5, eps_end=0.5)
    replaying = ControlledAgent(copy.deepcopy(net), StaticGain(0.2, -0.3, 0.1), cfg, False,
                                np.random.default_rng(5), sample=sample, buffer=buffer)  # fmt: skip
    by_hand = ControlledAgent(copy.deepcopy(net), StaticGain(0.2, -0.3, 0.1), cfg, False,
                              np.random.default_rng(5))  # fmt: skip
    return replaying, by_hand


def test_each_step_replays_draws_from_the_recent_buffer_through_the_same_update() -> None:
    """The replayed updates are :meth:`ControlledAgent.update` on transitions drawn
    uniformly from the last ``buffer`` (the seed's first child stream); exploration draws
    from the seed's own stream, as without replay."""
    sample, buffer = 3, 5
    agent, by_hand = _agents(sample, buffer)
    draws = np.random.default_rng(5).spawn(1)[0]
    ring: list[tuple[np.ndarray, int, float, np.ndarray, bool]] = []  # the buffer's slots
    gen = np.random.default_rng(1)
    obs = gen.normal(size=4)
    for t in range(12):
        nxt = obs + 0.1 * gen.normal(size=4)
        a = agent.act(obs)
        assert by_hand.act(obs) == a
        reward, done = float(gen.normal()), t % 4 == 3
        step = agent.update(obs, a, reward, nxt, done)
        assert by_hand.update(obs, a, reward, nxt, done) == step
        replayed = list(agent.replay_sampled(obs, a, reward, nxt, done))
        if t < buffer:
            ring.append((obs, a, reward, nxt, done))
        else:  # the oldest transition's slot
            ring[t % buffer] = (obs, a, reward, nxt, done)
        idx = draws.integers(len(ring), size=sample)
        expected = [by_hand.update(*ring[i]) for i in idx]
        assert replayed == expected
        assert agent.memory is not None and agent.memory.size == min(t + 1, buffer)
        obs = nxt
    assert agent.x_e == by_hand.x_e != 0.0  # the replayed updates moved the integrator
    assert agent.explorer.rng.bit_generator.state == by_hand.explorer.rng.bit_generator.state
    for p, q in zip(agent.net.parameters(), by_hand.net.parameters(), strict=True):
        assert torch.equal(p, q)


def test_a_checkpoint_holds_the_buffer_and_its_stream() -> None:
    agent, _ = _agents(2, 4)
    gen = np.random.default_rng(2)
    for _ in range(6):
        obs, nxt = gen.normal(size=4), gen.normal(size=4)
        list(agent.replay_sampled(obs, agent.act(obs), 1.0, nxt, False))
    state = copy.deepcopy(agent.state_dict())
    fresh, _ = _agents(2, 4)
    fresh.load_state_dict(state)
    obs, nxt = gen.normal(size=4), gen.normal(size=4)
    assert list(fresh.replay_sampled(obs, 0, 1.0, nxt, True)) == list(
        agent.replay_sampled(obs, 0, 1.0, nxt, True)
    )
