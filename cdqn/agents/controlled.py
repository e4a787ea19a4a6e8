"""Controlled deep Q-learning: online semi-gradient TD with a control reward u(t).

No target network, no random replay: each transition is used once, in temporal order
(episodic and sampled replay, both off by default, add updates: :mod:`cdqn.agents.episodic_replay`,
:mod:`cdqn.agents.replay`).  Per step (paper Sec. 4, Δt = α):

1. ``Q1 = Q(s, a)``, ``Q2 = max_a' Q(s', a')``, and the NTK values
   ``Θ1 = Θ((s,a),(s,a))``, ``Θ2 = Θ((s,a),(s',a'))`` in closed form;
2. tracking error ``e = r + γ Q̂2 − Q1``, where ``Q̂2 = Q2`` except at a terminal step
   (the MDP ended: no bootstrap, ``Q̂2 = 0``; a truncated step, the time limit, bootstraps),
   and integrator ``x_e ← x_e + α e``
   (paper Eq. xi, explicit Euler at Δt = α as in the research code);
3. control reward ``u = K(x_e, Q1, Q2)`` from the runtime controller;
4. SGD step on the controlled loss.  With ``δ = r + γ Q2 − Q1 + u`` every loss used here
   has the gradient ``−δ ∂Q(s,a)/∂θ`` (target, u and x_e held constant), so the step is
   ``θ ← θ + α δ ∂Q(s,a)/∂θ`` (paper Eq. theta_change_LQ) and the learning dynamics are
   ``Q̇1 = Θ1 (r + γ Q2 − Q1 + u)`` (paper Eq. controlled_Q1_hinf).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from cdqn.agents.base import EpsilonGreedy, StepRecord
from cdqn.agents.replay import Batch, ReplayBuffer
from cdqn.config import TrainConfig
from cdqn.control.runtime import RuntimeController, ScheduledLQR, StateSpace, StaticGain
from cdqn.network import FastTwoLayer, Forward, QNetwork, gradient_step

if TYPE_CHECKING:
    from cdqn.agents.episodic_replay import Transitions


def static_gain_loss(
    q_sa: torch.Tensor,
    q_next: float,
    reward: float,
    x_e: float,
    gains: tuple[float, float, float],
    discount: float,
) -> torch.Tensor:
    """Paper Eq. loss_LQ (H2) and its fixed-structure H∞ twin:

    .. math::  \\mathcal L = \\frac{1}{2(1+k_1)}\\big(r + (\\gamma-k_2)\\max_a Q(s',a)
               - (1+k_1)\\,Q(s,a) + k_3 x_e\\big)^2.
    """
    k1, k2, k3 = gains
    return (reward + (discount - k2) * q_next - (1 + k1) * q_sa + k3 * x_e) ** 2 / (2 * (1 + k1))


def control_reward_loss(
    q_sa: torch.Tensor, q_next: float, reward: float, u: float, discount: float
) -> torch.Tensor:
    """Paper Eq. loss_Hinf: ``½ (r + γ max_a Q(s',a) − Q(s,a) + u)²``; u = 0 gives Eq. loss_0."""
    return 0.5 * (reward + discount * q_next - q_sa + u) ** 2


class ControlledAgent:
    """Online controlled deep Q-learning (module docstring) for ``h2``, ``hinf``, ``hinf_f``
    and ``none``."""

    def __init__(
        self,
        net: QNetwork,
        controller: RuntimeController,
        cfg: TrainConfig,
        reset_integrator: bool,
        rng: np.random.Generator,
        sample: int = 0,
        buffer: int = 50_000,
    ) -> None:
        self.net = net
        self.fast = FastTwoLayer(net)
        self.controller = controller
        self.alpha = cfg.lr
        self.discount = cfg.discount
        self.bootstrap_terminal = cfg.bootstrap_terminal
        self.use_fast_path = cfg.fast_path
        self.reset_integrator = reset_integrator
        self.explorer = EpsilonGreedy(cfg, net.spec.n_actions, rng)
        self.x_e = 0.0
        self._cached: Forward | None = None
        self.sample = sample
        """Sampled replay's updates per step (:mod:`cdqn.agents.replay`; 0: off)."""
        self.memory = (
            ReplayBuffer(buffer, net.spec.n_obs, rng.spawn(1)[0]) if sample > 0 else None
        )  # its own stream (the seed's first child): the exploration's stays as without it

    @property
    def epsilon(self) -> float:
        return self.explorer.epsilon

    def start_episode(self) -> None:
        self.explorer.start_episode()
        if self.reset_integrator:
            self.x_e = 0.0
        self.controller.reset()

    def act(self, obs: np.ndarray) -> int:
        action = self.explorer.explore()
        if action is not None:
            return action
        self._cached = self.fast.forward(obs, reuse=self._cached)  # reused by update()
        return int(np.argmax(self._cached.q))

    def update(
        self, obs: np.ndarray, action: int, reward: float, next_obs: np.ndarray, terminated: bool
    ) -> StepRecord:
        f1 = self.fast.forward(obs, reuse=self._cached)  # the last step's pass at s' = s
        self._cached = None
        f2 = self.fast.forward(next_obs)
        a2 = int(np.argmax(f2.q))
        q1, q2 = float(f1.q[action]), float(f2.q[a2])
        theta1, theta2, grad_b1 = self.fast.td_terms(f1, action, f2, a2)
        q_next = q2 if (self.bootstrap_terminal or not terminated) else 0.0

        error = reward + self.discount * q_next - q1
        self.x_e += self.alpha * error
        u = self.controller.step(self.x_e, q1, q_next, theta1, theta2)
        delta = error + u
        loss = 0.5 * self.controller.loss_weight * delta * delta
        if self.use_fast_path:  # also gives the pass at s' with the new parameters
            self._cached = self.fast.sgd_step(f1, action, self.alpha * delta, grad_b1, f2)
        else:
            loss = self._autograd_step(obs, action, reward, q_next, u)
        return StepRecord(loss, q1, q2, u, self.x_e, theta1, theta2)

    def replay(self, tail: Transitions, repeats: int) -> Iterator[StepRecord]:
        """Episodic replay (:mod:`cdqn.agents.episodic_replay`): ``repeats`` passes over
        ``tail`` in temporal order, each transition through :meth:`update`."""
        for _ in range(repeats):
            yield from self._updates(tail, len(tail.actions))

    def replay_sampled(
        self, obs: np.ndarray, action: int, reward: float, next_obs: np.ndarray, terminated: bool
    ) -> Iterator[StepRecord]:
        """Sampled replay after the step on this transition (:mod:`cdqn.agents.replay`): the
        transition enters the buffer, then :attr:`sample` transitions drawn from it pass
        through :meth:`update`."""
        assert self.memory is not None
        self.memory.add(obs, action, reward, next_obs, terminated)
        yield from self._updates(self.memory.sample(self.sample), self.sample)

    def _updates(self, rows: Transitions | Batch, n: int) -> Iterator[StepRecord]:
        """:meth:`update` on the first ``n`` transitions of ``rows``, in order."""
        for i in range(n):
            yield self.update(
                rows.obs[i],
                int(rows.actions[i]),
                float(rows.rewards[i]),
                rows.next_obs[i],
                bool(rows.terminated[i]),
            )

    def _autograd_step(
        self, obs: np.ndarray, action: int, reward: float, q_next: float, u: float
    ) -> float:
        """The same step through the paper's loss and torch autograd (any architecture)."""
        x = torch.as_tensor(np.asarray(obs), dtype=self.net.hidden.weight.dtype)
        q_sa = self.net(x)[action]
        gains = _static_gains(self.controller)
        if gains is not None:
            loss = static_gain_loss(q_sa, q_next, reward, self.x_e, gains, self.discount)
        else:
            loss = control_reward_loss(q_sa, q_next, reward, u, self.discount)
        gradient_step(self.net, loss, self.alpha)
        return float(loss.detach())

    def state_dict(self) -> dict[str, Any]:
        return {
            "net": self.net.state_dict(),
            "x_e": self.x_e,
            "epsilon": self.explorer.epsilon,
            "rng": self.explorer.rng.bit_generator.state,
            "controller": getattr(self.controller, "x", None),
            "memory": None if self.memory is None else self.memory.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.net.load_state_dict(state["net"])
        self.x_e = state["x_e"]
        self.explorer.epsilon = state["epsilon"]
        self.explorer.rng.bit_generator.state = state["rng"]
        if state["controller"] is not None:
            assert isinstance(self.controller, StateSpace)  # the one controller with a state
            self.controller.x[:] = state["controller"]
        if self.memory is not None:
            self.memory.load_state_dict(state["memory"])


def _static_gains(controller: RuntimeController) -> tuple[float, float, float] | None:
    if isinstance(controller, StaticGain):
        return controller.k1, controller.k2, controller.k3
    if isinstance(controller, ScheduledLQR):
        return controller.gains
    return None
