"""A single run: train one configuration and seed as one MLflow run, with checkpoints,
divergence and signal handling, and a tracking store that may go away.

A single run is a population of one in its lifecycle (:mod:`cdqn.training.lifecycle`): one
:class:`~cdqn.training.member.Member`, opened, recorded, checkpointed, closed and
resumed as a population's members are.  It is built (:mod:`cdqn.training.build`), trained
by :func:`cdqn.training.loop.train` and checkpointed into its own run
(:mod:`cdqn.training.checkpoint`) every ``train.checkpoint_every`` episodes and when
SIGINT/SIGTERM stops it.  Whatever happens, the signals so far, the network and the status
(FINISHED, FAILED with ``failure_reason``, KILLED) are written before returning or raising;
a store that stays away longer than ``tracking.retry_s`` gets a local checkpoint instead
(status :data:`cdqn.training.result.OUTAGE`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import gymnasium as gym
from mlflow.entities import Run
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig

from cdqn.config import Config, to_schema, validate
from cdqn.envs import make_env
from cdqn.training.build import Job, build
from cdqn.training.checkpoint import (
    Checkpoint,
    CheckpointStore,
    capture,
    load_local,
    local_path,
    restore,
)
from cdqn.training.divergence import DivergenceError, failure_reason
from cdqn.training.interrupt import GracefulStop
from cdqn.training.lifecycle import RunLifecycle
from cdqn.training.loop import EpisodeStats, TrainState, train
from cdqn.training.member import Member
from cdqn.training.result import OUTAGE, RunResult
from cdqn.training.tracking import TrackingOutage

log = logging.getLogger("cdqn")


def start_run(cfg: DictConfig, conf: Config, env: gym.Env, uri: str, progress: bool) -> RunResult:
    """Train ``conf`` (``cfg`` resolved and validated) on ``env`` as a new MLflow run in the
    store at ``uri`` (already checked); closes ``env``."""
    life, m = RunLifecycle(conf, uri), Member(conf.seed, cfg)
    try:
        job = build(conf, env)
        life.open(m, job.setup)
    except BaseException:
        env.close()
        raise
    assert m.recorder is not None
    log.info("MLflow run %s (%s, %s, seed %d)",
             m.recorder.run_id, conf.env.name, conf.controller.name, conf.seed)  # fmt: skip
    return _train(job, life, m, TrainState(), progress)


def resume_run(
    cfg: DictConfig, client: MlflowClient, info: Run, uri: str, progress: bool
) -> RunResult:
    """Continue the single run ``info`` (KILLED, RUNNING or FAILED for a reason other than
    divergence) in the same MLflow run, from its last checkpoint, or from its local one
    when that is newer (written when the store went away, :meth:`_SingleRun.stop_locally`).

    The run's stored ``config.yaml`` is what runs; ``cfg`` only says where the store is
    (``tracking.*``).  Episodes whose metrics are already in the store are not logged twice.
    """
    from cdqn.training.population_checkpoint import stored_config  # resuming alone

    run_id = info.info.run_id
    stored = stored_config(client, run_id, cfg.tracking)
    conf = to_schema(stored, Config)
    validate(conf)
    env = make_env(conf.env)
    try:
        job = build(conf, env)
        store = CheckpointStore(client, run_id, conf.train.signals)
        ckpt = store.load()
    except BaseException:
        env.close()
        raise
    pending: list[tuple[str, float, int, int]] = []
    local = load_local(conf.tracking.local_checkpoints, run_id)
    if local is not None and (ckpt is None or local[0].episode >= ckpt.episode):
        ckpt, pending = local
        log.info("continuing from the local checkpoint %s",
                 local_path(conf.tracking.local_checkpoints, run_id))  # fmt: skip
    state, m = TrainState(), Member(conf.seed, stored)
    if ckpt is None:
        log.warning("run %s has no usable checkpoint: training it again from episode 0", run_id)
    else:
        restore(ckpt, job.agent, env, state, job.rng, m.signals)
    m.episode = state.episode
    log.info(
        "resuming MLflow run %s at episode %d of %d", run_id, state.episode, conf.train.episodes
    )
    life = RunLifecycle(conf, uri)
    life.resume(m, client, info, store, pending)
    result = _train(job, life, m, state, progress)
    if local is not None and result.status != OUTAGE:
        local_path(conf.tracking.local_checkpoints, run_id).unlink(missing_ok=True)
    return result


def _train(job: Job, life: RunLifecycle, m: Member, state: TrainState, progress: bool) -> RunResult:
    """The training loop of member ``m`` (its run open) with checkpoints, divergence and
    signal handling; closes the run.

    Whatever happens, the signals so far, the network and the status (FINISHED, FAILED with
    ``failure_reason``, KILLED) are written before returning or raising.
    """
    conf = job.conf
    m.returns, m.checkpointed = state.returns, state.episode
    start_steps, t0 = state.total_steps, time.perf_counter()
    life.watch(m)
    run = _SingleRun(job, life, m, state, GracefulStop())
    outage: TrackingOutage | None = None
    with run.stop:
        try:
            run.train(progress)
        except DivergenceError as err:
            m.status, m.reason = "FAILED", failure_reason(err)
        except KeyboardInterrupt:
            m.status, m.reason = "KILLED", run.interrupted()
            raise
        except TrackingOutage as err:  # at an episode boundary: checkpoint locally below
            outage = err
        except Exception as err:
            m.status, m.reason = "FAILED", f"{type(err).__name__}: {err}"
            raise
        finally:
            run.stop.closing()
            seconds = time.perf_counter() - t0
            run.close(outage)
    assert m.recorder is not None
    return RunResult(
        m.recorder.run_id, m.status, m.score, m.reason, run.stop.signum,
        returns=list(state.returns), steps=state.total_steps, seconds=seconds,
        rate=(state.total_steps - start_steps) / seconds if seconds > 0 else math.nan,
        steps_before=start_steps, epsilon=float(job.agent.epsilon),
        solve_threshold=conf.env.solve_threshold,
    )  # fmt: skip


@dataclass
class _SingleRun:
    """What the training of one single run holds: its job, its member in the lifecycle,
    the loop's state and the signal handler."""

    job: Job
    life: RunLifecycle
    m: Member
    state: TrainState
    stop: GracefulStop

    def train(self, progress: bool) -> None:
        """Train to ``train.episodes``, or to the episode boundary where a signal stops it
        (KILLED, checkpoint written)."""
        job, conf, state = self.job, self.job.conf, self.state
        episodes = conf.train.episodes
        train(
            job.env,
            job.agent,
            episodes=episodes,
            seed=conf.seed,
            discount=conf.train.discount,
            q_limit=conf.train.q_limit,
            signals=self.m.signals,
            state=state,
            on_episode=self.on_episode,
            progress=progress and conf.train.progress,
            desc=f"{conf.env.name}/{conf.controller.name}/s{conf.seed}",
            should_stop=self.stop.requested,
            replay=conf.weights.replay if conf.controller.name != "ddqn" else None,
            box=job.setup.box(),
        )
        if state.episode >= episodes:
            self.m.status = "FINISHED"
            return
        self.m.status = "KILLED"  # a signal stopped training at an episode boundary
        if self.m.checkpointed != state.episode:
            self.checkpoint()
        self.m.reason = (
            f"{self.stop.name} after episode {state.episode} of {episodes}; checkpoint "
            f"written, continue with resume={self._run_id}"
        )

    @property
    def _run_id(self) -> str:
        assert self.m.recorder is not None
        return self.m.recorder.run_id

    def on_episode(self, stats: EpisodeStats, st: TrainState) -> None:
        every, episodes = self.job.conf.train.checkpoint_every, self.job.conf.train.episodes
        self.m.episode = st.episode
        self.life.record(self.m, stats)
        if every and st.episode % every == 0 and st.episode < episodes:
            self.checkpoint()

    def _capture(self) -> Checkpoint:
        rows = self.m.signals.n if self.job.conf.train.signals else 0
        return capture(self.job.agent, self.job.env, self.state, self.job.rng, rows)

    def checkpoint(self) -> None:
        self.life.checkpoint(self.m, self._capture())

    def interrupted(self) -> str:
        """The ``failure_reason`` of a run stopped inside an episode (a second signal)."""
        return (
            f"stopped during episode {self.state.episode} of {self.job.conf.train.episodes}; "
            f"the last checkpoint is at episode {self.m.checkpointed}, continue with "
            f"resume={self._run_id}"
        )

    def close(self, outage: TrackingOutage | None) -> None:
        """Close the run (and the environment); a store that is away gets the checkpoint
        locally instead (status :data:`OUTAGE`, the run stays RUNNING)."""
        try:
            if outage is None:
                try:
                    self.life.close(self.m, self.job.net, box=self.job.setup.box())
                except TrackingOutage as err:
                    outage = err
        finally:
            self.job.env.close()
            if outage is not None:
                self.m.status, self.m.reason = OUTAGE, self.stop_locally(outage)

    def stop_locally(self, err: TrackingOutage) -> str:
        """The store stayed away past ``tracking.retry_s``: checkpoint (at the episode
        boundary where the write failed) and the metrics not yet written into a local
        file; say where."""
        conf = self.job.conf
        path = self.life.keep_locally(self.m, self._capture())
        message = (
            f"{err}. Checkpoint of episode {self.state.episode} of {conf.train.episodes} "
            f"written locally to {path}; the run stays RUNNING in the store. When the server "
            f"answers again: python -m cdqn.train resume={self._run_id} tracking.uri={err.uri} "
            f"tracking.local_checkpoints={path.parents[1]}"
        )
        log.error("%s", message)
        return message
