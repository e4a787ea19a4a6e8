"""The training loop of a population: ``K`` members stepped as one batch.

:func:`train_population` is :func:`cdqn.training.loop.train` for all members at once: one
call of the batched agent (:mod:`cdqn.agents.controlled_population`,
:mod:`cdqn.agents.ddqn_population`) and of the vectorised environment
(:mod:`cdqn.vector_env`) per population step, or one call for the steps up to the next that
needs the loop (:meth:`~cdqn.agents.controlled_population.ControlledPopulation.run`), each
member's signal rows and divergence test as a single run has them, members leaving the
batch when they finish or diverge.

Checkpoints (:class:`Checkpoints`, written by :mod:`cdqn.training.population`) follow one
of two schedules, by what the environments allow (:mod:`cdqn.vector_env`):

* **between two steps** (CartPole, Acrobot, MountainCar): each time the slowest member has
  completed another ``every`` episodes, and when a stop is asked, every member is captured
  at that population step, most of them inside an episode;
* **at episode boundaries** (any other environment): checkpoint ``n`` is due when the
  slowest member has completed ``D_n`` episodes (a multiple of ``every``).  Each member is
  captured at its own first episode boundary with at least ``D_n`` episodes completed
  (after the episode is recorded, before the reset that starts the next), and the capture
  is held until every member still training has one; then all are written as checkpoint
  ``n``, and ``D_{n+1}`` is the next multiple of ``every`` above the slowest member's
  count.  A stop drains the population: the members keep stepping, each is captured at
  the end of its current episode and leaves the batch KILLED with its checkpoint written,
  all of them into one checkpoint; a second signal stops at once (the last periodic
  checkpoint is then the one to resume from).  A resumed member starts its next episode
  with a reset from its restored ``np_random``; as its numbers depend on nothing but its
  own state, members restored at different episodes (and population steps) continue
  exactly as they would have (the shared exploration plan is realigned,
  :meth:`cdqn.agents.controlled_population.ExplorationPlan.load_state_dict`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm.auto import tqdm

from cdqn.agents.base import LoopState, StepRecord
from cdqn.agents.controlled_population import CHECK, DONE, ControlledPopulation, StagedLoop
from cdqn.agents.episodic_replay import PopulationTail, Transitions, qualifies
from cdqn.config import ReplayConfig
from cdqn.control.box import Box
from cdqn.records import column
from cdqn.training.divergence import (
    DivergenceError,
    check_controller,
    check_step,
    failure_reason,
    replay_failed,
)
from cdqn.training.loop import EpisodeStats
from cdqn.training.loop import episode_stats as episode_stats  # cdqn.profile times it here
from cdqn.training.member import Member
from cdqn.training.signals import COLUMNS
from cdqn.vector_env import ClassicControlTwin, VectorEnv, VectorStep

if TYPE_CHECKING:
    from cdqn.agents.base import PopulationAgent as Population

RUN_AHEAD = 256
"""Most population steps between two looks at ``should_stop`` and the checkpoint schedule
(a step that ends an episode or needs the divergence check returns earlier)."""

_RECORD = tuple(column(c) for c in StepRecord._fields)
"""Indices of a :class:`StepRecord`'s fields among the signal columns."""


@dataclass
class Checkpoints:
    """How the loop checkpoints a population (module docstring)."""

    every: int
    """Episodes of the slowest member between two periodic checkpoints (0: only at a stop)."""
    mid_episode: bool
    """Members are captured between any two steps; else each at its episode boundaries."""
    capture: Callable[[int, Member, np.ndarray, np.ndarray, np.ndarray], Any]
    """``capture(j, m, obs, t, ret)``: member ``m`` (row ``j``) as it stands now."""
    write: Callable[[list[tuple[Member, Any]], bool], None]
    """``write(captured, new)``: store the captures as a new checkpoint (``new``) or into
    the one written last (a drain's members, one after another)."""


class _Schedule:
    """When members are captured and checkpoints written (module docstring)."""

    def __init__(self, ckpts: Checkpoints | None, members: list[Member]) -> None:
        self.ckpts = ckpts
        self.every = ckpts.every if ckpts is not None else 0
        self.due = self.next_due(members)
        self.pending: dict[int, Any] = {}
        """Captures at episode boundaries for the checkpoint due, by seed."""
        self.draining = False
        self.drained = 0

    @property
    def at_boundaries(self) -> bool:
        return self.ckpts is not None and not self.ckpts.mid_episode

    def next_due(self, members: list[Member]) -> int:
        slowest = min(m.episode for m in members)
        return (slowest // self.every + 1) * self.every if self.every else 0

    def boundary(self, j: int, m: Member, obs: np.ndarray, t: np.ndarray, ret: np.ndarray) -> bool:
        """Member ``m`` (row ``j``) completed an episode and goes on: capture it if this is
        its boundary; True when it leaves the batch (a drain)."""
        c = self.ckpts
        if c is None or c.mid_episode:
            return False
        if self.draining:
            c.write([(m, c.capture(j, m, obs, t, ret))], self.drained == 0)
            self.drained += 1
            m.status = "KILLED"
            return True
        if self.every and m.episode >= self.due and m.seed not in self.pending:
            self.pending[m.seed] = c.capture(j, m, obs, t, ret)
        return False

    def drain(self) -> bool:
        """A stop was asked: True when the members drain (at episode boundaries)."""
        if self.at_boundaries:
            self.draining = True
            self.pending.clear()
        return self.draining

    def periodic(
        self, members: list[Member], capture_all: Callable[[], list[tuple[Member, Any]]]
    ) -> None:
        """After a population step: write the checkpoint due, if it is complete."""
        c = self.ckpts
        if c is None or not self.every or self.draining:
            return
        if c.mid_episode:
            if min(m.episode for m in members) < self.due:
                return
            c.write(capture_all(), True)
        elif all(m.seed in self.pending for m in members):
            c.write([(m, self.pending[m.seed]) for m in members], True)
            self.pending.clear()
        else:
            return
        self.due = self.next_due(members)


class _Staging:
    """Per-step signal rows of all active members, written as one ``(K, 10)`` block per
    step and moved into each member's :class:`SignalBuffer` in blocks."""

    def __init__(self, k: int, capacity: int = 2048) -> None:
        self.data = np.empty((capacity, k, len(COLUMNS)))
        self.n = 0
        self.flushed = np.zeros(k, dtype=np.int64)

    def next_block(self, members: list[Member]) -> np.ndarray:
        """The ``(K, 10)`` block of this step's rows, to be written in place."""
        if self.n == len(self.data):
            self.flush_all(members)
        self.n += 1
        return self.data[self.n - 1]

    def flush(self, j: int, member: Member) -> None:
        member.signals.extend(self.data[self.flushed[j] : self.n, j])
        self.flushed[j] = self.n

    def flush_all(self, members: list[Member]) -> None:
        for j, member in enumerate(members):
            self.flush(j, member)
        self.n = 0
        self.flushed[:] = 0

    def select(self, keep: np.ndarray, members: list[Member]) -> None:
        self.flush_all(members)
        self.data = np.empty((len(self.data), len(keep), len(COLUMNS)))
        self.flushed = np.zeros(len(keep), dtype=np.int64)


def train_population(
    agent: Population,
    venv: VectorEnv,
    members: list[Member],
    *,
    episodes: int,
    discount: float,
    q_limit: float,
    on_episode: Callable[[Member, EpisodeStats], None] | None = None,
    on_member_end: Callable[[Member, Population, int], None] | None = None,
    progress: bool = False,
    should_stop: Callable[[], bool] | None = None,
    max_steps: int | None = None,
    checkpoints: Checkpoints | None = None,
    replay: ReplayConfig | None = None,
    box: Box | None = None,
    step_by_step: bool = False,
    on_steps: Callable[[int], None] | None = None,
) -> None:
    """The training loop of :func:`cdqn.training.loop.train` for all members at once.

    Each member's environment is seeded with its seed at its first episode.  A member that
    finishes its ``episodes`` or diverges (:mod:`cdqn.training.divergence`) leaves the batch
    (``on_member_end`` is called with the member, the agent and its row, before the row is
    dropped).  ``max_steps`` (for the benchmark) ends the loop after that many population
    steps.  ``replay``: episodic replay after each member's qualifying episode, as
    :func:`cdqn.training.loop.train` does it; ``box``: the design's NTK box, for
    ``theta1_outside_box``, ``ratio_below_box`` and ``ratio_above_box``.

    A controlled population on a twin without radial features takes up to
    :data:`RUN_AHEAD` steps per compiled call (:meth:`ControlledPopulation.run`) and
    returns to this loop after a step that ends a member's episode or needs the divergence
    check, with the same numbers as step by step; ``step_by_step`` (for the profiler)
    takes one step per call of each part.  ``should_stop`` is asked, and ``on_steps`` told
    the population steps taken, after each call.

    ``checkpoints``: when and how members are captured and written (module docstring);
    with every member's signal rows flushed.  A member with a ``carry`` continues from it
    instead of starting with a reset; one without starts its next episode with a reset,
    seeded with its seed at its first episode.
    """
    ends = _Ends(episodes, discount, q_limit, box, on_episode)
    batch = _Batch(agent, venv, list(members), checkpoints, replay, step_by_step)
    bar = tqdm(total=episodes * len(members), disable=not progress, unit="ep", leave=True)
    steps = 0
    try:
        while batch.members:
            # one step first: a stop asked while the runs opened (a trial's time cap) ends
            # the loop before any episode does, as step by step
            limit = RUN_AHEAD if steps else 1
            limit = limit if max_steps is None else min(limit, max_steps - steps)
            leaving, taken = batch.step(ends, bar, limit)
            steps += taken
            if on_steps is not None:
                on_steps(taken)
            stop = not batch.schedule.draining and should_stop is not None and should_stop()
            if stop and batch.schedule.drain():  # each member leaves at the end of its episode
                stop = False
            if stop or (max_steps is not None and steps >= max_steps):
                leaving = batch.stop(leaving, write=stop)
            if leaving and not batch.leave(leaving, on_member_end):
                break
            if batch.schedule.every:
                batch.schedule.periodic(batch.members, batch.capture_all)
    finally:
        bar.close()


@dataclass
class _Ends:
    """What the loop does when a member's episode ends: the run's settings."""

    episodes: int
    discount: float
    q_limit: float
    box: Box | None
    on_episode: Callable[[Member, EpisodeStats], None] | None


class _Batch:
    """The members still training and the loop's per-member arrays, row ``j`` for
    ``members[j]``: observation, step within the episode, return so far, episode index."""

    def __init__(
        self,
        agent: Population,
        venv: VectorEnv,
        members: list[Member],
        checkpoints: Checkpoints | None,
        replay: ReplayConfig | None,
        step_by_step: bool,
    ) -> None:
        self.agent, self.venv, self.members = agent, venv, members
        self.checkpoints, self.replay = checkpoints, replay
        first = [
            venv.reset(j, m.seed if m.episode == 0 else None) if m.carry is None else m.carry["obs"]
            for j, m in enumerate(members)
        ]
        self.obs = np.stack(first)
        for j, m in enumerate(members):
            if m.carry is None:
                agent.start_episode(j)
        self.t = np.array([m.carry["t"] if m.carry else 0 for m in members], dtype=np.int64)
        self.ret = np.array([m.carry["ret"] if m.carry else 0.0 for m in members])
        self.schedule = _Schedule(checkpoints, members)
        self.ep = np.array([m.episode for m in members], dtype=float)
        self.staging = _Staging(len(members))
        self.tail = self._tail() if replay is not None and replay.repeats > 0 else None
        self.sampled = getattr(agent, "memory", None) is not None
        """Whether the members replay sampled transitions after each step."""
        fused = isinstance(agent, ControlledPopulation) and self.tail is None and not self.sampled
        fused = fused and not step_by_step
        self.twin: ClassicControlTwin | None = None
        if fused and isinstance(venv, ClassicControlTwin) and venv.compiled:
            self.twin = venv
        """The environments, when the agent takes several steps on them in one compiled
        call (:meth:`ControlledPopulation.run`)."""

    def _tail(self) -> PopulationTail:
        """The transitions of each member's episode in progress (episodic replay)."""
        assert self.replay is not None
        spec = getattr(self.venv.envs[0].spec, "max_episode_steps", None)
        tail = PopulationTail(
            len(self.members), self.obs.shape[1], self.replay.last or spec or 10_000
        )
        for j, m in enumerate(self.members):
            if m.carry is not None and m.carry.get("replay_tail") is not None:
                tail.restore(j, Transitions(**m.carry["replay_tail"]))
        return tail

    def _replay_steps(self, j: int) -> int:
        """Transitions of member ``j``'s episode that episodic replay uses."""
        assert self.replay is not None
        return min(int(self.t[j]), self.replay.last or int(self.t[j]))

    def capture_now(self, items: list[tuple[int, Member]]) -> list[tuple[Member, Any]]:
        """``items`` captured between two steps (signal rows flushed, each member's
        transitions of the episode in progress attached)."""
        assert self.checkpoints is not None
        self.staging.flush_all(self.members)
        for j, m in items:
            if self.tail is not None:
                m.replay_tail = self.tail.transitions(j, self._replay_steps(j))
        return [(m, self.checkpoints.capture(j, m, self.obs, self.t, self.ret)) for j, m in items]

    def capture_all(self) -> list[tuple[Member, Any]]:
        return self.capture_now(list(enumerate(self.members)))

    def step(self, ends: _Ends, bar: tqdm, limit: int) -> tuple[list[int], int]:
        """Population steps, at most ``limit``, up to the first that flags a member (one at
        a time, or several in one compiled call where the agent and environments allow it:
        :meth:`ControlledPopulation.run`); the rows of the members that leave the batch, and
        the steps taken."""
        agent = self.agent
        if self.twin is not None:
            assert isinstance(agent, ControlledPopulation)
            if self.staging.n == len(self.staging.data):
                self.staging.flush_all(self.members)
            out = self.twin.outputs()
            staged = StagedLoop(self.ep, self.t, self.ret, self.staging.data, self.staging.n,
                                out, ends.q_limit)  # fmt: skip
            taken = agent.run(self.obs, self.twin.arrays(), staged, limit)
            self.staging.n += taken
            rows = self.staging.data[self.staging.n - 1]
            return self._after(out, rows, int(agent.flags.any()), None, ends, bar), taken
        actions = agent.act(self.obs)
        out = self.venv.step(actions)
        rows = self.staging.next_block(self.members)
        loop = LoopState(self.ep, self.t, self.ret, rows, ends.q_limit)
        flagged = agent.update(actions, out, loop)
        if self.tail is not None:
            self.tail.append(self.obs, actions, out.reward, out.obs, out.terminated)
        failed = None
        if self.sampled:
            assert isinstance(agent, ControlledPopulation)
            failed = agent.replay_sampled(self.obs, actions, out, ends.q_limit)
        self.obs = out.obs
        return self._after(out, rows, flagged, failed, ends, bar), 1

    def _after(
        self,
        out: VectorStep,
        rows: np.ndarray,
        flagged: int,
        failed: np.ndarray | None,
        ends: _Ends,
        bar: tqdm,
    ) -> list[int]:
        """The members a step flagged (``out``: its environment outputs, ``rows``: its
        signal rows, ``failed``: sampled replay's failures): the divergence check and
        episode ends; the rows of the members that leave the batch."""
        agent = self.agent
        leaving: list[int] = []
        if flagged or (failed is not None and failed.max() >= 0):
            flags = agent.flags
            for j in np.flatnonzero(flags == CHECK).tolist():  # the single run's exact test
                if self._checked(j, rows[j], ends.q_limit):
                    flags[j] = DONE if out.terminated[j] or out.truncated[j] else 0
                else:
                    leaving.append(j)
            if failed is not None:
                self._sampled_failures(failed, flags, leaving)
            for j in np.flatnonzero(flags == DONE).tolist():
                end = (bool(out.terminated[j]), bool(out.truncated[j]), float(self.ret[j]))
                if self._episode_end(j, end, ends, bar):
                    leaving.append(j)
        return leaving

    def _sampled_failures(self, failed: np.ndarray, flags: np.ndarray, leaving: list[int]) -> None:
        """Members whose sampled replay (:mod:`cdqn.agents.replay`) failed the divergence
        test after a healthy step leave the batch FAILED, without their episode's end."""
        for j in np.flatnonzero(failed >= 0).tolist():
            if j in leaving:  # the step itself failed first, as in a single run
                continue
            m = self.members[j]
            err = replay_failed(int(failed[j]), m.episode, int(self.t[j] - 1), "sampled")
            m.status, m.reason = "FAILED", failure_reason(err)
            flags[j] = 0
            leaving.append(j)

    def _checked(self, j: int, row: np.ndarray, q_limit: float) -> bool:
        """The divergence check of member ``j``'s step (flagged by the kernel's cheap test);
        False when it diverged (closed FAILED)."""
        values = row.tolist()
        rec = StepRecord(*(values[i] for i in _RECORD))
        m, loss_seen = self.members[j], self.agent.loss_seen
        try:
            loss_seen[j] = check_step(
                rec, q_limit, bool(loss_seen[j]), m.episode, int(self.t[j] - 1)
            )
        except DivergenceError as err:
            m.status, m.reason = "FAILED", failure_reason(err)
            return False
        return True

    def _episode_end(self, j: int, end: tuple[bool, bool, float], ends: _Ends, bar: tqdm) -> bool:
        """Member ``j``'s episode ended (``end``: terminated, truncated, return): replay,
        check, record, then reset or leave; True when it leaves the batch."""
        m, t = self.members[j], self.t
        self.staging.flush(j, m)
        try:
            replayed = self._replayed(j, end, ends.q_limit)
            check_controller(self.agent.controller.state(j), m.episode, int(t[j] - 1))
        except DivergenceError as err:
            m.status, m.reason = "FAILED", failure_reason(err)
            return True
        m.returns.append(float(self.ret[j]))
        start = m.signals.n - int(t[j])
        stats = episode_stats(m.episode, m.signals.rows(start), m.returns, ends.discount,
                              replayed, ends.box)  # fmt: skip
        m.episode += 1
        if ends.on_episode is not None:
            ends.on_episode(m, stats)
        bar.update(1)
        if m.episode >= ends.episodes:
            m.status = "FINISHED"
            return True
        if self.schedule.boundary(j, m, self.obs, t, self.ret):
            return True
        self.obs[j] = self.venv.reset(j, None)
        self.agent.start_episode(j)
        t[j], self.ret[j], self.ep[j] = 0, 0.0, m.episode
        return False

    def _replayed(self, j: int, end: tuple[bool, bool, float], q_limit: float) -> int:
        """Episodic replay of member ``j``'s episode if it qualifies; the updates made."""
        if self.tail is None or self.replay is None or not qualifies(self.replay, *end):
            return 0
        agent = self.agent
        if not isinstance(agent, ControlledPopulation):
            raise TypeError(f"{type(agent).__name__} has no episodic replay")
        steps = self._replay_steps(j)
        replayed = agent.replay(j, self.tail.transitions(j, steps), self.replay.repeats,
                                     q_limit)  # fmt: skip
        if replayed < 0:
            raise replay_failed(-replayed - 1, self.members[j].episode, int(self.t[j] - 1))
        return replayed

    def stop(self, leaving: list[int], write: bool) -> list[int]:
        """Every member leaves now (KILLED unless it ended in this step); with ``write``,
        those still training are checkpointed first.  The rows that leave: all."""
        gone = set(leaving)
        survivors = [(j, m) for j, m in enumerate(self.members) if j not in gone]
        if write and self.checkpoints is not None and survivors:
            self.checkpoints.write(self.capture_now(survivors), True)
        for m in self.members:
            if m.status == "RUNNING":
                m.status = "KILLED"
        return list(range(len(self.members)))

    def leave(
        self,
        leaving: list[int],
        on_member_end: Callable[[Member, Population, int], None] | None,
    ) -> bool:
        """Drop the rows ``leaving`` from the batch (``on_member_end`` first); False when no
        member is left."""
        self.staging.flush_all(self.members)
        gone = set(leaving)
        for j in sorted(gone):
            if on_member_end is not None:
                on_member_end(self.members[j], self.agent, j)
        keep = np.array([j for j in range(len(self.members)) if j not in gone])
        self.members = [self.members[j] for j in keep]
        if not self.members:
            return False
        self.agent.select(keep)
        self.venv.select(keep)
        if self.tail is not None:
            self.tail.select(keep)
        self.staging.select(keep, self.members)
        self.obs, self.t, self.ret, self.ep = (
            self.obs[keep], self.t[keep], self.ret[keep], self.ep[keep]
        )  # fmt: skip
        return True
