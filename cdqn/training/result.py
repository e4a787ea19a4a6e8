"""What a training job returns and says about itself: :class:`RunResult` of a single run or
a population member, :class:`PopulationResult` of a population, and the closing summary."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient

OUTAGE = "OUTAGE"
"""Status of a run that stopped because its tracking store went away (still RUNNING there)."""
EXIT_OUTAGE = 75
"""Exit status then (EX_TEMPFAIL): resume once the store answers again."""
MODEL_TRAINING_VIEW = "workflowType=machine_learning"
"""The MLflow UI's query for its model-training view (runs table) of an experiment; MLflow 3
opens the GenAI view otherwise and remembers the choice in the browser."""
MOSTLY_RANDOM = 0.5
"""A run that ends with ε above this played mostly at random: its score says little."""


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
    """Environment steps per second of wall time, bookkeeping and logging included, of this
    process's training: ``(steps - steps_before) / seconds``."""
    steps_before: int = 0
    """Environment steps the run had when this process resumed it (0: not resumed)."""
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


@dataclass
class PopulationResult:
    """Outcome of a population: one :class:`RunResult` per member, in seed order."""

    members: list[RunResult]
    signum: int | None = None
    """The signal that stopped the population, if any."""

    def summary(self) -> RunResult:
        """One result for the Hydra job: the worst status, the mean final score."""
        order = {"FINISHED": 0, "KILLED": 1, "FAILED": 2}
        worst = max(self.members, key=lambda r: order.get(r.status, 3))
        scores = [r.final_score for r in self.members if math.isfinite(r.final_score)]
        failed = [f"{r.run_id}: {r.reason}" for r in self.members if r.status != "FINISHED"]
        return RunResult(
            ",".join(r.run_id for r in self.members),
            worst.status,
            float(np.mean(scores)) if scores else float("nan"),
            "; ".join(failed) or None,
            self.signum,
            members=list(self.members),
        )


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
        if result.steps_before:  # the time covers the resumed part alone, and so does the rate
            lines.append(
                f"  {result.steps} environment steps; resumed at step {result.steps_before}: "
                f"{result.steps - result.steps_before} steps in {result.seconds:.1f} s of "
                f"training{rate}"
            )
        else:
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


def solve_text(result: RunResult) -> str | None:
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
