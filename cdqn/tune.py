"""Tune a certified design: an Optuna study over the design specification, each trial a
population (docs/tuning.md)::

    python -m cdqn.tune env.id=CartPole-v1 env.max_episode_steps=500 env.solve_threshold=475 \\
        controller=hinf_f tune.trials=40 tune.seeds=5 tune.episodes=500

A trial samples a specification from ``tune.space`` (learning target γ_eff and 1 + k1, replay,
weight magnitudes, NTK-box quantiles), synthesises and certifies its design first (a
:class:`~cdqn.control.errors.DesignError` prunes the trial with its reason, nothing is
trained), then trains a population of ``tune.seeds`` seeds starting at ``tune.seed``.

Objective (maximised): the mean over the members of the area under their ``return_ma100``
curve, normalised by the number of episodes,

    J = (1/K) Σ_k (1/N) Σ_{e=1..N} MA100_k(e),   MA100_k(e) = mean(R_k[max(1, e−99) .. e]),

i.e. the average moving-average return over training: it rewards learning fast (early
episodes count) and well (late ones too).  A member that diverges keeps its lowest return for
its missing episodes.  Every ``tune.pruner.interval`` episodes the same quantity over the
first ``n`` episodes, J_n, is reported to Optuna; :class:`EpisodeMedianPruner` stops a trial
whose J_n is below the median J_n of the complete trials (the same episodes, like for like).
The study lives in ``tune.storage`` (SQLite): running the command again with the same study
name continues it, up to ``tune.trials`` trials in all; a trial cut short by an interruption
is tried again with the same specification.

Trials in parallel: every process given the same study and storage is an Optuna worker;
Hydra's launcher starts them (``python -m cdqn.tune -m hydra/launcher=local
tune.worker=0,1 ...``).  The workers claim trials one at a time under a lock next to the
storage until the study has ``tune.trials`` of them (exactly) and share the study's MLflow
parent run; once no trial of any worker runs any more, worker 0 writes the plots, the preset
and the fresh-seed evaluation.

MLflow: one parent run per study (settings, best value, optimisation history and parameter
importances as artifacts, the best preset and its fresh-seed evaluation), one child run per
trial (specification, design record and certificate, objective, ``trial_status`` = complete /
pruned / infeasible / failed), the members' runs nested under their trial.  The best
specification is written as a ``weights`` preset ``<tune.preset_dir>/weights/<name>.yaml``
(``python -m cdqn.train weights=<name> hydra.searchpath=[file://<preset_dir>]``) and
trained again on ``tune.eval_seeds`` fresh seeds from
``tune.eval_seed``.
"""

from __future__ import annotations

import copy
import csv
import hashlib
import json
import logging
import math
import os
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf, read_write
from optuna.pruners import BasePruner, NopPruner

from cdqn.config import (
    TARGET_FIELDS,
    Config,
    ConfigError,
    register_configs,
    resolve_tracking_uri,
    target_key,
    validate,
)
from cdqn.control.errors import DesignError
from cdqn.training.interrupt import GracefulStop

try:
    import fcntl
except ImportError:  # Windows: one worker per study
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger("cdqn.tune")
CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
STATUSES = ("complete", "pruned", "infeasible", "failed")
"""``trial_status`` of a trial's MLflow run."""


@dataclass
class ParamSpec:
    """One dimension of the search space.

    ``choices``: a categorical value at ``path``.  ``width``: the centre c of a range is
    sampled in [low, high] (or from ``choices``) and ``path`` becomes
    [c − width/2, c + width/2] (γ_eff, 1 + k1).
    ``scale``: a factor f in [low, high] multiplies every number at ``path`` (a weight's
    magnitude, e.g. ``weights.{controller}.w_p.num``).  Otherwise a number in [low, high]
    (``integer``: a whole one).  ``{controller}`` in ``path`` is the controller's name."""

    path: str = "???"
    low: float | None = None
    high: float | None = None
    log: bool = False
    """Sample on a log scale."""
    width: float | None = None
    scale: bool = False
    integer: bool = False
    choices: list[Any] | None = None


@dataclass
class PrunerConfig:
    kind: str = "median"
    """median (:class:`EpisodeMedianPruner`: J over the episodes so far against the median of
    the complete trials' at the same episode) or none."""
    startup_trials: int = 3
    """Trials that complete before any is pruned."""
    warmup_episodes: int = 50
    """Episodes before a trial can be pruned."""
    interval: int = 25
    """Episodes between the intermediate values reported to Optuna."""


@dataclass
class TuneSettings:
    study: str = "cdqn"
    """Optuna study name (also the MLflow parent run's name)."""
    storage: str = "sqlite:///optuna.db"
    """Optuna storage; an SQLite file survives a restart and the study continues."""
    trials: int = 20
    """Trials of the study in all (a resumed study runs the missing ones)."""
    seeds: int = 3
    """Population size K of a trial."""
    seed: int = 100
    """First seed of every trial's population (seed … seed+K−1, the same for all trials)."""
    episodes: int = 500
    """Training episodes per member (trials and evaluation)."""
    eval_seeds: int = 10
    """Fresh seeds of the final evaluation of the best specification (0: none)."""
    eval_seed: int = 1000
    """First seed of the evaluation; its seeds must not overlap the trials' seeds."""
    baseline: str | None = None
    """A controller (e.g. ddqn) trained on the evaluation seeds beside the best design."""
    sampler_seed: int = 0
    """Seed of Optuna's TPE sampler."""
    worker: int = 0
    """Index of this process among the study's parallel workers (``-m tune.worker=0,1``);
    worker 0 waits for the others' trials and writes the plots, preset and evaluation."""
    pruner: PrunerConfig = field(default_factory=PrunerConfig)
    space: dict[str, ParamSpec] = field(default_factory=dict)
    """The search space, name → :class:`ParamSpec`."""
    preset: str | None = None
    """Name of the weights preset written for the best trial (null: tuned_<study>)."""
    preset_dir: str = "presets"
    """Folder of user presets; the preset goes to <preset_dir>/weights/<name>.yaml."""


@dataclass
class TuneConfig(Config):
    tune: TuneSettings = field(default_factory=TuneSettings)


register_configs()
ConfigStore.instance().store(name="base_tune", node=TuneConfig)


# ----------------------------------------------------------------------------- settings


def validate_tune(conf: TuneConfig) -> None:
    """The training configuration's rules and the study's: one line per problem."""
    validate(conf)
    t = conf.tune
    errors: list[str] = []
    if conf.controller.name not in ("h2", "hinf", "hinf_f"):
        errors.append(
            f"controller={conf.controller.name}: tune searches the design of h2, hinf or hinf_f"
        )
    if conf.controller.design != "synthesize":
        errors.append(
            f"controller.design={conf.controller.design}: tune needs controller.design=synthesize"
        )
    for key, value, lo in (("trials", t.trials, 1), ("seeds", t.seeds, 1),
                           ("episodes", t.episodes, 1), ("eval_seeds", t.eval_seeds, 0),
                           ("pruner.interval", t.pruner.interval, 1),
                           ("worker", t.worker, 0)):  # fmt: skip
        if value < lo:
            errors.append(f"tune.{key}={value}: must be an integer >= {lo}")
    if t.pruner.kind not in ("median", "none"):
        errors.append(f"tune.pruner.kind={t.pruner.kind}: allowed median, none")
    trial = set(range(t.seed, t.seed + t.seeds))
    fresh = set(range(t.eval_seed, t.eval_seed + t.eval_seeds))
    if trial & fresh:
        last = t.eval_seed + t.eval_seeds - 1
        errors.append(
            f"tune.eval_seed={t.eval_seed}: evaluation seeds {t.eval_seed}..{last}"
            f" overlap the trials' seeds {t.seed}..{t.seed + t.seeds - 1}; choose fresh seeds"
        )
    if not t.space:
        errors.append("tune.space: empty; give at least one dimension")
    for name, p in t.space.items():
        errors += [f"tune.space.{name}: {e}" for e in _spec_errors(p, conf)]
    if errors:
        raise ConfigError("invalid configuration:\n  - " + "\n  - ".join(errors))


def _spec_errors(p: ParamSpec, conf: Config) -> list[str]:
    path = p.path.format(controller=conf.controller.name)
    if OmegaConf.select(OmegaConf.structured(conf), path, default="__missing__") == "__missing__":
        return [f"path={p.path!r} names no configuration key"]
    if p.choices is not None:
        return [] if p.choices else ["choices=[]: give at least one"]
    if p.low is None or p.high is None or not p.low < p.high:
        return [f"low={p.low}, high={p.high}: need numbers with low < high"]
    if p.log and p.low <= 0:
        return [f"low={p.low}: a log scale needs low > 0"]
    return []


# ----------------------------------------------------------------------------- the space


def sample(trial: Any, space: dict[str, ParamSpec]) -> dict[str, Any]:
    """The trial's specification: one value per dimension (Optuna's suggest API)."""
    out: dict[str, Any] = {}
    for name, p in space.items():
        if p.choices is not None:
            out[name] = trial.suggest_categorical(name, list(p.choices))
        elif p.integer:
            out[name] = trial.suggest_int(name, int(p.low), int(p.high), log=p.log)  # type: ignore[arg-type]
        else:
            out[name] = trial.suggest_float(name, float(p.low), float(p.high), log=p.log)  # type: ignore[arg-type]
    return out


def apply(cfg: DictConfig, space: dict[str, ParamSpec], params: dict[str, Any]) -> DictConfig:
    """``cfg`` with the specification ``params`` written into it (:class:`ParamSpec`)."""
    out = copy.deepcopy(cfg)
    name = str(cfg.controller.name)
    with read_write(out):
        for key, value in params.items():
            p = space[key]
            path = _own_target_path(p.path.format(controller=name), out.weights, name)
            if p.width is not None:
                value = [float(value) - p.width / 2, float(value) + p.width / 2]
            elif p.choices is None and p.scale:
                value = _scaled(OmegaConf.to_container(OmegaConf.select(out, path))
                                if OmegaConf.is_config(OmegaConf.select(out, path))
                                else OmegaConf.select(out, path), float(value))  # fmt: skip
            OmegaConf.update(out, path, value, merge=False)
    return out


def _own_target_path(path: str, weights: Any, controller: str) -> str:
    """``weights.target.<range>`` names that range of the tuned controller's learning target:
    ``weights.controller_target.<controller>.<range>`` where the environment sets it."""
    head = "weights.target."
    if not path.startswith(head) or path[len(head) :] not in TARGET_FIELDS:
        return path
    return target_key(weights, controller, path[len(head) :])


def _scaled(value: Any, factor: float) -> Any:
    if isinstance(value, list):
        return [_scaled(v, factor) for v in value]
    return float(value) * factor


# ----------------------------------------------------------------------------- objective


def ma100(returns: list[float]) -> np.ndarray:
    """MA100(e) = mean of the returns of episodes max(1, e−99) … e."""
    r = np.asarray(returns, float)
    c = np.concatenate([[0.0], np.cumsum(r)])
    e = np.arange(1, len(r) + 1)
    lo = np.maximum(0, e - 100)
    return (c[e] - c[lo]) / (e - lo)


def padded(returns: list[float], n: int, failed: bool) -> list[float] | None:
    """The first ``n`` returns of a member; a member that failed keeps its lowest return for
    its missing episodes; None while a running member has not reached ``n``."""
    if len(returns) >= n:
        return list(returns[:n])
    if failed and returns:
        return list(returns) + [min(returns)] * (n - len(returns))
    return None


def area(curves: list[list[float]]) -> float:
    """Mean over members of the mean of MA100 over the episodes given (module docstring)."""
    return float(np.mean([ma100(r).mean() for r in curves]))


class EpisodeMedianPruner(BasePruner):
    """Optuna pruner: prune a trial whose latest intermediate value J_n (the objective over its
    first n episodes) is below the median of the J_n of the study's complete trials, once
    ``startup_trials`` trials are complete and from episode ``warmup_episodes`` on.

    Optuna's own ``MedianPruner`` compares the trial's *best* value reported so far (for a
    maximised objective, the largest) with that median, which suits a score that only
    improves (accuracy after each epoch).  J_n is no such score: the first episodes, still
    random play, often give the largest J_n of a trial (and with negative rewards, as in
    Acrobot or MountainCar, J_n can fall all the time), so that a trial's best value is
    often its random-play start and clearly losing trials go on to the end.  Here the
    trial's J_n is compared with the complete trials' J_n at the same n."""

    def __init__(self, startup_trials: int = 3, warmup_episodes: int = 50) -> None:
        self.startup_trials = startup_trials
        self.warmup_episodes = warmup_episodes

    def prune(self, study: Any, trial: Any) -> bool:
        from optuna.trial import TrialState  # noqa: PLC0415

        n = trial.last_step
        if n is None or n < self.warmup_episodes:
            return False
        complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
        if not complete or len(complete) < self.startup_trials:
            return False
        others = [tr.intermediate_values[n] for tr in complete if n in tr.intermediate_values]
        if not others or all(math.isnan(v) for v in others):
            return False
        value = trial.intermediate_values[n]
        return math.isnan(value) or value < float(np.nanmedian(others))


def make_pruner(settings: PrunerConfig) -> BasePruner:
    """The study's pruner (``tune.pruner.kind``)."""
    if settings.kind == "none":
        return NopPruner()
    return EpisodeMedianPruner(settings.startup_trials, settings.warmup_episodes)


class Progress:
    """Returns of a population's members as they arrive, and its intermediate values."""

    def __init__(self, seeds: list[int]) -> None:
        self.returns: dict[int, list[float]] = {s: [] for s in seeds}
        self.failed: set[int] = set()

    def observe(self, member: Any) -> None:
        self.returns[member.seed] = member.returns

    def value_at(self, n: int) -> float | None:
        """J over the first ``n`` episodes once every member has them (or has failed)."""
        curves = [padded(r, n, s in self.failed) for s, r in self.returns.items()]
        if any(c is None for c in curves):
            return None
        return area(curves)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- MLflow


class Tracker:
    """The study's MLflow runs: a parent per study, a child per trial (module docstring)."""

    def __init__(self, uri: str, experiment: str) -> None:
        from mlflow.tracking import MlflowClient  # noqa: PLC0415

        from cdqn.training.sweep import ensure_store  # noqa: PLC0415
        from cdqn.training.tracking import check_tracking  # noqa: PLC0415

        check_tracking(uri)  # an unusable store: one line, exit status 2
        ensure_store(uri, experiment)
        self.client = MlflowClient(uri)
        exp = self.client.get_experiment_by_name(experiment)
        self.experiment_id = (
            exp.experiment_id if exp is not None else self.client.create_experiment(experiment)
        )
        # MLflow 3's UI then opens the experiment as model training (runs table), not GenAI
        self.client.set_experiment_tag(
            self.experiment_id, "mlflow.experimentKind", "custom_model_development"
        )

    def parent(self, study: Any, conf: TuneConfig, cfg: DictConfig) -> str:
        """The study's parent run: created at the first start, reopened on a restart."""
        from cdqn.training.tracking import flatten, git_commit  # noqa: PLC0415

        run_id = study.user_attrs.get("mlflow_parent")
        if run_id is not None:
            try:
                if self.client.get_run(run_id).info.status == "RUNNING":
                    return run_id  # another worker of the study has it open
                self.client.update_run(run_id, status="RUNNING")
                self.client.set_tag(run_id, "resumed", time.strftime("%Y-%m-%dT%H:%M:%S"))
                return run_id
            except Exception:  # the store changed: start a new parent
                log.warning("parent run %s not found; a new parent run is started", run_id)
        tags = {"study": conf.tune.study, "kind": "tune", "env": conf.env.name,
                "env_id": conf.env.id, "controller": conf.controller.name,
                "git_commit": git_commit()}  # fmt: skip
        run = self.client.create_run(self.experiment_id, run_name=f"tune-{conf.tune.study}",
                                     tags=tags)  # fmt: skip
        run_id = run.info.run_id
        container = OmegaConf.to_container(cfg, resolve=True)
        self.log_params(run_id, flatten(container))  # type: ignore[arg-type]
        self.client.log_dict(run_id, container, "config.yaml")
        study.set_user_attr("mlflow_parent", run_id)
        return run_id

    def child(self, parent: str, name: str, tags: dict[str, str], kind: str = "trial") -> str:
        run = self.client.create_run(
            self.experiment_id,
            run_name=name,
            tags={"mlflow.parentRunId": parent, "kind": kind, **tags},
        )
        return run.info.run_id

    def log_params(self, run_id: str, params: dict[str, Any]) -> None:
        from mlflow.entities import Param  # noqa: PLC0415

        items = [Param(k, json.dumps(v) if isinstance(v, list | dict) else str(v)[:6000])
                 for k, v in params.items()]  # fmt: skip
        for i in range(0, len(items), 100):
            self.client.log_batch(run_id, params=items[i : i + 100])

    def metrics(self, run_id: str, values: dict[str, float], step: int = 0) -> None:
        for k, v in values.items():
            if v is not None and math.isfinite(float(v)):
                self.client.log_metric(run_id, k, float(v), step=step)

    def end(self, run_id: str, status: str, trial_status: str, reason: str | None = None) -> None:
        self.client.set_tag(run_id, "trial_status", trial_status)
        if reason:
            self.client.set_tag(run_id, "reason", reason[:5000])
        self.client.set_terminated(run_id, status)

    def nest(self, parent: str, run_ids: list[str], reason: str | None = None) -> None:
        for rid in run_ids:
            self.client.set_tag(rid, "mlflow.parentRunId", parent)
            if reason:
                self.client.set_tag(rid, "failure_reason", reason)

    def returns(self, run_id: str) -> list[float]:
        hist = self.client.get_metric_history(run_id, "episode_return")
        return [m.value for m in sorted(hist, key=lambda m: m.step)]


# ----------------------------------------------------------------------------- trials


class Study:
    """One ``python -m cdqn.tune`` invocation: the study, its trials and the evaluation."""

    def __init__(self, cfg: DictConfig) -> None:
        self.conf: TuneConfig = OmegaConf.to_object(cfg)  # type: ignore[assignment]
        validate_tune(self.conf)
        self.cfg = cfg
        t = self.conf.tune
        self.space = t.space
        self.uri = resolve_tracking_uri(self.conf.tracking.uri)
        container = OmegaConf.to_container(cfg, resolve=True)
        container.pop("tune")  # type: ignore[union-attr]
        base = OmegaConf.merge(OmegaConf.structured(Config), container)
        with read_write(base):
            base.train.episodes = t.episodes
            base.train.progress = False
            base.train.population = t.seeds
            base.seed = t.seed
            base.tracking.uri = self.uri
        self.base = base
        self.boxes: dict[tuple[float, float], tuple[list[float], list[float]]] = {}
        self.stop = GracefulStop()
        """SIGINT/SIGTERM outside a population's training (synthesis, Optuna's bookkeeping):
        the study stops before the next trial trains; while a population trains, its own
        handler stops it at the episode boundary."""

    # the design of a specification -------------------------------------------------

    def specified(self, params: dict[str, Any], seed: int, population: int) -> DictConfig:
        """The training configuration of ``params``: a measured NTK box is measured once per
        quantile pair (on the network of ``tune.seed``) and written into theta_bounds, so
        that every member, the preset and a later ``cdqn.train`` run use the same design."""
        cfg = apply(self.base, self.space, params)
        with read_write(cfg):
            cfg.seed = seed
            cfg.train.population = population
            syn = cfg.controller.synthesis
            if syn.ntk_bounds == "measured":
                q = (float(syn.quantiles[0]), float(syn.quantiles[1]))
                if q not in self.boxes:
                    self.boxes[q] = self._measure(cfg)
                theta1, ratio = self.boxes[q]
                cfg.weights.theta_bounds.theta1 = theta1
                cfg.weights.theta_bounds.ratio = ratio
                cfg.weights.theta_bounds.nominal = None
                syn.ntk_bounds = "config"
        return cfg

    def _measure(self, cfg: DictConfig) -> tuple[list[float], list[float]]:
        import torch  # noqa: PLC0415

        from cdqn.envs import env_sizes, make_env  # noqa: PLC0415
        from cdqn.network import NetworkSpec, QNetwork  # noqa: PLC0415
        from cdqn.ntk_bounds import measured_box  # noqa: PLC0415

        conf: Config = OmegaConf.to_object(cfg)  # type: ignore[assignment]
        conf.seed = self.conf.tune.seed
        env = make_env(conf.env)
        n_obs, n_actions = env_sizes(env)
        env.close()
        torch.manual_seed(conf.seed)
        net = QNetwork(NetworkSpec(n_obs, n_actions, conf.network.width, conf.network.dtype))
        box = measured_box(conf, net)
        assert box is not None
        log.info("measured NTK box: Θ1 ∈ %s, Θ2/Θ1 ∈ %s", list(box.theta1), list(box.ratio))
        return [float(v) for v in box.theta1], [float(v) for v in box.ratio]

    @staticmethod
    def design(cfg: DictConfig) -> Any:
        """Synthesise and certify (raises :class:`DesignError` with the reason)."""
        from cdqn.control.factory import make_controller  # noqa: PLC0415

        conf: Config = OmegaConf.to_object(cfg)  # type: ignore[assignment]
        validate(conf)
        return make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)

    # a population ------------------------------------------------------------------

    def population(
        self, cfg: DictConfig, report: Callable[[int, float], bool] | None = None
    ) -> tuple[Progress, Any, int | None]:
        """Train ``cfg``'s population; ``report(n, J_n)`` is called each ``interval``
        episodes and returns True to prune.  Returns the progress, the result and the
        episode at which it was pruned (None: not pruned)."""
        from cdqn.training.run import run_population  # noqa: PLC0415

        seeds = [int(cfg.seed) + i for i in range(int(cfg.train.population))]
        prog = Progress(seeds)
        interval = self.conf.tune.pruner.interval
        state = {"next": interval, "pruned": None}

        def observe(member: Any) -> None:
            if member.status == "FAILED":
                prog.failed.add(member.seed)
            prog.observe(member)
            while report is not None and state["pruned"] is None:
                n = state["next"]
                if n > self.conf.tune.episodes:
                    break
                value = prog.value_at(n)
                if value is None:
                    break
                state["next"] = n + interval
                if report(n, value):
                    state["pruned"] = n

        result = run_population(
            cfg, progress=False, observe=observe, should_stop=lambda: state["pruned"] is not None
        )
        for s, r in zip(seeds, result.members, strict=False):  # members in seed order
            if r.status == "FAILED":
                prog.failed.add(s)
        return prog, result, state["pruned"]  # type: ignore[return-value]

    # one trial ---------------------------------------------------------------------

    def objective(self, trial: Any) -> float:
        import optuna  # noqa: PLC0415

        t = self.conf.tune
        params = sample(trial, self.space)
        child = self.tracker.child(
            self.parent,
            f"trial-{trial.number}",
            {"trial": str(trial.number), "study": t.study, "worker": str(t.worker)},
        )
        trial.set_user_attr("mlflow_run", child)
        trial.set_user_attr("worker", t.worker)
        self.tracker.log_params(child, params)
        try:
            cfg = self.specified(params, t.seed, t.seeds)
            self.tracker.client.log_dict(
                child, OmegaConf.to_container(cfg.weights, resolve=True), "spec/weights.yaml"
            )
            setup = self.design(cfg)
        except DesignError as err:
            reason = f"infeasible: {err}"
            trial.set_user_attr("status", "infeasible")
            trial.set_user_attr("reason", str(err))
            self.tracker.end(child, "FAILED", "infeasible", reason)
            log.info("trial %d infeasible: %s", trial.number, err)
            raise optuna.TrialPruned(reason) from None
        except BaseException as err:
            trial.set_user_attr("status", "failed")
            self.tracker.end(child, "FAILED", "failed", f"{type(err).__name__}: {err}")
            raise
        self._log_design(child, setup)
        if self.stop.requested():  # a signal during the synthesis: do not start training
            self.tracker.end(child, "KILLED", "failed", "interrupted by a signal")
            trial.set_user_attr("status", "interrupted")
            raise KeyboardInterrupt

        reported: dict[int, float] = {}

        def report(n: int, value: float) -> bool:
            reported[n] = value
            trial.report(value, n)
            self.tracker.metrics(child, {"objective_partial": value}, step=n)
            return bool(trial.should_prune())

        try:
            prog, result, pruned_at = self.population(cfg, report)
        except BaseException as err:
            self.tracker.end(child, "KILLED", "failed", f"{type(err).__name__}: {err}")
            trial.set_user_attr("status", "failed")
            raise
        ids = [r.run_id for r in result.members]
        trial.set_user_attr("runs", ids)
        if result.signum is not None:
            self.tracker.nest(child, ids)
            self.tracker.end(child, "KILLED", "failed", "interrupted by a signal")
            trial.set_user_attr("status", "interrupted")
            raise KeyboardInterrupt
        diverged = len(prog.failed)
        self.tracker.metrics(child, {"diverged_members": diverged})
        if pruned_at is not None:
            reason = (f"pruned at episode {pruned_at}: J over the first {pruned_at} episodes "
                      f"= {reported[pruned_at]:.2f}, below the median of the "
                      "complete trials at that episode")  # fmt: skip
            self.tracker.nest(child, ids, reason)
            trial.set_user_attr("status", "pruned")
            trial.set_user_attr("pruned_at", pruned_at)
            trial.set_user_attr("reason", reason)
            self.tracker.end(child, "KILLED", "pruned", reason)
            raise optuna.TrialPruned(reason)
        self.tracker.nest(child, ids)
        curves = [padded(r, t.episodes, s in prog.failed) for s, r in prog.returns.items()]
        if any(c is None for c in curves):
            reason = "a member recorded no episode"
            trial.set_user_attr("status", "failed")
            self.tracker.end(child, "FAILED", "failed", reason)
            raise RuntimeError(reason)
        value = area(curves)  # type: ignore[arg-type]
        final = float(np.mean([np.mean(c[-100:]) for c in curves]))  # type: ignore[index]
        trial.set_user_attr("status", "complete")
        trial.set_user_attr("final_score", final)
        self.tracker.metrics(child, {"objective": value, "final_score": final})
        self.tracker.end(child, "FINISHED", "complete")
        log.info("trial %d: J = %.2f, final MA100 = %.1f, %s", trial.number, value, final, params)
        return value

    def _log_design(self, run_id: str, setup: Any) -> None:
        rec = setup.design or {}
        self.tracker.client.log_dict(run_id, rec, "design/controller.json")
        if setup.artifacts is not None and (Path(setup.artifacts) / "report.txt").is_file():
            self.tracker.client.log_artifact(run_id, str(Path(setup.artifacts) / "report.txt"),
                                             "design")  # fmt: skip
        cert = rec.get("certificate") or {}
        lt = rec.get("learning_target") or {}
        tags = {"certificate": "PASSED" if cert.get("passed", True) else "FAILED",
                "design_source": setup.source}  # fmt: skip
        for k, v in tags.items():
            self.tracker.client.set_tag(run_id, k, str(v))
        values = {"worst_pole": cert.get("worst_pole"), "max_step_gain": lt.get("max_step_gain")}
        for i, k in enumerate(("k1", "k2", "k3")):
            if rec.get("gains"):
                values[k] = rec["gains"][i]
        for key in ("gamma_eff", "step_scale"):
            if isinstance(lt.get(key), list) and len(lt[key]) == 2:
                values[f"{key}_lo"], values[f"{key}_hi"] = lt[key]
        self.tracker.metrics(run_id, {k: v for k, v in values.items() if v is not None})

    # the study ---------------------------------------------------------------------

    def run(self) -> dict[str, Any]:
        import optuna  # noqa: PLC0415
        from optuna.trial import TrialState  # noqa: PLC0415

        t = self.conf.tune
        pruner = make_pruner(t.pruner)
        lock = StudyLock(t.storage)
        with lock:  # workers starting at once: one creates the storage, study and parent run
            self.tracker = Tracker(self.uri, self.conf.tracking.experiment)
            study = optuna.create_study(
                study_name=t.study,
                storage=_storage(t.storage),
                direction="maximize",
                pruner=pruner,
                load_if_exists=True,
            )
            self.parent = self.tracker.parent(study, self.conf, self.cfg)
            # a trial a signal cut short is tried again with its specification (a killed
            # process: Optuna's heartbeat fails it after the grace period and retries it)
            retried = list(study.user_attrs.get("retried", []))
            for tr in study.get_trials(deepcopy=False):
                interrupted = tr.user_attrs.get("status") in ("interrupted", "failed")
                if tr.state == TrialState.FAIL and interrupted and tr.number not in retried:
                    retried.append(tr.number)
                    if tr.params:
                        study.enqueue_trial(tr.params)
            study.set_user_attr("retried", retried)
            done = sum(tr.state in (TrialState.COMPLETE, TrialState.PRUNED)
                       for tr in study.get_trials(deepcopy=False))  # fmt: skip
            n_trials = len(study.trials)
        # a restarted study continues the sampler's stream instead of repeating its start;
        # workers draw distinct streams, and the constant liar keeps them off each other's
        # running trials
        study.sampler = optuna.samplers.TPESampler(
            seed=t.sampler_seed + n_trials + WORKER_SEED_STRIDE * t.worker, constant_liar=True
        )
        log.info("study %s, worker %d (MLflow parent run %s): %d of %d trials done",
                 t.study, t.worker, self.parent, done, t.trials)  # fmt: skip
        t0 = time.perf_counter()
        try:
            with self.stop:
                ran = self._trials(study, lock)
        except KeyboardInterrupt:
            self.tracker.client.set_tag(self.parent, "interrupted", "true")
            self.tracker.client.set_terminated(self.parent, "KILLED")
            raise
        wall = time.perf_counter() - t0
        if t.worker != 0:
            log.info("worker %d ran trials %s; worker 0 closes the study", t.worker, ran)
            return {"study": t.study, "worker": t.worker, "trials_run": ran,
                    "wall_seconds": wall, "parent_run": self.parent}  # fmt: skip
        summary = self.close(study, wall)
        summary["trials_run"] = ran
        return summary

    def _trials(self, study: Any, lock: StudyLock) -> list[int]:
        """Run trials until the study holds ``tune.trials`` complete, pruned or running ones.

        Counting them and creating the next trial (``study.optimize``'s ask) happen under
        ``lock``, so that workers never start more than ``tune.trials`` in all; the lock is
        released as soon as the trial exists.  Worker 0 then waits until no trial of another
        worker runs (a dead worker's trial is failed by the heartbeat and run again here).
        Returns the numbers of the trials this worker ran."""
        import optuna  # noqa: PLC0415
        from optuna.trial import TrialState  # noqa: PLC0415

        t = self.conf.tune
        claimed = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.RUNNING)
        ran: list[int] = []

        def objective(trial: Any) -> float:
            lock.release()
            ran.append(trial.number)
            return self.objective(trial)

        attempts, waiting = 0, False
        while attempts < t.trials:  # at most tune.trials trials per worker (failed ones too)
            lock.acquire()
            try:
                states = [tr.state for tr in study.get_trials(deepcopy=False)]
                if sum(s in claimed for s in states) >= t.trials:
                    if t.worker == 0 and TrialState.RUNNING in states:
                        lock.release()
                        if not waiting:
                            log.info("worker 0: waiting for the running trials of other workers")
                            waiting = True
                        time.sleep(WAIT_SECONDS)
                        optuna.storages.fail_stale_trials(study)
                        continue
                    break
                attempts += 1
                study.optimize(objective, n_trials=1, catch=(RuntimeError,))
            finally:
                lock.release()
            if self.stop.requested():  # a signal during Optuna's bookkeeping of the trial
                raise KeyboardInterrupt
        return ran

    def close(self, study: Any, wall: float) -> dict[str, Any]:
        from optuna.trial import TrialState  # noqa: PLC0415

        t = self.conf.tune
        trials = study.get_trials(deepcopy=False)
        retried = study.user_attrs.get("retried", [])
        count = {s: 0 for s in STATUSES}
        for tr in trials:
            if tr.state == TrialState.COMPLETE:
                count["complete"] += 1
            elif tr.state == TrialState.PRUNED:
                infeasible = tr.user_attrs.get("status") == "infeasible"
                count["infeasible" if infeasible else "pruned"] += 1
            elif tr.state == TrialState.FAIL and tr.number not in retried:
                count["failed"] += 1
        metrics = {f"trials_{k}": float(v) for k, v in count.items()}
        metrics["wall_seconds"] = wall
        summary: dict[str, Any] = {"study": t.study, "counts": count, "wall_seconds": wall,
                                   "parent_run": self.parent}  # fmt: skip
        self._plots(study)
        if count["complete"] == 0:
            self.tracker.metrics(self.parent, metrics)
            self.tracker.client.set_tag(self.parent, "best", "none: no trial completed")
            self.tracker.client.set_terminated(self.parent, "FINISHED")
            log.warning("study %s: no trial completed; no preset written", t.study)
            return summary
        best = study.best_trial
        metrics["best_value"] = best.value
        metrics["best_final_score"] = best.user_attrs.get("final_score", float("nan"))
        self.tracker.client.set_tag(self.parent, "best_trial", str(best.number))
        self.tracker.log_params(self.parent, {f"best.{k}": v for k, v in best.params.items()})
        cfg = self.specified(best.params, t.eval_seed, max(1, t.eval_seeds))
        name = t.preset or f"tuned_{t.study}"
        preset = write_preset(cfg, name, Path(t.preset_dir), best, self.conf)
        self.tracker.client.log_artifact(self.parent, str(preset), "preset")
        setup = self.design(cfg)
        self._log_design(self.parent, setup)
        summary |= {"best_trial": best.number, "best_value": best.value,
                    "best_params": best.params, "preset": str(preset),
                    "best_final_score": metrics["best_final_score"]}  # fmt: skip
        if setup.artifacts is not None and (Path(setup.artifacts) / "report.txt").is_file():
            summary["design_report"] = (Path(setup.artifacts) / "report.txt").read_text()
        if t.eval_seeds > 0:
            summary["evaluation"] = self.evaluate(cfg, "evaluation", t.study)
            metrics["eval_objective"] = summary["evaluation"]["objective"]
            metrics["eval_final_score"] = summary["evaluation"]["final_score"]
            if t.baseline:
                base = self._with_controller(cfg, t.baseline)
                summary["baseline"] = self.evaluate(base, f"baseline-{t.baseline}", t.study)
                metrics["baseline_objective"] = summary["baseline"]["objective"]
                metrics["baseline_final_score"] = summary["baseline"]["final_score"]
            self._curves(summary)
        self.tracker.metrics(self.parent, metrics)
        self.tracker.client.set_terminated(self.parent, "FINISHED")
        return summary

    def evaluate(self, cfg: DictConfig, name: str, study: str) -> dict[str, Any]:
        """Train ``cfg`` on the fresh seeds; its objective and final score, as a trial's."""
        run = self.tracker.child(self.parent, name, {"study": study}, kind="evaluation")
        t0 = time.perf_counter()
        prog, result, _ = self.population(cfg)
        ids = [r.run_id for r in result.members]
        self.tracker.nest(run, ids)
        seeds = list(prog.returns)
        if not any(prog.returns.values()):  # trained one after another: read the store
            prog.returns = {s: self.tracker.returns(rid) for s, rid in zip(seeds, ids, strict=True)}
            prog.failed = {s for s, r in zip(seeds, result.members, strict=True)
                           if r.status == "FAILED"}  # fmt: skip
        n = self.conf.tune.episodes
        curves = [padded(r, n, s in prog.failed) or r for s, r in prog.returns.items()]
        value = area(curves) if all(curves) else float("nan")
        final = float(np.mean([np.mean(c[-100:]) for c in curves if c]))
        mean_curve = np.mean([ma100(c) for c in curves if len(c) == n], axis=0)
        out = {"objective": value, "final_score": final, "seeds": seeds,
               "diverged": len(prog.failed), "seconds": time.perf_counter() - t0,
               "curve": mean_curve.tolist()}  # fmt: skip
        self.tracker.metrics(run, {"objective": value, "final_score": final})
        self.tracker.end(run, "FINISHED", "complete")
        log.info("%s on seeds %s: J = %.2f, final MA100 = %.1f", name, seeds, value, final)
        return out

    @staticmethod
    def _with_controller(cfg: DictConfig, name: str) -> DictConfig:
        out = copy.deepcopy(cfg)
        path = CONF_DIR / "controller" / f"{name}.yaml"
        if not path.is_file():
            raise ConfigError(f"tune.baseline={name}: no conf/controller/{name}.yaml")
        raw = OmegaConf.load(path)
        # a controller file in the global package (ddqn.yaml) also sets other groups' keys
        own = raw.controller if "controller" in raw else raw
        with read_write(out):
            out.controller = OmegaConf.merge(
                OmegaConf.structured(type(OmegaConf.to_object(cfg.controller))), own
            )
            if "controller" in raw:
                for key in raw:
                    if key != "controller":
                        out[key] = OmegaConf.merge(out[key], raw[key])
        return out

    def _curves(self, summary: dict[str, Any]) -> None:
        """The fresh-seed mean MA100 curves as CSV and a plot on the parent run."""
        import matplotlib  # noqa: PLC0415

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt  # noqa: PLC0415

        runs = {"best design": summary["evaluation"]}
        if "baseline" in summary:
            runs[f"{self.conf.tune.baseline}"] = summary["baseline"]
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "evaluation_ma100.csv"
            with path.open("w", newline="") as fh:
                w = csv.writer(fh)
                w.writerow(["episode", *runs])
                for e in range(len(summary["evaluation"]["curve"])):
                    w.writerow([e + 1, *(r["curve"][e] if e < len(r["curve"]) else ""
                                         for r in runs.values())])  # fmt: skip
            fig, ax = plt.subplots(figsize=(7, 4))
            for label, r in runs.items():
                ax.plot(np.arange(1, len(r["curve"]) + 1), r["curve"],
                        label=f"{label} (J = {r['objective']:.1f})")  # fmt: skip
            if self.conf.env.solve_threshold is not None:
                ax.axhline(self.conf.env.solve_threshold, color="grey", ls=":", lw=1)
            ax.set_xlabel("episode")
            ax.set_ylabel(f"mean return_ma100 over {len(summary['evaluation']['seeds'])} seeds")
            ax.set_title(f"{self.conf.env.id}: fresh seeds")
            ax.legend()
            fig.tight_layout()
            fig.savefig(Path(tmp) / "evaluation_ma100.png", dpi=120)
            plt.close(fig)
            self.tracker.client.log_artifacts(self.parent, tmp, "evaluation")

    def _plots(self, study: Any) -> None:
        """Optimisation history and parameter importances (optuna.visualization.matplotlib)."""
        import warnings  # noqa: PLC0415

        import matplotlib  # noqa: PLC0415

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt  # noqa: PLC0415
        from optuna.visualization import matplotlib as ovm  # noqa: PLC0415

        with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
            warnings.simplefilter("ignore")  # optuna marks these plots experimental
            for name, plot in (("optimization_history", ovm.plot_optimization_history),
                               ("param_importances", ovm.plot_param_importances)):  # fmt: skip
                try:
                    ax = plot(study)
                except (ValueError, RuntimeError) as err:  # too few complete trials
                    log.info("no %s plot: %s", name, err)
                    continue
                fig = ax.figure if hasattr(ax, "figure") else ax.flat[0].figure
                fig.set_size_inches(8, 5)
                fig.tight_layout()
                fig.savefig(Path(tmp) / f"{name}.png", dpi=120)
                plt.close(fig)
            rows = [{"number": tr.number, "state": tr.state.name, "value": tr.value,
                     "status": tr.user_attrs.get("status"), "reason": tr.user_attrs.get("reason"),
                     **tr.params} for tr in study.get_trials(deepcopy=False)]  # fmt: skip
            (Path(tmp) / "trials.json").write_text(json.dumps(rows, indent=1, default=str))
            self.tracker.client.log_artifacts(self.parent, tmp, "study")


HEARTBEAT = 60
"""Seconds between a running trial's heartbeats; a trial silent for 3 of them is stale."""
WAIT_SECONDS = 2.0
"""Worker 0 polls the storage this often while other workers' trials run."""
WORKER_SEED_STRIDE = 100_003
"""Worker w's TPE sampler is seeded with ``tune.sampler_seed + trials so far + w·stride``."""


class StudyLock:
    """An exclusive lock (``fcntl.flock``) shared by the processes of one machine that use
    the Optuna storage ``url``: the file ``<database>.tune-lock`` beside an SQLite storage,
    else one in the temporary folder named by the URL's hash.  ``release`` of a lock not
    held does nothing.  Without ``fcntl`` (Windows) it does nothing (one worker)."""

    def __init__(self, url: str) -> None:
        if url.startswith("sqlite:///"):
            db = Path(url[len("sqlite:///") :]).resolve()  # as _storage resolves it
            self.path = db.with_name(db.name + ".tune-lock")
        else:
            digest = hashlib.sha256(url.encode()).hexdigest()[:16]
            self.path = Path(tempfile.gettempdir()) / f"cdqn-tune-{digest}.lock"
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._handle: Any = None

    def acquire(self) -> None:
        if self._handle is not None:
            raise RuntimeError(f"{self.path}: the lock is already held by this process")
        self._handle = self.path.open("a")
        if fcntl is not None:
            fcntl.flock(self._handle, fcntl.LOCK_EX)

    def release(self) -> None:
        if self._handle is None:
            return
        if fcntl is not None:
            fcntl.flock(self._handle, fcntl.LOCK_UN)
        self._handle.close()
        self._handle = None

    def __enter__(self) -> StudyLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _storage(url: str) -> Any:
    """Optuna storage of ``url``: an SQLite path made absolute (its folder created), with
    heartbeats so that a trial whose process died is failed and retried once
    (``RetryHeartbeatStaleTrialCallback``) when the study runs again."""
    import warnings  # noqa: PLC0415

    import optuna  # noqa: PLC0415

    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
    if url.startswith("sqlite:///") and not url.startswith("sqlite:////"):
        path = Path(url[len("sqlite:///") :]).resolve()
        path.parent.mkdir(parents=True, exist_ok=True)
        url = f"sqlite:///{path}"
    if not url.startswith(("sqlite:", "postgresql", "mysql")):
        return url
    return optuna.storages.RDBStorage(
        url,
        heartbeat_interval=HEARTBEAT,
        grace_period=3 * HEARTBEAT,
        heartbeat_stale_trial_callback=optuna.storages.RetryHeartbeatStaleTrialCallback(
            max_retry=1
        ),
    )


def write_preset(cfg: DictConfig, name: str, folder: Path, best: Any, conf: TuneConfig) -> Path:
    """``<folder>/weights/<name>.yaml``: the best trial's complete ``weights`` group."""
    weights = OmegaConf.to_container(cfg.weights, resolve=True)
    weights["name"] = name  # type: ignore[index]
    out = folder / "weights" / f"{name}.yaml"
    out.parent.mkdir(parents=True, exist_ok=True)
    c = conf
    header = [
        f"# Weights preset written by python -m cdqn.tune (study {c.tune.study!r}, trial "
        f"{best.number}, objective {best.value:.4g}).",
        f"# Tuned for env.id={c.env.id} env.max_episode_steps={c.env.max_episode_steps} "
        f"controller={c.controller.name} network.width={c.network.width} "
        f"train.lr={c.train.lr:g} train.discount={c.train.discount:g}",
        f"# Train with: python -m cdqn.train env.id={c.env.id} "
        f"env.max_episode_steps={c.env.max_episode_steps} controller={c.controller.name} "
        f"network.width={c.network.width} train.eps_dec={c.train.eps_dec:g} "
        f"train.eps_schedule={c.train.eps_schedule} weights={name} "
        f"hydra.searchpath=[file://{folder.resolve()}]",
        f"# Specification: {json.dumps(best.params)}",
    ]
    out.write_text("\n".join(header) + "\n" + OmegaConf.to_yaml(OmegaConf.create(weights)))
    return out


def summary_text(s: dict[str, Any]) -> str:
    """The printed summary of a study."""
    if "counts" not in s:  # a worker other than 0
        return (f"study {s['study']}, worker {s['worker']}: ran trials {s['trials_run']} in "
                f"{s['wall_seconds']:.0f} s; MLflow parent run {s['parent_run']}; worker 0 "
                "writes the preset and the evaluation")  # fmt: skip
    c = s["counts"]
    lines = [
        f"study {s['study']}: {sum(c.values())} trials ({c['complete']} complete, "
        f"{c['pruned']} pruned, {c['infeasible']} infeasible, {c['failed']} failed) in "
        f"{s['wall_seconds']:.0f} s; MLflow parent run {s['parent_run']}"
    ]
    if "best_trial" in s:
        lines.append(f"best trial {s['best_trial']}: J = {s['best_value']:.2f} (final MA100 "
                     f"{s['best_final_score']:.1f}), {json.dumps(s['best_params'])}")  # fmt: skip
        lines.append(f"preset: {s['preset']}")
    for key in ("evaluation", "baseline"):
        if key in s:
            e = s[key]
            lines.append(f"{key} on fresh seeds {e['seeds'][0]}..{e['seeds'][-1]}: J = "
                         f"{e['objective']:.2f}, final MA100 {e['final_score']:.1f}, "
                         f"{e['diverged']} diverged ({e['seconds']:.0f} s)")  # fmt: skip
    if "design_report" in s:
        lines += ["design of the best specification:", s["design_report"].rstrip()]
    return "\n".join(lines)


def check_tune(cfg: DictConfig) -> None:
    """What ``python -m cdqn.tune`` refuses (for :func:`cdqn.cli.preflight`)."""
    validate_tune(OmegaConf.to_object(cfg))  # type: ignore[arg-type]


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="tune")
def main(cfg: DictConfig) -> None:
    try:
        summary = Study(cfg).run()
    except (ConfigError, DesignError) as err:
        log.error("%s", err)
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        log.error("interrupted: run the same command again to continue the study")
        sys.exit(130)
    print(summary_text(summary))


if __name__ == "__main__":
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    from cdqn.cli import preflight  # noqa: PLC0415

    preflight(sys.argv[1:], config_name="tune", check=check_tune)
    # the module's own main, not __main__'s: the joblib launcher's workers (tune.worker=0,1)
    # then import the task function and the config schema instead of unpickling copies
    from cdqn.tune import main as tune_main  # noqa: PLC0415

    tune_main()
