"""One ``python -m cdqn.tune`` invocation: the study, its trials and the evaluation.

A study tunes one agent on one environment: a synthesised design (``h2``, ``hinf``,
``hinf_f``) or Double DQN (``ddqn``).  Both are offered the same shared dimensions
(observation maps, exploration; ``conf/space/shared.yaml``), the same trials, seeds and
episodes; each adds its own (a design's learning target and weights, α and integrator
reset; Double DQN's α, target period and minibatch frequency).  A trial of a design
synthesises and certifies it before anything trains (:mod:`cdqn.tuning.trial`)."""

from __future__ import annotations

import copy
import dataclasses
import itertools
import json
import logging
import math
import time
import warnings
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, read_write

from cdqn.config import (
    AGENT_ENV_KEYS,
    BOXED_CONTROLLERS,
    CONF_DIR,
    TARGET_CONTROLLERS,
    Config,
    ConfigError,
    merged,
    of_kind,
    resolve_tracking_uri,
    to_schema,
)
from cdqn.records import Tag
from cdqn.training.interrupt import GracefulStop
from cdqn.tuning.clock import CAPPED, MEMBER_EPISODES, EvaluationSize, StudyClock, recorded_stop
from cdqn.tuning.evaluation import eval_processes, evaluate, write_comparison
from cdqn.tuning.objective import score_text
from cdqn.tuning.presets import preset_settings, specification_of, write_preset
from cdqn.tuning.report import log_design, plot_study
from cdqn.tuning.settings import (
    TuneConfig,
    TuneSettings,
    episode_budget,
    trial_cap,
    validate_tune,
    warm_start_preset,
)
from cdqn.tuning.space import (
    NORMALIZE_PATH,
    RBF_PATH,
    apply,
    fit_to_box,
    fit_to_budget,
    fit_to_observation,
    fitted_specification,
    highest_floor,
    with_each_input_map,
)
from cdqn.tuning.storage import WORKER_SEED_STRIDE, StudyLock, open_storage
from cdqn.tuning.tracker import Tracker
from cdqn.tuning.trial import STATUSES, is_infeasible, run_trials

log = logging.getLogger("cdqn.tune")


class Study:
    """The study of ``cfg`` (a composed ``conf/tune.yaml``)."""

    def __init__(self, cfg: DictConfig) -> None:
        from cdqn.envs import adopt, episode_cap

        adopted = adopt(cfg)  # the study's environment: label, cap, threshold, box source
        if adopted.change is not None:
            log.info("%s", adopted.change)
        cfg = adopted.cfg
        self.conf = of_kind(adopted.conf, TuneConfig)
        validate_tune(self.conf)
        self.cfg = cfg
        t = self.conf.tune
        self.agent = self.conf.controller.name
        self.designed = self.agent in TARGET_CONTROLLERS
        self.episodes = episode_budget(t, episode_cap(self.conf.env))
        self.space = self._offered(t.space)
        self.uri = resolve_tracking_uri(self.conf.tracking.uri)
        # interpolations kept: a key that reads another (``controller.lr: ${weights.ddqn.lr}``,
        # ``controller.reset_integrator: ${weights.reset_integrator.hinf_f}``) follows the
        # value a specification writes there, in the trial as in a run of the preset
        container = of_kind(OmegaConf.to_container(cfg, resolve=False), dict)
        container.pop("tune")
        base = merged(OmegaConf.structured(Config), container)
        with read_write(base):
            base.train.episodes = self.episodes
            base.train.progress = False
            base.train.population = t.seeds
            base.seed = t.seed
            base.tracking.uri = self.uri
        self.base = base
        self.boxes: dict[str, tuple[list[float], list[float]]] = {}
        if self.agent in BOXED_CONTROLLERS and base.controller.synthesis.ntk_bounds == "measured":
            self.space = fit_to_box(self.space, self._rho_max())
        self.stop = GracefulStop()
        """SIGINT/SIGTERM outside a population's training (synthesis, Optuna's bookkeeping):
        the study stops before the next trial trains; while a population trains, its own
        handler stops it at the episode boundary."""

    def _offered(self, space: dict[str, Any]) -> dict[str, Any]:
        """The search space as this environment's observation allows it."""
        import numpy as np
        from gymnasium.spaces import Box

        from cdqn.envs import OneHot, RadialFeatures, make_env

        most = min(self.conf.tune.max_rbf_features, RadialFeatures.MAX_FEATURES)
        env_cfg = copy.deepcopy(self.conf.env)
        env_cfg.rbf_centres = None
        env = make_env(env_cfg)
        box = of_kind(env.observation_space, Box)
        bounded = bool(np.all(np.isfinite(box.low)) and np.all(np.isfinite(box.high)))
        one_hot = OneHot.encodes(env.unwrapped.observation_space)
        env.close()
        space = fit_to_observation(space, bounded, int(box.shape[0]), most, one_hot)
        train = self.conf.train
        span = float(train.eps_start) - highest_floor(space, float(train.eps_end))
        return fit_to_budget(space, self.episodes, self.conf.tune.explore_share, span)

    def _rho_max(self) -> float:
        """The smallest upper Θ2/Θ1 of the boxes of the observation maps the space offers,
        each measured here once with the configured exploration, so that every trial of a
        map, in every worker, is designed on the same box (:meth:`specified`).  A map whose
        box cannot be measured is left to its trials, which say why; 1.0 (nothing left out)
        when no box is measured."""
        maps = [[(n, c) for c in p.choices or []] for n, p in self.space.items()
                if p.path in (NORMALIZE_PATH, RBF_PATH)]  # fmt: skip
        t = self.conf.tune
        ratios = []
        for combo in itertools.product(*maps):
            try:
                cfg = self.specified(dict(combo), t.seed, t.seeds)
            except Exception as err:  # a trial of this map reports it
                log.warning("NTK box of %s not measured before the trials: %s", dict(combo), err)
                continue
            ratios.append(float(cfg.weights.theta_bounds.ratio[1]))
        return min(ratios, default=1.0)

    # the configuration of a specification -----------------------------------------

    def specified(self, params: dict[str, Any], seed: int, population: int) -> DictConfig:
        """The training configuration of ``params``.  For a design whose NTK box is measured,
        the box is measured once per observation map and quantile pair (on the network of
        ``tune.seed``) and written into theta_bounds, so that every member, the preset and a
        later ``cdqn.train`` run use the same design."""
        cfg = apply(self.base, self.space, params)
        t = self.conf.tune
        with read_write(cfg):
            cfg.seed = seed
            cfg.train.population = population
            syn = cfg.controller.synthesis
            if self.agent in BOXED_CONTROLLERS and syn.ntk_bounds == "measured":
                key = OmegaConf.to_yaml({"env": cfg.env, "net": cfg.network, "q": syn.quantiles})
                if key not in self.boxes:
                    self.boxes[key] = self._measure(cfg)
                theta1, ratio = self.boxes[key]
                cfg.weights.theta_bounds.theta1 = theta1
                cfg.weights.theta_bounds.ratio = ratio
                cfg.weights.theta_bounds.nominal = None
                cfg.weights.theta_bounds.measured_on = f"{self.conf.env.name}, seed {t.seed}"
                syn.ntk_bounds = "config"
        return cfg

    def _measure(self, cfg: DictConfig) -> tuple[list[float], list[float]]:
        import torch

        from cdqn.envs import env_sizes, make_env
        from cdqn.network import NetworkSpec, QNetwork
        from cdqn.ntk_bounds import measured_box

        conf = to_schema(cfg, Config)
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

    def design(self, cfg: DictConfig) -> Any:
        """Synthesise and certify (raises :class:`DesignError` with the reason); None for
        Double DQN, which has no design."""
        from cdqn.config import validate
        from cdqn.control.factory import make_controller

        if not self.designed:
            return None
        conf = to_schema(cfg, Config)
        validate(conf)
        return make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)

    # the study ---------------------------------------------------------------------

    def run(self) -> dict[str, Any]:
        import optuna
        from optuna.trial import TrialState

        from cdqn.tuning.pruner import make_pruner

        t = self.conf.tune
        lock = StudyLock(t.storage)
        with lock:  # workers starting at once: one creates the storage, study and parent run
            self.tracker = Tracker(self.uri, self.conf.tracking.experiment)
            study = optuna.create_study(
                study_name=t.study,
                storage=open_storage(t.storage),
                direction="maximize",
                pruner=make_pruner(t.pruner, self.episodes),
                load_if_exists=True,
            )
            _same_environment(study, self.conf)
            self.parent = self.tracker.parent(study, self.conf, self.cfg)
            size = EvaluationSize(t.eval_seeds, eval_processes(t.eval_processes, t.eval_seeds),
                                  self.episodes, 2 if t.baseline else 1, t.seeds,
                                  trial_cap(t), t.recheck_seeds)  # fmt: skip
            self.clock = StudyClock(study, t.time_limit, size, joined=self.tracker.joined)
            self.tracker.client.set_tag(self.parent, "episodes", str(self.episodes))
            _retry_interrupted(study)
            if not study.trials:
                self._warm_start(study)
            done = sum(tr.state in (TrialState.COMPLETE, TrialState.PRUNED)
                       for tr in study.get_trials(deepcopy=False))  # fmt: skip
            n_trials = len(study.trials)
        # a restarted study continues the sampler's stream instead of repeating its start;
        # workers draw distinct streams, and the constant liar keeps them off each other's
        # running trials
        study.sampler = _sampler(t, n_trials)
        log.info("study %s (%s on %s, %d episodes per member), worker %d (MLflow parent run "
                 "%s): %d of %d trials done", t.study, self.agent, self.conf.env.id,
                 self.episodes, t.worker, self.parent, done, t.trials)  # fmt: skip
        t0 = time.perf_counter()
        try:
            with self.stop:
                ran = run_trials(self, study, lock)
        except KeyboardInterrupt:
            self.tracker.client.set_tag(self.parent, "interrupted", "true")
            self.tracker.client.set_terminated(self.parent, "KILLED")
            raise
        except Exception as err:  # the study's parent run ends FAILED with the reason
            self.tracker.client.set_tag(self.parent, Tag.FAILURE_REASON, str(err))
            self.tracker.client.set_terminated(self.parent, "FAILED")
            raise
        wall = time.perf_counter() - t0
        if t.worker != 0:
            log.info("worker %d ran trials %s; worker 0 closes the study", t.worker, ran)
            return {"study": t.study, "worker": t.worker, "trials_run": ran,
                    "wall_seconds": wall, "parent_run": self.parent}  # fmt: skip
        summary = self.close(study, wall)
        summary["trials_run"] = ran
        return summary

    def _warm_start(self, study: Any) -> None:
        """Queue a new study's first trials: the specifications of the ``tune.warm_start``
        presets (what made those environments learn), fitted to this study's space
        (:func:`cdqn.tuning.space.fitted_specification`), then each of them on the other
        observation maps the space offers (:func:`cdqn.tuning.space.with_each_input_map`).
        A specification equal to an earlier one is queued once, and no more than
        ``tune.trials``.  They count as trials of the budget, are sampled where they leave a
        dimension out, and are certified and pruned like any."""
        t = self.conf.tune
        fitted = [
            (name, fitted_specification(self.space, *self._preset_specification(name)))
            for name in (warm_start_preset(env_name, self.agent) for env_name in t.warm_start)
        ]
        crossed = [(name, other) for name, params in fitted
                   for other in with_each_input_map(self.space, params)]  # fmt: skip
        queued: list[dict[str, Any]] = []
        for name, params in fitted + crossed:
            if params in queued:
                continue
            if len(queued) == t.trials:
                log.info("tune.trials=%d: %s %s not queued", t.trials, name, json.dumps(params))
                continue
            queued.append(params)
            study.enqueue_trial(params, user_attrs={Tag.START_FROM: name})
            log.info("trial %d starts from %s: %s", len(queued) - 1, name, json.dumps(params))

    def _preset_specification(self, name: str) -> tuple[dict[str, Any], dict[str, Any]]:
        """The preset ``name``'s specification and the space it was searched in
        (:func:`~cdqn.tuning.presets.specification_of`), with the value it trained at each
        plain dimension of this space that its study did not search (a number or a choice at
        a path, e.g. the ε floor ``train.eps_end``): the preset is tried as it trained."""
        params, searched = specification_of(name, self.conf.tune.preset_dir)
        unsearched = {dim: p.path.format(controller=self.agent)
                      for dim, p in self.space.items()
                      if dim not in searched and not (p.scale or p.horizon or p.width)}  # fmt: skip
        kept = preset_settings(name, self.conf.tune.preset_dir, unsearched)
        return kept | params, searched | {dim: {"path": self.space[dim].path} for dim in kept}

    def close(self, study: Any, wall: float) -> dict[str, Any]:
        """Count the trials, write the plots and the best trial's preset, and evaluate it on
        fresh seeds (beside the other agents' studies of this environment)."""
        t = self.conf.tune
        count = _counts(study)
        metrics: dict[str, float] = {f"trials_{k}": float(v) for k, v in count.items()}
        metrics["wall_seconds"] = wall
        summary: dict[str, Any] = {"study": t.study, "agent": self.agent, "counts": count,
                                   "wall_seconds": wall, "parent_run": self.parent,
                                   "episodes": self.episodes}  # fmt: skip
        plot_study(self.tracker, self.parent, study)
        client = self.tracker.client
        stop = recorded_stop(study)
        if stop is not None:
            summary["stopped"] = stop.text(sum(count.values()))
            client.set_tag(self.parent, Tag.STOPPED, summary["stopped"])
            log.warning("study %s %s", t.study, summary["stopped"])
        if count["complete"] == 0:
            self.tracker.metrics(self.parent, metrics)
            why = "no trial completed" + (
                _too_long_hint(study, self.clock.size) or _refused_hint(count)
            )
            client.set_tag(self.parent, "best", f"none: {why}")
            client.set_terminated(self.parent, "FAILED")
            summary["no_result"] = why
            log.warning("study %s: %s; no preset written", t.study, why)
            return summary
        best = self.choose(study, summary)
        metrics["best_value"] = best.value
        metrics["best_final_score"] = best.user_attrs.get("final_score", float("nan"))
        client.set_tag(self.parent, "best_trial", str(best.number))
        for key, value in best.params.items():  # tags: a continued study may choose another
            client.set_tag(self.parent, f"best.{key}", str(value))
        cfg = self.specified(best.params, t.eval_seed, max(1, t.eval_seeds))
        name = t.preset or f"tuned_{t.study}"
        searched = dataclasses.replace(t, space=self.space)  # as this environment offered it
        preset = write_preset(cfg, name, Path(t.preset_dir), best, searched)
        client.log_artifact(self.parent, str(preset), "preset")
        summary |= {"best_trial": best.number, "best_value": best.value,
                    "best_params": best.params, "preset": str(preset),
                    "best_final_score": metrics["best_final_score"]}  # fmt: skip
        setup = self.design(cfg)
        if setup is not None:
            log_design(self.tracker, self.parent, setup)
            if setup.artifacts is not None and (Path(setup.artifacts) / "report.txt").is_file():
                from cdqn.control.design import with_box_source

                text = (Path(setup.artifacts) / "report.txt").read_text()
                summary["design_report"] = with_box_source(text, setup.design["box_source"])
        if t.eval_seeds > 0:
            self._evaluate(cfg, summary, metrics)
        self.tracker.metrics(self.parent, metrics)
        client.set_terminated(self.parent, "FINISHED")
        return summary

    def choose(self, study: Any, summary: dict[str, Any]) -> Any:
        """The trial the study stands by.  J ranks the trials by the three tuning seeds alone,
        and by how fast they learn as much as by where they end; so the
        ``tune.recheck_trials`` best complete trials by J are trained again on
        ``tune.recheck_seeds`` seeds of their own, and the one with the best final score over
        all its seeds is chosen (J over them breaks a tie),

        .. math::  F_{\\rm all} = (K\\,F_{\\rm trial} + R\\,F_{\\rm recheck}) / (K + R),
                   \\quad J_{\\rm all} = (K\\,J_{\\rm trial} + R\\,J_{\\rm recheck}) / (K + R)

        (K trial seeds, R recheck seeds; F is the mean over seeds of the MA100 of the last
        episode, J the mean area, :func:`cdqn.tuning.objective.area`; a recheck without a
        score ranks last).  Each recheck is an MLflow child run (``kind=recheck``) and its
        scores are kept in the study, so a resumed close does not train it again.  A recheck
        starts only when it and the evaluation still fit ``tune.time_limit``
        (:mod:`cdqn.tuning.clock`).  With fewer than two trials rechecked, the best by J."""
        from optuna.trial import TrialState

        t = self.conf.tune
        done = [tr for tr in study.get_trials(deepcopy=False) if tr.state == TrialState.COMPLETE]
        finalists = sorted(done, key=lambda tr: tr.value, reverse=True)[: t.recheck_trials]
        if len(finalists) < 2 or t.recheck_seeds < 1:
            return study.best_trial
        rows = []
        for tr in finalists:
            key = f"recheck_{tr.number}_seeds_{t.recheck_seed}_{t.recheck_seeds}"
            scores = study.user_attrs.get(key)
            if not isinstance(scores, dict):  # not rechecked yet
                if not self.clock.size.time_for_recheck(
                    study, self.clock.elapsed(), self.clock.aim, finalists
                ):
                    log.info("no time left for the recheck of trial %d (tune.time_limit)",
                             tr.number)  # fmt: skip
                    break
                cfg = self.specified(tr.params, t.recheck_seed, t.recheck_seeds)
                out = evaluate(self, cfg, f"recheck-trial-{tr.number}", kind="recheck")
                scores = {"objective": out["objective"], "final_score": out["final_score"]}
                study.set_user_attr(key, scores)
            rows.append(self._recheck_row(tr, scores))
        summary["recheck"] = rows
        if len(rows) < 2:  # nothing to choose between
            return study.best_trial
        chosen = max(rows, key=lambda row: (row["final_all"], row["all"]))
        return next(tr for tr in finalists if tr.number == chosen["trial"])

    def _recheck_row(self, trial: Any, scores: dict[str, float]) -> dict[str, Any]:
        """A finalist's scores on its trial's K seeds, on the recheck's R and over both
        (:meth:`choose`)."""
        k, r = self.conf.tune.seeds, self.conf.tune.recheck_seeds
        final = float(trial.user_attrs.get("final_score", math.nan))

        def over_both(on_trial: float, on_recheck: float) -> float:
            both = (k * on_trial + r * on_recheck) / (k + r)
            return both if math.isfinite(both) else -math.inf

        row = {"trial": trial.number, "objective": trial.value, "recheck": scores["objective"],
               "final": final, "recheck_final": scores["final_score"]}  # fmt: skip
        row["all"] = over_both(trial.value, scores["objective"])
        row["final_all"] = over_both(final, scores["final_score"])
        log.info("recheck of trial %d on seeds %d..%d: J = %.4g, final MA100 %s; over its %d "
                 "seeds J = %.4g, final MA100 %s", trial.number, self.conf.tune.recheck_seed,
                 self.conf.tune.recheck_seed + r - 1, row["recheck"],
                 score_text(row["recheck_final"]), k + r, row["all"],
                 score_text(row["final_all"]))  # fmt: skip
        return row

    def _evaluate(self, cfg: DictConfig, summary: dict[str, Any], metrics: dict) -> None:
        """The best specification (and ``tune.baseline``) on the fresh seeds, and the
        comparison with the other agents tuned on this environment."""
        t = self.conf.tune
        summary["evaluation"] = evaluate(self, cfg, "evaluation")
        metrics["eval_objective"] = summary["evaluation"]["objective"]
        metrics["eval_final_score"] = summary["evaluation"]["final_score"]
        if t.baseline:
            base = _with_controller(cfg, t.baseline)
            summary["baseline"] = evaluate(self, base, f"baseline-{t.baseline}")
            metrics["baseline_objective"] = summary["baseline"]["objective"]
            metrics["baseline_final_score"] = summary["baseline"]["final_score"]
        summary["comparison"] = write_comparison(self, summary)


def _same_environment(study: Any, conf: TuneConfig) -> None:
    """A study is one environment's: its id, constructor arguments and episode cap are
    recorded when it starts, and a run of the same ``tune.study`` in the same storage with
    another of them is refused (its trials, pruning medians and preset would mix two tasks;
    the label, and so the default study name, does not say the kwargs or an adopted id's
    cap).  A study that has trials but no record is not checked."""
    env = conf.env
    task = {"id": env.id, "kwargs": dict(env.kwargs), "max_episode_steps": env.max_episode_steps}
    task = json.loads(json.dumps(task, default=str))  # as the storage gives it back
    recorded = study.user_attrs.get("environment")
    if recorded is None:  # a study started without the record is left as it is
        if not study.get_trials(deepcopy=False):
            study.set_user_attr("environment", task)
    elif recorded != task:
        t = conf.tune
        raise ConfigError(
            f"tune.study={t.study}: the study in {t.storage} tunes env {_task_text(recorded)}, "
            f"not this run's env {_task_text(task)}; give this environment its own study, "
            "tune.study=<name> (or tune.storage=<url>)"
        )


def _too_long_hint(study: Any, size: EvaluationSize) -> str:
    """What to change when trials were stopped by their cap (:data:`cdqn.tuning.trial.TOO_LONG`):
    the episodes a trial fits at their measured pace; "" when none stopped there."""
    stopped = [(tr.duration.total_seconds(), int(tr.user_attrs.get(MEMBER_EPISODES, 0)))
               for tr in study.get_trials(deepcopy=False)
               if tr.user_attrs.get(CAPPED) and tr.duration is not None]  # fmt: skip
    if not stopped or size.trial_cap is None:
        return ""
    head = f": {len(stopped)} trial(s) stopped at their cap ({size.trial_cap:g} s)"
    played = sum(e for _, e in stopped)
    if not played:
        return (f"{head} without ending an episode; give a larger tune.time_limit or "
                "tune.trial_share")  # fmt: skip
    tau = sum(s for s, _ in stopped) / played
    fits = int(size.trial_cap / (tau * max(1, size.members)))
    return (f"{head} at {tau:.3g} s per member-episode, where a trial of {size.members} "
            f"members fits about {fits} of its {size.episodes} episodes; give "
            f"tune.episodes=<at most {fits}> (or a lower tune.steps), or a larger "
            "tune.time_limit")  # fmt: skip


def _refused_hint(count: dict[str, int]) -> str:
    """What to change when no trial trained to its end for another reason than its cap:
    specifications refused before training (infeasible) or trials that failed."""
    parts = [f"{count[k]} {k}" for k in ("infeasible", "failed", "pruned") if count[k]]
    if not parts:
        return ""
    return (f": {', '.join(parts)} (each trial run's tag `reason` says why); give more "
            "tune.trials, or keep tune.space to what the environment allows (a design's "
            "learning targets that its measured NTK box certifies)")  # fmt: skip


def _task_text(task: dict[str, Any]) -> str:
    kwargs = "".join(f" +env.kwargs.{k}={v}" for k, v in sorted(task["kwargs"].items()))
    return f"env.id={task['id']} env.max_episode_steps={task['max_episode_steps']}{kwargs}"


def _retry_interrupted(study: Any) -> None:
    """A trial a signal cut short is tried again with its specification (a killed process:
    Optuna's heartbeat fails it after the grace period and retries it)."""
    from optuna.trial import TrialState

    retried = list(study.user_attrs.get("retried", []))
    for tr in study.get_trials(deepcopy=False):
        interrupted = tr.user_attrs.get("status") in ("interrupted", "failed")
        if tr.state == TrialState.FAIL and interrupted and tr.number not in retried:
            retried.append(tr.number)
            if tr.params:
                study.enqueue_trial(tr.params)
    study.set_user_attr("retried", retried)


def _counts(study: Any) -> dict[str, int]:
    """Trials by ``trial_status`` (a retried trial counts once, as its retry)."""
    from optuna.trial import TrialState

    retried = study.user_attrs.get("retried", [])
    count = {s: 0 for s in STATUSES}
    for tr in study.get_trials(deepcopy=False):
        if tr.state == TrialState.COMPLETE:
            count["complete"] += 1
        elif tr.state == TrialState.PRUNED:
            count["infeasible" if is_infeasible(tr) else "pruned"] += 1
        elif tr.state == TrialState.FAIL and tr.number not in retried:
            count["failed"] += 1
    return count


def _with_controller(cfg: DictConfig, name: str) -> DictConfig:
    """``cfg`` with the controller ``name`` (``tune.baseline``), trained as ``controller=<name>``
    trains: the environment settings its weights give it (``weights.<name>.normalize`` and
    ``rbf_centres``, :data:`cdqn.config.AGENT_ENV_KEYS`) replace the study's."""
    out = copy.deepcopy(cfg)
    path = CONF_DIR / "controller" / f"{name}.yaml"
    if not path.is_file():
        raise ConfigError(f"tune.baseline={name}: no conf/controller/{name}.yaml")
    own = OmegaConf.load(path)
    weights = OmegaConf.select(out, f"weights.{name}", default=None)
    with read_write(out):
        out.controller = OmegaConf.merge(
            OmegaConf.structured(type(OmegaConf.to_object(cfg.controller))), own
        )
        for key in AGENT_ENV_KEYS:
            if weights is not None and key in weights:
                out.env[key] = f"${{weights.{name}.{key}}}"
    return out


def _sampler(t: TuneSettings, n_trials: int) -> Any:
    """Worker ``t.worker``'s TPE sampler, its stream continued after ``n_trials`` trials
    (``tune.sampler_seed``, ``tune.sampler_startup``, ``tune.sampler_multivariate``)."""
    import optuna

    with warnings.catch_warnings():  # multivariate and group are "experimental"
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return optuna.samplers.TPESampler(
            seed=t.sampler_seed + n_trials + WORKER_SEED_STRIDE * t.worker,
            constant_liar=True,
            n_startup_trials=t.sampler_startup,
            multivariate=t.sampler_multivariate,
            group=t.sampler_multivariate,
        )
