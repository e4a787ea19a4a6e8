"""Hydra entry point: compose the config, build env, network, controller and agent,
train, record to MLflow.

    python -m cdqn.train                                   # env=cartpole controller=hinf
    python -m cdqn.train env=acrobot controller=hinf_f seed=3 train.episodes=500
    python -m cdqn.train -m controller=h2,hinf,hinf_f,ddqn seed='range(10)'
    python -m cdqn.train resume=<run_id>                   # continue an interrupted run

Exit status: 0 finished (or a multirun that ran; its summary lists failed jobs), 1 the run
FAILED (diverged or crashed), 2 refused configuration or tracking store, 75 the tracking
store went away for longer than ``tracking.retry_s`` (checkpointed locally, resumable),
128 + signal number when SIGINT/SIGTERM stopped the run (KILLED, resumable).
"""

from __future__ import annotations

import copy
import logging
import math
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

import gymnasium as gym
import hydra
import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from cdqn.agents import Agent, make_agent
from cdqn.cli import preflight, resume_conflicts
from cdqn.config import (
    Config,
    ConfigError,
    register_configs,
    resolve_tracking_uri,
    validate,
)
from cdqn.control.errors import DesignError
from cdqn.control.factory import ControllerSetup, make_controller
from cdqn.envs import adopt_env_id, env_sizes, make_env
from cdqn.network import NetworkSpec, QNetwork, save_network
from cdqn.ntk_bounds import measured_box
from cdqn.training.callbacks import record_job
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
from cdqn.training.population import resume_population, run_population
from cdqn.training.population_checkpoint import population_runs, stored_config
from cdqn.training.signals import SignalBuffer
from cdqn.training.sweep import (
    config_hash,
    ensure_store,
    finished_elsewhere,
    process_tags,
    resumable_elsewhere,
)
from cdqn.training.tracking import (
    Recorder,
    TrackingError,
    TrackingOutage,
    check_tracking,
    fail_fast_http,
    flatten,
    git_commit,
)

log = logging.getLogger("cdqn")
register_configs()
OUTAGE = "OUTAGE"
"""Status of a run that stopped because its tracking store went away (still RUNNING there)."""
EXIT_OUTAGE = 75
"""Exit status then (EX_TEMPFAIL): resume once the store answers again."""


@dataclass
class RunResult:
    run_id: str
    status: str
    final_score: float
    """Mean return of the last 100 episodes."""
    reason: str | None = None
    """The run's ``failure_reason`` when it ended FAILED or KILLED."""
    signum: int | None = None
    """The signal that stopped a KILLED run."""
    returns: list[float] = field(default_factory=list)
    """Return of every episode, in order."""
    steps: int = 0
    """Environment steps of the whole run."""
    seconds: float = math.nan
    """Wall time of this process's training (a resumed run: since it was resumed)."""
    rate: float = math.nan
    """Environment steps per second of wall time, bookkeeping and logging included."""
    epsilon: float = math.nan
    """Exploration ε at the end."""
    solve_threshold: float | None = None
    """``env.solve_threshold`` of the run."""
    members: list[RunResult] = field(default_factory=list)
    """A population's member runs (empty for a single run)."""

    @property
    def solved_at(self) -> int | None:
        """First episode (from 1) whose 100-episode average return reaches the threshold."""
        return first_solve(self.returns, self.solve_threshold)


MODEL_TRAINING_VIEW = "workflowType=machine_learning"
"""The MLflow UI's query for its model-training view (runs table) of an experiment; MLflow 3
opens the GenAI view otherwise and remembers the choice in the browser."""
MOSTLY_RANDOM = 0.5
"""A run that ends with ε above this played mostly at random: its score says little."""


def first_solve(returns: list[float], threshold: float | None) -> int | None:
    """First episode ``n`` (from 1) with ``mean(returns[max(0, n-100):n]) >= threshold``,
    the episode at which ``return_ma100`` first reaches the threshold; None if never."""
    if threshold is None or not math.isfinite(threshold):
        return None
    for n in range(1, len(returns) + 1):
        if float(np.mean(returns[max(0, n - 100) : n])) >= threshold:
            return n
    return None


def result_lines(result: RunResult) -> list[str]:
    """What a finished run says about itself: score, solve, steps, time (one run)."""
    n = len(result.returns)
    score = (
        f"final score {result.final_score:.2f} (mean return of the last {min(n, 100)} of "
        f"{n} episodes)"
        if math.isfinite(result.final_score)
        else "no episode finished"
    )
    threshold = result.solve_threshold
    if threshold is None or not math.isfinite(threshold):
        solved = "no solve threshold"
    elif (at := result.solved_at) is None:
        solved = f"solve threshold {threshold:g} not reached"
    else:
        solved = f"solve threshold {threshold:g} reached at episode {at}"
    lines = [f"run {result.run_id} {result.status}: {score}; {solved}"]
    if math.isfinite(result.seconds):
        rate = f" ({result.rate:.0f} steps/s)" if math.isfinite(result.rate) else ""
        lines.append(
            f"  {result.steps} environment steps, {result.seconds:.1f} s of training{rate}"
        )
    if result.epsilon > MOSTLY_RANDOM:
        lines.append(
            f"  warning: ε = {result.epsilon:.2f} at the end (above {MOSTLY_RANDOM}): mostly "
            "random play, so the score says little about the learned policy; train longer "
            "(train.episodes) or explore less (train.eps_dec)"
        )
    return lines


def summary_text(result: RunResult, uri: str, experiment: str) -> str:
    """The closing summary of ``python -m cdqn.train``: each run, the store, the UI command."""
    lines: list[str] = []
    for r in result.members or [result]:
        lines += result_lines(r)
    server = uri.startswith(("http://", "https://"))
    base = uri.rstrip("/") if server else "http://127.0.0.1:5000"
    try:
        exp = MlflowClient(uri).get_experiment_by_name(experiment)
    except MlflowException:
        exp = None
    page = f"{base}/#/experiments/{exp.experiment_id if exp else ''}?{MODEL_TRAINING_VIEW}"
    lines.append(f"store: {uri}, experiment {experiment!r}; look at it with")
    if not server:
        lines.append(f"  mlflow ui --backend-store-uri {uri}")
    lines.append(f"  and open {page} (the runs table)")
    return "\n".join(lines)


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
    box = measured_box(conf, net)  # None unless controller.synthesis.ntk_bounds=measured
    setup = make_controller(
        conf.controller, conf.weights, conf.train.discount, conf.train.lr, box=box
    )
    agent = make_agent(conf.controller, conf.train, net, setup, rng)
    return Job(conf, env, setup, net, agent, rng)


def run(cfg: DictConfig, progress: bool = True) -> RunResult:
    """Train one configuration and record it as one MLflow run; with ``resume=<run_id>``
    continue that run from its last checkpoint instead (:func:`resume`)."""
    if cfg.get("resume"):
        return resume(cfg, progress)
    if (adopted := adopt_env_id(cfg)) is not None:
        log.info("%s", adopted)
    if cfg.train.get("population", 1) > 1:  # K seeds as one batch (cdqn.training.population)
        return run_population(cfg, progress).summary()
    conf: Config = OmegaConf.to_object(cfg)  # type: ignore[assignment]
    validate(conf)
    env = make_env(conf.env)  # refuses unknown ids, continuous actions before any store is touched
    try:
        uri = resolve_tracking_uri(conf.tracking.uri)
        if (
            uri.startswith("sqlite:///") or conf.tracking.skip_finished
        ):  # sweeps (cdqn.training.sweep)
            check_tracking(uri, conf.tracking.timeout)
            ensure_store(uri, conf.tracking.experiment)  # a fresh SQLite store, once
            if conf.tracking.skip_finished and (done := finished_elsewhere(cfg, uri)) is not None:
                env.close()
                return RunResult(done[0], "FINISHED", done[1], "skipped: already FINISHED")
            if conf.tracking.skip_finished and (killed := resumable_elsewhere(cfg, uri)):
                env.close()
                return _continue(cfg, killed, uri, progress)
        check_tracking(uri, conf.tracking.timeout)
        job = build(conf, env)
    except BaseException:
        env.close()
        raise

    container = OmegaConf.to_container(cfg, resolve=True)
    params = flatten(container)  # type: ignore[arg-type]
    tags = {
        "env": conf.env.name,
        "env_id": conf.env.id,
        "controller": conf.controller.name,
        "seed": str(conf.seed),
        "git_commit": git_commit(),
        "design_source": job.setup.source,
        "config_hash": config_hash(cfg),
        **process_tags(),
        **job.setup.tags(),
    }
    try:
        recorder = Recorder.start(
            uri,
            conf.tracking.experiment,
            f"{conf.env.name}-{conf.controller.name}-s{conf.seed}",
            params,
            tags,
            config=container,  # type: ignore[arg-type]
        )
    except BaseException:
        env.close()
        raise
    if job.setup.design:
        recorder.log_dict(job.setup.design, "design/controller.json")
    if job.setup.artifacts is not None:
        recorder.log_dir(job.setup.artifacts, "design")
    log.info(
        "MLflow run %s (%s, %s, seed %d)",
        recorder.run_id,
        conf.env.name,
        conf.controller.name,
        conf.seed,
    )
    store = CheckpointStore(recorder.client, recorder.run_id, conf.train.signals)
    return _train(job, recorder, store, TrainState(), SignalBuffer(), progress, set())


def resume(cfg: DictConfig, progress: bool = True) -> RunResult:
    """Continue run ``cfg.resume`` in the same MLflow run, from its last checkpoint.

    The run's stored ``config.yaml`` is what runs; ``cfg`` only says where the store is
    (``tracking.*``) and whether to show progress.  Episodes whose metrics are already in
    the store are not logged twice.  Runs that FINISHED or diverged are refused.
    """
    run_id = str(cfg.resume)
    uri = resolve_tracking_uri(cfg.tracking.uri)
    check_tracking(uri, cfg.tracking.timeout)
    client = MlflowClient(uri)
    try:
        info = client.get_run(run_id)
    except MlflowException:
        raise TrackingError(f"resume={run_id}: no such run in tracking.uri={uri!r}") from None
    status, reason = info.info.status, info.data.tags.get("failure_reason", "")
    if status == "FINISHED":
        raise ConfigError(f"resume={run_id}: the run FINISHED; there is nothing to continue")
    if status == "FAILED" and reason.startswith("diverged"):
        raise ConfigError(
            f"resume={run_id}: the run FAILED because it {reason}; with the same seed it would "
            "diverge again (start a new run with other settings)"
        )
    if "population_id" in info.data.tags:  # a member: continue its whole population
        runs = population_runs(client, info)
        return resume_population(uri, cfg.tracking, runs, progress).summary()
    if status == "RUNNING":
        log.warning(
            "run %s is marked RUNNING (its process ended without closing it, e.g. SIGKILL); "
            "continuing it. Stop any process still training it first.",
            run_id,
        )
    stored = stored_config(client, run_id, cfg.tracking)
    conf: Config = OmegaConf.to_object(stored)  # type: ignore[assignment]
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
            "resumed_from_episode": str(state.episode),
            "resume_count": str(int(info.data.tags.get("resume_count", "0")) + 1),
            **process_tags(),
        }
    )
    if reason:
        recorder.set_tags({"previous_failure_reason": reason})
        client.delete_tag(run_id, "failure_reason")
    logged = recorder.logged_episodes()
    recorder.add_pending(pending)  # metrics the store did not take before it went away
    result = _train(job, recorder, store, state, signals, progress, logged)
    if local is not None and result.status != OUTAGE:
        local_path(conf.tracking.local_checkpoints, run_id).unlink(missing_ok=True)
    return result


def _continue(cfg: DictConfig, run_id: str, uri: str, progress: bool) -> RunResult:
    """A restarted sweep's job whose run was KILLED (or left RUNNING by a process that is
    gone): continue that run from its checkpoint (:func:`resume`)."""
    log.info("continuing run %s of this configuration from its last checkpoint", run_id)
    again = copy.deepcopy(cfg)
    with read_write(again), open_dict(again):
        again.resume = run_id
        again.tracking.uri = uri
    return resume(again, progress)


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
        epsilon=float(job.agent.epsilon),
        solve_threshold=conf.env.solve_threshold,
    )


def _solve_text(result: RunResult) -> str | None:
    """``solved at episode 412`` / ``solved by 3 of 10 seeds`` / ``not solved`` (None: no
    threshold), for the multirun summary."""
    runs = result.members or [result]
    threshold = runs[0].solve_threshold
    if threshold is None or not math.isfinite(threshold) or not any(r.returns for r in runs):
        return None
    solved = [r.solved_at for r in runs if r.solved_at is not None]
    if len(runs) > 1:
        return f"solved by {len(solved)} of {len(runs)} seeds"
    return f"solved at episode {solved[0]}" if solved else "not solved"


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
                recorder.log_signals(signals, conf.train.lr)
            if conf.tracking.log_model:
                with tempfile.TemporaryDirectory() as tmp:
                    save_network(job.net, Path(tmp))
                    recorder.log_dir(Path(tmp), "model")
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


def _is_multirun() -> bool:
    try:
        return HydraConfig.get().mode == RunMode.MULTIRUN
    except ValueError:
        return False


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> float:
    multirun = _is_multirun()
    try:
        if cfg.get("resume"):
            conflicts = resume_conflicts(list(HydraConfig.get().overrides.task))
            if conflicts:
                raise ConfigError("invalid configuration:\n  - " + "\n  - ".join(conflicts))
        result = run(cfg, progress=not multirun and sys.stderr.isatty())
    except (ConfigError, DesignError) as err:  # user errors, TrackingError included
        log.error("%s", err)
        record_job("REFUSED", reason=str(err))
        if not multirun:
            sys.exit(2)
        return float("nan")
    except TrackingOutage as err:  # a population's store went away (its runs stay RUNNING)
        record_job(OUTAGE, reason=str(err))
        if not multirun:
            sys.exit(EXIT_OUTAGE)
        return float("nan")
    except KeyboardInterrupt:
        log.error("interrupted")
        sys.exit(130)
    except Exception as err:  # a crash; the MLflow run (if any) is already FAILED
        record_job("FAILED", reason=f"{type(err).__name__}: {err}")
        if not multirun:
            raise
        log.exception("job failed")
        return float("nan")
    record_job(result.status, result.run_id, result.reason, result.final_score, _solve_text(result))
    if result.status == OUTAGE:
        sys.exit(EXIT_OUTAGE)
    if not multirun:
        print(summary_text(result, resolve_tracking_uri(cfg.tracking.uri), cfg.tracking.experiment))
    if result.status == "KILLED":
        sys.exit(128 + (result.signum or 2))
    if result.status == "FAILED" and not multirun:
        sys.exit(1)
    return result.final_score if math.isfinite(result.final_score) else float("nan")


if __name__ == "__main__":
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    preflight(sys.argv[1:])
    main()
