"""Checkpoints: what a run needs to continue bit for bit from an episode boundary.

A checkpoint is stored as artifacts of the run itself, so any machine that reaches the
tracking store can resume it (``python -m cdqn.train resume=<run_id>``)::

    checkpoint/slot-a/state.pt                  two slots, written in turn: a checkpoint cut
    checkpoint/slot-b/state.pt                  short by a hard kill never spoils the other
    checkpoint/signals/rows-<start>-<stop>.npy  per-step signals, each chunk written once

``state.pt`` (``torch.save``, read back with ``weights_only=True``) holds the episode counter,
the returns so far, the total step count, the number of signal rows, the agent's
``state_dict()`` (network, exploration ε, controller state x_e and x_c; for Double DQN the
target network, step counter and replay buffer) and the RNG states: the run's NumPy
generator, torch's generator and the environment's ``np_random``.  Plain gradient descent
(:func:`cdqn.network.gradient_step`) keeps no state of its own.

A large array that is mostly zeros, bit for bit, is stored as the positions and values of
its other entries (:func:`_encode`): Double DQN's replay of one-hot observations (Taxi-v4:
500 inputs, one of them 1) takes 2 of every 500 numbers.  Decoding gives the same bits.
"""

from __future__ import annotations

import logging
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from mlflow.tracking import MlflowClient

from cdqn.agents.base import Agent
from cdqn.records import Artifact, folder
from cdqn.training.loop import TrainState
from cdqn.training.signals import COLUMNS, SignalBuffer
from cdqn.training.tracking import retrying

log = logging.getLogger("cdqn")

FORMAT = 2
READABLE = (1, 2)
"""Formats :meth:`CheckpointStore.load` and :func:`load_local` read (1: no sparse arrays)."""
SPARSE_MIN = 4096
"""Arrays of at least this many entries are checked for sparsity (:func:`_encode`)."""
SPARSE_SHARE = 0.125
"""At most this share of entries with a nonzero bit pattern: stored sparse."""
ROOT = folder(Artifact.CHECKPOINT)
SLOTS = ("a", "b")
_CHUNK = re.compile(r"rows-(\d+)-(\d+)\.npy$")


@dataclass
class Checkpoint:
    """The state of a run at an episode boundary (see the module docstring)."""

    episode: int
    """Episodes completed; training continues with this episode index."""
    returns: list[float]
    total_steps: int
    signal_rows: int
    """Rows of the signal table at the boundary (0 when signals are not stored)."""
    agent: dict[str, Any]
    numpy_rng: dict[str, Any]
    torch_rng: torch.Tensor
    env_rng: dict[str, Any]
    signals: np.ndarray | None = None
    """The signal rows, filled in by :meth:`CheckpointStore.load`."""


def capture(
    agent: Agent,
    env: gym.Env,
    state: TrainState,
    rng: np.random.Generator,
    signal_rows: int,
) -> Checkpoint:
    """Snapshot of a run at an episode boundary (between two episodes, never inside one)."""
    return Checkpoint(
        episode=state.episode,
        returns=[float(r) for r in state.returns],
        total_steps=state.total_steps,
        signal_rows=signal_rows,
        agent=agent.state_dict(),
        numpy_rng=dict(rng.bit_generator.state),
        torch_rng=torch.get_rng_state(),
        env_rng=dict(env.unwrapped.np_random.bit_generator.state),
    )


def restore(
    ckpt: Checkpoint,
    agent: Agent,
    env: gym.Env,
    state: TrainState,
    rng: np.random.Generator,
    signals: SignalBuffer,
) -> None:
    """Put a freshly built run (same config, same seed) into the state of ``ckpt``."""
    agent.load_state_dict(ckpt.agent)
    rng.bit_generator.state = ckpt.numpy_rng
    torch.set_rng_state(ckpt.torch_rng)
    bit_generator = getattr(np.random, ckpt.env_rng["bit_generator"])()
    bit_generator.state = ckpt.env_rng
    env.unwrapped.np_random = np.random.Generator(bit_generator)
    state.episode = ckpt.episode
    state.returns = list(ckpt.returns)
    state.total_steps = ckpt.total_steps
    if ckpt.signals is not None:
        signals.load(ckpt.signals)


class CheckpointStore:
    """Writes and reads the checkpoints of one MLflow run."""

    def __init__(
        self,
        client: MlflowClient,
        run_id: str,
        store_signals: bool = True,
        kind: type = Checkpoint,
    ) -> None:
        self.client = client
        self.run_id = run_id
        self.store_signals = store_signals
        self.kind = kind
        """The checkpoint dataclass stored (:class:`Checkpoint`; a population member's:
        :class:`cdqn.training.population_checkpoint.MemberCheckpoint`, ordered by ``sequence``)."""
        self.retry_s = 0.0
        """Seconds a write is retried while the store does not answer."""
        self._next_slot = 0
        self._rows_saved = 0

    def save(self, ckpt: Any, signals: SignalBuffer, announce: bool = True) -> None:
        """Write the signal rows not yet stored, then the state into the older slot
        (``announce``: log it; a population logs one line for all its members)."""
        with tempfile.TemporaryDirectory() as tmp:
            if self.store_signals and ckpt.signal_rows > self._rows_saved:
                start, stop = self._rows_saved, ckpt.signal_rows
                chunk = Path(tmp) / f"rows-{start:010d}-{stop:010d}.npy"
                np.save(chunk, signals.rows(start, stop))
                self._log(chunk, f"{ROOT}/signals")
                self._rows_saved = stop
            path = Path(tmp) / "state.pt"
            torch.save(_encode(_fields(ckpt)), path)
            slot = SLOTS[self._next_slot]
            self._log(path, f"{ROOT}/slot-{slot}")
        self._next_slot = 1 - self._next_slot
        if announce:
            log.debug("checkpoint at episode %d (slot %s)", ckpt.episode, slot)

    def _log(self, path: Path, artifact_path: str) -> None:
        """One artifact, retried while the store does not answer (``retry_s``)."""
        uri = str(getattr(self.client, "_tracking_client", self.client).tracking_uri)
        retrying(
            lambda: self.client.log_artifact(self.run_id, str(path), artifact_path),
            f"checkpoint {artifact_path} of run {self.run_id}",
            self.retry_s,
            uri,
        )

    def load(self) -> Checkpoint | None:
        """The latest complete checkpoint of the run, or None when it has none."""
        for ckpt, slot in self.candidates():
            if self.complete(ckpt, slot):
                return ckpt
        return None

    def candidates(self) -> list[tuple[Any, int]]:
        """The readable checkpoints in the slots (without signal rows) and their slot
        indices, newest first."""
        found: list[tuple[Any, int]] = []
        with tempfile.TemporaryDirectory() as tmp:
            for i, slot in enumerate(SLOTS):
                try:
                    local = self.client.download_artifacts(
                        self.run_id, f"{ROOT}/slot-{slot}/state.pt", tmp
                    )
                    data = _decode(torch.load(local, weights_only=True))
                    if data.get("format") not in READABLE:
                        raise ValueError(f"format {data.get('format')}, expected {READABLE}")
                    del data["format"]
                    data.pop("optimizer", None)  # an SGD state (empty) in older checkpoints
                    found.append((self.kind(**data), i))
                except Exception as err:  # missing slot or a write cut short by a hard kill
                    log.debug("checkpoint slot %s unusable: %s", slot, err)
        return sorted(found, key=lambda c: -getattr(c[0], "sequence", c[0].episode))

    def complete(self, ckpt: Any, slot: int) -> bool:
        """Fill in the signal rows of ``ckpt`` (read from ``slot``) and continue writing
        after it; False when its rows cannot be read."""
        with tempfile.TemporaryDirectory() as tmp:
            try:
                if self.store_signals and ckpt.signal_rows > 0:
                    ckpt.signals = self._load_signals(ckpt.signal_rows, Path(tmp))
                else:
                    ckpt.signal_rows = 0
            except Exception as err:
                log.warning("checkpoint at episode %d unusable: %s", ckpt.episode, err)
                return False
        self._next_slot = 1 - slot
        self._rows_saved = ckpt.signal_rows
        return True

    def _load_signals(self, rows: int, tmp: Path) -> np.ndarray:
        """Rows ``[0, rows)`` from the chunks (a chain of chunks ending exactly at ``rows``)."""
        chunks: dict[int, list[tuple[int, str]]] = {}
        for info in self.client.list_artifacts(self.run_id, f"{ROOT}/signals"):
            m = _CHUNK.search(info.path)
            if m:
                chunks.setdefault(int(m[1]), []).append((int(m[2]), info.path))
        parts, pos = [], 0
        while pos < rows:
            options = [c for c in chunks.get(pos, []) if c[0] <= rows]
            if not options:
                raise ValueError(f"signal rows from {pos} missing in {ROOT}/signals")
            stop, path = max(options)
            part = np.load(self.client.download_artifacts(self.run_id, path, str(tmp)))
            if part.shape != (stop - pos, len(COLUMNS)):
                raise ValueError(f"{path}: shape {part.shape}, expected {stop - pos} rows")
            parts.append(part)
            pos = stop
        return np.concatenate(parts)


LOCAL_FILE = "state.pt"


def local_path(folder: str | Path, run_id: str) -> Path:
    """Where the local checkpoint of ``run_id`` lives: ``<folder>/<run_id>/state.pt``."""
    return Path(folder).resolve() / run_id / LOCAL_FILE


def save_local(
    folder: str | Path,
    run_id: str,
    ckpt: Any,
    signals: SignalBuffer,
    pending: list[tuple[str, float, int, int]],
    name: str = LOCAL_FILE,
) -> Path:
    """Write ``ckpt`` (a :class:`Checkpoint` or a population member's checkpoint) with all
    its signal rows and the metrics not yet in the store (``pending``) to
    :func:`local_path` (file ``name`` there), for a run whose tracking store went away."""
    path = local_path(folder, run_id).with_name(name)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = _fields(ckpt)
    data["local_signals"] = signals.rows(0, ckpt.signal_rows).copy()
    data["pending"] = [list(p) for p in pending]
    tmp = path.with_suffix(".tmp")
    torch.save(_encode(data), tmp)
    tmp.replace(path)  # a kill while writing leaves the previous file intact
    return path


def load_local(
    folder: str | Path, run_id: str, kind: type = Checkpoint, name: str = LOCAL_FILE
) -> tuple[Any, list[tuple[str, float, int, int]]] | None:
    """The local checkpoint of ``run_id`` (a ``kind``) and its pending metrics, or None."""
    path = local_path(folder, run_id).with_name(name)
    if not path.is_file():
        return None
    data = _decode(torch.load(path, weights_only=True))
    if data.pop("format", None) not in READABLE:
        log.warning("%s: not a checkpoint of this version of cdqn; ignored", path)
        return None
    rows = data.pop("local_signals")
    pending = [(str(k), float(v), int(ts), int(st)) for k, v, ts, st in data.pop("pending")]
    ckpt = kind(**data)
    ckpt.signals = rows if ckpt.signal_rows > 0 else None
    return ckpt, pending


def _fields(ckpt: Any) -> dict[str, Any]:
    data = {k: v for k, v in vars(ckpt).items() if k != "signals"}
    data["format"] = FORMAT
    return data


def _encode(obj: Any) -> Any:
    """NumPy arrays and scalars -> torch tensors and Python numbers (``weights_only`` safe);
    a sparse array as :func:`_sparse` gives it."""
    if isinstance(obj, np.ndarray):
        return _sparse(obj) or {"__ndarray__": torch.from_numpy(np.array(obj))}
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, dict):
        return {k: _encode(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(_encode(v) for v in obj)
    return obj


def _sparse(a: np.ndarray) -> dict[str, Any] | None:
    """``a`` as the flat positions and values of its entries whose bit pattern is not zero,
    when it has at least :data:`SPARSE_MIN` entries and at most :data:`SPARSE_SHARE` of them
    are such (module docstring); None otherwise.  Positions are found on the bits, so a
    −0.0 is kept as a value and the decoded array is bit-identical."""
    if a.size < SPARSE_MIN or a.dtype.kind not in "fiub" or a.dtype.itemsize not in (1, 2, 4, 8):
        return None
    flat = np.ascontiguousarray(a).reshape(-1)
    bits = flat.view(f"u{a.dtype.itemsize}")
    if np.count_nonzero(bits) > SPARSE_SHARE * a.size:  # dense: no index array built
        return None
    where = np.flatnonzero(bits)
    return {
        "__sparse__": torch.from_numpy(where),
        "values": torch.from_numpy(flat[where].copy()),
        "shape": list(a.shape),
    }


def _decode(obj: Any) -> Any:
    if isinstance(obj, dict):
        if set(obj) == {"__ndarray__"}:
            return obj["__ndarray__"].numpy()
        if set(obj) == {"__sparse__", "values", "shape"}:
            values = obj["values"].numpy()
            out = np.zeros(int(np.prod(obj["shape"])), values.dtype)
            out[obj["__sparse__"].numpy()] = values
            return out.reshape(obj["shape"])
        return {k: _decode(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(_decode(v) for v in obj)
    return obj
