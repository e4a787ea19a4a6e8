"""Uniform replay buffer: Double DQN's minibatches, and the controlled agents' sampled replay.

Sampled replay (``weights.replay.sample = m``, off by default) departs from the paper's
online learning, where each transition is used once, in temporal order (paper Sec. 4).
After each environment step, the step's transition enters a buffer of the last
``weights.replay.buffer`` transitions, and ``m`` transitions drawn from it uniformly with
replacement (:meth:`ReplayBuffer.sample`, the run's own generator) pass, one after another,
through the same controlled update as a step: the integrator ``x_e`` and the controller's
state continue, the exploration does not move, and no signal row is written.  Each replayed
update passes the divergence test of a step.  The NTK model (paper Eq. controlled_Q1_hinf)
then describes each update at its own transition.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np


class Batch(NamedTuple):
    obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_obs: np.ndarray
    terminated: np.ndarray


class ReplayBuffer:
    """Ring buffer of transitions, sampled uniformly with replacement."""

    def __init__(self, capacity: int, n_obs: int, rng: np.random.Generator) -> None:
        self.capacity = capacity
        self.obs = np.zeros((capacity, n_obs))
        self.next_obs = np.zeros((capacity, n_obs))
        self.actions = np.zeros(capacity, dtype=np.int64)
        self.rewards = np.zeros(capacity)
        self.terminated = np.zeros(capacity)
        self.size = 0
        self.pos = 0
        self.rng = rng

    def add(
        self, obs: np.ndarray, action: int, reward: float, next_obs: np.ndarray, terminated: bool
    ) -> None:
        i = self.pos
        self.obs[i], self.actions[i], self.rewards[i] = obs, action, reward
        self.next_obs[i], self.terminated[i] = next_obs, float(terminated)
        self.pos = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch_size: int) -> Batch:
        idx = self.rng.integers(self.size, size=batch_size)
        return Batch(
            self.obs[idx],
            self.actions[idx],
            self.rewards[idx],
            self.next_obs[idx],
            self.terminated[idx],
        )

    def state_dict(self) -> dict[str, Any]:
        n = self.size
        return {
            "obs": self.obs[:n].copy(),
            "next_obs": self.next_obs[:n].copy(),
            "actions": self.actions[:n].copy(),
            "rewards": self.rewards[:n].copy(),
            "terminated": self.terminated[:n].copy(),
            "pos": self.pos,
            "rng": self.rng.bit_generator.state,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        n = len(state["actions"])
        self.obs[:n], self.next_obs[:n] = state["obs"], state["next_obs"]
        self.actions[:n], self.rewards[:n] = state["actions"], state["rewards"]
        self.terminated[:n] = state["terminated"]
        self.size, self.pos = n, state["pos"]
        self.rng.bit_generator.state = state["rng"]


class StackedReplay:
    """``K`` :class:`ReplayBuffer` ring buffers in stacked arrays (a Double DQN population):
    ``obs``, ``next_obs`` ``(K, capacity, n_obs)``, ``actions``, ``rewards``, ``terminated``
    ``(K, capacity)``, ``size`` and ``pos`` ``(K,)``.  Member ``k`` holds exactly what the
    single run's buffer holds, in the same slots; its minibatch indices are drawn from its
    own generator as :meth:`ReplayBuffer.sample` draws them (``rng.integers(size, size=B)``).
    Only ``terminated`` is stored: a transition cut by the time limit bootstraps.
    """

    def __init__(self, k: int, capacity: int, n_obs: int) -> None:
        self.capacity = capacity
        self.obs = np.zeros((k, capacity, n_obs))
        self.next_obs = np.zeros((k, capacity, n_obs))
        self.actions = np.zeros((k, capacity), dtype=np.int64)
        self.rewards = np.zeros((k, capacity))
        self.terminated = np.zeros((k, capacity))
        self.size = np.zeros(k, dtype=np.int64)
        self.pos = np.zeros(k, dtype=np.int64)

    def add_all(self, step: Batch) -> None:
        """One transition per member (``(K, n_obs)`` and ``(K,)`` arrays), each in its own
        ring as :meth:`ReplayBuffer.add` stores it."""
        rows, pos = np.arange(len(self.pos)), self.pos
        self.obs[rows, pos], self.next_obs[rows, pos] = step.obs, step.next_obs
        self.actions[rows, pos], self.rewards[rows, pos] = step.actions, step.rewards
        self.terminated[rows, pos] = step.terminated
        self.pos = (pos + 1) % self.capacity
        self.size = np.minimum(self.size + 1, self.capacity)

    def select(self, keep: np.ndarray) -> None:
        """Keep only the members ``keep`` (indices, in that order)."""
        self.obs, self.next_obs = self.obs[keep], self.next_obs[keep]
        self.actions, self.rewards = self.actions[keep], self.rewards[keep]
        self.terminated, self.size, self.pos = (
            self.terminated[keep],
            self.size[keep],
            self.pos[keep],
        )

    def state_dict(self, k: int, rng: np.random.Generator) -> dict[str, Any]:
        """Member ``k``'s buffer as :meth:`ReplayBuffer.state_dict` writes it."""
        n = int(self.size[k])
        return {
            "obs": self.obs[k, :n].copy(),
            "next_obs": self.next_obs[k, :n].copy(),
            "actions": self.actions[k, :n].copy(),
            "rewards": self.rewards[k, :n].copy(),
            "terminated": self.terminated[k, :n].copy(),
            "pos": int(self.pos[k]),
            "rng": rng.bit_generator.state,
        }

    def load_state_dict(self, k: int, state: dict[str, Any], rng: np.random.Generator) -> None:
        """Inverse of :meth:`state_dict` (also takes a :class:`ReplayBuffer`'s)."""
        n = len(state["actions"])
        self.obs[k, :n], self.next_obs[k, :n] = state["obs"], state["next_obs"]
        self.actions[k, :n], self.rewards[k, :n] = state["actions"], state["rewards"]
        self.terminated[k, :n] = state["terminated"]
        self.size[k], self.pos[k] = n, state["pos"]
        rng.bit_generator.state = state["rng"]
