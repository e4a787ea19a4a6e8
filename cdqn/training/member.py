"""A run in training: one seed of a configuration, with its MLflow run, checkpoints, signal
rows and where it stands.  A single run is one :class:`Member` (:mod:`cdqn.training.single`),
a population ``K`` of them (:mod:`cdqn.training.population_loop`); both pass through the
same lifecycle (:mod:`cdqn.training.lifecycle`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from omegaconf import DictConfig

from cdqn.training.signals import SignalBuffer

if TYPE_CHECKING:  # a member's run is opened by its lifecycle
    from cdqn.agents.episodic_replay import Transitions
    from cdqn.training.checkpoint import CheckpointStore
    from cdqn.training.tracking import Recorder


@dataclass
class Member:
    """One seed of a configuration in training and its bookkeeping (module docstring)."""

    seed: int
    cfg: DictConfig
    recorder: Recorder | None = None
    """Writes the member's MLflow run (:mod:`cdqn.training.lifecycle`)."""
    store: CheckpointStore | None = None
    """The checkpoints of the member's run."""
    signals: SignalBuffer = field(default_factory=SignalBuffer)
    returns: list[float] = field(default_factory=list)
    episode: int = 0
    status: str = "RUNNING"
    reason: str | None = None
    carry: dict | None = None
    replay_tail: Transitions | None = None
    """Episodic replay: the transitions of the episode in progress, set for checkpoints."""
    """Where a restored member stands between two steps (observation ``obs``, step ``t`` of
    the episode, return so far ``ret``); None: it starts with a reset."""
    checkpointed: int | None = None
    """Episode of the member's last checkpoint, if any."""
    logged: set[int] = field(default_factory=set)
    """Episodes whose metrics are already stored (a resumed member skips them)."""

    @property
    def score(self) -> float:
        return float(np.mean(self.returns[-100:])) if self.returns else float("nan")
