"""Checkpoints of populations: every member's state between two population steps.

A population (:mod:`cdqn.training.population`) checkpoints as a whole: each time its slowest
member has completed another ``train.checkpoint_every`` episodes, and when SIGINT/SIGTERM
stops it.  Members' episodes have different lengths, so at that moment most members are
inside an episode.  Where the environments can be captured between two steps (CartPole,
Acrobot, MountainCar, :mod:`cdqn.vector_env`) a member's checkpoint holds everything
between two steps; for any other environment each member is captured at its own episode
boundary (``loop`` is None; the schedule is in :mod:`cdqn.training.population_loop`), and
the members of one checkpoint may stand at different episodes.  Each member's checkpoint
is stored in its own MLflow run, in the slots of a single run
(:class:`cdqn.training.checkpoint.CheckpointStore`), as a :class:`MemberCheckpoint`:

* ``agent``: the population agent's ``state_dict(i)`` for the member's row ``i``;
* ``env``: the vectorised environment's ``state_dict(i)`` (the physical state, the step
  count of the time limit, the member's ``np_random``); at an episode boundary its
  ``boundary_state(i)`` (the member's ``np_random``);
* ``loop``: the training loop's per-member values: observation ``obs``, step ``t`` within
  the episode, return so far ``ret`` and the signal rows of the episode in progress
  ``rows`` (its metrics are computed from them when it ends); None at an episode boundary
  (the member starts its next episode with a reset);
* the episode counter, the returns and the signal rows so far;
* ``sequence`` and ``population``: the number of the checkpoint and the run ids of every
  member it captured.  Members restored together must come from the same checkpoint (they
  share one exploration plan), so resume picks the newest ``sequence`` that every member
  still to train holds in one of its slots.

The population agent's checkpoint protocol (what a batched agent provides so that its
populations checkpoint and resume bit for bit)::

    agent.state_dict(i) -> dict          # member i's whole learning state between two steps
    agent.load_state_dict(i, state)      # put member i of a freshly built agent into it

``state`` is a tree of dicts, lists, Python numbers and NumPy arrays (stored with
``torch.save`` and read back with ``weights_only=True``): parameters,
integrator and controller states, generator states together with anything drawn from them
but not yet used (the undrawn part of an exploration plan), and for Double DQN the target
network, step counter and replay buffer.  A freshly built agent (same configuration, same
seeds) that loads every member's state continues as the interrupted one would have.
"""

from __future__ import annotations

import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from mlflow.entities import Run
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from cdqn.config import Config, ConfigError, merged
from cdqn.records import Tag
from cdqn.training.divergence import is_divergence
from cdqn.training.signals import COLUMNS
from cdqn.training.tracking import CONFIG_ARTIFACT


class PopulationAgent(Protocol):
    """The checkpoint protocol of a population agent (module docstring)."""

    def state_dict(self, i: int) -> dict[str, Any]: ...

    def load_state_dict(self, i: int, state: dict[str, Any]) -> None: ...


@dataclass
class MemberCheckpoint:
    """One member's state between two population steps (module docstring)."""

    sequence: int
    """Number of the population checkpoint (1, 2, … over the population's life)."""
    population: list[str]
    """Run ids of the members captured by this checkpoint."""
    episode: int
    """Episodes the member completed."""
    returns: list[float]
    signal_rows: int
    agent: dict[str, Any]
    env: dict[str, Any]
    loop: dict[str, Any] | None
    """The loop's values between two steps; None: captured at an episode boundary."""
    signals: np.ndarray | None = None
    """The signal rows, filled in by :meth:`cdqn.training.checkpoint.CheckpointStore.complete`."""


CLOSING_FILE = "closing.pt"
"""Local file of a member that ended while the tracking store was away."""


@dataclass
class MemberClosing:
    """What closing the run of a member that ended (FINISHED, or FAILED by divergence) while
    the tracking store was away writes, kept in ``tracking.local_checkpoints`` until the
    store answers again (with the metrics not yet written, and the model beside it)."""

    status: str
    reason: str | None
    returns: list[float]
    signal_rows: int
    signals: np.ndarray | None = None
    """The signal rows, filled in when read back."""


def capture_member(
    sequence: int,
    population: list[str],
    member: Any,
    agent: PopulationAgent,
    venv: Any,
    i: int,
    obs: np.ndarray,
    t: np.ndarray,
    ret: np.ndarray,
    signal_rows: int,
    boundary: bool = False,
) -> MemberCheckpoint:
    """Snapshot of ``member`` (row ``i`` of ``agent`` and ``venv``) between two steps, or
    (``boundary``) between two of its episodes, before the reset that starts the next."""
    return MemberCheckpoint(
        sequence=sequence,
        population=list(population),
        episode=member.episode,
        returns=[float(r) for r in member.returns],
        signal_rows=signal_rows,
        agent=agent.state_dict(i),
        env=venv.boundary_state(i) if boundary else venv.state_dict(i),
        loop=None
        if boundary
        else {
            "obs": np.array(obs[i]),
            "t": int(t[i]),
            "ret": float(ret[i]),
            "rows": member.signals.rows(member.signals.n - int(t[i])).copy(),
            "replay_tail": None
            if member.replay_tail is None
            else {k: np.array(v) for k, v in member.replay_tail._asdict().items()},
        },
    )


def restore_member(
    ckpt: MemberCheckpoint, member: Any, agent: PopulationAgent, venv: Any, i: int
) -> None:
    """Put ``member`` and row ``i`` of a freshly built ``agent`` and ``venv`` into ``ckpt``."""
    agent.load_state_dict(i, ckpt.agent)
    if ckpt.loop is None:
        venv.load_boundary_state(i, ckpt.env)
    else:
        venv.load_state_dict(i, ckpt.env)
    member.episode = ckpt.episode
    member.returns = list(ckpt.returns)
    member.carry = None if ckpt.loop is None else dict(ckpt.loop)
    member.checkpointed = ckpt.episode
    # all rows so far, or (signals not stored) those of the episode in progress
    if ckpt.signals is not None:
        member.signals.load(ckpt.signals)
    elif ckpt.loop is not None:
        member.signals.load(ckpt.loop["rows"])
    else:
        member.signals.load(np.empty((0, len(COLUMNS))))


def loadable(ckpt: MemberCheckpoint, venv: Any) -> bool:
    """Whether ``venv`` can continue from ``ckpt`` (a capture between two steps needs
    environments that can be put mid-episode)."""
    return ckpt.loop is None or bool(venv.checkpointable)


def common_sequence(found: Mapping[int, list[tuple[MemberCheckpoint, int]]]) -> int | None:
    """The newest checkpoint ``sequence`` every member in ``found`` (seed → readable
    checkpoints) holds, or None when they share none."""
    shared: set[int] | None = None
    for items in found.values():
        seqs = {c.sequence for c, _ in items}
        shared = seqs if shared is None else shared & seqs
    return max(shared) if shared else None


def stored_config(client: MlflowClient, run_id: str, tracking: Any) -> DictConfig:
    """Run ``run_id``'s stored ``config.yaml`` with ``tracking`` in place of its own."""
    with tempfile.TemporaryDirectory() as tmp:
        try:
            path = client.download_artifacts(run_id, CONFIG_ARTIFACT, tmp)
        except Exception:
            raise ConfigError(
                f"resume={run_id}: the run has no {CONFIG_ARTIFACT} artifact, so it cannot be "
                "rebuilt (was it started by cdqn.train?)"
            ) from None
        try:
            stored = merged(OmegaConf.structured(Config), OmegaConf.load(path))
        except OmegaConfBaseException as err:
            raise ConfigError(
                f"resume={run_id}: its {CONFIG_ARTIFACT} does not fit this version of cdqn "
                f"({' '.join(str(err).split())})"
            ) from None
    stored.resume = None
    stored.tracking = tracking
    return stored


def population_runs(client: MlflowClient, run: Run) -> list[Run]:
    """The runs of ``run``'s population (tag ``population_id``) that can be continued:
    KILLED, RUNNING, or FAILED for a reason other than divergence; by seed."""
    pid = run.data.tags[Tag.POPULATION_ID]
    found = client.search_runs(
        [run.info.experiment_id], filter_string=f"tags.{Tag.POPULATION_ID} = '{pid}'"
    )
    keep = [
        r
        for r in found
        if r.info.status in ("KILLED", "RUNNING")
        or (
            r.info.status == "FAILED"
            and not is_divergence(r.info.status, r.data.tags.get(Tag.FAILURE_REASON))
        )
    ]
    return sorted(keep, key=lambda r: int(r.data.tags.get(Tag.SEED, "0")))
