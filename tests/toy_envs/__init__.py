"""A package that registers toy environments when imported, as a user's own package does:
``env.id=tests.toy_envs:CdqnChain-v0`` imports it first (``gymnasium.make``'s
``<module>:<Id>``).

``CdqnChain-v0``: walk right along a chain of ``length`` cells (``Box`` observation, two
actions, numbered from ``action_start``; ``cells=True``: an integer ``Box`` of the cells to
either side; ``form``: the same observation as a ``(2, 1)`` column, the cells as a
``MultiDiscrete``, the position as a ``MultiBinary``, the cells as a ``Dict`` of two
``Discrete``, ``x`` and the cell as a ``Dict`` of a ``Box`` and a ``Discrete``, or with a
``Text`` part), capped at 50 steps;
``CdqnChainNoCap-v0``: the same, registered without an episode cap."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.spaces import Box, Dict, Discrete, MultiBinary, MultiDiscrete, Text


class Chain(gym.Env):
    """Cells ``0 … length−1``, start at 0; action 1 moves right, 0 left, each reversed with
    probability ``slip``; every step pays ``step_reward``; the episode terminates at the
    last cell.  Observation ``[x, 1 − x]`` with ``x`` the position scaled to [0, 1]."""

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(
        self,
        length: int = 8,
        slip: float = 0.1,
        step_reward: float = -1.0,
        cells: bool = False,
        action_start: int = 0,
        form: str = "box",
    ) -> None:
        self.length, self.slip, self.step_reward, self.cells = length, slip, step_reward, cells
        self.form = form
        self.observation_space: gym.Space[Any] = {
            "box": Box(0, length - 1, (2,), dtype=np.int64)
            if cells
            else Box(0.0, 1.0, (2,), dtype=np.float32),
            "column": Box(0.0, 1.0, (2, 1), dtype=np.float32),
            "multi_discrete": MultiDiscrete([length, length], start=[1, 0]),
            "multi_binary": MultiBinary(length),
            "dict": Dict({"right": Discrete(length), "left": Discrete(length, start=1)}),
            "mixed": Dict({"x": Box(0.0, 1.0, (1,), dtype=np.float32), "cell": Discrete(length)}),
            "text": Dict({"x": Box(0.0, 1.0, (1,), dtype=np.float32), "note": Text(4)}),
        }[form]
        self.action_space = Discrete(2, start=action_start)
        self.pos = 0

    def _obs(self) -> Any:
        x = self.pos / (self.length - 1)
        if self.form == "dict":
            return {"left": self.pos + 1, "right": self.length - 1 - self.pos}
        if self.form in ("mixed", "text"):
            other = {"cell": self.pos} if self.form == "mixed" else {"note": "walk"}
            return {"x": np.array([x], dtype=np.float32), **other}
        if self.form == "multi_discrete":  # cells to the left (numbered from 1) and right
            return np.array([self.pos + 1, self.length - 1 - self.pos], dtype=np.int64)
        if self.form == "multi_binary":
            return (np.arange(self.length) == self.pos).astype(np.int8)
        if self.form == "column":
            return np.array([[x], [1.0 - x]], dtype=np.float32)
        if self.cells:  # an integer observation: the cells to the left and to the right
            return np.array([self.pos, self.length - 1 - self.pos], dtype=np.int64)
        return np.array([x, 1.0 - x], dtype=np.float32)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self.pos = 0
        return self._obs(), {}

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if not self.action_space.contains(action):
            raise ValueError(f"action {action} is not in {self.action_space}")
        move = 1 if action == self.action_space.start + 1 else -1
        if self.np_random.random() < self.slip:
            move = -move
        self.pos = min(max(self.pos + move, 0), self.length - 1)
        return self._obs(), self.step_reward, self.pos == self.length - 1, False, {}


gym.register("CdqnChain-v0", entry_point=Chain, max_episode_steps=50, reward_threshold=-12.0)
gym.register("CdqnChainNoCap-v0", entry_point=Chain)
