"""What ``python -m cdqn.train`` runs: one configuration as a single run or a population,
a new run or the continuation of an interrupted one.

:func:`run` decides: ``resume=<run_id>`` continues that run (:func:`resume`), a
``train.population`` above 1 trains the seeds as a population (:func:`run_population`),
anything else is a single run (:mod:`cdqn.training.single`).  With
``tracking.skip_finished=true`` (restarted sweeps, :mod:`cdqn.training.sweep`) a
configuration whose run FINISHED is skipped and one whose run was KILLED is continued.
"""

from __future__ import annotations

import copy
import logging
import signal
from collections.abc import Callable
from typing import TYPE_CHECKING

from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig, open_dict, read_write

from cdqn.config import Config, ConfigError, resolve_tracking_uri, to_schema
from cdqn.envs import Adopted, adopt, make_env
from cdqn.records import Tag
from cdqn.training.build import member_config, member_seeds
from cdqn.training.divergence import is_divergence
from cdqn.training.result import PopulationResult, RunResult
from cdqn.training.single import resume_run, start_run
from cdqn.training.store import ensure_store
from cdqn.training.sweep import finished_elsewhere, resumable_elsewhere
from cdqn.training.tracking import TrackingError, check_tracking

if TYPE_CHECKING:
    from cdqn.training.member import Member

log = logging.getLogger("cdqn")


def run(cfg: DictConfig, progress: bool = True) -> RunResult:
    """Train one configuration and record it as one MLflow run (a population: one run per
    member, :meth:`PopulationResult.summary` returned); with ``resume=<run_id>`` continue
    that run from its last checkpoint instead (:func:`resume`).  The configuration is
    adopted by its environment first (:func:`cdqn.envs.adopt`)."""
    if cfg.get("resume"):
        return resume(cfg, progress)
    return run_adopted(adopted_config(cfg), progress)


def adopted_config(cfg: DictConfig) -> Adopted:
    """:func:`cdqn.envs.adopt`, with what it changed logged."""
    adopted = adopt(cfg)
    if adopted.change is not None:
        log.info("%s", adopted.change)
    return adopted


def run_adopted(adopted: Adopted, progress: bool = True) -> RunResult:
    """:func:`run` of a configuration already adopted by its environment."""
    cfg, conf = adopted.cfg, adopted.conf
    if conf.train.population > 1:  # K seeds as one batch (cdqn.training.population)
        return _population(adopted, progress).summary()
    env = make_env(conf.env)  # refuses unknown ids, continuous actions before any store is touched
    try:
        uri = resolve_tracking_uri(conf.tracking.uri)
        if uri.startswith("sqlite:///") or conf.tracking.skip_finished:  # sweeps
            check_tracking(uri, conf.tracking.timeout)
            ensure_store(uri, conf.tracking.experiment)  # a fresh SQLite store, once
            if conf.tracking.skip_finished and (done := finished_elsewhere(cfg, uri)) is not None:
                env.close()
                return RunResult(done[0], "FINISHED", done[1], "skipped: already FINISHED")
            if conf.tracking.skip_finished and (killed := resumable_elsewhere(cfg, uri)):
                env.close()
                return _continue(cfg, killed, uri, progress)
        check_tracking(uri, conf.tracking.timeout)
    except BaseException:
        env.close()
        raise
    return start_run(cfg, conf, env, uri, progress)


def run_population(
    cfg: DictConfig,
    progress: bool = True,
    observe: Callable[[Member], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> PopulationResult:
    """Train seeds ``seed … seed+population−1`` of ``cfg``, each as its own MLflow run: as
    one batch (:func:`cdqn.training.population.start_population`, where ``observe`` and
    ``should_stop`` serve :mod:`cdqn.tune`) when the configuration allows it
    (:func:`cdqn.training.batching.batchable`), else one single run after another.  The
    configuration is adopted by its environment first (:func:`cdqn.envs.adopt`)."""
    return _population(adopted_config(cfg), progress, observe, should_stop)


def _population(
    adopted: Adopted,
    progress: bool = True,
    observe: Callable[[Member], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> PopulationResult:
    from cdqn.training.batching import batchable  # a population's modules: loaded for one
    from cdqn.training.population import start_population

    cfg, conf = adopted.cfg, adopted.conf
    if batchable(conf):
        return start_population(cfg, progress, observe, should_stop)
    log.info("population of %s: members trained one after another", conf.controller.name)
    seeds = member_seeds(conf.seed, conf.train.population)
    members: list[RunResult] = []
    for i, seed in enumerate(seeds):
        members.append(result := run_adopted(_member(cfg, seed), progress))
        if result.signum is not None:  # SIGINT/SIGTERM stops the population, not one member
            left = seeds[i + 1 :]
            if left:
                name = signal.Signals(result.signum).name
                log.warning("stopped by %s: members of seeds %s not started", name, left)
            return PopulationResult(members, result.signum)
    return PopulationResult(members)


def _member(cfg: DictConfig, seed: int) -> Adopted:
    """The adopted single run that the member of seed ``seed`` stands for."""
    member = member_config(cfg, seed)
    return Adopted(member, to_schema(member, Config), None)


def resume(cfg: DictConfig, progress: bool = True) -> RunResult:
    """Continue run ``cfg.resume`` in the same MLflow run, from its last checkpoint; a
    population member continues its whole population.

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
    status, reason = info.info.status, info.data.tags.get(Tag.FAILURE_REASON, "")
    if status == "FINISHED":
        raise ConfigError(f"resume={run_id}: the run FINISHED; there is nothing to continue")
    if is_divergence(status, reason):
        raise ConfigError(
            f"resume={run_id}: the run FAILED because it {reason}; with the same seed it would "
            "diverge again (start a new run with other settings)"
        )
    if Tag.POPULATION_ID in info.data.tags:  # a member: continue its whole population
        from cdqn.training.population import resume_population
        from cdqn.training.population_checkpoint import population_runs

        runs = population_runs(client, info)
        return resume_population(uri, cfg.tracking, runs, progress).summary()
    return resume_run(cfg, client, info, uri, progress)


def _continue(cfg: DictConfig, run_id: str, uri: str, progress: bool) -> RunResult:
    """A restarted sweep's job whose run was KILLED (or left RUNNING by a process that is
    gone): continue that run from its checkpoint (:func:`resume`)."""
    log.info("continuing run %s of this configuration from its last checkpoint", run_id)
    again = copy.deepcopy(cfg)
    with read_write(again), open_dict(again):
        again.resume = run_id
        again.tracking.uri = uri
    return resume(again, progress)
