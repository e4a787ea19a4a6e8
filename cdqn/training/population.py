"""A population's runs: ``K`` seeds of one configuration trained in one process as one batch.

``python -m cdqn.train train.population=10 seed=0`` trains seeds 0, 1, …, 9 together.  The
members' networks are stacked and each step of all of them (forward passes, NTK,
controllers, SGD steps, signal rows) is two compiled calls built from the row functions a
single run uses, or one call for many steps (:mod:`cdqn.agents.controlled_population`);
their environments step as one
(:mod:`cdqn.vector_env`); :func:`cdqn.training.population_loop.train_population` is the
loop.  So the per-step Python of the trainer, the environment and the bookkeeping is paid
once for ``K`` members.  This module takes the members' runs through their lifecycle
(:mod:`cdqn.training.lifecycle`).

Each member is still its own MLflow run with the content of a single run of its seed
(params with ``seed`` set to the member's seed and ``train.population=1``, the same tags
plus ``population``, per-episode metrics, ``signals/steps.parquet``, ``signals/fft.parquet``,
``config.yaml`` and the model), and learns what that single run learns: every array
operation acts on each member's row alone, through the kernels a single run uses, so the
numbers are bit-identical (``tests/test_population.py``).

:class:`ControlledPopulation` is the batched :class:`cdqn.agents.ControlledAgent` (fast
path) for ``none``, ``h2``, ``hinf`` and ``hinf_f``,
:class:`cdqn.agents.ddqn_population.DDQNPopulation` the batched
:class:`cdqn.agents.DDQNAgent`.  Configurations that cannot be batched
(``train.fast_path=false``, a measured NTK box) train their members one after another as
single runs (:func:`cdqn.training.run.run_population`).

A population checkpoints as a whole (:mod:`cdqn.training.population_checkpoint`): each time
its slowest member has completed another ``train.checkpoint_every`` episodes, and when
SIGINT/SIGTERM stops it, every member's state goes into its own run's checkpoint slots and
the members still training are closed KILLED with ``resume=<run_id>`` in their
``failure_reason``.  Members of CartPole, Acrobot and MountainCar are captured between two
steps (a signal stops the population at the end of the current population step); members
of any other environment at their own episode boundaries (a signal lets each member finish
its current episode; the schedule is in :mod:`cdqn.training.population_loop`).
``python -m cdqn.train resume=<run_id>`` on any member continues every unfinished member of
its population (:func:`resume_population`), bit for bit as if uninterrupted; a restarted
sweep with ``tracking.skip_finished=true`` does the same for its KILLED members.
"""

from __future__ import annotations

import logging
import math
import shutil
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig, OmegaConf

from cdqn.config import Config, resolve_tracking_uri, to_schema, validate
from cdqn.control.box import Box
from cdqn.control.factory import make_controller
from cdqn.records import Tag
from cdqn.training.build import build_population, member_config, member_seeds
from cdqn.training.checkpoint import CheckpointStore, load_local, local_path
from cdqn.training.interrupt import GracefulStop
from cdqn.training.lifecycle import RunLifecycle
from cdqn.training.loop import EpisodeStats
from cdqn.training.member import Member
from cdqn.training.population_checkpoint import (
    CLOSING_FILE,
    MemberCheckpoint,
    MemberClosing,
    capture_member,
    common_sequence,
    loadable,
    restore_member,
    stored_config,
)
from cdqn.training.population_loop import Checkpoints, train_population
from cdqn.training.result import OUTAGE, PopulationResult, RunResult
from cdqn.training.store import ensure_store
from cdqn.training.sweep import config_hash, final_score, find_finished, find_resumable
from cdqn.training.tracking import TrackingOutage, check_tracking
from cdqn.vector_env import VectorEnv

if TYPE_CHECKING:
    from cdqn.agents.base import PopulationAgent as Population

log = logging.getLogger("cdqn")


def start_population(
    cfg: DictConfig,
    progress: bool = True,
    observe: Callable[[Member], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> PopulationResult:
    """Train seeds ``seed … seed+population−1`` of ``cfg`` as one batch (the configuration
    must be :func:`cdqn.training.batching.batchable`), each as its own MLflow run (module
    docstring).  With ``tracking.skip_finished`` members that FINISHED are skipped and
    KILLED ones continued.  ``observe(member)`` is called after each recorded episode and a
    true ``should_stop()`` ends the population as a signal does (members KILLED); both
    serve :mod:`cdqn.tune` (intermediate values, pruning).  ``cfg`` is adopted and
    validated (:func:`cdqn.training.run.run_population`)."""
    conf = to_schema(cfg, Config)
    uri = resolve_tracking_uri(conf.tracking.uri)
    check_tracking(uri, conf.tracking.timeout)
    ensure_store(uri, conf.tracking.experiment)
    seeds = member_seeds(conf.seed, conf.train.population)
    members = [Member(s, member_config(cfg, s)) for s in seeds]
    results: dict[int, RunResult] = {}
    if conf.tracking.skip_finished:
        members, signum = _skip_finished(cfg, conf, uri, members, results, progress)
        if signum is not None:
            return PopulationResult([results[s] for s in sorted(results)], signum)
    if not members:
        return PopulationResult([results[s] for s in sorted(results)])
    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
    agent, venv = build_population(conf, setup, [m.seed for m in members])
    life = RunLifecycle(conf, uri, MemberCheckpoint)
    tags = {Tag.POPULATION: f"{seeds[0]}-{seeds[-1]}", Tag.POPULATION_ID: uuid.uuid4().hex}
    try:
        for m in members:
            life.open(m, setup, tags)
        log.info(
            "MLflow runs %s (%s, %s, seeds %d-%d)",
            ", ".join(m.recorder.run_id for m in members if m.recorder is not None),
            conf.env.name, conf.controller.name, members[0].seed, members[-1].seed,
        )  # fmt: skip
    except BaseException:
        for env in venv.envs:
            env.close()
        raise
    signum = train_members(life, agent, venv, members, results, progress, observe=observe,
                           should_stop=should_stop, box=setup.box())  # fmt: skip
    return PopulationResult([results[s] for s in sorted(results)], signum)


def _skip_finished(
    cfg: DictConfig,
    conf: Config,
    uri: str,
    members: list[Member],
    results: dict[int, RunResult],
    progress: bool,
) -> tuple[list[Member], int | None]:
    """A restarted sweep (``tracking.skip_finished``): the results of ``members`` whose run
    FINISHED go into ``results``, KILLED ones are continued (:func:`_resume_killed`).  The
    members still to train, and the signal that stopped a continued one, if any."""
    client = MlflowClient(uri)
    for m in members:
        done = find_finished(client, conf.tracking.experiment, config_hash(m.cfg))
        if done is not None:
            log.info(
                "skipping %s/%s seed %d: run %s already FINISHED with this configuration",
                conf.env.name, conf.controller.name, m.seed, done.info.run_id,
            )  # fmt: skip
            results[m.seed] = RunResult(
                done.info.run_id, "FINISHED", final_score(client, done), "skipped"
            )
    members = [m for m in members if m.seed not in results]
    if not members:
        return members, None
    signum = _resume_killed(cfg, uri, members, results, progress)  # (cdqn.training.sweep)
    return [m for m in members if m.seed not in results], signum


def train_members(
    life: RunLifecycle,
    agent: Population,
    venv: VectorEnv,
    members: list[Member],
    results: dict,
    progress: bool,
    sequence: int = 0,
    observe: Callable[[Member], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    box: Box | None = None,
) -> int | None:
    """Train ``members`` (their runs open in ``life``) to the end, with checkpoints (every
    ``train.checkpoint_every`` episodes of the slowest member and on SIGINT/SIGTERM, see
    :mod:`cdqn.training.population_checkpoint`); put each member's ``RunResult`` into
    ``results`` and close its run.  ``sequence``: number of the last checkpoint (a resumed
    population continues the count); ``box``: the design's NTK box, for the per-episode
    ``theta1_outside_box``, ``ratio_below_box`` and ``ratio_above_box``.  Returns the signal
    that stopped training, if any.

    A tracking store that does not answer for ``tracking.retry_s`` stops the population as
    a signal does, at the end of the population step: every member still training is
    checkpointed into ``tracking.local_checkpoints``, a member that ended in that step
    keeps what closing its run writes there (:meth:`RunLifecycle.close_locally`), all runs
    stay RUNNING in the store, and each member's result has status ``OUTAGE``;
    :func:`resume_population` continues from those files once the store answers again."""
    conf = life.conf
    for m in members:  # writes retried while the store does not answer (tracking.retry_s)
        if m.recorder is not None:
            life.watch(m)
    runs = _PopulationRuns(life, agent, venv, members, results, sequence, observe,
                           should_stop, box)  # fmt: skip
    with runs.stop:
        try:
            train_population(
                agent,
                venv,
                members,
                episodes=conf.train.episodes,
                discount=conf.train.discount,
                q_limit=conf.train.q_limit,
                on_episode=runs.on_episode,
                on_member_end=runs.on_member_end,
                progress=progress and conf.train.progress,
                should_stop=runs.stopping,
                checkpoints=Checkpoints(
                    conf.train.checkpoint_every, venv.checkpointable, runs.capture, runs.write
                ),  # fmt: skip
                replay=conf.weights.replay if conf.controller.name != "ddqn" else None,
                box=box,
            )
        except BaseException as err:  # close the members' runs that are still open
            runs.stop.closing()
            runs.close_open(err)
            raise
        finally:
            for env in venv.envs:
                env.close()
    if runs.outage is not None:
        message = _outage_message(runs.outage, members, conf)
        log.error("%s", message)
        for m in members:
            results[m.seed].reason = message
    return runs.stop.signum


class _PopulationRuns:
    """What the loop of a population calls back into: recording, checkpoints and closing
    of the members' runs, and the outage that stopped it (at most one)."""

    def __init__(
        self,
        life: RunLifecycle,
        agent: Population,
        venv: VectorEnv,
        members: list[Member],
        results: dict,
        sequence: int,
        observe: Callable[[Member], None] | None,
        should_stop: Callable[[], bool] | None,
        box: Box | None,
    ) -> None:
        self.life, self.agent, self.venv, self.members = life, agent, venv, members
        self.results, self.sequence, self.box = results, sequence, box
        self.observe, self.should_stop = observe, should_stop
        self.outage: TrackingOutage | None = None
        self.boundaries = not venv.checkpointable  # members captured at episode boundaries
        self.stop = GracefulStop()
        self.t0 = time.perf_counter()
        self.before = {m.seed: m.signals.n for m in members}  # steps of resumed members

    def went_away(self, err: TrackingOutage) -> None:
        """No more writes to the store: metrics are only queued from now on."""
        if self.outage is None:
            self.outage = err
        for m in self.members:
            if m.recorder is not None:
                m.recorder.flush_seconds = math.inf

    def stopping(self) -> bool:
        return (
            self.outage is not None
            or self.stop.requested()
            or (self.should_stop is not None and self.should_stop())
        )

    def capture(
        self, j: int, m: Member, obs: np.ndarray, t: np.ndarray, ret: np.ndarray
    ) -> MemberCheckpoint:
        rows = m.signals.n if self.life.conf.train.signals else 0
        return capture_member(0, [], m, self.agent, self.venv, j, obs, t, ret, rows,
                              self.boundaries)  # fmt: skip

    def write(self, items: list[tuple[Member, MemberCheckpoint]], new: bool) -> None:
        """Store the captures as checkpoint ``sequence`` (a new one if ``new``), in the
        members' runs or, while the store is away, in their local files."""
        self.sequence += new
        ids = [m.recorder.run_id for m, _ in items if m.recorder is not None]
        for _, ckpt in items:
            ckpt.sequence, ckpt.population = self.sequence, ids
        if self.outage is None:
            try:
                for m, ckpt in items:
                    self.life.checkpoint(m, ckpt, announce=False)
                first = min(c.episode for _, c in items)
                last = max(c.episode for _, c in items)
                span = f"episode {first}" if first == last else f"episodes {first}-{last}"
                what = f"{len(items)} members" if len(items) > 1 else f"seed {items[0][0].seed}"
                log.debug("checkpoint at %s (%s)", span, what)
            except TrackingOutage as err:
                self.went_away(err)
        if self.outage is not None:  # every member of this checkpoint locally, one sequence
            for m, ckpt in items:
                self.life.keep_locally(m, ckpt)

    def on_episode(self, m: Member, stats: EpisodeStats) -> None:
        try:
            self.life.record(m, stats)
        except TrackingOutage as err:  # the episode's metrics stay pending
            self.went_away(err)
        if self.observe is not None:
            self.observe(m)

    def killed_reason(self, m: Member, during: str) -> str:
        assert m.recorder is not None
        if self.boundaries:
            during = during.replace("during episode", "after episode", 1)
        if m.checkpointed is None:
            return f"{during}; no checkpoint yet, resume={m.recorder.run_id} trains it again"
        where = (
            "checkpoint written"
            if self.stop.requested() and m.checkpointed == m.episode
            else f"the last checkpoint is at episode {m.checkpointed}"
        )
        return f"{during}; {where}, continue the population with resume={m.recorder.run_id}"

    def on_member_end(self, m: Member, pop: Population, j: int) -> None:
        assert m.recorder is not None
        net = pop.network(j)
        episodes = self.life.conf.train.episodes
        if m.status == "KILLED" and self.outage is None:
            during = f"{self.stop.name or 'stopped'} during episode {m.episode} of {episodes}"
            m.reason = self.killed_reason(m, during)
        if self.outage is None:
            try:
                self.life.close(m, net, box=self.box)
            except TrackingOutage as err:
                self.went_away(err)
        status = m.status
        if self.outage is not None:
            status = OUTAGE
            if m.status != "KILLED":  # it ended in the step where the store went away
                self.life.close_locally(m, net)
        seconds = time.perf_counter() - self.t0
        before = self.before[m.seed]
        self.results[m.seed] = RunResult(
            m.recorder.run_id, status, m.score, m.reason, returns=list(m.returns),
            steps=m.signals.n, seconds=seconds, rate=(m.signals.n - before) / seconds,
            steps_before=before, epsilon=float(pop.epsilon[j]),
            solve_threshold=self.life.conf.env.solve_threshold,
        )  # fmt: skip

    def close_open(self, err: BaseException) -> None:
        """``err`` stopped the loop: close the runs of the members still open."""
        for m in self.members:
            if m.seed not in self.results and m.recorder is not None:
                m.status = "KILLED" if isinstance(err, KeyboardInterrupt) else "FAILED"
                m.reason = f"{type(err).__name__}: {err}"
                if m.status == "KILLED":
                    m.reason = self.killed_reason(m, f"stopped during episode {m.episode}")
                self.life.close(m, None)


def _outage_message(err: TrackingOutage, members: list[Member], conf: Config) -> str:
    """What a population stopped by an outage says: the server, the local files, the
    command that continues it."""
    ids = [m.recorder.run_id for m in members if m.recorder is not None]
    folder = Path(conf.tracking.local_checkpoints).resolve()
    episodes = ", ".join(f"{m.seed}: {m.episode}" for m in members)
    where = (
        f"checkpoints of the members (episodes completed by seed: {episodes}) written locally "
        f"to {folder}/<run id>/ for the runs {', '.join(ids)}"
    )
    return (
        f"{err}. The population stopped: {where}; its runs stay RUNNING in the store. When "
        f"the server answers again: python -m cdqn.train resume={ids[0]} "
        f"tracking.uri={err.uri} tracking.local_checkpoints={folder}"
    )


def _resume_killed(
    cfg: DictConfig, uri: str, members: list[Member], results: dict, progress: bool
) -> int | None:
    """Resume the runs of ``members`` that a restarted sweep finds KILLED (or left RUNNING by
    a process that is gone), population by population; their results go into ``results``.
    Returns the signal that stopped one of them, if any."""
    client = MlflowClient(uri)
    groups: dict[str, list] = {}
    for m in members:
        found = find_resumable(client, str(cfg.tracking.experiment), config_hash(m.cfg))
        if found is not None and Tag.POPULATION_ID in found.data.tags:
            groups.setdefault(found.data.tags[Tag.POPULATION_ID], []).append(found)
    for runs in groups.values():
        ids = ", ".join(r.info.run_id for r in runs)
        log.info("continuing KILLED population members from their checkpoints: %s", ids)
        out = resume_population(uri, cfg.tracking, runs, progress)
        for r in out.members:
            seed = int(client.get_run(r.run_id).data.tags[Tag.SEED])
            results[seed] = r
        if out.signum is not None:
            return out.signum
    return None


def resume_population(uri: str, tracking: Any, runs: list, progress: bool) -> PopulationResult:
    """Continue the members ``runs`` (MLflow runs of one population) from their newest
    common checkpoint, each in its own run, to the planned episode count.

    The checkpoint is the newest the members share: in their runs, or in
    ``tracking.local_checkpoints`` when the store went away during the last attempt (then
    the metrics the store did not take are written first, and a member that ended while
    the store was away is closed from its local record without training).  Without a
    common checkpoint the members train again from episode 0 in their runs (episodes whose
    metrics are stored are not logged twice); as every member's numbers depend on its seed
    alone, the result is the same either way.
    """
    client = MlflowClient(uri)
    folder = tracking.local_checkpoints
    results: dict = {}
    open_runs = []
    for r in runs:
        closed = close_from_local(uri, client, r, tracking)
        if closed is None:
            open_runs.append(r)
        else:
            results[int(r.data.tags.get(Tag.SEED, "0"))] = closed
    runs = open_runs
    if not runs:
        _forget_local(folder, [], results)
        return PopulationResult([results[s] for s in sorted(results)])
    cfgs = [stored_config(client, r.info.run_id, tracking) for r in runs]
    confs = [to_schema(c, Config) for c in cfgs]
    conf = confs[0]
    validate(conf)
    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
    members = [Member(c.seed, cfg) for c, cfg in zip(confs, cfgs, strict=True)]
    agent, venv = build_population(conf, setup, [m.seed for m in members])
    life = RunLifecycle(conf, uri, MemberCheckpoint)
    try:
        start = _restart_point(client, conf, members, runs, venv)
        for j, (m, r) in enumerate(zip(members, runs, strict=True)):
            if start.chosen:
                restore_member(start.chosen[m.seed], m, agent, venv, j)
            life.resume(m, client, r, start.stores[m.seed], start.pending.get(m.seed, []))
            log.info(
                "resuming MLflow run %s (seed %d) at episode %d of %d",
                r.info.run_id, m.seed, m.episode, conf.train.episodes,
            )  # fmt: skip
    except BaseException:
        for env in venv.envs:
            env.close()
        raise
    signum = train_members(life, agent, venv, members, results, progress, start.sequence,
                           box=setup.box())  # fmt: skip
    _forget_local(folder, [r.info.run_id for r in runs], results)
    return PopulationResult([results[s] for s in sorted(results)], signum)


@dataclass
class _RestartPoint:
    """Where a resumed population starts: the checkpoint of each member (none: episode 0),
    the stores to continue writing into, metrics a lost store did not take, and the number
    of the newest checkpoint written so far."""

    chosen: dict[int, MemberCheckpoint]
    stores: dict[int, CheckpointStore]
    pending: dict[int, list]
    sequence: int


def _restart_point(
    client: MlflowClient, conf: Config, members: list[Member], runs: list, venv: VectorEnv
) -> _RestartPoint:
    """The newest checkpoint every member holds, in its run or in its local file
    (:func:`resume_population`)."""

    def stores() -> dict[int, CheckpointStore]:
        return {
            m.seed: CheckpointStore(client, r.info.run_id, conf.train.signals, MemberCheckpoint)
            for m, r in zip(members, runs, strict=True)
        }

    point = _RestartPoint({}, stores(), {}, 0)
    found = {m.seed: point.stores[m.seed].candidates() for m in members}
    point.sequence = max((c.sequence for items in found.values() for c, _ in items), default=0)
    common = common_sequence(found)
    if common is not None:
        for m in members:
            ckpt, slot = next(c for c in found[m.seed] if c[0].sequence == common)
            if not loadable(ckpt, venv) or not point.stores[m.seed].complete(ckpt, slot):
                point.chosen = {}
                break
            point.chosen[m.seed] = ckpt
    if not point.chosen:
        point.stores = stores()
    _local_restart_point(point, conf.tracking.local_checkpoints, members, runs, venv, common)
    if not point.chosen:
        log.warning("population has no common usable checkpoint: training it from episode 0")
    return point


def _local_restart_point(
    point: _RestartPoint,
    folder: str,
    members: list[Member],
    runs: list,
    venv: VectorEnv,
    common: int | None,
) -> None:
    """Take the members' local checkpoints (the store went away during the last attempt)
    into ``point`` when they cover the whole population and are not older than ``common``."""
    local = {
        m.seed: load_local(folder, r.info.run_id, MemberCheckpoint)
        for m, r in zip(members, runs, strict=True)
    }
    seqs = {item[0].sequence for item in local.values() if item is not None}
    if (
        None not in local.values()
        and len(seqs) == 1
        and all(loadable(item[0], venv) for item in local.values() if item is not None)
    ):
        if (newest := seqs.pop()) >= (common or 0):
            log.info("continuing the population from its local checkpoints in %s",
                     Path(folder).resolve())  # fmt: skip
            point.chosen = {seed: item[0] for seed, item in local.items() if item is not None}
            point.pending = {seed: item[1] for seed, item in local.items() if item is not None}
            point.sequence = max(point.sequence, newest)
    elif any(item is not None for item in local.values()):
        log.warning("local checkpoints in %s do not cover the whole population; ignored",
                    Path(folder).resolve())  # fmt: skip


def _forget_local(folder: str, run_ids: list[str], results: dict) -> None:
    """Remove the local files of ``run_ids`` once nothing stopped for an outage again."""
    if any(r.status == OUTAGE for r in results.values()):
        return
    for run_id in [*run_ids, *(r.run_id for r in results.values())]:
        shutil.rmtree(local_path(folder, run_id).parent, ignore_errors=True)


def close_from_local(uri: str, client: MlflowClient, run: Any, tracking: Any) -> RunResult | None:
    """Close ``run`` from its local record (:meth:`RunLifecycle.close_locally`), as the
    population would have closed it; None when it has none."""
    folder = tracking.local_checkpoints
    run_id = run.info.run_id
    found = load_local(folder, run_id, MemberClosing, CLOSING_FILE)
    if found is None:
        return None
    closing, pending = found
    conf = to_schema(stored_config(client, run_id, tracking), Config)
    m = Member(conf.seed, OmegaConf.create(), status=closing.status, reason=closing.reason)
    m.returns = list(closing.returns)
    m.episode = len(m.returns)
    if closing.signals is not None:
        m.signals.load(closing.signals)
    life = RunLifecycle(conf, uri, MemberCheckpoint)
    life.resume(m, client, run, None, pending, to_close=True)
    log.info("closing run %s (seed %d, %s while the store was away) from %s",
             run_id, m.seed, m.status, local_path(folder, run_id).parent)  # fmt: skip
    model = local_path(folder, run_id).parent / "model"
    life.close(m, None, model if model.is_dir() else None)
    return RunResult(run_id, m.status, m.score, m.reason, returns=list(m.returns),
                     steps=m.signals.n, solve_threshold=conf.env.solve_threshold)  # fmt: skip
