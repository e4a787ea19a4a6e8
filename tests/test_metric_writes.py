"""A run's metrics written by :func:`cdqn.training.tracking.log_metrics` read back from a
real SQLite store exactly as the same metrics written by MLflow's ``log_batch``: every
history, the latest values, NaN and ±inf, values written twice (a resumed run), and a run
that is deleted refused alike."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
from mlflow.entities import Metric
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient

from cdqn.training.tracking import log_metrics

KEYS = ("episode_return", "episode_length", "loss_mean")


def _metrics(first: int, last: int) -> list[Metric]:
    """Episodes ``first..last-1`` of three keys, a NaN and both infinities among them, and
    one key whose newest value comes first in the list."""
    out = []
    for ep in range(first, last):
        values = {"episode_return": float(ep) * 1.5, "episode_length": float(ep % 7)}
        values["loss_mean"] = math.nan if ep % 5 == 0 else (math.inf if ep % 11 == 0 else -ep)
        if ep % 13 == 0:
            values["loss_mean"] = -math.inf
        out += [Metric(k, v, 1_000 + ep, ep) for k, v in values.items()]
    return sorted(out, key=lambda m: (m.key != "episode_length", -m.step))


def _history(client: MlflowClient, run_id: str) -> dict[str, list[tuple[int, int, str]]]:
    """Each key's history as (step, timestamp, repr of value), in step order."""
    return {
        k: sorted(
            (m.step, m.timestamp, repr(m.value)) for m in client.get_metric_history(run_id, k)
        )
        for k in KEYS
    }


@pytest.fixture
def client(tmp_path: Path) -> MlflowClient:
    return MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")


def _counted_log_batch(client: MlflowClient, monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The run ids of the client's ``log_batch`` calls from now on (it still writes)."""
    calls: list[str] = []
    original = client.log_batch

    def log_batch(run_id: str, **kwargs: Any) -> None:
        calls.append(run_id)
        original(run_id, **kwargs)

    monkeypatch.setattr(client, "log_batch", log_batch)
    return calls


def test_a_sql_store_holds_what_log_batch_would(
    client: MlflowClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    exp = client.create_experiment("writes")
    ours, theirs = (client.create_run(exp).info.run_id for _ in range(2))
    calls = _counted_log_batch(client, monkeypatch)
    for first, last in ((0, 40), (40, 41), (41, 300)):
        batch = _metrics(first, last)
        log_metrics(client, ours, batch)
        client.log_batch(theirs, metrics=batch)
    assert ours not in calls  # one session of its own on a SQL store
    assert _history(client, ours) == _history(client, theirs)
    assert len(_history(client, ours)["loss_mean"]) == 300
    assert client.get_run(ours).data.metrics == client.get_run(theirs).data.metrics
    assert client.get_run(ours).data.metrics["episode_return"] == 299 * 1.5


def test_values_written_again_are_kept_once(
    client: MlflowClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    run_id = client.create_run(client.create_experiment("again")).info.run_id
    log_metrics(client, run_id, _metrics(0, 50))
    before = _history(client, run_id)
    calls = _counted_log_batch(client, monkeypatch)
    log_metrics(client, run_id, _metrics(30, 60))  # 30..49 already stored
    assert calls == [run_id]  # the insert failed as a whole; log_batch skips what is stored
    after = _history(client, run_id)
    assert all(len(after[k]) == 60 for k in KEYS)
    assert {k: v[:50] for k, v in after.items()} == before
    assert client.get_run(run_id).data.metrics["episode_return"] == 59 * 1.5


def test_a_deleted_run_is_refused_as_log_batch_refuses_it(client: MlflowClient) -> None:
    run_id = client.create_run(client.create_experiment("deleted")).info.run_id
    client.delete_run(run_id)
    with pytest.raises(MlflowException) as ours:
        log_metrics(client, run_id, _metrics(0, 10))
    with pytest.raises(MlflowException) as theirs:
        client.log_batch(run_id, metrics=_metrics(0, 10))
    assert str(ours.value) == str(theirs.value)
    client.restore_run(run_id)
    assert _history(client, run_id) == {k: [] for k in KEYS}
