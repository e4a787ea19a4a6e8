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
    return env


def env_sizes(env: gym.Env) -> tuple[int, int]:
    """(observation size, number of actions)."""
    assert isinstance(env.action_space, Discrete)
    return int(env.observation_space.shape[0]), int(env.action_space.n)
