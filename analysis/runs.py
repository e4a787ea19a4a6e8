"""Load cdqn runs from any MLflow tracking store into pandas.

A cdqn run (written by :mod:`cdqn.training.tracking`) carries

* tags ``env``, ``env_id``, ``controller``, ``seed``, ``git_commit``, ``design_source``
  (and ``failure_reason`` when it failed);
* params: the resolved config flattened with dots (``env.solve_threshold``, ``train.lr``,
  ``weights.hinf.w_p.num`` as a JSON list, ...);
* per-episode metrics with ``step`` = episode index (:data:`EPISODE_METRICS`);
* artifacts ``signals/steps.parquet``, ``signals/fft.parquet``, ``design/controller.json``
  and, for synthesized designs, ``design/closed_loop_sv.csv``.

:class:`RunStore` reads them: :meth:`RunStore.runs` gives one row per run (tags as columns,
params as ``params.<name>``), :meth:`RunStore.episodes` one row per (run, episode) with one
column per metric, and the artifact readers load one run's files on demand.  Only FINISHED
runs are returned unless other statuses are asked for.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from functools import cached_property, lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")

from mlflow.entities import ViewType
from mlflow.exceptions import MlflowException
from mlflow.store.db.db_types import DATABASE_ENGINES
from mlflow.tracking import MlflowClient

from analysis.shared import AGENT_SETTINGS, SEEDS, SHARED_SETTINGS
from cdqn import records
from cdqn.config import TrackingConfig, resolve_tracking_uri, sqlite_file

DEFAULT_URI = TrackingConfig.uri
"""The training default (``sqlite:///mlflow.db`` in the working folder)."""
DEFAULT_EXPERIMENT = TrackingConfig.experiment

EPISODE_METRICS = tuple(m for m in records.EPISODE_METRICS if m != records.Metric.REPLAY_UPDATES)
"""Per-episode metrics a cdqn run logs (MLflow ``step`` = episode index, from 0);
the ``*_box`` shares only the agents with an NTK box (NaN for the others)."""

T = records.Tag
TAG_COLUMNS = (T.ENV, T.ENV_ID, T.CONTROLLER, T.SEED, T.GIT_COMMIT, T.DESIGN_SOURCE)
"""Tags every cdqn run carries; they become columns of :meth:`RunStore.runs`."""

RUN_KEY = ("run_id", "env", "controller", "seed", "settings")
"""The columns that identify a run in the per-episode table."""

SETTINGS = (
    "train.bootstrap_terminal",
    *(s.key for s in SHARED_SETTINGS if s.key != SEEDS),
    *(key for keys in AGENT_SETTINGS.values() for key in keys),
)
"""Tags and params that change results: runs of one environment that differ in any of them
are never averaged together (:func:`comparable_runs` puts them into separate groups): the
terminal bootstrap, every setting the agents of a column share and every agent's own
(:mod:`analysis.shared`); a key ending in ``.`` stands for every param under it
(:func:`setting_keys`)."""


def setting_keys(runs: pd.DataFrame) -> list[str]:
    """:data:`SETTINGS` with each key ending in ``.`` replaced by the params under it that
    ``runs`` have (``weights.hinf_f.`` → ``weights.hinf_f.w_p.num``, …)."""
    params = [c.removeprefix("params.") for c in runs.columns if c.startswith("params.")]
    out: list[str] = []
    for key in SETTINGS:
        out.extend(sorted(p for p in params if p.startswith(key)) if key.endswith(".") else [key])
    return list(dict.fromkeys(out))


class EmptyStoreError(RuntimeError):
    """The store holds no runs to analyse (or not the experiment asked for)."""


def param_value(text: Any, default: Any = None) -> Any:
    """Decode one MLflow param string (``"[200.0, 500.0]"``, ``"195.0"``, ``"None"``)."""
    if text is None or (isinstance(text, float) and np.isnan(text)):
        return default
    if not isinstance(text, str):
        return text
    if text in ("None", "null", ""):
        return default
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


class RunStore:
    """The cdqn runs of one experiment in one MLflow tracking store.

    Parameters
    ----------
    uri:
        Any MLflow tracking URI (``sqlite:///mlflow.db``, ``http://host:5000``, a folder).
    experiment:
        Experiment name.
    statuses:
        Run statuses to include; FINISHED only by default.
    threads:
        Parallel metric-history requests (the store answers one run and key per request).
    """

    def __init__(
        self,
        uri: str = DEFAULT_URI,
        experiment: str = DEFAULT_EXPERIMENT,
        statuses: Sequence[str] = ("FINISHED",),
        threads: int = 8,
    ) -> None:
        self.uri = resolve_tracking_uri(uri)
        self.experiment = experiment
        self.statuses = tuple(s.upper() for s in statuses)
        self.threads = threads
        self._tmp = tempfile.TemporaryDirectory(prefix="cdqn-analysis-")

    def __repr__(self) -> str:
        return f"RunStore({self.uri!r}, experiment={self.experiment!r})"

    def describe(self) -> str:
        """``experiment 'cdqn' at sqlite:///...`` for messages."""
        return f"experiment {self.experiment!r} at {self.uri}"

    @cached_property
    def client(self) -> MlflowClient:
        """The MLflow client (created on first use)."""
        return MlflowClient(self.uri)

    def exists(self) -> bool:
        """False for an embedded ``sqlite:///`` store whose file does not exist.

        (Opening it would create an empty database there.)
        """
        database = sqlite_file(self.uri)
        return database is None or database.exists()

    # ------------------------------------------------------------------ runs
    @cached_property
    def _all_runs(self) -> pd.DataFrame:
        if not self.exists():
            return _empty_runs()
        try:
            exp = self.client.get_experiment_by_name(self.experiment)
        except MlflowException:
            exp = None
        if exp is None:
            return _empty_runs()
        rows: list[dict[str, Any]] = []
        token: str | None = None
        while True:
            page = self.client.search_runs(
                [exp.experiment_id],
                run_view_type=ViewType.ACTIVE_ONLY,
                max_results=1000,
                page_token=token,
            )
            for run in page:
                row: dict[str, Any] = {
                    "run_id": run.info.run_id,
                    "run_name": run.info.run_name,
                    "status": run.info.status,
                    "start_time": run.info.start_time,
                    "artifact_uri": run.info.artifact_uri,
                }
                tags = run.data.tags
                for tag in (*TAG_COLUMNS, T.FAILURE_REASON):
                    row[tag] = tags.get(tag)
                row.update({f"params.{k}": v for k, v in run.data.params.items()})
                rows.append(row)
            token = page.token
            if not token:
                break
        if not rows:
            return _empty_runs()
        df = pd.DataFrame(rows)
        df = df[df["env"].notna() & df["controller"].notna()]  # runs not written by cdqn
        df["seed"] = pd.to_numeric(df["seed"], errors="coerce").astype("Int64")
        thresholds = df.get("params.env.solve_threshold", pd.Series(None, index=df.index))
        df["solve_threshold"] = [_as_float(param_value(v)) for v in thresholds]
        return df.sort_values(["env", "controller", "seed", "start_time"]).reset_index(drop=True)

    def runs(self, statuses: Sequence[str] | None = None) -> pd.DataFrame:
        """One row per cdqn run (tagged ``env`` and ``controller``) with the given statuses.

        Default statuses: the store's (FINISHED only unless set otherwise).

        Columns: ``run_id, run_name, status, start_time, artifact_uri``, the tags of
        :data:`TAG_COLUMNS` plus ``failure_reason``, ``solve_threshold`` (float, NaN if the
        environment has none) and every param as ``params.<dotted.name>`` (raw strings; see
        :func:`param_value`).
        """
        wanted = self.statuses if statuses is None else tuple(s.upper() for s in statuses)
        df = self._all_runs
        return df[df["status"].isin(wanted)].reset_index(drop=True)

    def require_runs(self, statuses: Sequence[str] | None = None) -> pd.DataFrame:
        """:meth:`runs`, raising :class:`EmptyStoreError` when there are none."""
        df = self.runs(statuses)
        if df.empty:
            wanted = self.statuses if statuses is None else statuses
            n_all = len(self._all_runs)
            extra = f" ({n_all} runs with other statuses)" if n_all else ""
            if not self.exists():
                extra = " (no such database file)"
            raise EmptyStoreError(
                f"no {'/'.join(wanted)} cdqn runs in {self.describe()}{extra}; "
                "pass --tracking-uri and --experiment to point at the store"
            )
        return df

    # --------------------------------------------------------------- metrics
    def metric_history(self, run_id: str, key: str) -> pd.DataFrame:
        """``episode, value`` of one metric of one run (the last value per episode)."""
        long = self._metrics_client([run_id], [key])
        return long[["episode", "value"]].reset_index(drop=True)

    def episodes(
        self,
        metrics: Iterable[str] = EPISODE_METRICS,
        runs: pd.DataFrame | None = None,
    ) -> pd.DataFrame:
        """One row per (run, episode): :data:`RUN_KEY`, ``episode`` and one column per metric.

        ``runs`` selects the runs (rows of :meth:`runs`); default: all runs of the store's
        statuses.  A database-backed store (sqlite, PostgreSQL, MySQL, MSSQL) is read with
        one query per metric; any other store (a tracking server, a file store) with one
        ``get_metric_history`` request per run and metric, ``threads`` at a time.  If a run
        logged an episode twice (a resumed run), the later value counts.
        """
        metrics = list(metrics)
        runs = self.runs() if runs is None else runs
        if "settings" not in runs.columns:  # runs not grouped by comparable_runs
            runs = runs.assign(settings="")
        columns = [*RUN_KEY, "episode", *metrics]
        if runs.empty or not metrics:
            return pd.DataFrame(columns=columns)
        run_ids = list(runs["run_id"])
        long = None
        if self.uri.split(":", 1)[0].split("+", 1)[0] in DATABASE_ENGINES:
            long = self._metrics_sql(run_ids, metrics)
        if long is None:
            long = self._metrics_client(run_ids, metrics)
        if long.empty:
            return pd.DataFrame(columns=columns)
        wide = long.pivot(index=["run_id", "episode"], columns="key", values="value")
        wide = wide.reindex(columns=metrics).reset_index()
        wide.columns.name = None
        out = wide.merge(runs[list(RUN_KEY)], on="run_id", how="left")
        return out[columns].sort_values(["env", "controller", "seed", "episode"], ignore_index=True)

    def _metrics_client(self, run_ids: list[str], keys: list[str]) -> pd.DataFrame:
        """Long table ``run_id, key, episode, value`` through the public client API."""

        def fetch(job: tuple[str, str]) -> pd.DataFrame:
            hist = self.client.get_metric_history(*job)
            n = len(hist)
            return pd.DataFrame(
                {
                    "run_id": job[0],
                    "key": job[1],
                    "episode": np.fromiter((m.step for m in hist), np.int64, n),
                    "timestamp": np.fromiter((m.timestamp for m in hist), np.int64, n),
                    "value": np.fromiter((m.value for m in hist), float, n),
                }
            )

        jobs = [(rid, key) for rid in run_ids for key in keys]
        with ThreadPoolExecutor(max_workers=max(1, self.threads)) as pool:
            frames = list(pool.map(fetch, jobs))
        return _latest(pd.concat(frames, ignore_index=True))

    def _metrics_sql(self, run_ids: list[str], keys: list[str]) -> pd.DataFrame | None:
        """Long table ``run_id, key, episode, value`` straight from the store's database.

        Reads MLflow's own ``metrics`` table model (NaN is stored as ``is_nan``), with the
        same values the client API returns; ``None`` if the database cannot be read so.
        """
        import sqlalchemy as sa
        from mlflow.store.tracking.dbmodels.models import SqlMetric

        cols = SqlMetric.__table__.c
        names = ["run_id", "key", "episode", "timestamp", "value", "is_nan"]
        frames = []
        try:
            engine = sa.create_engine(self.uri)
        except (sa.exc.SQLAlchemyError, ImportError):
            return None
        db_error = getattr(engine.dialect.dbapi, "Error", sa.exc.SQLAlchemyError)
        try:
            raw = engine.raw_connection()  # plain DB-API tuples: no per-row objects
            try:
                cursor = raw.cursor()
                for i in range(0, len(run_ids), 500):
                    query = sa.select(
                        cols.run_uuid,
                        cols.key,
                        cols.step,
                        cols.timestamp,
                        cols.value,
                        cols.is_nan,
                    ).where(cols.key.in_(keys), cols.run_uuid.in_(run_ids[i : i + 500]))
                    sql = query.compile(engine, compile_kwargs={"literal_binds": True})
                    cursor.execute(str(sql))
                    frames.append(pd.DataFrame.from_records(cursor.fetchall(), columns=names))
            finally:
                raw.close()
        except (sa.exc.SQLAlchemyError, db_error):
            return None
        finally:
            engine.dispose()
        df = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
        if df.empty:
            return pd.DataFrame(columns=["run_id", "key", "episode", "value"])
        df["value"] = df["value"].astype(float).where(~df["is_nan"].astype(bool), np.nan)
        return _latest(df)

    # ------------------------------------------------------------- artifacts
    def has_artifact(self, run_id: str, path: str) -> bool:
        """Whether the run stored the artifact file ``path``."""
        folder = path.rsplit("/", 1)[0] if "/" in path else None
        try:
            listed = self.client.list_artifacts(run_id, folder)
        except (MlflowException, OSError):
            return False
        return any(item.path == path for item in listed)

    def artifact_path(self, run_id: str, path: str) -> Path | None:
        """Local copy of one artifact file, or ``None`` if the run has none."""
        return _download(self, run_id, path)

    def steps(self, run_id: str) -> pd.DataFrame | None:
        """``signals/steps.parquet``: one row per environment step (``None`` if absent).

        Columns ``episode, step, reward, q1, q2, u, x_e, theta1, theta2, loss``.
        """
        path = self.artifact_path(run_id, records.Artifact.STEPS)
        return None if path is None else pd.read_parquet(path)

    def fft(self, run_id: str) -> pd.DataFrame | None:
        """``signals/fft.parquet``: amplitude spectra ``freq, reward, q1, q2`` (or ``None``).

        ``freq`` is in cycles per unit of learning time (one training step is Δt = α).
        """
        path = self.artifact_path(run_id, records.Artifact.FFT)
        return None if path is None else pd.read_parquet(path)

    def design(self, run_id: str) -> dict[str, Any] | None:
        """``design/controller.json``, the controller the run used (or ``None``)."""
        path = self.artifact_path(run_id, records.Artifact.DESIGN_RECORD)
        return None if path is None else json.loads(path.read_text())

    def closed_loop_sv(self, run_id: str) -> pd.DataFrame | None:
        """``design/closed_loop_sv.csv``: ``omega, sigma_max, sigma_min`` (or ``None``)."""
        path = self.artifact_path(run_id, records.Artifact.DESIGN + "closed_loop_sv.csv")
        return None if path is None else pd.read_csv(path)


def setting_values(runs: pd.DataFrame, key: str) -> pd.Series:
    """The value of tag or param ``key`` of every run, decoded and as text (``"64"``,
    ``"[2, 3]"``, ``"None"``); None where a run does not have it."""
    column = key if key in runs.columns else f"params.{key}"
    if column not in runs.columns:
        return pd.Series(None, index=runs.index, dtype=object)
    return runs[column].map(lambda v: None if v is None else _text(param_value(v)))


def _text(value: Any) -> str:
    return json.dumps(value) if isinstance(value, list | dict) else str(value)


def environment(runs: pd.DataFrame) -> pd.Series:
    """A run's environment for the analysis: its ``env`` tag, or its ``env_id`` when the tag
    names a preset of another id (runs made before ``env.id=<id>`` named runs by the id)."""
    from cdqn.envs import env_presets

    presets = env_presets()

    def one(env: Any, env_id: Any) -> Any:
        preset = presets.get(str(env))
        return env_id if preset is not None and env_id and env_id != preset.id else env

    return pd.Series(
        [one(e, i) for e, i in zip(runs["env"], runs["env_id"], strict=True)],
        index=runs.index,
        dtype=object,
    )


def comparable_runs(runs: pd.DataFrame) -> tuple[pd.DataFrame, list[str]]:
    """Runs grouped by the settings that change results, one run per seed and group (the
    latest started), and notes on what was grouped or left out.

    ``env`` becomes :func:`environment`; ``settings`` is ``""`` when the runs of every
    (environment, controller) agree in all :data:`SETTINGS`, else, per run, its values of
    the settings that differ within one of them (``network.width=64, train.episodes=3``).
    A seed run twice with the same settings counts once (the latest)."""
    notes: list[str] = []
    runs = runs.copy()
    if runs.empty:
        runs["settings"] = pd.Series(dtype=object)
        return runs, notes
    runs["env"] = environment(runs)
    keys = setting_keys(runs)
    values = {key: setting_values(runs, key) for key in keys}
    cells = [runs["env"], runs["controller"]]
    varying = [key for key in keys if (values[key].groupby(cells).nunique(dropna=False) > 1).any()]
    runs["settings"] = [", ".join(f"{key}={values[key][i]}" for key in varying) for i in runs.index]
    key = ["env", "settings", "controller", "seed"]
    counts = runs.groupby(key, dropna=False).size()
    for (env, settings, ctrl, seed), n in counts[counts > 1].items():
        where = f" [{settings}]" if settings else ""
        notes.append(f"{env}/{ctrl}{where} seed {seed}: {n} runs, only the latest one counts")
    latest = runs.sort_values("start_time").drop_duplicates(key, keep="last")
    if varying:
        groups = latest["settings"].nunique()
        notes.append(
            f"the runs differ in {', '.join(varying)}: {groups} groups of settings, never "
            "averaged together; pick one with --where KEY=VALUE"
        )
    latest = latest.sort_values(["env", "settings", "controller", "seed", "start_time"])
    return latest.reset_index(drop=True), notes


class WhereError(ValueError):
    """A ``--where KEY=VALUE`` filter names no setting of the runs or matches no run."""


def where(runs: pd.DataFrame, conditions: Sequence[str]) -> pd.DataFrame:
    """The runs whose tag or param ``KEY`` equals ``VALUE`` for every ``KEY=VALUE``
    (values compared decoded: ``train.lr=5e-5`` matches the param ``5e-05``)."""
    for cond in conditions:
        key, sep, value = cond.partition("=")
        key = key.strip()
        if not sep or not key:
            raise WhereError(f"--where {cond!r}: expected KEY=VALUE, e.g. train.episodes=2000")
        column = key if key in runs.columns else f"params.{key}"
        if column not in runs.columns:
            known = [*TAG_COLUMNS, *SETTINGS[:8]]
            raise WhereError(
                f"--where {cond}: no run has a tag or param {key!r}; e.g. {', '.join(known)}"
            )
        have = setting_values(runs, key)
        want = _text(param_value(value.strip()))
        hit = runs[have == want]
        if hit.empty:
            present = ", ".join(sorted({str(v) for v in have}))
            raise WhereError(f"--where {cond}: no run has {key}={value}; present: {present}")
        runs = hit
    return runs


@lru_cache(maxsize=256)
def _download(store: RunStore, run_id: str, path: str) -> Path | None:
    if not store.has_artifact(run_id, path):
        return None
    dst = Path(store._tmp.name) / run_id
    dst.mkdir(parents=True, exist_ok=True)
    return Path(store.client.download_artifacts(run_id, path, str(dst)))


def _latest(long: pd.DataFrame) -> pd.DataFrame:
    """Keep the last-logged value per (run, key, episode), as MLflow orders history."""
    long = long.astype({"run_id": "category", "key": "category"})  # cheap sorting
    long = long.sort_values(["run_id", "key", "episode", "timestamp", "value"], kind="stable")
    long = long.drop_duplicates(["run_id", "key", "episode"], keep="last")
    long = long.astype({"run_id": str, "key": str})
    return long[["run_id", "key", "episode", "value"]].reset_index(drop=True)


def _as_float(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


def _empty_runs() -> pd.DataFrame:
    cols = [
        "run_id",
        "run_name",
        "status",
        "start_time",
        "artifact_uri",
        *TAG_COLUMNS,
        T.FAILURE_REASON,
        "solve_threshold",
    ]
    return pd.DataFrame(columns=cols)
