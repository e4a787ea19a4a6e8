"""One trial of a study: sample a specification, certify its design, train a population,
report J_n to the pruner, record everything in MLflow."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from cdqn.config import ConfigError
from cdqn.control.errors import DesignError
from cdqn.records import Metric, Tag
from cdqn.tuning.clock import CAPPED, MEMBER_EPISODES, Pace
from cdqn.tuning.objective import Progress, area, padded, score_text
from cdqn.tuning.report import log_design
from cdqn.tuning.space import sample

log = logging.getLogger("cdqn.tune")
STATUSES = ("complete", "pruned", "infeasible", "failed")


def is_infeasible(trial: Any) -> bool:
    """Whether a finished Optuna trial was refused before training (no design meets its
    specification); such a trial does not count against ``tune.trials``."""
    return trial.user_attrs.get("status") == "infeasible"


"""``trial_status`` of a trial's MLflow run."""
OVERDUE = -1
"""``train_population``'s pruning episode for a trial stopped by the study's time limit."""
TOO_LONG = -2
"""``train_population``'s pruning episode for a trial stopped at its own time cap."""
WAIT_SECONDS = 2.0
"""Worker 0 polls the storage this often while other workers' trials run."""


def run_trials(study_obj: Any, study: Any, lock: Any) -> list[int]:
    """Run trials until the study holds ``tune.trials`` complete, pruned or running ones that
    train, or as many infeasible ones (a specification no design meets is refused before it
    trains, in about a second, and does not use up the budget), or until one more trial and
    the evaluation would end past ``tune.time_limit``
    (:meth:`cdqn.tuning.clock.StudyClock.check`).

    Counting them and creating the next trial (``study.optimize``'s ask) happen under
    ``lock``, so that workers never start more than ``tune.trials`` in all; the lock is
    released as soon as the trial exists.  Worker 0 then waits until no trial of another
    worker runs (a dead worker's trial is failed by the heartbeat and run again here).
    Returns the numbers of the trials this worker ran."""
    import optuna
    from optuna.trial import TrialState

    t = study_obj.conf.tune
    claimed = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.RUNNING)
    ran: list[int] = []

    refused: list[ConfigError] = []

    def objective(trial: Any) -> float:
        lock.release()
        ran.append(trial.number)
        try:
            return Trial(study_obj, trial).run()
        except ConfigError as err:  # the search space gives values cdqn refuses: stop here
            refused.append(ConfigError(f"tune.space: trial {trial.number}'s sample is {err}"))
            trial.set_user_attr("status", "refused")
            trial.study.stop()
            raise optuna.TrialPruned(str(refused[-1])) from None

    attempts, waiting, timed_out = 0, False, False
    while attempts < 2 * t.trials:  # per worker: tune.trials that train, as many refused
        lock.acquire()
        try:
            trials = study.get_trials(deepcopy=False)
            states = [tr.state for tr in trials]
            infeasible = sum(map(is_infeasible, trials))
            trained = sum(s in claimed for s in states) - infeasible
            full = trained >= t.trials or infeasible >= t.trials
            timed_out = timed_out or (not full and study_obj.clock.check() is not None)
            if full or timed_out:
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
            if refused:
                raise refused[0]
        finally:
            lock.release()
        if study_obj.stop.requested():  # a signal during Optuna's bookkeeping of the trial
            raise KeyboardInterrupt
    return ran


def train_population(
    study_obj: Any, cfg: DictConfig, report: Callable[[int, float], bool] | None = None
) -> tuple[Progress, Any, int | None]:
    """Train ``cfg``'s population; ``report(n, J_n)`` is called each ``interval`` episodes and
    returns True to prune.  With ``report``, the population also stops when the study's
    clock is overdue or the trial trains, or at its pace will train, past its cap
    (:meth:`cdqn.tuning.clock.StudyClock.overdue`, :meth:`~cdqn.tuning.clock.StudyClock.too_long`).
    Returns the progress, the result and the episode at which it was pruned (None: not
    pruned; :data:`OVERDUE`, :data:`TOO_LONG`: stopped by the clock)."""
    from cdqn.training.divergence import is_divergence
    from cdqn.training.run import run_population

    seeds = [int(cfg.seed) + i for i in range(int(cfg.train.population))]
    prog = Progress(seeds)
    interval = study_obj.conf.tune.pruner.interval
    episodes = int(cfg.train.episodes)
    state: dict[str, Any] = {"next": interval, "pruned": None, "overdue": False, "long": False}
    clock = getattr(study_obj, "clock", None) if report is not None else None
    started = time.monotonic()
    pace = Pace(len(seeds) * episodes)

    def should_stop() -> bool:
        if state["pruned"] is not None or state["overdue"] or state["long"]:
            return True
        if clock is None:
            return False
        trained = time.monotonic() - started
        state["long"] = clock.too_long(trained, pace.total())
        state["overdue"] = not state["long"] and clock.overdue(pace.projected())
        return bool(state["overdue"] or state["long"])

    def observe(member: Any) -> None:
        if is_divergence(member.status, member.reason):
            prog.failed.add(member.seed)
        prog.observe(member)
        played = sum(len(r) for r in prog.returns.values())  # once per episode
        pace.mark(time.monotonic() - started, played)
        while report is not None and state["pruned"] is None:
            n = state["next"]
            if n > episodes:
                break
            value = prog.value_at(n)
            if value is None:
                break
            state["next"] = n + interval
            if report(n, value):
                state["pruned"] = n

    result = run_population(cfg, progress=False, observe=observe, should_stop=should_stop)
    for s, r in zip(seeds, result.members, strict=False):  # members in seed order
        if is_divergence(r.status, r.reason):
            prog.failed.add(s)
    if state["pruned"] is None and (state["overdue"] or state["long"]):
        state["pruned"] = TOO_LONG if state["long"] else OVERDUE
    return prog, result, state["pruned"]


class Trial:
    """One Optuna trial of ``study_obj`` (:class:`cdqn.tuning.study.Study`)."""

    def __init__(self, study_obj: Any, trial: Any) -> None:
        self.s, self.trial = study_obj, trial
        self.tracker = study_obj.tracker
        self.reported: dict[int, float] = {}

    def run(self) -> float:
        """The trial's objective J (raises ``optuna.TrialPruned`` when pruned or infeasible)."""
        t = self.s.conf.tune
        params = sample(self.trial, self.s.space)
        self.child = self.tracker.child(
            self.s.parent, f"trial-{self.trial.number}",
            {"trial": str(self.trial.number), "study": t.study, "worker": str(t.worker)},
        )  # fmt: skip
        self.trial.set_user_attr("mlflow_run", self.child)
        if start := self.trial.user_attrs.get(Tag.START_FROM):
            self.tracker.client.set_tag(self.child, Tag.START_FROM, start)
        self.trial.set_user_attr("worker", t.worker)
        self.tracker.log_params(self.child, params)
        cfg = self._certified(params)
        if self.s.stop.requested():  # a signal during the synthesis: do not start training
            self._end("KILLED", "failed", "interrupted by a signal", status="interrupted")
            raise KeyboardInterrupt
        try:
            prog, result, pruned_at = train_population(self.s, cfg, self._report)
        except BaseException as err:  # a signal ends it KILLED, an error FAILED
            end = "FAILED" if isinstance(err, Exception) else "KILLED"
            self._end(end, "failed", f"{type(err).__name__}: {err}", status="failed")
            raise
        return self._score(params, prog, result, pruned_at)

    def _certified(self, params: dict[str, Any]) -> DictConfig:
        """The specification's configuration, its design synthesised and certified first."""
        import optuna

        t = self.s.conf.tune
        try:
            cfg = self.s.specified(params, t.seed, t.seeds)
            spec = OmegaConf.to_container(cfg.weights, resolve=True)
            self.tracker.client.log_dict(self.child, spec, "spec/weights.yaml")
            setup = self.s.design(cfg)
        except DesignError as err:
            self.trial.set_user_attr("reason", str(err))
            self._end("FAILED", "infeasible", f"infeasible: {err}", status="infeasible")
            log.info("trial %d infeasible: %s", self.trial.number, err)
            raise optuna.TrialPruned(f"infeasible: {err}") from None
        except BaseException as err:
            self._end("FAILED", "failed", f"{type(err).__name__}: {err}", status="failed")
            raise
        if setup is not None:
            log_design(self.tracker, self.child, setup)
        return cfg

    def _report(self, n: int, value: float) -> bool:
        self.reported[n] = value
        self.trial.report(value, n)
        self.tracker.metrics(self.child, {"objective_partial": value}, step=n)
        return bool(self.trial.should_prune())

    def _end(self, run_status: str, trial_status: str, reason: str | None, status: str) -> None:
        """End the trial's MLflow run (``run_status``, tags ``trial_status`` and ``reason``)
        and record ``status`` on the Optuna trial."""
        self.trial.set_user_attr("status", status)
        self.tracker.end(self.child, run_status, trial_status, reason)

    def _score(self, params: dict[str, Any], prog: Progress, result: Any,
               pruned_at: int | None) -> float:  # fmt: skip
        import optuna

        ids = [r.run_id for r in result.members]
        self.trial.set_user_attr("runs", ids)
        played = sum(len(r) for r in prog.returns.values())
        self.trial.set_user_attr(MEMBER_EPISODES, played)  # the study clock's measure
        if result.signum is not None:
            self.tracker.nest(self.child, ids)
            self._end("KILLED", "failed", "interrupted by a signal", status="interrupted")
            raise KeyboardInterrupt
        self.tracker.metrics(self.child, {"diverged_members": len(prog.failed)})
        if pruned_at is not None:
            t = self.s.conf.tune
            stopped = f"stopped after {min(len(r) for r in prog.returns.values())} episodes"
            if pruned_at == OVERDUE:
                reason = (f"{stopped}: the evaluation would otherwise end past the study's "
                          f"time limit ({t.time_limit:g} s)")  # fmt: skip
                log.info("trial %d %s", self.trial.number, reason)
            elif pruned_at == TOO_LONG:
                reason = (f"{stopped}: at its pace it trains for longer than its cap, "
                          f"tune.trial_share × tune.time_limit = "
                          f"{self.s.clock.size.trial_cap:g} s, after which it and its "
                          "evaluation would no longer fit the limit")  # fmt: skip
                self.trial.set_user_attr(CAPPED, True)
                log.info("trial %d %s", self.trial.number, reason)
            else:
                reason = (f"pruned at episode {pruned_at}: J over the first {pruned_at} "
                          f"episodes = {self.reported[pruned_at]:.2f}, below the median of "
                          "the complete trials at that episode")  # fmt: skip
                self.trial.set_user_attr("pruned_at", pruned_at)
            self.tracker.nest(self.child, ids, reason)
            self.tracker.drop_checkpoints(ids)
            self.trial.set_user_attr("reason", reason)
            self._end("KILLED", "pruned", reason, status="pruned")
            raise optuna.TrialPruned(reason)
        self.tracker.nest(self.child, ids)
        n = self.s.episodes
        found = [padded(r, n, s in prog.failed) for s, r in prog.returns.items()]
        curves = [c for c in found if c is not None]
        if len(curves) < len(found):
            self._end("FAILED", "failed", "a member recorded no episode", status="failed")
            raise RuntimeError("a member recorded no episode")
        value = area(curves)
        final = float(np.mean([np.mean(c[-100:]) for c in curves]))
        self.trial.set_user_attr("status", "complete")
        self.trial.set_user_attr("final_score", final)
        self.tracker.metrics(self.child, {Metric.OBJECTIVE: value, Metric.FINAL_SCORE: final})
        self.tracker.end(self.child, "FINISHED", "complete")
        log.info("trial %d: J = %.2f, final MA100 = %s, %s", self.trial.number, value,
                 score_text(final), params)  # fmt: skip
        return value
