"""MLflow recorder: one run per training job.

Episode-level numbers go to MLflow metrics (step = episode index), batched so that the
store is written every few seconds rather than once per episode; per-step series go into
compressed parquet artifacts (``signals/steps.parquet``, ``signals/fft.parquet``), never
one metric call per environment step.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import math
import operator
import os
import sqlite3
import subprocess
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar
from urllib.parse import urlsplit

import mlflow
from mlflow.entities import Metric, Param, RunStatus, RunTag
from mlflow.exceptions import MlflowException
from mlflow.store.artifact.artifact_repository_registry import get_artifact_repository
from mlflow.tracking import MlflowClient

from cdqn.config import EXPERIMENT_TAGS, ConfigError, sqlite_file
from cdqn.control.box import Box
from cdqn.records import Artifact, Tag, folder
from cdqn.records import Metric as M
from cdqn.training.divergence import is_divergence
from cdqn.training.loop import EpisodeStats
from cdqn.training.signals import SeriesPoint, SignalBuffer, amplitude_spectra, signal_series

log = logging.getLogger("cdqn")
T = TypeVar("T")

MAX_PARAM_LENGTH = 6000
CONFIG_ARTIFACT = Artifact.CONFIG
"""The run's resolved configuration (without the ``hydra`` section)."""


class TrackingError(ConfigError):
    """The tracking store named by ``tracking.uri`` cannot be used (unreachable, not an
    MLflow server, not writable, no such run)."""


class TrackingOutage(RuntimeError):
    """The tracking store stopped answering during a run for longer than
    ``tracking.retry_s``."""

    def __init__(self, uri: str, what: str, seconds: float, err: BaseException) -> None:
        super().__init__(
            f"the tracking server {uri} did not answer for {seconds:.0f} s "
            f"(tracking.retry_s) while writing {what}: {type(err).__name__}: "
            f"{' '.join(str(err).split())[:300]}"
        )
        self.uri = uri


_TRANSIENT_TEXT = ("API request", "Max retries", "Connection", "connection", "timed out",
                   "Temporarily", "503", "502", "504")  # fmt: skip


def transient(err: BaseException) -> bool:
    """Whether ``err`` is a store that does not answer (worth retrying), not a refusal."""
    if isinstance(err, OSError | ConnectionError | TimeoutError):
        return True
    if isinstance(err, MlflowException):
        code = str(getattr(err, "error_code", ""))
        return code in ("TEMPORARILY_UNAVAILABLE", "INTERNAL_ERROR") or any(
            t in str(err) for t in _TRANSIENT_TEXT
        )
    return type(err).__module__.startswith(("requests", "urllib3"))


def retrying(
    call: Callable[[], T], what: str, retry_s: float, uri: str, first_delay: float = 0.5
) -> T:
    """``call()``, retried with exponential backoff (``first_delay`` doubling up to 10 s)
    while the store does not answer, for up to ``retry_s`` seconds; then
    :class:`TrackingOutage`.  Other errors are raised at once."""
    t0, delay, warned = time.monotonic(), first_delay, False
    while True:
        try:
            result = call()
        except Exception as err:
            if not transient(err):
                raise
            waited = time.monotonic() - t0
            if waited >= retry_s:
                raise TrackingOutage(uri, what, waited, err) from err
            if not warned:
                log.warning("tracking server %s not answering (%s); retrying %s for up to %g s",
                            uri, type(err).__name__, what, retry_s)  # fmt: skip
                warned = True
            time.sleep(min(delay, max(retry_s - waited, 0.0)))
            delay = min(delay * 2, 10.0)
            continue
        if warned:
            log.warning("tracking server %s answers again (%s written after %.1f s)",
                        uri, what, time.monotonic() - t0)  # fmt: skip
        return result


def fail_fast_http(timeout: float) -> None:
    """Let MLflow's HTTP client give up on an unreachable server at once (its own retries
    take minutes); :func:`retrying` does the waiting, for ``tracking.retry_s``."""
    os.environ.setdefault("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")
    os.environ.setdefault("MLFLOW_HTTP_REQUEST_TIMEOUT", str(max(int(timeout), 1)))


def check_tracking(uri: str, timeout: float = 10.0) -> None:
    """Fail fast, before anything expensive is built, when ``uri`` cannot take a run.

    ``http(s)://``: the server must answer ``GET /health`` and the experiments API within
    ``timeout`` seconds (checked directly, without MLflow's minutes-long retries).
    ``sqlite:///`` and local paths: the folder must exist (or be creatable) and be writable.
    """
    scheme = urlsplit(uri).scheme
    if scheme in ("http", "https"):
        _check_server(uri, timeout)
    elif (path := sqlite_file(uri)) is not None:
        if str(path) not in ("", ":memory:"):
            _check_folder(path.parent, uri)
            _check_database(path, uri)
    elif scheme in ("", "file"):
        _check_folder(Path(urlsplit(uri).path if scheme == "file" else uri), uri)


def check_readable(uri: str, timeout: float = 10.0, name: str = "--tracking-uri") -> None:
    """Fail fast when ``uri`` is no store to read runs from: a server that does not answer
    as MLflow, a ``sqlite:///`` file that does not exist or is not an SQLite database
    (:class:`TrackingError` naming the option ``name``)."""
    scheme = urlsplit(uri).scheme
    if scheme in ("http", "https"):
        _check_server(uri, timeout, name)
    elif (path := sqlite_file(uri)) is not None:
        if str(path) in ("", ":memory:"):
            return
        if not path.exists():
            raise TrackingError(f"{name}={uri!r}: no such file {path}")
        _check_database(path, uri, write=False, name=name)


def _check_server(uri: str, timeout: float, name: str = "tracking.uri") -> None:
    base = uri.rstrip("/")
    hint = (
        "start one with `mlflow server --backend-store-uri sqlite:///mlflow.db --serve-artifacts "
        f"--host {urlsplit(uri).hostname} --port {urlsplit(uri).port or 5000}`, or choose another "
        f"{name}" + (" (tracking=local for an embedded store)" if name == "tracking.uri" else "")
    )
    t0 = time.monotonic()
    try:
        with urllib.request.urlopen(f"{base}/health", timeout=timeout) as resp:
            body = resp.read(100).decode("utf-8", "replace").strip()
    except urllib.error.HTTPError as err:
        raise TrackingError(
            f"{name}={uri!r}: not an MLflow tracking server (GET /health answered "
            f"HTTP {err.code}); {hint}"
        ) from None
    except (urllib.error.URLError, OSError) as err:
        reason = getattr(err, "reason", err)
        raise TrackingError(
            f"{name}={uri!r}: no MLflow tracking server reachable ({reason}, after "
            f"{time.monotonic() - t0:.1f} s, tracking.timeout={timeout:g}); {hint}"
        ) from None
    if body != "OK":
        raise TrackingError(
            f"{name}={uri!r}: not an MLflow tracking server (GET /health answered "
            f"{body[:40]!r}, expected 'OK'); {hint}"
        )
    api = f"{base}/api/2.0/mlflow/experiments/search?max_results=1"
    try:
        with urllib.request.urlopen(api, timeout=timeout) as resp:
            json.loads(resp.read())
    except (urllib.error.URLError, OSError, ValueError) as err:
        raise TrackingError(
            f"{name}={uri!r}: the server answers /health but not the MLflow REST API "
            f"({err}); is it an MLflow tracking server (not --artifacts-only)?"
        ) from None


def _check_folder(folder: Path, uri: str) -> None:
    """The folder exists (or is created) and takes a new file: tried, as permissions alone
    do not tell (a read-only file system, ``/sys``, refuses root too)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise TrackingError(
            f"tracking.uri={uri!r}: cannot create the folder {folder} ({err.strerror or err}); "
            "choose a folder you can write to"
        ) from None
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as err:
        raise TrackingError(
            f"tracking.uri={uri!r}: cannot write to the folder {folder} ({err.strerror or err}); "
            "choose a folder you can write to"
        ) from None


SQLITE_HEADER = b"SQLite format 3\x00"
"""The first 16 bytes of every SQLite database file."""


def _check_database(path: Path, uri: str, write: bool = True, name: str = "tracking.uri") -> None:
    """An existing ``path`` must be a SQLite database (an empty file is one), writable if
    ``write``."""
    if not path.exists():
        return
    hint = "choose another file (a new one is created) or move this one away"
    if not path.is_file():
        raise TrackingError(f"{name}={uri!r}: {path} is not a file; {hint}")
    try:
        with path.open("r+b" if write else "rb") as handle:
            head = handle.read(len(SQLITE_HEADER))
    except OSError as err:
        raise TrackingError(f"{name}={uri!r}: cannot open {path} ({err.strerror or err})") from None
    if head and head != SQLITE_HEADER:
        raise TrackingError(f"{name}={uri!r}: {path} is not an SQLite database; {hint}")
    tables = _tables(path) if head else set()
    if tables and not tables >= MLFLOW_TABLES:
        shown = ", ".join(sorted(tables)[:4]) + (", ..." if len(tables) > 4 else "")
        raise TrackingError(
            f"{name}={uri!r}: {path} is another program's SQLite database (tables {shown}), "
            f"not an MLflow store; {hint}"
        )


MLFLOW_TABLES = frozenset({"experiments", "runs"})
"""Tables every MLflow SQLite store has; a database with tables but not these (an Optuna
study's ``optuna.db``, say) is not one, and MLflow would add its own tables to it."""


def _tables(path: Path) -> set[str]:
    """The table names of the SQLite database at ``path``, read-only; empty when it cannot be
    read now (a writer holds it: the store's own checks then report what is wrong)."""
    try:
        with contextlib.closing(
            sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5.0)
        ) as db:
            rows = db.execute("SELECT name FROM sqlite_master WHERE type = 'table'").fetchall()
    except sqlite3.Error:
        return set()
    return {str(r[0]) for r in rows}


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


def closes_for_good(status: str, reason: str | None) -> bool:
    """Whether a run closed with ``status`` and ``reason`` is never continued (FINISHED, or
    FAILED by divergence), so that its signal series are logged once, for the whole run."""
    return status == "FINISHED" or is_divergence(status, reason)


def delete_artifacts(client: MlflowClient, run_id: str, artifact_path: str) -> None:
    """Remove run ``run_id``'s artifacts under ``artifact_path`` (e.g. its resume
    checkpoints); a store that cannot delete keeps them, with a warning."""
    run = client.get_run(run_id)
    try:
        repo = get_artifact_repository(run.info.artifact_uri)
        if any(True for _ in client.list_artifacts(run_id, artifact_path)):
            repo.delete_artifacts(artifact_path)
    except Exception as err:  # stores without delete (e.g. some proxies): keep them
        log.warning("run %s: could not delete its %s/ artifacts (%s: %s)", run_id,
                    artifact_path, type(err).__name__, err)  # fmt: skip


class Recorder:
    """Writes one cdqn run into an MLflow store."""

    def __init__(self, client: MlflowClient, run_id: str, flush_seconds: float = 5.0) -> None:
        self.client = client
        self.run_id = run_id
        self.flush_seconds = flush_seconds
        self.retry_s = 0.0
        """Seconds a write is retried while the store does not answer (``tracking.retry_s``;
        0: not retried)."""
        self._pending: list[Metric] = []
        self._last_flush = time.monotonic()

    @property
    def uri(self) -> str:
        """The tracking URI the run is written to."""
        return str(self.client._tracking_client.tracking_uri)

    def _retry(self, call: Callable[[], T], what: str) -> T:
        return retrying(call, f"{what} of run {self.run_id}", self.retry_s, self.uri)

    @property
    def pending(self) -> list[tuple[str, float, int, int]]:
        """Metrics not yet written: ``(key, value, timestamp, step)``."""
        return [(m.key, m.value, m.timestamp, m.step) for m in self._pending]

    def add_pending(self, items: list[tuple[str, float, int, int]]) -> None:
        """Queue metrics (from :attr:`pending` of an earlier process) for the next flush."""
        self._pending.extend(Metric(k, float(v), int(ts), int(st)) for k, v, ts, st in items)

    @classmethod
    def start(
        cls,
        uri: str,
        experiment: str,
        run_name: str,
        params: Mapping[str, Any],
        tags: Mapping[str, str],
        config: Mapping[str, Any] | None = None,
    ) -> Recorder:
        """Create the experiment if needed, open a run, log params, tags and ``config`` (the
        resolved configuration, as artifact ``config.yaml``, which resume and evaluation read).

        Raises :class:`TrackingError` when the store refuses (e.g. an experiment of that name
        is deleted, the artifact location is not writable).
        """
        mlflow.set_tracking_uri(uri)
        client = MlflowClient(uri)
        try:
            exp = client.get_experiment_by_name(experiment)
            if exp is not None and exp.lifecycle_stage != "active":
                raise TrackingError(
                    f"tracking.experiment={experiment!r} is deleted in {uri}; restore it "
                    "(mlflow experiments restore) or choose another name"
                )
            exp_id = (
                exp.experiment_id
                if exp is not None
                else client.create_experiment(experiment, tags=EXPERIMENT_TAGS)
            )
            run = client.create_run(exp_id, run_name=run_name, tags=dict(tags))
        except MlflowException as err:
            raise TrackingError(f"tracking.uri={uri!r}: cannot open a run ({err})") from None
        rec = cls(client, run.info.run_id)
        items = [Param(k, _param_value(v)) for k, v in sorted(params.items())]
        for i in range(0, len(items), 100):
            client.log_batch(rec.run_id, params=items[i : i + 100])
        if config is not None:
            try:
                client.log_dict(rec.run_id, dict(config), CONFIG_ARTIFACT)
            except Exception as err:  # the artifact store: permissions, proxy, disk
                client.set_terminated(rec.run_id, status="FAILED")
                raise TrackingError(
                    f"tracking.uri={uri!r}: cannot write artifacts of run {rec.run_id} to "
                    f"{run.info.artifact_uri} ({type(err).__name__}: {err})"
                ) from None
        return rec

    @classmethod
    def attach(cls, uri: str, run_id: str) -> Recorder:
        """Reopen the existing run ``run_id`` (status RUNNING again) to continue it."""
        mlflow.set_tracking_uri(uri)
        client = MlflowClient(uri)
        client.update_run(run_id, status="RUNNING")
        return cls(client, run_id)

    def logged_episodes(self) -> set[int]:
        """Episodes whose metrics are already in the store (a resumed run skips them)."""
        return {m.step for m in self.client.get_metric_history(self.run_id, M.EPISODE_RETURN)}

    def set_tags(self, tags: Mapping[str, str]) -> None:
        batch = [RunTag(k, str(v)) for k, v in tags.items()]
        self._retry(lambda: self.client.log_batch(self.run_id, tags=batch), "tags")

    def log_episode(self, stats: EpisodeStats) -> None:
        ts = int(time.time() * 1000)
        self._pending.extend(Metric(k, v, ts, stats.episode) for k, v in stats.metrics().items())
        if time.monotonic() - self._last_flush > self.flush_seconds:
            self.flush()

    def flush(self) -> None:
        """Write the pending metrics (a batch written is dropped from :attr:`pending`)."""
        while self._pending:
            batch = self._pending[:METRICS_PER_WRITE]
            self._retry(functools.partial(log_metrics, self.client, self.run_id, batch),
                        "metrics")  # fmt: skip
            del self._pending[: len(batch)]
        self._last_flush = time.monotonic()

    def log_dict(self, data: Mapping[str, Any], artifact_file: str) -> None:
        self._retry(
            lambda: self.client.log_dict(self.run_id, dict(data), artifact_file), artifact_file
        )

    def log_dir(self, local_dir: Path, artifact_path: str) -> None:
        self._retry(
            lambda: self.client.log_artifacts(self.run_id, str(local_dir), artifact_path),
            f"artifacts {artifact_path}/",
        )

    def log_signals(
        self, signals: SignalBuffer, dt: float, box: Box | None = None, series: bool = True
    ) -> None:
        """``signals/steps.parquet`` and ``signals/fft.parquet`` (columns in
        :mod:`cdqn.training.signals`); with ``series``, also the downsampled signals and
        spectra as metric series (:func:`cdqn.training.signals.signal_series`, ``box`` the
        design's NTK box) in one batch, which MLflow draws on the run's page."""
        steps = signals.to_frame()
        spectra = amplitude_spectra(steps, dt)
        with tempfile.TemporaryDirectory() as tmp:
            for frame, path in ((steps, Artifact.STEPS), (spectra, Artifact.FFT)):
                frame.to_parquet(Path(tmp) / Path(path).name, compression="zstd", index=False)
            where = folder(Artifact.SIGNALS)
            self._retry(lambda: self.client.log_artifacts(self.run_id, tmp, where), where)
        if series:
            self.log_series(signal_series(signals.rows(0), spectra, box))

    def log_series(self, points: list[SeriesPoint]) -> None:
        """Write ``points`` (at most 1000, one ``log_batch``) as metrics of the run."""
        ts = int(time.time() * 1000)
        batch = [Metric(p.key, p.value, ts, p.step) for p in points]
        if batch:
            self._retry(lambda: self.client.log_batch(self.run_id, metrics=batch), "series")

    def delete_artifacts(self, artifact_path: str) -> None:
        """Remove the run's artifacts under ``artifact_path`` (:func:`delete_artifacts`)."""
        delete_artifacts(self.client, self.run_id, artifact_path)

    def finish(
        self,
        status: str = "FINISHED",
        failure_reason: str | None = None,
        final_score: float | None = None,
    ) -> None:
        """Flush metrics and close the run with ``status`` (FINISHED, FAILED or KILLED);
        ``final_score`` (mean return of the last 100 episodes) is logged as metric
        ``final_score``."""
        if final_score is not None and math.isfinite(final_score):
            self._pending.append(
                Metric(M.FINAL_SCORE, float(final_score), int(time.time() * 1000), 0)
            )
        self.flush()
        if failure_reason is not None:
            self.set_tags({Tag.FAILURE_REASON: failure_reason[:5000]})
        state = RunStatus.to_string(RunStatus.from_string(status))
        self._retry(lambda: self.client.set_terminated(self.run_id, status=state), "status")


METRICS_PER_WRITE = 5000
"""Metric values written per call of :func:`log_metrics` by :meth:`Recorder.flush`."""


def log_metrics(client: MlflowClient, run_id: str, metrics: Sequence[Metric]) -> None:
    """Write ``metrics`` to run ``run_id``: what ``client.log_batch(run_id, metrics=...)``
    stores, in less time on a SQL store.

    MLflow's SQL store (``sqlite:``, ``postgresql:``, …) builds one ORM object per value in
    ``log_batch``, about 60 µs each, and opens a session for each of its checks: at eleven
    metrics per episode, a third of a CartPole controlled run.  Here one session does what
    ``log_batch`` does with MLflow's own table model, checks and value rules (NaN stored as
    ``is_nan``, ±inf as ±float max): the run must be active, every value goes in one
    ``executemany`` into the ``metrics`` table, and each key's newest value updates
    ``latest_metrics``.  Values already stored (a resumed run writing again what it had
    written) make the insert fail as a whole, and then go through ``log_batch``, which skips
    them.  Other stores (a tracking server, ``file:``, an MLflow without those parts):
    ``log_batch`` in chunks of 1000, its limit.
    """
    import sqlalchemy.exc
    from mlflow.store.tracking.dbmodels.models import SqlMetric
    from mlflow.store.tracking.sqlalchemy_store import SqlAlchemyStore

    store = client._tracking_client.store
    parts = ("sanitize_metric_value", "_get_run", "_check_run_is_active",
             "_update_latest_metrics_if_necessary")  # fmt: skip
    if not isinstance(store, SqlAlchemyStore) or not all(hasattr(store, p) for p in parts):
        _log_batches(client, run_id, metrics)
        return
    rows: list[dict[str, Any]] = []
    newest: dict[str, dict[str, Any]] = {}
    for m in metrics:
        is_nan, value = store.sanitize_metric_value(float(m.value))
        row = {"run_uuid": run_id, "key": m.key, "value": value, "is_nan": is_nan,
               "timestamp": int(m.timestamp), "step": int(m.step)}  # fmt: skip
        rows.append(row)
        old = newest.get(m.key)
        if old is None or _recency(row) > _recency(old):
            newest[m.key] = row
    if not rows:
        return
    try:
        with _write_session(store) as session:
            store._check_run_is_active(store._get_run(session=session, run_uuid=run_id))
            session.execute(SqlMetric.__table__.insert(), rows)
            latest = [SqlMetric(**row) for row in newest.values()]
            store._update_latest_metrics_if_necessary(latest, session)
    except MlflowException as err:  # the store wraps the driver's error
        if not isinstance(err.__cause__, sqlalchemy.exc.IntegrityError):
            raise
        _log_batches(client, run_id, metrics)


_recency = operator.itemgetter("step", "timestamp", "value")
"""MLflow's order of a key's values for ``latest_metrics``, on the stored values."""


def _log_batches(client: MlflowClient, run_id: str, metrics: Sequence[Metric]) -> None:
    """``metrics`` through ``log_batch``, 1000 at a time (its limit)."""
    for i in range(0, len(metrics), 1000):
        client.log_batch(run_id, metrics=list(metrics[i : i + 1000]))


def _write_session(store: Any) -> contextlib.AbstractContextManager[Any]:
    """A session of ``store`` that may write (MLflow ≥ 3 asks for it; 2.x has no flag)."""
    try:
        return store.ManagedSessionMaker(read_only=False)
    except TypeError:
        return store.ManagedSessionMaker()


def _param_value(value: Any) -> str:
    text = json.dumps(value) if isinstance(value, list | dict) else str(value)
    return text[:MAX_PARAM_LENGTH]
