"""The controlled agent of a population: ``K`` members' steps as two compiled calls, or
several steps in one.

:class:`ControlledPopulation` is :class:`cdqn.agents.ControlledAgent` (fast path) for ``K``
members at once.  Per step and member it runs exactly the single agent's algorithm
(paper Sec. 4, Δt = α):

1. act: ε-greedy on ``Q(s, ·)``, the forward pass at ``s`` being the one the last update
   left (``s`` = the last ``s'``) unless the episode restarted;
2. update: ``Q(s', ·)``, ``a' = argmax``, ``Q1 = Q(s, a)``, ``Q2 = Q(s', a')``, Θ1, Θ2;
   ``e = r + γ Q̂2 − Q1``; ``x_e ← x_e + α e``; ``u = K(x_e, Q1, Q̂2)``;
   ``θ ← θ + α (e + u) ∂Q(s,a)/∂θ``; the step's signal row; the divergence pre-check.

Each is one compiled loop over the members (:func:`_act_kernel`, :func:`_update_kernel`)
built from the row functions of :mod:`cdqn.network` and the controller arithmetic of
:mod:`cdqn.control.kernels`, so the per-step Python is paid once for ``K`` members and each
member computes the numbers of the single run of its seed, bit for bit
(``tests/test_population.py``).  The one difference from a single run's step is when
``W_1`` changes: a member's SGD step leaves its ``W_1`` update pending
(:func:`cdqn.network.sgd_deferred_row`) and the member's next forward pass applies it
element by element on its way through ``W_1`` (:func:`cdqn.network.forward_pending_row`),
with the same operations, so one pass over ``W_1`` per step does both (over the rows of
the nonzero inputs of ``s`` and ``s'`` only, as every product with ``x`` in
:mod:`cdqn.network`).  Nothing reads
``W_1`` in between; :meth:`ControlledPopulation.flush` applies what is pending before the
parameters are read from outside.  Exploration is drawn ahead in blocks
(:func:`cdqn.agents.base.explore_ahead`); it depends on nothing but each member's generator.
Sampled replay (:mod:`cdqn.agents.replay`) is a third compiled call after the update
(:func:`_sampled_kernel`), from each member's buffer with the indices its own generator
draws as the single run's :class:`~cdqn.agents.replay.ReplayBuffer` draws them.

On a compiled environment twin (:func:`cdqn.vector_env.twin_step`) without sampled or
episodic replay, :meth:`ControlledPopulation.run` takes act, the environments' step and
update for up to the exploration plan's next block in one compiled call
(:func:`_run_kernel`), and returns after the first step that flags a member: the loop's
Python is paid once per episode end rather than once per step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numba import njit

from cdqn.agents.base import LoopState, decide, draw_ahead, explore_ahead
from cdqn.agents.episodic_replay import Transitions
from cdqn.agents.replay import Batch, StackedReplay
from cdqn.config import TrainConfig
from cdqn.control.kernels import scheduled_lqr_step, state_space_step, static_gain_u
from cdqn.control.runtime import (
    NoControl,
    RuntimeController,
    ScheduledLQR,
    StateSpace,
    StaticGain,
)
from cdqn.network import (
    Forward,
    Params,
    QNetwork,
    StackedForward,
    StackedPending,
    StackedTwoLayer,
    apply_pending_row,
    forward_pending_row,
    member_params,
    member_pass,
    member_pending,
    sgd_deferred_row,
    td_row,
)
from cdqn.vector_env import TwinArrays, VectorStep, twin_step

NO_CONTROL, STATIC_GAIN, STATE_SPACE, SCHEDULED_LQR = 0, 1, 2, 3
DONE, CHECK = 1, 2
"""Flags of :meth:`ControlledPopulation.update`: the episode ended; the step failed the
cheap divergence test."""
_KINDS = {NoControl: NO_CONTROL, StaticGain: STATIC_GAIN, StateSpace: STATE_SPACE,
          ScheduledLQR: SCHEDULED_LQR}  # fmt: skip


class StepScratch(NamedTuple):
    """One member's step at a time (kept small so that it stays in cache): the pass at s'
    (``x``, ``p``, ``q``) and Θ1, Θ2 and α δ rounded to the network's dtype, as the single
    run's arrays hold them (``values``)."""

    x: np.ndarray
    p: np.ndarray
    q: np.ndarray
    values: np.ndarray


class StepSettings(NamedTuple):
    """The controlled step's constants: α = Δt (``lr``), γ (``discount``) and whether a
    terminal step bootstraps."""

    lr: float
    discount: float
    bootstrap_terminal: bool


class StagedLoop(NamedTuple):
    """What :meth:`ControlledPopulation.run` writes for the loop: :class:`StepLog`'s ``ep``,
    ``t`` and ``ret``, the signal rows of several steps ``(steps, K, 10)`` from row
    ``start`` on, the last step's environment outputs ``out`` and the divergence test's
    ``q_limit``."""

    ep: np.ndarray
    t: np.ndarray
    ret: np.ndarray
    rows: np.ndarray
    start: int
    out: VectorStep
    q_limit: float


class StepLog(NamedTuple):
    """What a population's step writes for the loop, per member: episode ``ep`` ``(K,)``,
    step ``t`` (counted), return ``ret`` (the reward added), the signal ``rows`` ``(K, 10)``,
    :data:`DONE` / :data:`CHECK` ``flags`` and ``loss_seen``."""

    ep: np.ndarray
    t: np.ndarray
    ret: np.ndarray
    rows: np.ndarray
    flags: np.ndarray
    loss_seen: np.ndarray


class PlanView(NamedTuple):
    """The arrays of an :class:`ExplorationPlan` as the kernels take them."""

    plan: np.ndarray
    uniform: np.ndarray
    epsilon: np.ndarray
    decision: np.ndarray
    per_episode: bool


class ControllerView(NamedTuple):
    """The arrays of a :class:`ControllerArrays` as the kernels take them; ``x`` is the
    controller state ``x_c``."""

    kind: int
    gains: np.ndarray
    loss_weight: np.ndarray
    Ad: np.ndarray
    Bd: np.ndarray
    C: np.ndarray
    D: np.ndarray
    x: np.ndarray
    w_x: np.ndarray
    w_c: float
    research: bool
    target: np.ndarray
    unsolved: np.ndarray


def batchable_controller(controller: RuntimeController) -> bool:
    """Whether :class:`ControllerArrays` can run this runtime controller."""
    return type(controller) in _KINDS


@dataclass
class ControllerArrays:
    """``K`` copies of one runtime controller as arrays, stepped inside the update kernel.

    :attr:`view` holds them as the kernels take them: ``gains`` ``(K, 3)``, static gains or
    the H2 controller's last gains; ``loss_weight`` ``(K,)``; ``Ad, Bd, C, D`` and the
    states ``x`` ``(K, n)`` of a state-space controller (empty otherwise); ``w_x, w_c,
    research, target`` of the scheduled H2 and its per-member count of steps without an LQR
    solution, ``unsolved``.
    """

    view: ControllerView
    """The arrays the kernels step (not copies)."""
    reset_state: bool
    """Whether ``x`` returns to 0 at each episode start."""

    @classmethod
    def of(cls, controller: RuntimeController, k: int) -> ControllerArrays:
        if not batchable_controller(controller):
            raise TypeError(f"{type(controller).__name__} has no batched form")
        kind = _KINDS[type(controller)]
        gains = np.zeros((k, 3))
        Ad = Bd = np.zeros((0, 0))
        C = D = w_x = np.zeros(0)
        n = 0
        w_c, research, reset_state = 0.0, False, False
        target = np.zeros(0)
        if isinstance(controller, StaticGain):
            gains[:] = (controller.k1, controller.k2, controller.k3)
        elif isinstance(controller, StateSpace):
            Ad, Bd, C, D = controller.Ad, controller.Bd, controller.C, controller.D
            n, reset_state = len(C), controller.reset_state
        elif isinstance(controller, ScheduledLQR):
            gains[:] = controller.gains
            w_x, w_c, research = controller.w_x, controller.w_c, controller.research_map
            target = controller.target
        view = ControllerView(
            kind, gains, np.full(k, float(controller.loss_weight)), Ad, Bd, C, D,
            np.zeros((k, n)), w_x, w_c, research, target, np.zeros(k, dtype=np.int64),
        )  # fmt: skip
        return cls(view, reset_state)

    def reset(self, i: int) -> None:
        """Episode start of member ``i``."""
        if self.reset_state:
            self.view.x[i] = 0.0

    def state(self, i: int) -> np.ndarray | None:
        """Member ``i``'s controller state ``x_c`` (None for static controllers)."""
        return self.view.x[i] if self.view.kind == STATE_SPACE else None

    def select(self, keep: np.ndarray) -> None:
        v = self.view
        self.view = v._replace(gains=v.gains[keep], loss_weight=v.loss_weight[keep],
                               x=v.x[keep], unsolved=v.unsolved[keep])  # fmt: skip

    def state_dict(self, i: int) -> dict[str, Any]:
        """Member ``i``'s controller state: ``x_c``, the H2 controller's last gains, loss
        weight and unsolved count."""
        v = self.view
        return {"gains": v.gains[i].copy(), "loss_weight": float(v.loss_weight[i]),
                "x": v.x[i].copy(), "unsolved": int(v.unsolved[i])}  # fmt: skip

    def load_state_dict(self, i: int, state: dict[str, Any]) -> None:
        v = self.view
        v.gains[i], v.loss_weight[i] = state["gains"], state["loss_weight"]
        v.x[i], v.unsolved[i] = state["x"], state["unsolved"]


class ExplorationPlan:
    """ε-greedy decisions of ``K`` members, drawn ``block`` steps ahead from each member's
    generator (:func:`cdqn.agents.base.explore_ahead`).  Under ``eps_schedule=episode`` the
    draws are made ahead (:func:`cdqn.agents.base.draw_ahead`) and compared with each
    member's ε when the step is taken (:func:`cdqn.agents.base.decide`), since ε changes at
    episode ends."""

    def __init__(
        self, cfg: TrainConfig, n_actions: int, rngs: list[np.random.Generator], block: int = 512
    ) -> None:
        self.rngs = list(rngs)
        self.epsilon = np.full(len(rngs), float(cfg.eps_start))
        self.eps_end, self.eps_dec = float(cfg.eps_end), float(cfg.eps_dec)
        self.per_step = cfg.eps_schedule == "step"
        self.per_episode = cfg.eps_schedule == "episode"
        self.n_actions = n_actions
        self.plan = np.empty((block, len(rngs)), dtype=np.int64)
        """Decisions (random action or −1); per episode: the random actions."""
        self.uniform = np.empty((block, len(rngs)) if self.per_episode else (0, len(rngs)))
        """Per episode: the uniforms compared with ε."""
        self.decision = np.empty(len(rngs), dtype=np.int64)
        self.pos = block

    def next(self) -> np.ndarray:
        """This step's decisions ``(K,)``: a random action, or −1 for the greedy one."""
        self.refill()
        self.pos += 1
        if not self.per_episode:
            return self.plan[self.pos - 1]
        decide(self.uniform[self.pos - 1], self.plan[self.pos - 1], self.epsilon, self.decision)
        return self.decision

    def refill(self) -> None:
        """Draw the next block of decisions once every one drawn has been taken."""
        if self.pos == len(self.plan):
            for k in range(len(self.rngs)):
                self._draw(k, 0)
            self.pos = 0

    @property
    def view(self) -> PlanView:
        """The plan as :func:`_run_kernel` takes it."""
        return PlanView(self.plan, self.uniform, self.epsilon, self.decision, self.per_episode)

    def start_episode(self, i: int) -> None:
        """``eps_schedule=episode``: member ``i``'s ε falls by ``eps_dec`` (to ``eps_end``)."""
        if self.per_episode and self.epsilon[i] > self.eps_end:
            self.epsilon[i] = max(self.eps_end, self.epsilon[i] - self.eps_dec)

    def _draw(self, k: int, start: int) -> None:
        """Fill member ``k``'s rows ``start:`` of the plan with its next decisions (per
        episode: draws); ε after them (per step and per decision schedules)."""
        plan = self.plan[start:, k]
        if self.per_episode:
            draw_ahead(self.rngs[k], self.n_actions, self.uniform[start:, k], plan)
            return
        self.epsilon[k] = explore_ahead(
            self.rngs[k], self.epsilon[k], self.eps_end, self.eps_dec, self.per_step,
            self.n_actions, plan,
        )  # fmt: skip

    def select(self, keep: np.ndarray) -> None:
        self.rngs = [self.rngs[i] for i in keep]
        self.epsilon, self.plan = self.epsilon[keep], np.ascontiguousarray(self.plan[:, keep])
        self.uniform = np.ascontiguousarray(self.uniform[:, keep])
        self.decision = self.decision[keep]

    def state_dict(self, i: int) -> dict[str, Any]:
        """Member ``i``'s generator state, ε after the drawn decisions, and the decisions
        (per episode: the draws) drawn but not yet taken (so that a restored plan continues
        bit for bit)."""
        state = {"rng": self.rngs[i].bit_generator.state, "epsilon": float(self.epsilon[i]),
                 "undrawn": self.plan[self.pos :, i].copy()}  # fmt: skip
        if self.per_episode:
            state["undrawn_uniform"] = self.uniform[self.pos :, i].copy()
        return state

    def load_state_dict(self, i: int, state: dict[str, Any]) -> None:
        """Restore member ``i`` into a fresh plan (every member is restored, one after
        another).

        The members share one position in the plan, but members captured at different
        population steps (each at its own episode boundary) hold different numbers of
        undrawn decisions.  The position becomes that of the member holding the most; a
        member holding fewer has its undrawn decisions moved to the position and the rest of
        its rows drawn now from its generator.  Decisions depend on nothing but the member's
        generator and ε, and drawing ``n`` of them in one call or in several gives the same
        decisions and generator state (:func:`cdqn.agents.base.explore_ahead`), so every
        member continues with the decisions it would have taken."""
        self.rngs[i].bit_generator.state = state["rng"]
        self.epsilon[i] = state["epsilon"]
        undrawn = np.asarray(state["undrawn"], dtype=np.int64)
        block = len(self.plan)
        start = block - len(undrawn)
        if start < self.pos:  # the others move up to the earlier position and draw more
            held = block - self.pos
            for k in range(len(self.rngs)):
                if k != i:
                    self.plan[start : start + held, k] = self.plan[self.pos :, k].copy()
                    if self.per_episode:
                        self.uniform[start : start + held, k] = self.uniform[self.pos :, k].copy()
                    self._draw(k, start + held)
            self.pos = start
        self.plan[self.pos : self.pos + len(undrawn), i] = undrawn
        if self.per_episode:
            self.uniform[self.pos : self.pos + len(undrawn), i] = np.asarray(
                state["undrawn_uniform"], dtype=float
            )
        self._draw(i, self.pos + len(undrawn))


class ControlledPopulation:
    """:class:`cdqn.agents.ControlledAgent` (fast path) for ``K`` members at once (module
    docstring)."""

    def __init__(
        self,
        nets: list[QNetwork],
        controller: RuntimeController,
        cfg: TrainConfig,
        reset_integrator: bool,
        rngs: list[np.random.Generator],
        sample: int = 0,
        buffer: int = 50_000,
    ) -> None:
        self.net = StackedTwoLayer.from_networks(nets)
        self.spec = spec = nets[0].spec
        k, dtype = len(nets), self.net.dtype
        self.controller = ControllerArrays.of(controller, k)
        self.explore = ExplorationPlan(cfg, spec.n_actions, rngs)
        self.settings = StepSettings(
            float(cfg.lr), float(cfg.discount), bool(cfg.bootstrap_terminal)
        )
        self.reset_integrator = reset_integrator
        self.x_e = np.zeros(k)
        # Each member's forward pass at s with its current parameters: input (NaN: none
        # yet), pre-activation, Q-values.  The update leaves the pass at s' in them.
        self.x = np.full((k, spec.n_obs), np.nan, dtype)
        self.p = np.empty((k, spec.width), dtype)
        self.q = np.empty((k, spec.n_actions), dtype)
        self.scratch = StepScratch(
            np.empty(spec.n_obs, dtype),
            np.empty(spec.width, dtype),
            np.empty(spec.n_actions, dtype),
            np.empty(3, dtype),
        )
        # Each member's last step's ∂Q_a/∂b_1 and α δ x: its pending W_1 update, if
        # ``pending`` (module docstring).
        self.g = np.zeros((k, spec.width), dtype)
        self.sx = np.zeros((k, spec.n_obs), dtype)
        self.pending = np.zeros(k, dtype=np.bool_)
        self.actions = np.empty(k, dtype=np.int64)
        self.flags = np.zeros(k, dtype=np.int8)
        self.loss_seen = np.zeros(k, dtype=np.bool_)
        self.sample = sample
        """Sampled replay's updates per step (:mod:`cdqn.agents.replay`; 0: off)."""
        self.memory = StackedReplay(k, buffer, spec.n_obs) if sample > 0 else None
        self.samplers = [rng.spawn(1)[0] for rng in rngs] if sample > 0 else []
        """Each member's sampling stream, the single run's (its seed's first child)."""

    def __len__(self) -> int:
        return len(self.x_e)

    @property
    def epsilon(self) -> np.ndarray:
        """Each member's ε after the decisions drawn so far."""
        return self.explore.epsilon

    def start_episode(self, i: int) -> None:
        self.explore.start_episode(i)
        if self.reset_integrator:
            self.x_e[i] = 0.0
        self.controller.reset(i)

    def act(self, obs: np.ndarray) -> np.ndarray:
        """ε-greedy actions ``(K,)`` (the array is reused by the next call)."""
        _act_kernel(tuple(self.net.params), tuple(self.passes), tuple(self.deferred), obs,
                    self.explore.next(), self.actions)  # fmt: skip
        return self.actions

    @property
    def passes(self) -> StackedForward:
        """Each member's forward pass at ``s`` with its current parameters."""
        return StackedForward(self.x, self.p, self.q)

    @property
    def deferred(self) -> StackedPending:
        """Each member's pending ``W_1`` update (module docstring)."""
        return StackedPending(self.sx, self.g, self.pending)

    def flush(self) -> None:
        """Apply every member's pending ``W_1`` update (module docstring)."""
        _flush_kernel(self.net.w1t, tuple(self.deferred))

    def update(self, actions: np.ndarray, step: VectorStep, loop: LoopState) -> int:
        """One controlled step of every member on the environments' ``step``.

        Writes each member's signal row (columns of :data:`cdqn.training.signals.COLUMNS`,
        episode ``loop.ep``, step ``loop.t``) into ``loop.rows``, then adds the reward to
        ``loop.ret`` and counts the step in ``loop.t``.  :attr:`flags` tells the loop what
        needs its attention: :data:`CHECK` for a step that fails the cheap divergence test
        (``u + x_e + loss`` finite and ``max(|Q1|, |Q2|) ≤ loop.q_limit``; a healthy step
        always passes it), :data:`DONE` for the end of an episode, 0 otherwise;
        :attr:`loss_seen` records that a member has had a step that passed.  Returns the
        number of flagged members.
        """
        log = StepLog(loop.ep, loop.t, loop.ret, loop.rows, self.flags, self.loss_seen)
        return _update_kernel(
            tuple(self.net.params), tuple(self.passes), tuple(self.scratch),
            tuple(self.deferred), actions, tuple(step), tuple(self.settings),
            tuple(self.controller.view), self.x_e, tuple(log), loop.q_limit,
        )  # fmt: skip

    def run(self, obs: np.ndarray, twin: TwinArrays, loop: StagedLoop, steps: int) -> int:
        """Up to ``steps`` population steps in one compiled call (:func:`_run_kernel`):
        each is :meth:`act` on ``obs``, :func:`cdqn.vector_env.twin_step` into
        ``loop.out``, :meth:`update` with its signal rows in ``loop.rows[loop.start + n]``,
        and ``obs`` becomes ``loop.out.obs``.  It stops after the first step that flags a
        member (:attr:`flags`), before a step the exploration plan or ``loop.rows`` has no
        row for, and after ``steps``.  Returns the steps taken; each member's numbers are
        those of :meth:`act`, :meth:`cdqn.vector_env.ClassicControlTwin.step` and
        :meth:`update` step by step."""
        self.explore.refill()
        limit = min(steps, len(self.explore.plan) - self.explore.pos, len(loop.rows) - loop.start)
        taken = _run_kernel(
            tuple(self.net.params), tuple(self.passes), tuple(self.scratch),
            tuple(self.deferred), tuple(self.explore.view), self.explore.pos, tuple(twin), obs,
            self.actions, tuple(loop.out), tuple(self.settings), tuple(self.controller.view),
            self.x_e, (loop.ep, loop.t, loop.ret, loop.rows, self.flags, self.loss_seen),
            loop.start, loop.q_limit, limit,
        )  # fmt: skip
        self.explore.pos += taken
        return taken

    def replay(self, k: int, tail: Transitions, repeats: int, q_limit: float) -> int:
        """Episodic replay of member ``k`` (:func:`_replay_kernel`); returns the number of
        updates, negative (−(i + 1)) when update ``i`` failed the divergence test."""
        dtype = self.x.dtype
        tail = tail._replace(
            obs=np.ascontiguousarray(tail.obs, dtype=dtype),
            next_obs=np.ascontiguousarray(tail.next_obs, dtype=dtype),
        )
        return _replay_kernel(
            k, tuple(self.net.params), tuple(self.passes), tuple(self.scratch),
            tuple(self.deferred), tuple(tail), repeats, tuple(self.settings),
            tuple(self.controller.view), self.x_e, q_limit,
        )  # fmt: skip

    def replay_sampled(self, obs: np.ndarray, actions: np.ndarray, step: VectorStep,
                       q_limit: float) -> np.ndarray:  # fmt: skip
        """Sampled replay of every member after the step from ``obs`` (:mod:`cdqn.agents.replay`,
        :func:`_sampled_kernel`): the transitions enter the buffers, each member draws
        :attr:`sample` of its own.  Per member, the index of the replayed update that failed
        the divergence test, or −1."""
        assert self.memory is not None
        mem, k = self.memory, len(self.x_e)
        mem.add_all(Batch(obs, actions, step.reward, step.obs, step.terminated))
        draws = zip(self.samplers, mem.size, strict=True)
        idx = np.stack([g.integers(n, size=self.sample) for g, n in draws])
        failed = np.full(k, -1, dtype=np.int64)
        _sampled_kernel(
            tuple(self.net.params), tuple(self.passes), tuple(self.scratch),
            tuple(self.deferred), (mem.obs, mem.actions, mem.rewards, mem.next_obs,
            mem.terminated), idx, tuple(self.settings), tuple(self.controller.view), self.x_e,
            q_limit, failed,
        )  # fmt: skip
        return failed

    def select(self, keep: np.ndarray) -> None:
        """Keep only the members ``keep`` (indices, in that order)."""
        self.flush()
        if self.memory is not None:
            self.memory.select(keep)
            self.samplers = [self.samplers[j] for j in keep]
        self.g, self.sx, self.pending = self.g[keep], self.sx[keep], self.pending[keep]
        self.net.select(keep)
        self.controller.select(keep)
        self.explore.select(keep)
        self.x_e = self.x_e[keep]
        self.x, self.p, self.q = self.x[keep], self.p[keep], self.q[keep]
        self.actions, self.flags = self.actions[keep], self.flags[keep]
        self.loss_seen = self.loss_seen[keep]

    def state_dict(self, i: int) -> dict[str, Any]:
        """Member ``i``'s state between two steps: parameters, the cached forward pass at
        ``s``, the integrator ``x_e``, controller and exploration state (the population
        agents' checkpoint protocol, :mod:`cdqn.training.population_checkpoint`)."""
        self.flush()
        n = self.net
        return {
            "w1t": n.w1t[i].copy(), "b1": n.b1[i].copy(), "w2": n.w2[i].copy(),
            "b2": n.b2[i].copy(), "x": self.x[i].copy(), "p": self.p[i].copy(),
            "q": self.q[i].copy(), "x_e": float(self.x_e[i]),
            "loss_seen": bool(self.loss_seen[i]),
            "controller": self.controller.state_dict(i),
            "explore": self.explore.state_dict(i),
            "memory": None if self.memory is None
            else self.memory.state_dict(i, self.samplers[i]),
        }  # fmt: skip

    def load_state_dict(self, i: int, state: dict[str, Any]) -> None:
        """Put member ``i`` into ``state`` (from :meth:`state_dict`)."""
        n = self.net
        n.w1t[i], n.b1[i], n.w2[i], n.b2[i] = state["w1t"], state["b1"], state["w2"], state["b2"]
        self.pending[i] = False
        self.x[i], self.p[i], self.q[i] = state["x"], state["p"], state["q"]
        self.x_e[i], self.loss_seen[i] = state["x_e"], state["loss_seen"]
        self.controller.load_state_dict(i, state["controller"])
        self.explore.load_state_dict(i, state["explore"])
        if self.memory is not None:
            self.memory.load_state_dict(i, state["memory"], self.samplers[i])

    def network(self, i: int) -> QNetwork:
        """Member ``i``'s network as a :class:`QNetwork`."""
        net = QNetwork(self.spec)
        self.flush()
        self.net.copy_to(i, net)
        return net


@njit(cache=True)
def flag_step(log, k, healthy, ended):
    """The loop's flag of member ``k``'s step into ``log.flags[k]``: :data:`CHECK` unless
    ``healthy`` (it passed the cheap divergence test), else :data:`DONE` if the episode
    ``ended``, else 0; a healthy step sets ``log.loss_seen[k]``.  Returns whether it is
    flagged."""
    if not healthy:
        log.flags[k] = CHECK
    elif ended:
        log.flags[k] = DONE
        log.loss_seen[k] = True
    else:
        log.flags[k] = 0
        log.loss_seen[k] = True
    return log.flags[k] != 0


@njit(cache=True)
def _flush_kernel(w1t, pending):
    d = StackedPending(*pending)
    for k in range(w1t.shape[0]):
        if d.pending[k]:
            apply_pending_row(w1t[k], d.sx[k], d.g[k])
            d.pending[k] = False


@njit(cache=True)
def _act_kernel(net, passes, pending, obs, plan, actions):
    """Per member: the forward pass at ``obs`` (applying a pending ``W_1`` update) unless
    ``x`` already holds it (as :meth:`cdqn.network.StackedTwoLayer.forward` with ``reuse``),
    then the planned random action or ``argmax Q(obs, ·)``.  Bundles as plain tuples
    (:mod:`cdqn.network`, bundles)."""
    n, f, d = Params(*net), StackedForward(*passes), StackedPending(*pending)
    for k in range(obs.shape[0]):
        _pass_at(k, obs[k], n, f, d)
        actions[k] = plan[k] if plan[k] >= 0 else np.argmax(f.q[k])


@njit(cache=True)
def _pass_at(k, obs, n, f, d):
    """Member ``k``'s forward pass at ``obs`` into ``f.x[k], f.p[k], f.q[k]`` (applying its
    pending ``W_1`` update), unless ``f.x[k]`` already holds ``obs``."""
    same = True
    for i in range(obs.shape[0]):
        if obs[i] != f.x[k, i]:
            same = False
    if not same:
        for i in range(obs.shape[0]):
            f.x[k, i] = obs[i]
        forward_pending_row(member_params(n, k), member_pass(f, k), member_pending(d, k))
        d.pending[k] = False


@njit(cache=True)
def _control(k, c, theta1, theta2, discount, xe, q1, q_next):
    """Member ``k``'s control input ``u = K(x_e, Q1, Q̂2)`` of the controller ``c``
    (:class:`ControllerView`), stepping its state (:mod:`cdqn.control.kernels`)."""
    if c.kind == NO_CONTROL:
        return 0.0
    if c.kind == STATIC_GAIN:
        return static_gain_u(c.gains[k, 0], c.gains[k, 1], c.gains[k, 2], xe, q1, q_next)
    if c.kind == STATE_SPACE:
        return state_space_step(c.Ad, c.Bd, c.C, c.D, c.x[k], xe, q1, q_next)
    u, c.loss_weight[k], solved = scheduled_lqr_step(
        theta1, theta2, discount, c.w_x, c.w_c, c.research, c.target, c.gains[k], xe, q1, q_next
    )
    if not solved:
        c.unsolved[k] += 1
    return u


@njit(cache=True)
def _controlled_step(k, n, f, s2, d, a, reward, terminated, settings, c, x_e):
    """Member ``k``'s controlled step on the transition ``(f.x[k], a, reward, s2.x)``, in the
    order of operations of :meth:`cdqn.agents.ControlledAgent.update`: ``f`` holds the pass
    at ``s``, ``s2.x`` holds ``s'``; afterwards ``f`` holds the pass at ``s'`` with the new
    parameters, and the step's ``W_1`` update is pending in ``d`` (module docstring).
    Returns ``(Q1, Q2, u, x_e, Θ1, Θ2, loss)``."""
    nk, fk, dk = member_params(n, k), member_pass(f, k), member_pending(d, k)
    f2, values = Forward(s2.x, s2.p, s2.q), s2.values
    forward_pending_row(nk, f2, dk)
    b = np.argmax(f2.q)
    q1, q2 = float(fk.q[a]), float(f2.q[b])
    values[0], values[1] = td_row(nk.w2, fk, f2, a, b, dk.g)
    theta1, theta2 = float(values[0]), float(values[1])
    q_next = q2 if (settings.bootstrap_terminal or not terminated) else 0.0

    alpha, discount = settings.lr, settings.discount
    error = reward + discount * q_next - q1
    x_e[k] += alpha * error
    xe = x_e[k]
    u = _control(k, c, theta1, theta2, discount, xe, q1, q_next)
    delta = error + u
    loss = 0.5 * c.loss_weight[k] * delta * delta
    values[2] = alpha * delta
    # the step; the member's pass becomes the one at s' with the new parameters
    sgd_deferred_row(nk, fk, a, values[2], f2, fk, dk)
    d.pending[k] = True
    for i in range(f2.x.shape[0]):
        f.x[k, i] = f2.x[i]
    return q1, q2, u, xe, theta1, theta2, loss


@njit(cache=True)
def _update_kernel(net, passes, scratch, pending, actions, step, settings, controller, x_e,
                   log, q_limit):  # fmt: skip
    """:meth:`ControlledPopulation.update` (module docstring), member by member
    (:func:`_controlled_step`).  Bundles as plain tuples (:mod:`cdqn.network`, bundles):
    :class:`~cdqn.network.Params`, :class:`~cdqn.network.StackedForward`,
    :class:`StepScratch`, :class:`~cdqn.network.StackedPending`,
    :class:`cdqn.vector_env.VectorStep`, :class:`StepSettings`, :class:`ControllerView`,
    :class:`StepLog`."""
    n, f, s2 = Params(*net), StackedForward(*passes), StepScratch(*scratch)
    d = StackedPending(*pending)
    st, c, lg = VectorStep(*step), ControllerView(*controller), StepLog(*log)
    stp = StepSettings(*settings)
    flagged = 0
    for k in range(actions.shape[0]):
        for i in range(s2.x.shape[0]):
            s2.x[i] = st.obs[k, i]
        reward = st.reward[k]
        q1, q2, u, xe, theta1, theta2, loss = _controlled_step(
            k, n, f, s2, d, actions[k], reward, st.terminated[k], stp, c, x_e
        )
        row = lg.rows[k]
        row[0], row[1], row[2], row[3], row[4] = lg.ep[k], lg.t[k], reward, q1, q2
        row[5], row[6], row[7], row[8], row[9] = u, xe, theta1, theta2, loss
        lg.ret[k] += reward
        lg.t[k] += 1
        healthy = math.isfinite(u + xe + loss) and max(abs(q1), abs(q2)) <= q_limit
        flagged += flag_step(lg, k, healthy, st.terminated[k] or st.truncated[k])
    return flagged


@njit(cache=True)
def _run_kernel(net, passes, scratch, pending, explore, pos, twin, obs, actions, out, settings,
                controller, x_e, log, start, q_limit, limit):  # fmt: skip
    """:meth:`ControlledPopulation.run`: per step, the plan's decisions (as
    :meth:`ExplorationPlan.next`), :func:`_act_kernel`, :func:`cdqn.vector_env.twin_step`,
    :func:`_update_kernel` into the rows ``start + n`` of ``log``'s rows ``(·, K, 10)``;
    returns the steps taken."""
    e, st = PlanView(*explore), VectorStep(*out)
    ep, t, ret, rows, flags, loss_seen = log
    for n in range(limit):
        decisions = e.plan[pos + n]
        if e.per_episode:
            decide(e.uniform[pos + n], decisions, e.epsilon, e.decision)
            decisions = e.decision
        _act_kernel(net, passes, pending, obs, decisions, actions)
        twin_step(twin, actions, out)
        flagged = _update_kernel(net, passes, scratch, pending, actions, out, settings,
                                 controller, x_e, (ep, t, ret, rows[start + n], flags,
                                 loss_seen), q_limit)  # fmt: skip
        obs[:] = st.obs
        if flagged:
            return n + 1
    return limit


@njit(cache=True)
def _replay_kernel(k, net, passes, scratch, pending, tail, repeats, settings, controller, x_e,
                   q_limit):  # fmt: skip
    """Episodic replay of member ``k``: ``repeats`` passes over the transitions ``tail``
    (:class:`cdqn.agents.episodic_replay.Transitions`) in order, each through
    :func:`_controlled_step` after the forward pass at its ``obs`` (reused when the member's
    pass already holds it, as :meth:`cdqn.agents.ControlledAgent.update` reuses its cached
    pass).  Returns the number of updates, or ``−(i + 1)`` when update ``i`` failed the
    divergence test.  Bundles as in :func:`_update_kernel`."""
    n, f, s2 = Params(*net), StackedForward(*passes), StepScratch(*scratch)
    d, tr, c = StackedPending(*pending), Transitions(*tail), ControllerView(*controller)
    stp = StepSettings(*settings)
    count = 0
    for _ in range(repeats):
        for j in range(tr.obs.shape[0]):
            _pass_at(k, tr.obs[j], n, f, d)
            for i in range(s2.x.shape[0]):
                s2.x[i] = tr.next_obs[j, i]
            q1, q2, u, xe, theta1, theta2, loss = _controlled_step(
                k, n, f, s2, d, tr.actions[j], tr.rewards[j], tr.terminated[j], stp, c, x_e
            )
            if not (math.isfinite(u + xe + loss) and max(abs(q1), abs(q2)) <= q_limit):
                return -(count + 1)
            count += 1
    return count


@njit(cache=True)
def _sampled_kernel(net, passes, scratch, pending, memory, idx, settings, controller, x_e,
                    q_limit, failed):  # fmt: skip
    """Sampled replay (:meth:`ControlledPopulation.replay_sampled`): member ``k``'s
    transitions ``idx[k]`` of its buffer ``memory`` (``obs, actions, rewards, next_obs,
    terminated``, each ``(K, capacity, …)``) pass in order through :func:`_controlled_step`
    after the forward pass at their ``obs``, as in :func:`_replay_kernel`.  ``failed[k]``:
    the index of the update that failed the divergence test (the member stops there), or
    left at −1.  Bundles as in :func:`_update_kernel`."""
    n, f, s2 = Params(*net), StackedForward(*passes), StepScratch(*scratch)
    d, c, stp = StackedPending(*pending), ControllerView(*controller), StepSettings(*settings)
    obs, actions, rewards, next_obs, terminated = memory
    for k in range(idx.shape[0]):
        for j in range(idx.shape[1]):
            i = idx[k, j]
            _pass_at(k, obs[k, i], n, f, d)
            for m in range(s2.x.shape[0]):
                s2.x[m] = next_obs[k, i, m]
            q1, q2, u, xe, theta1, theta2, loss = _controlled_step(
                k, n, f, s2, d, actions[k, i], rewards[k, i], terminated[k, i] != 0.0, stp, c, x_e
            )
            if not (math.isfinite(u + xe + loss) and max(abs(q1), abs(q2)) <= q_limit):
                failed[k] = j
                break
