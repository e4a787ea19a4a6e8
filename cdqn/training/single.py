"""A single run: train one configuration and seed as one MLflow run, with checkpoints,
divergence and signal handling, and a tracking store that may go away.

The run is built (:mod:`cdqn.training.build`), trained by :func:`cdqn.training.loop.train`,
recorded by :class:`cdqn.training.tracking.Recorder` and checkpointed into its own run
(:mod:`cdqn.training.checkpoint`) every ``train.checkpoint_every`` episodes and when
SIGINT/SIGTERM stops it.  Whatever happens, the signals so far, the network and the status
(FINISHED, FAILED with ``failure_reason``, KILLED) are written before returning or raising;
a store that stays away longer than ``tracking.retry_s`` gets a local checkpoint instead
(status :data:`cdqn.training.result.OUTAGE`).
"""

from __future__ import annotations

import logging
import math
import tempfile
import time
from pathlib import Path
from urllib.parse import urlsplit

import gymnasium as gym
import numpy as np
from mlflow.entities import Run
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig, OmegaConf

from cdqn.config import Config, validate
from cdqn.envs import make_env
from cdqn.network import save_network
from cdqn.records import Artifact, Tag, folder
from cdqn.training.build import Job, build
from cdqn.training.checkpoint import ROOT as CHECKPOINT_ROOT
from cdqn.training.checkpoint import (
    CheckpointStore,
    capture,
    load_local,
    local_path,
    restore,
    save_local,
)
from cdqn.training.interrupt import GracefulStop
from cdqn.training.loop import DivergenceError, EpisodeStats, TrainState, train
from cdqn.training.population_checkpoint import stored_config
from cdqn.training.result import OUTAGE, RunResult
from cdqn.training.signals import SignalBuffer
from cdqn.training.sweep import config_hash, process_tags, run_name
from cdqn.training.tracking import (
    Recorder,
    TrackingOutage,
    closes_for_good,
    fail_fast_http,
    flatten,
    git_commit,
)

log = logging.getLogger("cdqn")


def start_run(cfg: DictConfig, conf: Config, env: gym.Env, uri: str, progress: bool) -> RunResult:
    """Train ``conf`` (``cfg`` resolved and validated) on ``env`` as a new MLflow run in the
    store at ``uri`` (already checked); closes ``env``."""
    try:
        job = build(conf, env)
    except BaseException:
        env.close()
        raise

    container = OmegaConf.to_container(cfg, resolve=True)
    params = flatten(container)
    tags = {
        Tag.ENV: conf.env.name,
        Tag.ENV_ID: conf.env.id,
        Tag.CONTROLLER: conf.controller.name,
        Tag.SEED: str(conf.seed),
        Tag.GIT_COMMIT: git_commit(),
        Tag.DESIGN_SOURCE: job.setup.source,
        Tag.CONFIG_HASH: config_hash(cfg),
        **process_tags(),
        **job.setup.tags(),
    }
    try:
        recorder = Recorder.start(
            uri,
            conf.tracking.experiment,
            run_name(conf),
            params,
            tags,
            config=container,
        )
    except BaseException:
        env.close()
        raise
    if job.setup.design:
        recorder.log_dict(job.setup.design, Artifact.DESIGN_RECORD)
    if job.setup.artifacts is not None:
        recorder.log_dir(job.setup.artifacts, folder(Artifact.DESIGN))
    log.info(
        "MLflow run %s (%s, %s, seed %d)",
        recorder.run_id,
        conf.env.name,
        conf.controller.name,
        conf.seed,
    )
    store = CheckpointStore(recorder.client, recorder.run_id, conf.train.signals)
    return _train(job, recorder, store, TrainState(), SignalBuffer(), progress, set())


def resume_run(
    cfg: DictConfig, client: MlflowClient, info: Run, uri: str, progress: bool
) -> RunResult:
    """Continue the single run ``info`` (KILLED, RUNNING or FAILED for a reason other than
    divergence) in the same MLflow run, from its last checkpoint, or from its local one
    when that is newer (written when the store went away, :func:`_stop_locally`).

    The run's stored ``config.yaml`` is what runs; ``cfg`` only says where the store is
    (``tracking.*``).  Episodes whose metrics are already in the store are not logged twice.
    """
    run_id = info.info.run_id
    status, reason = info.info.status, info.data.tags.get(Tag.FAILURE_REASON, "")
    if status == "RUNNING":
        log.warning(
            "run %s is marked RUNNING (its process ended without closing it, e.g. SIGKILL); "
            "continuing it. Stop any process still training it first.",
            run_id,
        )
    stored = stored_config(client, run_id, cfg.tracking)
    conf: Config = OmegaConf.to_object(stored)
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
    state, signals = TrainState(), SignalBuffer()
    if ckpt is None:
        log.warning("run %s has no usable checkpoint: training it again from episode 0", run_id)
    else:
        restore(ckpt, job.agent, env, state, job.rng, signals)
    log.info(
        "resuming MLflow run %s at episode %d of %d", run_id, state.episode, conf.train.episodes
    )
    recorder = Recorder.attach(uri, run_id)
    recorder.set_tags(
        {
            Tag.RESUMED_FROM_EPISODE: str(state.episode),
            Tag.RESUME_COUNT: str(int(info.data.tags.get(Tag.RESUME_COUNT, "0")) + 1),
            **process_tags(),
        }
    )
    if reason:
        recorder.set_tags({Tag.PREVIOUS_FAILURE_REASON: reason})
        client.delete_tag(run_id, Tag.FAILURE_REASON)
    logged = recorder.logged_episodes()
    recorder.add_pending(pending)  # metrics the store did not take before it went away
    result = _train(job, recorder, store, state, signals, progress, logged)
    if local is not None and result.status != OUTAGE:
        local_path(conf.tracking.local_checkpoints, run_id).unlink(missing_ok=True)
    return result


def _train(
    job: Job,
    recorder: Recorder,
    store: CheckpointStore,
    state: TrainState,
    signals: SignalBuffer,
    progress: bool,
    logged: set[int],
) -> RunResult:
    """The training loop with checkpoints, divergence and signal handling; closes the run.

    Whatever happens, the signals so far, the network and the status (FINISHED, FAILED with
    ``failure_reason``, KILLED) are written before returning or raising.
    """
    conf = job.conf
    episodes, every = conf.train.episodes, conf.train.checkpoint_every
    last_checkpoint = state.episode
    start_steps, t0 = state.total_steps, time.perf_counter()

    def checkpoint(st: TrainState) -> None:
        nonlocal last_checkpoint
        recorder.flush()
        rows = signals.n if conf.train.signals else 0
        store.save(capture(job.agent, job.env, st, job.rng, rows), signals)
        last_checkpoint = st.episode

    def on_episode(stats: EpisodeStats, st: TrainState) -> None:
        if stats.episode not in logged:
            recorder.log_episode(stats)
        if every and st.episode % every == 0 and st.episode < episodes:
            checkpoint(st)

    status, reason = "FINISHED", None
    outage: TrackingOutage | None = None
    store.retry_s = recorder.retry_s = conf.tracking.retry_s
    if urlsplit(recorder.uri).scheme in ("http", "https"):
        fail_fast_http(conf.tracking.timeout)
    stop = GracefulStop()
    with stop:
        try:
            train(
                job.env,
                job.agent,
                episodes=episodes,
                seed=conf.seed,
                discount=conf.train.discount,
                q_limit=conf.train.q_limit,
                signals=signals,
                state=state,
                on_episode=on_episode,
                progress=progress and conf.train.progress,
                desc=f"{conf.env.name}/{conf.controller.name}/s{conf.seed}",
                should_stop=stop.requested,
                replay=conf.weights.replay if conf.controller.name != "ddqn" else None,
                box=job.setup.box(),
            )
            if state.episode < episodes:  # a signal stopped training at an episode boundary
                status = "KILLED"
                if last_checkpoint != state.episode:
                    checkpoint(state)
                reason = (
                    f"{stop.name} after episode {state.episode} of {episodes}; checkpoint "
                    f"written, continue with resume={recorder.run_id}"
                )
        except DivergenceError as err:
            status, reason = "FAILED", f"diverged: {err}"
        except KeyboardInterrupt:
            status = "KILLED"
            reason = (
                f"stopped during episode {state.episode} of {episodes}; the last checkpoint "
                f"is at episode {last_checkpoint}, continue with resume={recorder.run_id}"
            )
            raise
        except TrackingOutage as err:  # at an episode boundary: checkpoint locally below
            outage = err
        except Exception as err:
            status, reason = "FAILED", f"{type(err).__name__}: {err}"
            raise
        finally:
            stop.closing()
            seconds = time.perf_counter() - t0
            score = float(np.mean(state.returns[-100:])) if state.returns else float("nan")
            try:
                if outage is None:
                    outage = _close_run(job, recorder, signals, status, reason, score)
            finally:
                job.env.close()
                if outage is not None:
                    status, reason = OUTAGE, _stop_locally(job, recorder, state, signals, outage)
                elif status != "FINISHED":
                    log.warning("run %s %s: %s", recorder.run_id, status, reason)
    return RunResult(
        recorder.run_id,
        status,
        score,
        reason,
        stop.signum,
        returns=list(state.returns),
        steps=state.total_steps,
        seconds=seconds,
        rate=(state.total_steps - start_steps) / seconds if seconds > 0 else math.nan,
        steps_before=start_steps,
        epsilon=float(job.agent.epsilon),
        solve_threshold=conf.env.solve_threshold,
    )


def _close_run(
    job: Job,
    recorder: Recorder,
    signals: SignalBuffer,
    status: str,
    reason: str | None,
    score: float,
) -> TrackingOutage | None:
    """Signals, model, final score and status of the run (a FINISHED run's checkpoints are
    deleted unless ``train.keep_checkpoints``); the outage if the store stopped answering."""
    conf = job.conf
    try:
        try:
            if conf.train.signals:
                recorder.log_signals(
                    signals, conf.train.lr, job.setup.box(), closes_for_good(status, reason)
                )
            if conf.tracking.log_model:
                with tempfile.TemporaryDirectory() as tmp:
                    save_network(job.net, Path(tmp))
                    recorder.log_dir(Path(tmp), folder(Artifact.MODEL))
            if status == "FINISHED" and not conf.train.keep_checkpoints:
                recorder.delete_artifacts(CHECKPOINT_ROOT)  # nothing left to resume
        except TrackingOutage:
            raise
        except BaseException:
            recorder.finish(status, reason, score)
            raise
        recorder.finish(status, reason, score)
    except TrackingOutage as err:
        return err
    return None


def _stop_locally(
    job: Job, recorder: Recorder, state: TrainState, signals: SignalBuffer, err: TrackingOutage
) -> str:
    """The store stayed away past ``tracking.retry_s``: checkpoint (at the episode boundary
    where the write failed) and the metrics not yet written into a local file; say where."""
    conf = job.conf
    rows = signals.n if conf.train.signals else 0
    ckpt = capture(job.agent, job.env, state, job.rng, rows)
    path = save_local(conf.tracking.local_checkpoints, recorder.run_id, ckpt, signals,
                      recorder.pending)  # fmt: skip
    message = (
        f"{err}. Checkpoint of episode {state.episode} of {conf.train.episodes} written locally "
        f"to {path}; the run stays RUNNING in the store. When the server answers again: "
        f"python -m cdqn.train resume={recorder.run_id} tracking.uri={err.uri} "
        f"tracking.local_checkpoints={path.parents[1]}"
    )
    log.error("%s", message)
    return message
