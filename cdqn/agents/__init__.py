"""Agents: controlled deep Q-learning (h2, hinf, hinf_f, none) and the Double DQN baseline."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from cdqn.agents.base import Agent, StepRecord
from cdqn.agents.controlled import ControlledAgent
from cdqn.config import ControllerConfig, ReplayConfig, TrainConfig
from cdqn.control.setup import ControllerSetup
from cdqn.network import QNetwork

if TYPE_CHECKING:
    from cdqn.agents.ddqn import DDQNAgent

__all__ = ["Agent", "ControlledAgent", "DDQNAgent", "StepRecord", "make_agent"]


def __getattr__(name: str) -> Any:
    """``DDQNAgent``, loaded when first asked for: a controlled run never loads Double DQN."""
    if name == "DDQNAgent":
        from cdqn.agents.ddqn import DDQNAgent

        return DDQNAgent
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def make_agent(
    cfg: ControllerConfig,
    train: TrainConfig,
    net: QNetwork,
    setup: ControllerSetup,
    rng: np.random.Generator,
    replay: ReplayConfig | None = None,
) -> Agent:
    """The agent of ``cfg.name``: Double DQN or the controlled agent with ``setup`` (and the
    sampled replay of ``replay``, :mod:`cdqn.agents.replay`)."""
    if cfg.name == "ddqn":
        from cdqn.agents.ddqn import DDQNAgent

        return DDQNAgent(net, cfg, train, rng)
    sample, buffer = (0, 1) if replay is None else (replay.sample, replay.buffer)
    return ControlledAgent(
        net, setup.controller, train, cfg.reset_integrator, rng, sample=sample, buffer=buffer
    )
