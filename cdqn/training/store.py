"""The tracking store made ready once: created under a file lock, a fresh SQLite store copied
from a migrated empty one.

A fresh SQLite store is created by the first process that opens it; that migration is not
safe when several joblib workers do it at the same moment.  Every process opens the store
through :func:`ensure_store`, which does it under an exclusive lock on ``<database>.lock``
(:class:`cdqn.training.sweep.PrepareStore` calls it in the launching process before a
multirun's jobs start).

MLflow creates a SQLite store by running its schema migrations one by one, 2.5–3.5 s of CPU
on this project's machines, the same for every new store.  cdqn keeps one migrated,
empty store per MLflow version in its cache folder (``~/.cache/cdqn/mlflow/<version>``; made
by MLflow itself the first time) and copies it into place for a database file that does not
exist yet.  The copy holds the schema alone: MLflow adds the ``Default`` experiment, with its
artifact location and creation time, when it first opens the copy, as it does in a store it
migrated itself.  Where the cache folder cannot be written, MLflow migrates the store itself.
"""

from __future__ import annotations

import contextlib
import logging
import os
import random
import shutil
import sqlite3
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from mlflow import __version__ as mlflow_version
from mlflow.tracking import MlflowClient

from cdqn import cache_dir
from cdqn.config import EXPERIMENT_TAGS, SQLITE, ConfigError, sqlite_file

try:
    import fcntl

    LOCKS = True
except ImportError:  # Windows: no advisory locks, PrepareStore still creates the store once
    LOCKS = False

log = logging.getLogger("cdqn")


def ensure_store(uri: str, experiment: str, attempts: int = 5) -> None:
    """Create (and migrate) the store at ``uri`` and the experiment.

    For a SQLite store this happens under an exclusive lock on ``<database>.lock``: a fresh
    store's first migration, run by several processes at once, fails and leaves the
    database unusable (a half-finished ``_alembic_tmp_*`` table).  A database file that does
    not exist yet is copied from the migrated empty store (module docstring).  Other errors
    are retried, then raised as :class:`cdqn.config.ConfigError` (exit status 2, one line).
    """
    for attempt in range(attempts):
        try:
            with _store_lock(uri):
                place_migrated(uri)
                client = MlflowClient(uri)
                if client.get_experiment_by_name(experiment) is None:
                    client.create_experiment(experiment, tags=EXPERIMENT_TAGS)
            return
        except Exception as err:
            if attempt == attempts - 1:
                raise ConfigError(
                    f"tracking.uri={uri!r}: the store cannot be opened "
                    f"({type(err).__name__}: {' '.join(str(err).split())[:300]})"
                ) from None
            delay = 0.2 * 2**attempt * (1 + random.random())
            log.warning("tracking store %s not ready (%s); retrying in %.1f s", uri, err, delay)
            time.sleep(delay)


@contextlib.contextmanager
def _store_lock(uri: str) -> Iterator[None]:
    """Exclusive lock on ``<database>.lock`` for ``sqlite:///`` URIs (POSIX); else nothing."""
    database = sqlite_file(uri)
    if database is None or not LOCKS:
        yield
        return
    path = Path(f"{database}.lock")
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def place_migrated(uri: str) -> None:
    """Copy the migrated empty store to the database file of a ``sqlite:///`` ``uri`` when
    none is there yet (an empty file counts as none, as for SQLite); nothing for other stores
    or when the cache cannot provide one.  Callers hold the store's lock (:func:`ensure_store`)
    or are its only user."""
    database = sqlite_file(uri)
    if database is None or "?" in uri or (database.exists() and database.stat().st_size > 0):
        return
    template = migrated_template()
    if template is None:
        return
    part = database.with_name(f".{database.name}.{os.getpid()}.part")
    try:
        database.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(template, part)
        os.replace(part, database)
    except OSError:  # MLflow, opening the store itself, reports what is wrong with the place
        part.unlink(missing_ok=True)


def migrated_template() -> Path | None:
    """This MLflow version's migrated empty store in cdqn's cache folder, made by MLflow the
    first time (without the ``Default`` experiment, which MLflow adds on opening a copy);
    None when it cannot be made there (the cache folder cannot be written, say)."""
    folder = cache_dir() / "mlflow" / mlflow_version
    template = folder / "store.db"
    if template.exists():
        return template
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=folder) as tmp:
            made = Path(tmp) / "store.db"
            MlflowClient(f"{SQLITE}{made}").search_experiments()  # MLflow's own migration
            with contextlib.closing(sqlite3.connect(made)) as db:
                with db:
                    db.execute("DELETE FROM experiments")
                db.execute("VACUUM")
            os.replace(made, template)  # atomic: a process reading the template sees a whole one
    except Exception as err:  # a shortcut only: MLflow then migrates the store itself
        log.debug("no migrated store template in %s: %s", folder, err)
        return None
    return template
