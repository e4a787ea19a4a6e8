"""A population's runs: ``K`` seeds of one configuration trained in one process as one batch.

``python -m cdqn.train train.population=10 seed=0`` trains seeds 0, 1, …, 9 together.  The
members' networks are stacked and each step of all of them (forward passes, NTK,
controllers, SGD steps, signal rows) is two compiled calls built from the row functions a
single run uses (:mod:`cdqn.training.population_step`); their environments step as one
(:mod:`cdqn.vector_env`); :func:`cdqn.training.population_loop.train_population` is the
loop.  So the per-step Python of the trainer, the environment and the bookkeeping is paid
once for ``K`` members.  This module opens, checkpoints and closes the members' runs.

Each member is still its own MLflow run with the content of a single run of its seed
(params with ``seed`` set to the member's seed and ``train.population=1``, the same tags
plus ``population``, per-episode metrics, ``signals/steps.parquet``, ``signals/fft.parquet``,
``config.yaml`` and the model), and learns what that single run learns: every array
operation acts on each member's row alone, through the kernels a single run uses, so the
numbers are bit-identical (``tests/test_population.py``).

:class:`ControlledPopulation` is the batched :class:`cdqn.agents.ControlledAgent` (fast
path) for ``none``, ``h2``, ``hinf`` and ``hinf_f``,
:class:`cdqn.training.ddqn_population.DDQNPopulation` the batched
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
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig, OmegaConf

from cdqn.config import Config, resolve_tracking_uri, validate
from cdqn.control.box import Box
from cdqn.control.factory import make_controller
from cdqn.control.setup import ControllerSetup
from cdqn.network import QNetwork, save_network
from cdqn.records import Artifact, Tag, folder
from cdqn.training.build import build_population, member_config, member_seeds
from cdqn.training.checkpoint import ROOT as CHECKPOINT_ROOT
from cdqn.training.checkpoint import CheckpointStore, load_local, local_path, save_local
from cdqn.training.interrupt import GracefulStop
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
from cdqn.training.population_loop import Checkpoints, Member, train_population
from cdqn.training.population_step import ControlledPopulation
from cdqn.training.result import OUTAGE, PopulationResult, RunResult
from cdqn.training.sweep import (
    config_hash,
    ensure_store,
    final_score,
    find_finished,
    find_resumable,
    process_tags,
    run_name,
)
from cdqn.training.tracking import (
    Recorder,
    TrackingOutage,
    check_tracking,
    closes_for_good,
    fail_fast_http,
    flatten,
    git_commit,
)
from cdqn.vector_env import VectorEnv

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
    conf: Config = OmegaConf.to_object(cfg)
    uri = resolve_tracking_uri(conf.tracking.uri)
    check_tracking(uri, conf.tracking.timeout)
    ensure_store(uri, conf.tracking.experiment)
    members = [
        Member(s, member_config(cfg, s)) for s in member_seeds(conf.seed, conf.train.population)
    ]
    results: dict[int, RunResult] = {}
    if conf.tracking.skip_finished:
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
        if members:  # continue this job's KILLED members (cdqn.training.sweep)
            signum = _resume_killed(cfg, uri, members, results, progress)
            members = [m for m in members if m.seed not in results]
            if signum is not None:
                return PopulationResult([results[s] for s in sorted(results)], signum)
    if not members:
        return PopulationResult([results[s] for s in sorted(results)])
    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)

    agent, venv = build_population(conf, setup, [m.seed for m in members])
    seeds = member_seeds(conf.seed, conf.train.population)
    population_id = uuid.uuid4().hex
    try:
        for m in members:
            m.recorder = start_member_run(
                m, conf, setup, uri, f"{seeds[0]}-{seeds[-1]}", population_id
            )
        log.info(
            "MLflow runs %s (%s, %s, seeds %d-%d)",
            ", ".join(m.recorder.run_id for m in members if m.recorder is not None),
            conf.env.name, conf.controller.name, members[0].seed, members[-1].seed,
        )  # fmt: skip
    except BaseException:
        for env in venv.envs:
            env.close()
        raise
    signum = train_members(
        conf,
        agent,
        venv,
        members,
        results,
        progress,
        observe=observe,
        should_stop=should_stop,
        box=setup.box(),
    )
    return PopulationResult([results[s] for s in sorted(results)], signum)


def train_members(
    conf: Config,
    agent: ControlledPopulation,
    venv: VectorEnv,
    members: list[Member],
    results: dict,
    progress: bool,
    sequence: int = 0,
    stores: dict[int, CheckpointStore] | None = None,
    observe: Callable[[Member], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    box: Box | None = None,
) -> int | None:
    """Train ``members`` (their runs open) to the end, with checkpoints (every
    ``train.checkpoint_every`` episodes of the slowest member and on SIGINT/SIGTERM, see
    :mod:`cdqn.training.population_checkpoint`); put each member's ``RunResult`` into
    ``results`` and close its run.  ``sequence``: number of the last checkpoint (a resumed
    population continues the count); ``box``: the design's NTK box, for the per-episode
    ``theta1_outside_box``, ``ratio_below_box`` and ``ratio_above_box``.  Returns the signal
    that stopped training, if any.

    A tracking store that does not answer for ``tracking.retry_s`` stops the population as
    a signal does, at the end of the population step: every member still training is
    checkpointed into ``tracking.local_checkpoints`` (:func:`_write_local`), a member that
    ended in that step keeps what closing its run writes there (:func:`close_locally`), all
    runs stay RUNNING in the store, and each member's result has status ``OUTAGE``;
    :func:`resume_population` continues from those files once the store answers again."""
    envs = list(venv.envs)
    episodes = conf.train.episodes
    folder = conf.tracking.local_checkpoints
    stores = stores or {
        m.seed: CheckpointStore(
            m.recorder.client, m.recorder.run_id, conf.train.signals, kind=MemberCheckpoint
        )
        for m in members
        if m.recorder is not None
    }
    counter = [sequence]
    outage: list[TrackingOutage] = []
    """The outage that stopped the population (at most one)."""
    for m in members:  # writes retried while the store does not answer (tracking.retry_s)
        if m.recorder is not None:
            m.recorder.retry_s = stores[m.seed].retry_s = conf.tracking.retry_s
            if m.recorder.uri.startswith(("http://", "https://")):
                fail_fast_http(conf.tracking.timeout)

    def went_away(err: TrackingOutage) -> None:
        """No more writes to the store: metrics are only queued from now on."""
        if not outage:
            outage.append(err)
        for m in members:
            if m.recorder is not None:
                m.recorder.flush_seconds = math.inf

    boundaries = not venv.checkpointable  # members captured at their episode boundaries

    def capture(
        j: int, m: Member, obs: np.ndarray, t: np.ndarray, ret: np.ndarray
    ) -> MemberCheckpoint:
        rows = m.signals.n if conf.train.signals else 0
        return capture_member(0, [], m, agent, venv, j, obs, t, ret, rows, boundaries)

    def write(items: list[tuple[Member, MemberCheckpoint]], new: bool) -> None:
        counter[0] += new
        ids = [m.recorder.run_id for m, _ in items if m.recorder is not None]
        for _, ckpt in items:
            ckpt.sequence, ckpt.population = counter[0], ids
        if not outage:
            try:
                for m, ckpt in items:
                    assert m.recorder is not None
                    m.recorder.flush()
                    stores[m.seed].save(ckpt, m.signals, announce=False)
                    m.checkpointed = ckpt.episode
                first = min(c.episode for _, c in items)
                last = max(c.episode for _, c in items)
                span = f"episode {first}" if first == last else f"episodes {first}-{last}"
                what = f"{len(items)} members" if len(items) > 1 else f"seed {items[0][0].seed}"
                log.debug("checkpoint at %s (%s)", span, what)
            except TrackingOutage as err:
                went_away(err)
        if outage:  # every member of this checkpoint into its local file, one sequence
            for m, ckpt in items:
                _write_local(folder, m, ckpt)

    def on_episode(m: Member, stats: object) -> None:
        assert m.recorder is not None
        if stats.episode not in m.logged:
            try:
                m.recorder.log_episode(stats)
            except TrackingOutage as err:  # the episode's metrics stay pending
                went_away(err)
        if observe is not None:
            observe(m)

    stop = GracefulStop()
    t0 = time.perf_counter()
    before = {m.seed: m.signals.n for m in members}  # steps of resumed members

    def killed_reason(m: Member, during: str) -> str:
        assert m.recorder is not None
        if boundaries:
            during = during.replace("during episode", "after episode", 1)
        if m.checkpointed is None:
            return f"{during}; no checkpoint yet, resume={m.recorder.run_id} trains it again"
        where = (
            "checkpoint written"
            if stop.requested() and m.checkpointed == m.episode
            else f"the last checkpoint is at episode {m.checkpointed}"
        )
        return f"{during}; {where}, continue the population with resume={m.recorder.run_id}"

    def on_member_end(m: Member, pop: ControlledPopulation, j: int) -> None:
        assert m.recorder is not None
        net = pop.network(j)
        if m.status == "KILLED" and not outage:
            m.reason = killed_reason(
                m, f"{stop.name or 'stopped'} during episode {m.episode} of {episodes}"
            )
        if not outage:
            try:
                finish_member(m, net, conf, box=box)
            except TrackingOutage as err:
                went_away(err)
        status = m.status
        if outage:
            status = OUTAGE
            if m.status != "KILLED":  # it ended in the step where the store went away
                close_locally(m, net, conf, folder)
        seconds = time.perf_counter() - t0
        results[m.seed] = RunResult(
            m.recorder.run_id, status, m.score, m.reason, returns=list(m.returns),
            steps=m.signals.n, seconds=seconds, rate=(m.signals.n - before[m.seed]) / seconds,
            steps_before=before[m.seed],
            epsilon=float(pop.epsilon[j]), solve_threshold=conf.env.solve_threshold,
        )  # fmt: skip

    def stopping() -> bool:
        return bool(outage) or stop.requested() or (should_stop is not None and should_stop())

    with stop:
        try:
            train_population(
                agent,
                venv,
                members,
                episodes=episodes,
                discount=conf.train.discount,
                q_limit=conf.train.q_limit,
                on_episode=on_episode,
                on_member_end=on_member_end,
                progress=progress and conf.train.progress,
                should_stop=stopping,
                checkpoints=Checkpoints(
                    conf.train.checkpoint_every, venv.checkpointable, capture, write
                ),
                replay=conf.weights.replay if conf.controller.name != "ddqn" else None,
                box=box,
            )
        except BaseException as err:  # close the members' runs that are still open
            stop.closing()
            for m in members:
                if m.seed not in results and m.recorder is not None:
                    m.status = "KILLED" if isinstance(err, KeyboardInterrupt) else "FAILED"
                    m.reason = f"{type(err).__name__}: {err}"
                    if m.status == "KILLED":
                        m.reason = killed_reason(m, f"stopped during episode {m.episode}")
                    finish_member(m, None, conf)
            raise
        finally:
            for env in envs:
                env.close()
    if outage:
        message = _outage_message(outage[0], members, conf)
        log.error("%s", message)
        for m in members:
            results[m.seed].reason = message
    return stop.signum


def _write_local(folder: str, m: Member, ckpt: MemberCheckpoint) -> None:
    """Member ``m``'s checkpoint and its metrics not yet written, in its local file."""
    assert m.recorder is not None
    pending = [p for p in m.recorder.pending if p[3] < ckpt.episode]  # its episodes only
    save_local(folder, m.recorder.run_id, ckpt, m.signals, pending)
    m.checkpointed = ckpt.episode


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
    confs: list[Config] = [OmegaConf.to_object(c) for c in cfgs]
    conf = confs[0]
    validate(conf)
    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
    members = [Member(c.seed, cfg) for c, cfg in zip(confs, cfgs, strict=True)]
    agent, venv = build_population(conf, setup, [m.seed for m in members])
    try:
        stores = {
            m.seed: CheckpointStore(client, r.info.run_id, conf.train.signals, MemberCheckpoint)
            for m, r in zip(members, runs, strict=True)
        }
        found = {m.seed: stores[m.seed].candidates() for m in members}
        sequence = max((c.sequence for items in found.values() for c, _ in items), default=0)
        common = common_sequence(found)
        chosen = {}
        if common is not None:
            for m in members:
                ckpt, slot = next(c for c in found[m.seed] if c[0].sequence == common)
                if not loadable(ckpt, venv) or not stores[m.seed].complete(ckpt, slot):
                    chosen = {}
                    break
                chosen[m.seed] = ckpt
        if not chosen:
            stores = {
                m.seed: CheckpointStore(client, r.info.run_id, conf.train.signals, MemberCheckpoint)
                for m, r in zip(members, runs, strict=True)
            }
        pending: dict[int, list] = {}
        local = {
            m.seed: load_local(folder, r.info.run_id, MemberCheckpoint)
            for m, r in zip(members, runs, strict=True)
        }
        seqs = {item[0].sequence for item in local.values() if item is not None}
        if (
            None not in local.values()
            and len(seqs) == 1
            and all(loadable(item[0], venv) for item in local.values())
        ):
            if (newest := seqs.pop()) >= (common or 0):
                log.info("continuing the population from its local checkpoints in %s",
                         Path(folder).resolve())  # fmt: skip
                chosen = {seed: item[0] for seed, item in local.items()}
                pending = {seed: item[1] for seed, item in local.items()}
                sequence = max(sequence, newest)
        elif any(item is not None for item in local.values()):
            log.warning("local checkpoints in %s do not cover the whole population; ignored",
                        Path(folder).resolve())  # fmt: skip
        if not chosen:
            log.warning("population has no common usable checkpoint: training it from episode 0")
        for j, (m, r) in enumerate(zip(members, runs, strict=True)):
            if chosen:
                restore_member(chosen[m.seed], m, agent, venv, j)
            reason = r.data.tags.get(Tag.FAILURE_REASON, "")
            if r.info.status == "RUNNING":
                log.warning("run %s is marked RUNNING (its process ended without closing it); "
                            "continuing it", r.info.run_id)  # fmt: skip
            m.recorder = Recorder.attach(uri, r.info.run_id)
            tags = {
                Tag.RESUMED_FROM_EPISODE: str(m.episode),
                Tag.RESUME_COUNT: str(int(r.data.tags.get(Tag.RESUME_COUNT, "0")) + 1),
                **process_tags(),
            }
            if reason:
                tags[Tag.PREVIOUS_FAILURE_REASON] = reason
                client.delete_tag(r.info.run_id, Tag.FAILURE_REASON)
            m.recorder.set_tags(tags)
            m.logged = m.recorder.logged_episodes()
            m.recorder.add_pending(pending.get(m.seed, []))  # what the store did not take
            log.info(
                "resuming MLflow run %s (seed %d) at episode %d of %d",
                r.info.run_id, m.seed, m.episode, conf.train.episodes,
            )  # fmt: skip
    except BaseException:
        for env in venv.envs:
            env.close()
        raise
    signum = train_members(
        conf, agent, venv, members, results, progress, sequence, stores, box=setup.box()
    )
    _forget_local(folder, [r.info.run_id for r in runs], results)
    return PopulationResult([results[s] for s in sorted(results)], signum)


def _forget_local(folder: str, run_ids: list[str], results: dict) -> None:
    """Remove the local files of ``run_ids`` once nothing stopped for an outage again."""
    if any(r.status == OUTAGE for r in results.values()):
        return
    for run_id in [*run_ids, *(r.run_id for r in results.values())]:
        shutil.rmtree(local_path(folder, run_id).parent, ignore_errors=True)


def close_locally(m: Member, net: QNetwork | None, conf: Config, folder: str) -> Path:
    """Keep what closing member ``m``'s run writes (status, metrics not yet written, signal
    rows, model) in ``folder``, for a member that ended while the store was away."""
    assert m.recorder is not None
    rows = m.signals.n if conf.train.signals else 0
    closing = MemberClosing(m.status, m.reason, [float(r) for r in m.returns], rows)
    path = save_local(folder, m.recorder.run_id, closing, m.signals, m.recorder.pending,
                      CLOSING_FILE)  # fmt: skip
    if conf.tracking.log_model and net is not None:
        save_network(net, path.parent / "model")
    return path


def close_from_local(uri: str, client: MlflowClient, run: Any, tracking: Any) -> RunResult | None:
    """Close ``run`` from its local record (:func:`close_locally`), as the population would
    have closed it; None when it has none."""
    folder = tracking.local_checkpoints
    run_id = run.info.run_id
    found = load_local(folder, run_id, MemberClosing, CLOSING_FILE)
    if found is None:
        return None
    closing, pending = found
    conf: Config = OmegaConf.to_object(stored_config(client, run_id, tracking))
    m = Member(conf.seed, OmegaConf.create(), status=closing.status, reason=closing.reason)
    m.returns = list(closing.returns)
    if closing.signals is not None:
        m.signals.load(closing.signals)
    m.recorder = Recorder.attach(uri, run_id)
    m.recorder.set_tags(
        {
            Tag.RESUMED_FROM_EPISODE: str(len(m.returns)),
            Tag.RESUME_COUNT: str(int(run.data.tags.get(Tag.RESUME_COUNT, "0")) + 1),
            **process_tags(),
        }
    )
    m.recorder.add_pending(pending)
    log.info("closing run %s (seed %d, %s while the store was away) from %s",
             run_id, m.seed, m.status, local_path(folder, run_id).parent)  # fmt: skip
    model = local_path(folder, run_id).parent / "model"
    finish_member(m, None, conf, model if model.is_dir() else None)
    return RunResult(run_id, m.status, m.score, m.reason, returns=list(m.returns),
                     steps=m.signals.n, solve_threshold=conf.env.solve_threshold)  # fmt: skip


def start_member_run(
    m: Member,
    conf: Config,
    setup: ControllerSetup,
    uri: str,
    population: str,
    population_id: str | None = None,
) -> Recorder:
    """Open member ``m``'s MLflow run with the params, tags and artifacts of a single run;
    tag ``population_id`` names the population (what ``resume=`` finds its members by)."""
    container = OmegaConf.to_container(m.cfg, resolve=True)
    tags = {
        Tag.ENV: conf.env.name,
        Tag.ENV_ID: conf.env.id,
        Tag.CONTROLLER: conf.controller.name,
        Tag.SEED: str(m.seed),
        Tag.GIT_COMMIT: git_commit(),
        Tag.DESIGN_SOURCE: setup.source,
        Tag.CONFIG_HASH: config_hash(m.cfg),
        Tag.POPULATION: population,
        Tag.POPULATION_ID: population_id or uuid.uuid4().hex,
        **process_tags(),
        **setup.tags(),
    }
    rec = Recorder.start(
        uri,
        conf.tracking.experiment,
        run_name(conf, m.seed),
        flatten(container),
        tags,
        config=container,
    )
    if setup.design:
        rec.log_dict(setup.design, Artifact.DESIGN_RECORD)
    if setup.artifacts is not None:
        rec.log_dir(setup.artifacts, folder(Artifact.DESIGN))
    log.debug(
        "MLflow run %s (%s, %s, seed %d)", rec.run_id, conf.env.name, conf.controller.name, m.seed
    )
    return rec


def finish_member(
    m: Member,
    net: QNetwork | None,
    conf: Config,
    model: Path | None = None,
    box: Box | None = None,
) -> None:
    """Signals, model (of ``net``, or the saved one in folder ``model``) and status of
    member ``m``'s run, as a single run writes them (``box``: the design's NTK box, drawn
    with the signal series).  A store that went away (:class:`TrackingOutage`) leaves the
    run open."""
    rec = m.recorder
    assert rec is not None
    try:
        if conf.train.signals:
            final = closes_for_good(m.status, m.reason)
            rec.log_signals(m.signals, conf.train.lr, box, final)
        if conf.tracking.log_model and net is not None:
            with tempfile.TemporaryDirectory() as tmp:
                save_network(net, Path(tmp))
                rec.log_dir(Path(tmp), folder(Artifact.MODEL))
        elif conf.tracking.log_model and model is not None:
            rec.log_dir(model, folder(Artifact.MODEL))
        if m.status == "FINISHED" and not conf.train.keep_checkpoints:
            rec.delete_artifacts(CHECKPOINT_ROOT)  # nothing left to resume
    except TrackingOutage:
        raise
    except BaseException:
        _close(m)
        raise
    _close(m)


def _close(m: Member) -> None:
    rec = m.recorder
    assert rec is not None
    status = m.status if m.status != "RUNNING" else "KILLED"
    rec.finish(status, m.reason, m.score)
    if status != "FINISHED":
        log.warning("run %s %s: %s", rec.run_id, status, m.reason)
