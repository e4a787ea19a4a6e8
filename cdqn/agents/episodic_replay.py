"""Episodic replay for the controlled agents (paper Sec. 4, remark on replay).

The controlled agents learn from each transition once, in temporal order: no random replay.
The paper's remark allows replaying *episodes*, and the research code does it on Acrobot:
after an episode that reached the goal it trains 500 more times on that episode's final
transition.  Here, after an episode that qualifies (:func:`qualifies`), its last
``weights.replay.last`` transitions (or all of them) pass ``weights.replay.repeats`` more
times, in temporal order, through the same controlled update (integrator ``x_e`` and
controller state continue; the exploration does not move).  Replayed updates write no signal
rows (those are environment steps); each episode records their number, ``replay_updates``.

Nothing of it survives an episode boundary: single runs, which checkpoint at episode
boundaries, need no replay state; a population checkpoint, taken between two steps, holds
each member's transitions of the episode in progress.
"""

from __future__ import annotations

from collections import deque
from typing import NamedTuple

import numpy as np

from cdqn.config import ReplayConfig


class Transitions(NamedTuple):
    """Transitions in temporal order: ``obs`` and ``next_obs`` ``(L, n_obs)``, ``(L,)`` rest."""

    obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_obs: np.ndarray
    terminated: np.ndarray


def qualifies(cfg: ReplayConfig, terminated: bool, truncated: bool, episode_return: float) -> bool:
    """Whether an episode that ended this way is replayed (:class:`cdqn.config.ReplayConfig`)."""
    if cfg.repeats <= 0:
        return False
    ended = {"terminated": terminated, "truncated": truncated and not terminated, "any": True}
    if not ended[cfg.when]:
        return False
    return cfg.min_return is None or episode_return >= cfg.min_return


class EpisodeTail:
    """The last ``cfg.last`` transitions of the running episode (all of them when ``None``)."""

    def __init__(self, cfg: ReplayConfig) -> None:
        self.items: deque[tuple[np.ndarray, int, float, np.ndarray, bool]] = deque(maxlen=cfg.last)

    def clear(self) -> None:
        self.items.clear()

    def append(
        self, obs: np.ndarray, action: int, reward: float, next_obs: np.ndarray, terminated: bool
    ) -> None:
        self.items.append(
            (
                np.array(obs, dtype=float),
                action,
                reward,
                np.array(next_obs, dtype=float),
                terminated,
            )
        )

    def transitions(self) -> Transitions:
        obs, actions, rewards, next_obs, terminated = zip(*self.items, strict=True)
        return Transitions(
            np.stack(obs),
            np.array(actions, dtype=np.int64),
            np.array(rewards, dtype=float),
            np.stack(next_obs),
            np.array(terminated, dtype=np.bool_),
        )


class PopulationTail:
    """:class:`EpisodeTail` for ``K`` members stepping together: a ring of the last
    ``capacity`` population steps; member ``j``'s running episode is the newest ``t[j]`` of
    them."""

    def __init__(self, k: int, n_obs: int, capacity: int) -> None:
        self.obs = np.zeros((capacity, k, n_obs))
        self.next_obs = np.zeros((capacity, k, n_obs))
        self.actions = np.zeros((capacity, k), dtype=np.int64)
        self.rewards = np.zeros((capacity, k))
        self.terminated = np.zeros((capacity, k), dtype=np.bool_)
        self.pos = 0
        self.filled = 0

    def append(
        self,
        obs: np.ndarray,
        actions: np.ndarray,
        rewards: np.ndarray,
        next_obs: np.ndarray,
        terminated: np.ndarray,
    ) -> None:
        i = self.pos
        self.obs[i], self.actions[i], self.rewards[i] = obs, actions, rewards
        self.next_obs[i], self.terminated[i] = next_obs, terminated
        self.pos = (i + 1) % len(self.obs)
        self.filled = min(self.filled + 1, len(self.obs))

    def transitions(self, j: int, steps: int) -> Transitions:
        """Member ``j``'s last ``steps`` transitions (at most the ring's capacity)."""
        n = min(steps, self.filled)
        idx = (self.pos - n + np.arange(n)) % len(self.obs)
        return Transitions(
            self.obs[idx, j],
            self.actions[idx, j],
            self.rewards[idx, j],
            self.next_obs[idx, j],
            self.terminated[idx, j],
        )

    def restore(self, j: int, tail: Transitions) -> None:
        """Make ``tail`` member ``j``'s newest transitions (a resumed population, before its
        first step)."""
        n = min(len(tail.actions), len(self.obs))
        idx = (self.pos - n + np.arange(n)) % len(self.obs)
        self.obs[idx, j], self.actions[idx, j] = tail.obs[-n:], tail.actions[-n:]
        self.rewards[idx, j], self.next_obs[idx, j] = tail.rewards[-n:], tail.next_obs[-n:]
        self.terminated[idx, j] = tail.terminated[-n:]
        self.filled = max(self.filled, n)

    def select(self, keep: np.ndarray) -> None:
        self.obs, self.next_obs = self.obs[:, keep], self.next_obs[:, keep]
        self.actions, self.rewards = self.actions[:, keep], self.rewards[:, keep]
        self.terminated = self.terminated[:, keep]
