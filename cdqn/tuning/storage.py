"""The study's Optuna storage and the lock its parallel workers share."""

from __future__ import annotations

import hashlib
import tempfile
from pathlib import Path
from typing import Any

from cdqn.config import SQLITE, sqlite_file

try:
    import fcntl

    LOCKS = True
except ImportError:  # Windows: one worker per study
    LOCKS = False


HEARTBEAT = 60
"""Seconds between a running trial's heartbeats; a trial silent for 3 of them is stale."""
WORKER_SEED_STRIDE = 100_003
"""Worker w's TPE sampler is seeded with ``tune.sampler_seed + trials so far + w·stride``."""


class StudyLock:
    """An exclusive lock (``fcntl.flock``) shared by the processes of one machine that use
    the Optuna storage ``url``: the file ``<database>.tune-lock`` beside an SQLite storage,
    else one in the temporary folder named by the URL's hash.  ``release`` of a lock not
    held does nothing.  Without ``fcntl`` (Windows) it does nothing (one worker)."""

    def __init__(self, url: str) -> None:
        if (database := sqlite_file(url)) is not None:
            db = database.resolve()  # as _storage resolves it
            self.path = db.with_name(db.name + ".tune-lock")
        else:
            digest = hashlib.sha256(url.encode()).hexdigest()[:16]
            self.path = Path(tempfile.gettempdir()) / f"cdqn-tune-{digest}.lock"
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._handle: Any = None

    def acquire(self) -> None:
        if self._handle is not None:
            raise RuntimeError(f"{self.path}: the lock is already held by this process")
        self._handle = self.path.open("a")
        if LOCKS:
            fcntl.flock(self._handle, fcntl.LOCK_EX)

    def release(self) -> None:
        if self._handle is None:
            return
        if LOCKS:
            fcntl.flock(self._handle, fcntl.LOCK_UN)
        self._handle.close()
        self._handle = None

    def __enter__(self) -> StudyLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def open_storage(url: str) -> Any:
    """Optuna storage of ``url``: an SQLite path made absolute (its folder created), with
    heartbeats so that a trial whose process died is failed and retried once
    (``RetryHeartbeatStaleTrialCallback``) when the study runs again."""
    import warnings

    import optuna

    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
    if (database := sqlite_file(url)) is not None and not database.is_absolute():
        path = database.resolve()
        path.parent.mkdir(parents=True, exist_ok=True)
        url = f"{SQLITE}{path}"
    if not url.startswith(("sqlite:", "postgresql", "mysql")):
        return url
    return optuna.storages.RDBStorage(
        url,
        heartbeat_interval=HEARTBEAT,
        grace_period=3 * HEARTBEAT,
        heartbeat_stale_trial_callback=optuna.storages.RetryHeartbeatStaleTrialCallback(
            max_retry=1
        ),
    )
