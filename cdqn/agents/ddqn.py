"""Double DQN baseline (van Hasselt et al. 2016) on the same network and environment.

Per environment step: store the transition; every ``train_freq`` steps (once
``learning_starts`` transitions are stored) draw a uniform minibatch and take one SGD step
on

.. math::  \\mathcal L = \\tfrac12 \\sum_i \\big(r_i + \\gamma (1 - d_i)\\,
           \\bar Q(s'_i, \\arg\\max_{a} Q(s'_i, a)) - Q(s_i, a_i)\\big)^2,

with the target network ``Q̄`` copied from the online network every ``target_update``
steps.  The sum (not the mean) over the batch gives each sample the same SGD step size α
as the online agents.  Q1, Q2, Θ1 and Θ2 of the current transition are recorded as for
the controlled agents (paper Remark: with a target network, Θ2 is effectively 0).
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import torch

from cdqn.agents.base import EpsilonGreedy, StepRecord
from cdqn.agents.replay import ReplayBuffer
from cdqn.config import ControllerConfig, TrainConfig
from cdqn.ddqn_kernels import double_dqn_learn
from cdqn.network import (
    FastTwoLayer,
    QNetwork,
    Replay,
    gradient_step,
    step_settings_array,
)


def step_settings(cfg: ControllerConfig, train: TrainConfig) -> tuple[float, float]:
    """Double DQN's (α, γ): ``controller.lr`` and ``controller.discount``, each falling back
    to ``train.lr`` / ``train.discount`` when null (single runs and populations alike)."""
    lr = train.lr if cfg.lr is None else cfg.lr
    return lr, train.discount if cfg.discount is None else cfg.discount


class DDQNAgent:
    def __init__(
        self, net: QNetwork, cfg: ControllerConfig, train: TrainConfig, rng: np.random.Generator
    ) -> None:
        self.net = net
        self.target = copy.deepcopy(net)
        self.fast = FastTwoLayer(net)
        self.fast_target = FastTwoLayer(self.target)
        self.use_fast_path = train.fast_path
        self.lr, self.discount = step_settings(cfg, train)
        self.cfg = cfg
        self.explorer = EpsilonGreedy(train, net.spec.n_actions, rng)
        self.buffer = ReplayBuffer(cfg.buffer_size, net.spec.n_obs, rng)
        self.dtype = net.hidden.weight.dtype
        self.hyper = step_settings_array(self.lr, self.discount, self.fast.dtype)
        b = self.buffer
        self.replay = Replay(b.obs[None], b.next_obs[None], b.actions[None], b.rewards[None],
                             b.terminated[None])  # fmt: skip
        self.steps = 0
        self.last_loss = float("nan")

    @property
    def epsilon(self) -> float:
        return self.explorer.epsilon

    def start_episode(self) -> None:
        self.explorer.start_episode()

    def act(self, obs: np.ndarray) -> int:
        action = self.explorer.explore()
        if action is not None:
            return action
        return int(np.argmax(self.fast.forward(obs).q))

    def update(
        self, obs: np.ndarray, action: int, reward: float, next_obs: np.ndarray, terminated: bool
    ) -> StepRecord:
        f1, f2 = self.fast.forward(obs), self.fast.forward(next_obs)
        a2 = int(np.argmax(f2.q))
        theta1, theta2, _ = self.fast.td_terms(f1, action, f2, a2)
        record = StepRecord(
            loss=self.last_loss,
            q1=float(f1.q[action]),
            q2=float(f2.q[a2]),
            u=0.0,
            x_e=0.0,
            theta1=theta1,
            theta2=theta2,
        )
        self.buffer.add(obs, action, reward, next_obs, terminated)
        self.steps += 1
        if self.steps >= self.cfg.learning_starts and self.steps % self.cfg.train_freq == 0:
            self.last_loss = self._learn()
            record = record._replace(loss=self.last_loss)
        if self.steps % self.cfg.target_update == 0:
            self.target.load_state_dict(self.net.state_dict())
        return record

    def _learn(self) -> float:
        if self.use_fast_path:
            return self._fast_learn()
        b = self.buffer.sample(self.cfg.batch_size)
        obs = torch.as_tensor(b.obs, dtype=self.dtype)
        next_obs = torch.as_tensor(b.next_obs, dtype=self.dtype)
        actions = torch.as_tensor(b.actions)
        with torch.no_grad():
            best = self.net(next_obs).argmax(dim=1, keepdim=True)  # Double DQN: online argmax
            q_next = self.target(next_obs).gather(1, best).squeeze(1)
            target = (
                torch.as_tensor(b.rewards, dtype=self.dtype)
                + self.discount * (1.0 - torch.as_tensor(b.terminated, dtype=self.dtype)) * q_next
            )
        q_sa = self.net(obs).gather(1, actions.unsqueeze(1)).squeeze(1)
        loss = 0.5 * torch.sum((target - q_sa) ** 2)
        gradient_step(self.net, loss, self.lr)
        return float(loss.detach())

    def _fast_learn(self) -> float:
        """:meth:`_learn` with the two-layer network's gradients written out by hand
        (:func:`cdqn.ddqn_kernels.double_dqn_learn` on a stack of one): the minibatch drawn as
        :meth:`ReplayBuffer.sample` draws it, gathered by the kernel."""
        idx = self.buffer.rng.integers(self.buffer.size, size=self.cfg.batch_size)
        loss = np.empty(1)
        double_dqn_learn(self.fast.stack, self.fast_target.stack, self.replay, idx[None],
                         np.ones(1, dtype=np.bool_), self.hyper, loss)  # fmt: skip
        return float(loss[0])

    def state_dict(self) -> dict[str, Any]:
        return {
            "net": self.net.state_dict(),
            "target": self.target.state_dict(),
            "epsilon": self.explorer.epsilon,
            "steps": self.steps,
            "last_loss": self.last_loss,
            "buffer": self.buffer.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.net.load_state_dict(state["net"])
        self.target.load_state_dict(state["target"])
        self.explorer.epsilon = state["epsilon"]
        self.steps = state["steps"]
        self.last_loss = state.get("last_loss", float("nan"))
        self.buffer.load_state_dict(state["buffer"])
