"""Environments: any gymnasium id with a discrete action space."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium.spaces import Box, Discrete

from cdqn.config import ConfigError, EnvConfig


class ObservationSubset(gym.ObservationWrapper):
    """Keep only the observation features ``indices`` (e.g. pole angle and velocity)."""

    def __init__(self, env: gym.Env, indices: list[int]) -> None:
        super().__init__(env)
        space = env.observation_space
        assert isinstance(space, Box)
        self.indices = np.asarray(indices, dtype=np.int64)
        self.observation_space = Box(
            space.low[self.indices], space.high[self.indices], dtype=space.dtype
        )

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return observation[self.indices]


class ObservationScale(gym.ObservationWrapper):
    """Map each observation feature affinely from its ``[low, high]`` to ``[−1, 1]``
    (``env.normalize``); features with an infinite bound are passed through unchanged.

    A wide network's NTK compares inputs through ``x·y`` and its ReLU pattern: features on
    very different scales (Mountain car's velocity is a hundredth of its position) leave
    the kernel blind to the small ones, so every state looks alike to the learning update
    (Θ2/Θ1 within 1 ± 0.007 on Mountain car)."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        space = env.observation_space
        assert isinstance(space, Box)
        low, high = space.low.astype(np.float64), space.high.astype(np.float64)
        finite = np.isfinite(low) & np.isfinite(high) & (high > low)
        self.offset = np.where(finite, 0.5 * (low + high), 0.0).astype(space.dtype)
        self.scale = np.where(finite, 2.0 / np.where(finite, high - low, 1.0), 1.0).astype(
            space.dtype
        )
        self.observation_space = Box(
            np.where(finite, -1.0, low).astype(space.dtype),
            np.where(finite, 1.0, high).astype(space.dtype),
            dtype=space.dtype,
        )

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return (observation - self.offset) * self.scale


def make_env(cfg: EnvConfig) -> gym.Env:
    """Build the environment of ``cfg``: gymnasium id, episode cap and feature subset."""
    if cfg.id not in gym.registry:
        known = ", ".join(sorted(k for k in gym.registry if "/" not in k)[:12])
        raise ConfigError(
            f"env.id={cfg.id!r} is not a registered gymnasium environment (e.g. {known}, ...)"
        )
    kwargs = {} if cfg.max_episode_steps is None else {"max_episode_steps": cfg.max_episode_steps}
    env = gym.make(cfg.id, **kwargs)
    if not isinstance(env.action_space, Discrete):
        env.close()
        raise ConfigError(
            f"env.id={cfg.id!r} has action space {env.action_space}; cdqn needs a Discrete one"
        )
    space = env.observation_space
    if not isinstance(space, Box) or len(space.shape) != 1:
        env.close()
        raise ConfigError(f"env.id={cfg.id!r}: cdqn needs a flat Box observation, got {space}")
    if cfg.obs_indices is not None:
        bad = [i for i in cfg.obs_indices if not 0 <= i < space.shape[0]]
        if bad or not cfg.obs_indices:
            env.close()
            raise ConfigError(
                f"env.obs_indices={list(cfg.obs_indices)}: indices must lie in "
                f"[0, {space.shape[0]}) for {cfg.id}"
            )
        env = ObservationSubset(env, list(cfg.obs_indices))
    if cfg.normalize:
        env = ObservationScale(env)
    return env


def env_sizes(env: gym.Env) -> tuple[int, int]:
    """(observation size, number of actions)."""
    assert isinstance(env.action_space, Discrete)
    return int(env.observation_space.shape[0]), int(env.action_space.n)
