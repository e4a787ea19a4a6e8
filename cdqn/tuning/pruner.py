"""Pruning a trial whose learning curve falls behind the complete trials' at the same episode."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from optuna.pruners import BasePruner, NopPruner

from cdqn.tuning.settings import PrunerConfig, warmup


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
        from optuna.trial import TrialState

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


def make_pruner(settings: PrunerConfig, episodes: int) -> BasePruner:
    """The study's pruner (``tune.pruner.kind``) for trials of ``episodes`` episodes."""
    if settings.kind == "none":
        return NopPruner()
    return EpisodeMedianPruner(settings.startup_trials, warmup(settings, episodes))
