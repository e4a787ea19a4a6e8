"""Building what a run trains with from its configuration: the environment's sizes, the
Q-network, the controller design and the agent, for a single run (:func:`build`) and for a
population of seeds (:func:`build_population`, the same calls per member)."""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import TYPE_CHECKING

import gymnasium as gym
import numpy as np
import torch
from omegaconf import DictConfig, read_write

from cdqn.agents import Agent, make_agent
from cdqn.config import Config
from cdqn.control.factory import make_controller
from cdqn.control.setup import ControllerSetup
from cdqn.envs import env_sizes, make_env
from cdqn.network import NetworkSpec, QNetwork

if TYPE_CHECKING:
    from cdqn.agents.controlled_population import ControlledPopulation
    from cdqn.agents.ddqn_population import DDQNPopulation
    from cdqn.vector_env import VectorEnv


@dataclass
class Job:
    """Everything one run trains with, built from its configuration."""

    conf: Config
    env: gym.Env
    setup: ControllerSetup
    net: QNetwork
    agent: Agent
    rng: np.random.Generator


def build(conf: Config, env: gym.Env) -> Job:
    """Controller, network and agent of ``conf`` on ``env``; the same calls, in the same
    order, for a new run and a resumed one (so both see the same random streams)."""
    n_obs, n_actions = env_sizes(env)
    torch.manual_seed(conf.seed)
    rng = np.random.default_rng(conf.seed)
    net = QNetwork(NetworkSpec(n_obs, n_actions, conf.network.width, conf.network.dtype))
    box = None  # the design's box unless controller.synthesis.ntk_bounds=measured
    if conf.controller.synthesis.ntk_bounds != "config":
        from cdqn.ntk_bounds import measured_box

        box = measured_box(conf, net)
    setup = make_controller(
        conf.controller, conf.weights, conf.train.discount, conf.train.lr, box=box
    )
    agent = make_agent(conf.controller, conf.train, net, setup, rng, conf.weights.replay)
    return Job(conf, env, setup, net, agent, rng)


def member_seeds(seed: int, population: int) -> list[int]:
    """Seeds of a population: ``seed, seed+1, …, seed+population−1``."""
    return [seed + i for i in range(population)]


def member_config(cfg: DictConfig, seed: int) -> DictConfig:
    """The configuration of the single run a member stands for."""
    out = copy.deepcopy(cfg)
    with read_write(out):
        out.seed = seed
        out.train.population = 1
    return out


def build_population(
    conf: Config, setup: ControllerSetup, seeds: list[int]
) -> tuple[ControlledPopulation | DDQNPopulation, VectorEnv]:
    """Agent and environments of a population, with the calls of :func:`build` per member
    (network initialised under ``torch.manual_seed(seed)``, exploration from
    ``np.random.default_rng(seed)``)."""
    from cdqn.agents.controlled_population import ControlledPopulation
    from cdqn.agents.ddqn_population import DDQNPopulation
    from cdqn.vector_env import make_vector_env

    envs = [make_env(conf.env) for _ in seeds]
    n_obs, n_actions = env_sizes(envs[0])
    nets, rngs = [], []
    for seed in seeds:
        torch.manual_seed(seed)
        rngs.append(np.random.default_rng(seed))
        nets.append(QNetwork(NetworkSpec(n_obs, n_actions, conf.network.width, conf.network.dtype)))
    if conf.controller.name == "ddqn":
        return DDQNPopulation(nets, conf.controller, conf.train, rngs), make_vector_env(envs)
    agent = ControlledPopulation(
        nets, setup.controller, conf.train, conf.controller.reset_integrator, rngs,
        sample=conf.weights.replay.sample, buffer=conf.weights.replay.buffer,
    )  # fmt: skip
    return agent, make_vector_env(envs)
