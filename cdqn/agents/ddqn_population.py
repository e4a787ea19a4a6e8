"""The Double DQN agent of a population: ``K`` members' steps as two compiled calls.

:class:`DDQNPopulation` is :class:`cdqn.agents.DDQNAgent` (fast path) for ``K`` members at
once, with the interface of :class:`cdqn.agents.controlled_population.ControlledPopulation` that
:func:`cdqn.training.population.train_population` drives.  Per step and member it runs exactly the
single agent's algorithm:

1. act: ε-greedy on ``Q(s, ·)`` (the member's own :class:`EpsilonGreedy`);
2. record: ``Q(s', ·)``, ``a' = argmax``, ``Q1 = Q(s, a)``, ``Q2 = Q(s', a')``, Θ1, Θ2 and
   the last minibatch loss; store ``(s, a, r, s', terminated)`` in the member's buffer;
3. learn: every ``train_freq`` steps once ``learning_starts`` transitions are stored, one
   minibatch step on

   .. math::  \\mathcal L = \\tfrac12 \\sum_i \\big(r_i + \\gamma (1 - d_i)\\,
              \\bar Q(s'_i, \\arg\\max_{a} Q(s'_i, a)) - Q(s_i, a_i)\\big)^2,

   ``d_i`` the transition's ``terminated`` (a transition cut by the time limit
   bootstraps); every ``target_update`` steps ``Q̄ ← Q``.

Steps 1–2 are one compiled loop over the members built from the row functions a single run
uses (:func:`cdqn.network.forward_row`, :func:`cdqn.network.td_row`); step 3 draws each
learning member's minibatch indices with the member's generator as the single run draws
them (exploration and sampling share it, so neither can be drawn ahead), then one compiled
call (:func:`cdqn.ddqn_kernels.double_dqn_learn`) gathers every learning member's minibatch from
its buffer and takes its step with the kernel a single run uses on its stack of one
(:mod:`cdqn.ddqn_kernels`; the loop over the nonzero inputs for a minibatch of mostly
zeros, chosen from the minibatch alone).  So each member computes the numbers of the single
run of its seed, bit for bit (``tests/test_ddqn_population.py``); what the population saves is the
per-step Python of ``K`` runs.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np
from numba import njit

from cdqn.agents.base import EpsilonGreedy, LoopState
from cdqn.agents.controlled_population import StepLog, flag_step
from cdqn.agents.ddqn import step_settings
from cdqn.agents.replay import StackedReplay
from cdqn.config import ControllerConfig, TrainConfig
from cdqn.ddqn_kernels import double_dqn_learn
from cdqn.network import (
    Forward,
    Params,
    QNetwork,
    Replay,
    StackedForward,
    StackedTwoLayer,
    forward_row,
    member_params,
    member_pass,
    step_settings_array,
    td_row,
)
from cdqn.vector_env import VectorStep


class RecordScratch(NamedTuple):
    """One member's step at a time: the pass at s' (``x``, ``p``, ``q``), ``∂Q_a/∂b_1``
    (``g``) and Θ1, Θ2 (``theta``) in the network's dtype, as the single run's arrays hold
    them."""

    x: np.ndarray
    p: np.ndarray
    q: np.ndarray
    g: np.ndarray
    theta: np.ndarray


class Buffers(NamedTuple):
    """The members' replay buffers as the kernels take them
    (:class:`cdqn.agents.replay.StackedReplay`'s arrays, not copies)."""

    obs: np.ndarray
    next_obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    terminated: np.ndarray
    size: np.ndarray
    pos: np.ndarray


class Learning(NamedTuple):
    """Per member: its step count, the schedule ``(learning_starts, train_freq,
    target_update)`` (shared), whether it learns on this step, its last minibatch loss and
    whether its pass is cached (:attr:`DDQNPopulation.cached`)."""

    steps: np.ndarray
    schedule: np.ndarray
    learn: np.ndarray
    last_loss: np.ndarray
    cached: np.ndarray


class _NoController:
    """What the population loop asks of a controller: Double DQN has no state ``x_c``."""

    def state(self, i: int) -> None:
        return None


class DDQNPopulation:
    """:class:`cdqn.agents.DDQNAgent` (fast path) for ``K`` members at once (module
    docstring).  ``nets`` are the members' initial networks (also their target networks),
    ``rngs`` their generators (exploration and minibatch sampling, as in a single run)."""

    def __init__(
        self,
        nets: list[QNetwork],
        cfg: ControllerConfig,
        train: TrainConfig,
        rngs: list[np.random.Generator],
    ) -> None:
        self.net = StackedTwoLayer.from_networks(nets)
        self.target = StackedTwoLayer.from_networks(nets)
        self.spec = spec = nets[0].spec
        k, dtype = len(nets), self.net.dtype
        self.cfg = cfg
        self.rngs = list(rngs)
        self.explorers = [EpsilonGreedy(train, spec.n_actions, rng) for rng in self.rngs]
        self.replay = StackedReplay(k, cfg.buffer_size, spec.n_obs)
        self.hyper = step_settings_array(*step_settings(cfg, train), dtype)
        self.schedule = np.array([cfg.learning_starts, cfg.train_freq, cfg.target_update])
        self.steps = np.zeros(k, dtype=np.int64)
        self.last_loss = np.full(k, np.nan)
        self.learn = np.zeros(k, dtype=np.bool_)
        # Each member's forward pass at s (the act's) and s as the buffer stores it.
        self.obs = np.zeros((k, spec.n_obs))
        self.x = np.empty((k, spec.n_obs), dtype)
        self.p = np.empty((k, spec.width), dtype)
        self.q = np.empty((k, spec.n_actions), dtype)
        # One member's pass at s', ∂Q_a/∂b_1 and Θ1, Θ2 in the network's dtype (as the single
        # run's arrays hold them).
        self.scratch = RecordScratch(
            np.empty(spec.n_obs, dtype),
            np.empty(spec.width, dtype),
            np.empty(spec.n_actions, dtype),
            np.empty(spec.width, dtype),
            np.empty(2, dtype),
        )
        self.idx = np.zeros((k, cfg.batch_size), dtype=np.int64)
        self.plan = np.empty(k, dtype=np.int64)
        self.actions = np.empty(k, dtype=np.int64)
        self.flags = np.zeros(k, dtype=np.int8)
        self.loss_seen = np.zeros(k, dtype=np.bool_)
        self.cached = np.zeros(k, dtype=np.bool_)
        """``x, p, q`` hold the pass at the last ``s'`` with the current parameters (the member
        did not learn on its last step): the act at the same observation takes it as it is."""
        self.controller = _NoController()

    def __len__(self) -> int:
        return len(self.steps)

    @property
    def epsilon(self) -> np.ndarray:
        return np.array([e.epsilon for e in self.explorers])

    def start_episode(self, i: int) -> None:
        self.explorers[i].start_episode()

    def act(self, obs: np.ndarray) -> np.ndarray:
        """ε-greedy actions ``(K,)`` (the array is reused by the next call)."""
        for k, explorer in enumerate(self.explorers):
            a = explorer.explore()
            self.plan[k] = -1 if a is None else a
        self.obs[:] = obs
        _act_kernel(tuple(self.net.params), tuple(self.passes), self.cached, obs, self.plan,
                    self.actions)  # fmt: skip
        return self.actions

    @property
    def passes(self) -> StackedForward:
        """Each member's forward pass at ``s`` (the act's)."""
        return StackedForward(self.x, self.p, self.q)

    @property
    def learning(self) -> Learning:
        """The members' learning schedule and state as the kernels take them."""
        return Learning(self.steps, self.schedule, self.learn, self.last_loss, self.cached)

    def update(self, actions: np.ndarray, step: VectorStep, loop: LoopState) -> int:
        """One Double DQN step of every member on the environments' ``step``: signal rows
        into ``rows``, ``ret`` and ``t`` advanced, :attr:`flags` and :attr:`loss_seen` as in
        :meth:`cdqn.agents.controlled_population.ControlledPopulation.update`.  Returns the
        number of flagged members."""
        n, r = self.net, self.replay
        log = tuple(StepLog(loop.ep, loop.t, loop.ret, loop.rows, self.flags, self.loss_seen))
        buffers = Buffers(r.obs, r.next_obs, r.actions, r.rewards, r.terminated, r.size, r.pos)
        _record_kernel(
            tuple(n.params), tuple(self.passes), tuple(self.scratch), actions, tuple(step),
            self.obs, tuple(buffers), tuple(self.learning), log,
        )  # fmt: skip
        learning = np.flatnonzero(self.learn)
        for k in learning:  # ReplayBuffer.sample's draw
            self.idx[k] = self.rngs[k].integers(r.size[k], size=self.cfg.batch_size)
        if len(learning):
            replay = Replay(r.obs, r.next_obs, r.actions, r.rewards, r.terminated)
            double_dqn_learn(n, self.target, replay, self.idx, self.learn, self.hyper,
                             self.last_loss)  # fmt: skip
        return _learn_kernel(tuple(n.params), tuple(self.target.params), tuple(self.learning),
                             tuple(step), log, loop.q_limit)  # fmt: skip

    def select(self, keep: np.ndarray) -> None:
        """Keep only the members ``keep`` (indices, in that order)."""
        self.net.select(keep)
        self.target.select(keep)
        self.replay.select(keep)
        self.rngs = [self.rngs[i] for i in keep]
        self.explorers = [self.explorers[i] for i in keep]
        self.steps, self.last_loss, self.learn = (
            self.steps[keep],
            self.last_loss[keep],
            self.learn[keep],
        )
        self.obs, self.x, self.p, self.q = self.obs[keep], self.x[keep], self.p[keep], self.q[keep]
        self.idx, self.plan, self.actions = self.idx[keep], self.plan[keep], self.actions[keep]
        self.flags, self.loss_seen = self.flags[keep], self.loss_seen[keep]
        self.cached = self.cached[keep]

    def network(self, i: int) -> QNetwork:
        """Member ``i``'s online network as a :class:`QNetwork`."""
        net = QNetwork(self.spec)
        self.net.copy_to(i, net)
        return net

    def member_state(self, i: int) -> dict[str, Any]:
        """Member ``i``'s state as :meth:`cdqn.agents.DDQNAgent.state_dict` writes it
        (networks, buffer with the generator's state, ε, step counter, last loss)."""
        target = QNetwork(self.spec)
        self.target.copy_to(i, target)
        return {
            "net": self.network(i).state_dict(),
            "target": target.state_dict(),
            "epsilon": self.explorers[i].epsilon,
            "steps": int(self.steps[i]),
            "last_loss": float(self.last_loss[i]),
            "buffer": self.replay.state_dict(i, self.rngs[i]),
        }

    def load_member_state(self, i: int, state: dict[str, Any]) -> None:
        """Inverse of :meth:`member_state` (also takes a :class:`DDQNAgent`'s state)."""
        for stack, key in ((self.net, "net"), (self.target, "target")):
            s = state[key]
            stack.w1t[i] = s["hidden.weight"].numpy().T
            stack.b1[i] = s["hidden.bias"].numpy()
            stack.w2[i] = s["out.weight"].numpy()
            stack.b2[i] = s["out.bias"].numpy()
        self.explorers[i].epsilon = state["epsilon"]
        self.cached[i] = False
        self.steps[i] = state["steps"]
        self.last_loss[i] = state.get("last_loss", math.nan)
        self.replay.load_state_dict(i, state["buffer"], self.rngs[i])

    def state_dict(self, i: int) -> dict[str, Any]:
        """Member ``i``'s state between two population steps (the population checkpoint
        protocol, :mod:`cdqn.training.population_checkpoint`): :meth:`member_state`, its
        cached forward pass and its loop flag."""
        return {
            **self.member_state(i),
            "pass": (self.x[i].copy(), self.p[i].copy(), self.q[i].copy()),
            "loss_seen": bool(self.loss_seen[i]),
        }

    def load_state_dict(self, i: int, state: dict[str, Any]) -> None:
        """Inverse of :meth:`state_dict`, into member ``i`` of a freshly built population."""
        self.load_member_state(i, state)
        self.x[i], self.p[i], self.q[i] = state["pass"]
        self.loss_seen[i] = state["loss_seen"]

    def population_state(self) -> dict[str, Any]:
        """Every member's state (:meth:`member_state`) and the loop's flags."""
        return {
            "members": [self.member_state(i) for i in range(len(self))],
            "loss_seen": self.loss_seen.copy(),
        }

    def load_population_state(self, state: dict[str, Any]) -> None:
        """Inverse of :meth:`population_state`, on a population of as many members."""
        if len(state["members"]) != len(self):
            raise ValueError(
                f"state of {len(state['members'])} members for a population of {len(self)}"
            )
        for i, s in enumerate(state["members"]):
            self.load_member_state(i, s)
        self.loss_seen[:] = state["loss_seen"]


@njit(cache=True)
def _act_kernel(net, passes, cached, obs, plan, actions):
    """Per member: the forward pass at ``obs`` (kept in ``passes`` for the update; the
    cached one if it is at ``obs`` with the current parameters), then the planned random
    action or ``argmax Q(obs, ·)``.  Bundles as plain tuples (:mod:`cdqn.network`,
    bundles)."""
    n, f = Params(*net), StackedForward(*passes)
    for k in range(obs.shape[0]):
        same = cached[k]
        for i in range(obs.shape[1]):
            same = same and f.x[k, i] == obs[k, i]
        if not same:
            for i in range(obs.shape[1]):
                f.x[k, i] = obs[k, i]
            forward_row(member_params(n, k), member_pass(f, k))
        actions[k] = plan[k] if plan[k] >= 0 else np.argmax(f.q[k])


@njit(cache=True)
def _record_kernel(net, passes, scratch, actions, step, obs, buffer, learning, log):
    """Per member, in the order of :meth:`cdqn.agents.DDQNAgent.update`: the pass at s',
    Q1, Q2, Θ1, Θ2 and the signal row (with the last loss), the transition ``(obs[k],
    actions[k], step)`` into the buffer, the step count and whether the member learns on
    this step; the pass at s' is kept as the next act's if the member does not learn.
    Bundles as plain tuples: :class:`~cdqn.network.Params`,
    :class:`~cdqn.network.StackedForward`, :class:`RecordScratch`,
    :class:`cdqn.vector_env.VectorStep`, :class:`Buffers`, :class:`Learning`,
    :class:`~cdqn.agents.controlled_population.StepLog`."""
    n, f, s2 = Params(*net), StackedForward(*passes), RecordScratch(*scratch)
    st, buf, ln, lg = VectorStep(*step), Buffers(*buffer), Learning(*learning), StepLog(*log)
    learning_starts, train_freq = ln.schedule[0], ln.schedule[1]
    f2, theta = Forward(s2.x, s2.p, s2.q), s2.theta
    for k in range(actions.shape[0]):
        for i in range(f2.x.shape[0]):
            f2.x[i] = st.obs[k, i]
        nk, fk = member_params(n, k), member_pass(f, k)
        forward_row(nk, f2)
        a, b = actions[k], np.argmax(f2.q)
        q1, q2 = float(fk.q[a]), float(f2.q[b])
        theta[0], theta[1] = td_row(nk.w2, fk, f2, a, b, s2.g)

        row, reward = lg.rows[k], st.reward[k]
        row[0], row[1], row[2], row[3], row[4] = lg.ep[k], lg.t[k], reward, q1, q2
        row[5], row[6], row[7], row[8], row[9] = 0.0, 0.0, theta[0], theta[1], ln.last_loss[k]
        lg.ret[k] += reward
        lg.t[k] += 1

        j = buf.pos[k]  # ReplayBuffer.add
        for i in range(f2.x.shape[0]):
            buf.obs[k, j, i] = obs[k, i]
            buf.next_obs[k, j, i] = st.obs[k, i]
        buf.actions[k, j], buf.rewards[k, j] = a, reward
        buf.terminated[k, j] = 1.0 if st.terminated[k] else 0.0
        buf.pos[k] = (j + 1) % buf.obs.shape[1]
        buf.size[k] = min(buf.size[k] + 1, buf.obs.shape[1])
        ln.steps[k] += 1
        ln.learn[k] = ln.steps[k] >= learning_starts and ln.steps[k] % train_freq == 0
        ln.cached[k] = not ln.learn[k]
        if ln.cached[k]:
            fk.x[:], fk.p[:], fk.q[:] = f2.x, f2.p, f2.q


@njit(cache=True)
def _learn_kernel(online, target, learning, step, log, q_limit):
    """Per member, after the minibatch steps (:func:`cdqn.ddqn_kernels.double_dqn_learn`): the
    loss of a learning member into its signal row, the target copy every ``target_update``
    steps, and the flags of the population loop (bundles as in :func:`_record_kernel`)."""
    n, tg, ln = Params(*online), Params(*target), Learning(*learning)
    st, lg = VectorStep(*step), StepLog(*log)
    target_update = ln.schedule[2]
    flagged = 0
    for k in range(ln.steps.shape[0]):
        if ln.learn[k]:
            lg.rows[k, 9] = ln.last_loss[k]
        if ln.steps[k] % target_update == 0:
            tg.w1t[k][:] = n.w1t[k]
            tg.b1[k][:] = n.b1[k]
            tg.w2[k][:] = n.w2[k]
            tg.b2[k][:] = n.b2[k]
        row = lg.rows[k]
        healthy = math.isfinite(row[9]) and max(abs(row[3]), abs(row[4])) <= q_limit
        flagged += flag_step(lg, k, healthy, st.terminated[k] or st.truncated[k])
    return flagged
