"""Checkpoints store a mostly-zero array as its nonzero entries and read it back bit for bit;
a Double DQN run on a one-hot environment (Taxi-v4) checkpoints its replay that way and
resumes to the run it would have been."""

from __future__ import annotations

import signal
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient

from cdqn.training.checkpoint import ROOT, SLOTS, _decode, _encode
from cdqn.training.run import run
from tests.conftest import compose_config
from tests.helpers import assert_same_run, signals_after_checkpoint


def _round_trip(obj: object) -> object:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "state.pt"
        torch.save(_encode(obj), path)
        return _decode(torch.load(path, weights_only=True))


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int64, np.uint8, np.bool_])
def test_a_sparse_array_round_trips_bit_for_bit(dtype: type) -> None:
    """A one-hot table with a few −0.0, NaN and ±inf entries among its ones comes back with
    the same bits, shape and dtype, and is stored as its nonzero entries only."""
    rng = np.random.default_rng(0)
    a = np.zeros((300, 500), dtype)
    a[np.arange(300), rng.integers(0, 500, 300)] = 1
    if np.issubdtype(dtype, np.floating):
        a[0, :4] = [-0.0, np.nan, np.inf, -np.inf]
    encoded = _encode(a)
    assert set(encoded) == {"__sparse__", "values", "shape"}
    assert encoded["values"].numel() <= 304
    back = _round_trip({"obs": a})["obs"]
    assert back.dtype == a.dtype and back.shape == a.shape
    assert back.tobytes() == a.tobytes()


def test_dense_and_small_arrays_are_stored_as_they_are() -> None:
    """An array with many nonzero entries, or too few entries to be worth it, stays dense."""
    dense = np.random.default_rng(1).normal(size=(100, 100))
    small = np.zeros(10)
    assert set(_encode(dense)) == {"__ndarray__"} and set(_encode(small)) == {"__ndarray__"}
    back = _round_trip([dense, small])
    assert back[0].tobytes() == dense.tobytes() and back[1].tobytes() == small.tobytes()


TAXI = [
    "env.id=Taxi-v4",
    "env.max_episode_steps=40",
    "network=small",
    "controller=ddqn",
    "controller.buffer_size=5000",
    "controller.learning_starts=50",
    "controller.batch_size=8",
    "train.episodes=12",
    "train.checkpoint_every=3",
    "train.progress=false",
    "seed=3",
]


@pytest.fixture
def signal_after(monkeypatch: pytest.MonkeyPatch) -> Iterator[Callable[..., None]]:
    yield from signals_after_checkpoint(monkeypatch)


def _arrays(obj: object, path: str = "") -> Iterator[tuple[str, tuple]]:
    """``(path, (rows, shape, form, numbers stored))`` of every array in a raw ``state.pt``."""
    if isinstance(obj, dict):
        form = next((k for k in ("__sparse__", "__ndarray__") if k in obj), None)
        if form is not None:
            shape = tuple(obj["shape"]) if form == "__sparse__" else tuple(obj[form].shape)
            numbers = obj["values"].numel() if form == "__sparse__" else obj[form].numel()
            yield path, (shape[0] if shape else 0, shape, form, numbers)
            return
        for key, value in obj.items():
            yield from _arrays(value, f"{path}/{key}")
    elif isinstance(obj, list | tuple):
        for i, value in enumerate(obj):
            yield from _arrays(value, f"{path}[{i}]")


def test_one_hot_replay_checkpoints_small_and_resumes_equal(
    tmp_path: Path, signal_after: Callable[..., None]
) -> None:
    """Taxi-v4's observation goes in one-hot (500 inputs): the replay's observations are
    stored as their ones, so a checkpoint holds far less than the dense 2 × 500 × 8 bytes
    per transition; the run stopped after its first checkpoint resumes to the returns and
    signals of an uninterrupted run."""
    store = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = MlflowClient(store)
    base = [*TAXI, f"tracking.uri={store}"]
    signal_after(2, signal.SIGTERM)
    killed = run(compose_config(base), progress=False)
    assert killed.status == "KILLED" and 6 <= len(killed.returns) < 12

    with tempfile.TemporaryDirectory() as tmp:
        local = client.download_artifacts(killed.run_id, f"{ROOT}/slot-{SLOTS[0]}/state.pt", tmp)
        stored = dict(_arrays(torch.load(local, weights_only=True)))
    one_hot = {path: form for path, form in stored.items() if form[1][-1:] == (500,)}
    transitions = {form[1][0] for form in one_hot.values()}
    assert len(one_hot) >= 2 and min(transitions) > 100, one_hot  # obs and next_obs at least
    for path, (rows, shape, kind, numbers) in one_hot.items():
        assert kind == "__sparse__" and numbers <= rows, (path, shape, kind, numbers)

    resumed = run(compose_config([f"resume={killed.run_id}", f"tracking.uri={store}"]), False)
    assert (resumed.run_id, resumed.status) == (killed.run_id, "FINISHED")
    reference = run(compose_config([*base, "train.checkpoint_every=0"]), progress=False)
    assert_same_run(client, killed.run_id, reference.run_id)
