"""Agents: controlled deep Q-learning (h2, hinf, hinf_f, none) and the Double DQN baseline."""

from __future__ import annotations

import numpy as np

from cdqn.agents.base import Agent, StepRecord
from cdqn.agents.controlled import ControlledAgent
from cdqn.agents.ddqn import DDQNAgent
from cdqn.config import ControllerConfig, TrainConfig
from cdqn.control.setup import ControllerSetup
from cdqn.network import QNetwork

__all__ = ["Agent", "ControlledAgent", "DDQNAgent", "StepRecord", "make_agent"]


def make_agent(
    cfg: ControllerConfig,
    train: TrainConfig,
    net: QNetwork,
    setup: ControllerSetup,
    rng: np.random.Generator,
) -> Agent:
    """The agent of ``cfg.name``: Double DQN or the controlled agent with ``setup``."""
    if cfg.name == "ddqn":
        return DDQNAgent(net, cfg, train, rng)
    return ControlledAgent(net, setup.controller, train, cfg.reset_integrator, rng)
