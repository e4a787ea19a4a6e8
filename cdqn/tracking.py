"""MLflow recorder: one run per training job.

Episode-level numbers go to MLflow metrics (step = episode index), batched so that the
store is written every few seconds rather than once per episode; per-step series go into
compressed parquet artifacts (``signals/steps.parquet``, ``signals/fft.parquet``), never
one metric call per environment step.
"""

from __future__ import annotations

import json
import subprocess
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import mlflow
from mlflow.entities import Metric, Param, RunStatus, RunTag
from mlflow.tracking import MlflowClient

from cdqn.signals import SignalBuffer, amplitude_spectra
from cdqn.trainer import EpisodeStats

MAX_PARAM_LENGTH = 6000


def flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}} -> {"a.b": 1}``; lists stay values."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            out.update(flatten(value, f"{name}."))
        else:
            out[name] = value
    return out


def git_commit() -> str:
    """Commit of the cdqn source tree, ``+dirty`` if it has local changes, else ``unknown``."""
    here = Path(__file__).resolve().parent
    try:
        sha = subprocess.run(
            ["git", "-C", str(here), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
            timeout=10,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return sha + ("+dirty" if dirty else "")


class Recorder:
    """Writes one cdqn run into an MLflow store."""

    def __init__(self, client: MlflowClient, run_id: str, flush_seconds: float = 5.0) -> None:
        self.client = client
        self.run_id = run_id
        self.flush_seconds = flush_seconds
        self._pending: list[Metric] = []
        self._last_flush = time.monotonic()

    @classmethod
    def start(
        cls,
        uri: str,
        experiment: str,
        run_name: str,
        params: Mapping[str, Any],
        tags: Mapping[str, str],
    ) -> Recorder:
        """Create the experiment if needed, open a run, log params and tags."""
        mlflow.set_tracking_uri(uri)
        client = MlflowClient(uri)
        exp = client.get_experiment_by_name(experiment)
        exp_id = exp.experiment_id if exp is not None else client.create_experiment(experiment)
        run = client.create_run(exp_id, run_name=run_name, tags=dict(tags))
        rec = cls(client, run.info.run_id)
        items = [Param(k, _param_value(v)) for k, v in sorted(params.items())]
        for i in range(0, len(items), 100):
            client.log_batch(rec.run_id, params=items[i : i + 100])
        return rec

    def set_tags(self, tags: Mapping[str, str]) -> None:
        self.client.log_batch(self.run_id, tags=[RunTag(k, str(v)) for k, v in tags.items()])

    def log_episode(self, stats: EpisodeStats) -> None:
        ts = int(time.time() * 1000)
        self._pending.extend(Metric(k, v, ts, stats.episode) for k, v in stats.metrics().items())
        if time.monotonic() - self._last_flush > self.flush_seconds:
            self.flush()

    def flush(self) -> None:
        for i in range(0, len(self._pending), 1000):
            self.client.log_batch(self.run_id, metrics=self._pending[i : i + 1000])
        self._pending = []
        self._last_flush = time.monotonic()

    def log_dict(self, data: Mapping[str, Any], artifact_file: str) -> None:
        self.client.log_dict(self.run_id, dict(data), artifact_file)

    def log_dir(self, local_dir: Path, artifact_path: str) -> None:
        self.client.log_artifacts(self.run_id, str(local_dir), artifact_path)

    def log_signals(self, signals: SignalBuffer, dt: float) -> None:
        """``signals/steps.parquet`` and ``signals/fft.parquet`` (columns in cdqn.signals)."""
        steps = signals.to_frame()
        with tempfile.TemporaryDirectory() as tmp:
            steps.to_parquet(Path(tmp) / "steps.parquet", compression="zstd", index=False)
            amplitude_spectra(steps, dt).to_parquet(
                Path(tmp) / "fft.parquet", compression="zstd", index=False
            )
            self.client.log_artifacts(self.run_id, tmp, "signals")

    def finish(self, status: str = "FINISHED", failure_reason: str | None = None) -> None:
        """Flush metrics and close the run with ``status`` (FINISHED, FAILED or KILLED)."""
        self.flush()
        if failure_reason is not None:
            self.set_tags({"failure_reason": failure_reason[:5000]})
        self.client.set_terminated(
            self.run_id, status=RunStatus.to_string(RunStatus.from_string(status))
        )


def _param_value(value: Any) -> str:
    text = json.dumps(value) if isinstance(value, list | dict) else str(value)
    return text[:MAX_PARAM_LENGTH]
