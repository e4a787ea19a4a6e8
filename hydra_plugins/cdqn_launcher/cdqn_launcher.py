"""Hydra's joblib launcher, with its workers stopping together on a signal.

A multirun on the local cores (``hydra/launcher=local``) runs its jobs in joblib's worker
processes.  Two things would leave a stopped multirun with work lost or still running:

- a SIGTERM sent to the command alone (``kill <pid>``, ``timeout``, a container's stop)
  ends only the parent process, and the workers go on training, orphaned;
- a job that a signal stopped ends with ``SystemExit`` (exit status 128 + the signal), and
  joblib, on the first job that raises, terminates the other workers, perhaps while they
  write their checkpoints or mark their runs.

While its jobs run, this launcher passes each SIGTERM it receives on to its live workers,
and a job that exits returns its exit status to the launcher instead of raising.  So each
worker stops as a single run does (at the end of the current episode, checkpointed, its runs
marked KILLED; a second signal stops it at once, :mod:`cdqn.training.interrupt`), the
launcher waits for all of them, and the command then exits with the largest status of its
jobs (143 after SIGTERM, 130 after Ctrl-C).  Jobs still queued then do not start: the
signal leaves a stop file that a worker reads before it starts a job.  Running the same
command again continues.  A first Ctrl-C reaches the workers from the terminal (the whole
process group); the launcher waits for them, and a second Ctrl-C stops it at once.

Selected in ``conf/hydra/launcher/local.yaml``; the ``cdqn_local`` option of the
``hydra/launcher`` group is registered here.
"""

import atexit
import contextlib
import logging
import multiprocessing
import os
import shutil
import signal
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any

from hydra.core.config_store import ConfigStore
from hydra.core.utils import JobReturn, JobStatus
from hydra.types import HydraContext, TaskFunction
from hydra_plugins.hydra_joblib_launcher.config import JobLibLauncherConf
from hydra_plugins.hydra_joblib_launcher.joblib_launcher import JoblibLauncher
from omegaconf import DictConfig

log = logging.getLogger(__name__)


@dataclass
class CdqnLocalLauncherConf(JobLibLauncherConf):
    _target_: str = "hydra_plugins.cdqn_launcher.cdqn_launcher.CdqnLocalLauncher"


ConfigStore.instance().store(
    group="hydra/launcher", name="cdqn_local", node=CdqnLocalLauncherConf, provider="cdqn"
)


@dataclass(frozen=True)
class JobExit:
    """What a job that exited returns to the launcher: its exit status."""

    code: int


def exit_status(code: object) -> int:
    """The process exit status of ``SystemExit(code)``, as Python sets it."""
    if code is None:
        return 0
    return code if isinstance(code, int) else 1


class ExitAsValue:
    """A worker's task function: the job's own, with ``SystemExit`` returned as a
    :class:`JobExit`, and not started once ``stop_file`` holds the exit status of a signal
    (module docstring).  Picklable where the job's function is."""

    def __init__(self, task: TaskFunction, stop_file: Path) -> None:
        self.task = task
        self.stop_file = stop_file

    def __call__(self, cfg: DictConfig) -> Any:
        if self.stop_file.exists():
            return JobExit(int(self.stop_file.read_text() or 1))
        try:
            return self.task(cfg)
        except SystemExit as stop:
            return JobExit(exit_status(stop.code))


def workers() -> list[int]:
    """The process ids of this process's live child processes (joblib's loky workers are
    ``multiprocessing`` processes of it)."""
    return [p.pid for p in multiprocessing.active_children() if p.pid is not None]


@contextmanager
def signals_to_workers(stop_file: Path) -> Iterator[None]:
    """While the block runs, each SIGTERM to this process is sent on to its workers, and a
    first SIGINT waits for them; either writes its exit status into ``stop_file``, so that
    no queued job starts (module docstring).  The process goes on waiting."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    interrupts = 0

    def on_term(signum: int, frame: FrameType | None) -> None:
        stop_file.write_text(str(128 + signum))
        pids = workers()
        log.warning("SIGTERM: passed on to %d worker(s); each stops at the end of its "
                    "episode (send it again to stop them at once)", len(pids))  # fmt: skip
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):  # ended meanwhile
                os.kill(pid, signal.SIGTERM)

    def on_int(signum: int, frame: FrameType | None) -> None:
        nonlocal interrupts
        interrupts += 1
        if interrupts > 1:
            raise KeyboardInterrupt
        stop_file.write_text(str(128 + signum))
        log.warning("SIGINT: waiting for the workers to stop at the end of their episodes "
                    "(press Ctrl-C again to stop at once)")  # fmt: skip

    previous: dict[int, Callable[..., Any] | int | None] = {
        signal.SIGTERM: signal.signal(signal.SIGTERM, on_term),
        signal.SIGINT: signal.signal(signal.SIGINT, on_int),
    }
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


class CdqnLocalLauncher(JoblibLauncher):
    """:class:`JoblibLauncher` whose workers stop together on a signal (module docstring)."""

    def setup(
        self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig
    ) -> None:
        folder = tempfile.mkdtemp(prefix="cdqn-multirun-")
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
        self.stop_file = Path(folder) / "stop"
        task = ExitAsValue(task_function, self.stop_file)
        super().setup(hydra_context=hydra_context, task_function=task, config=config)

    def launch(
        self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int
    ) -> Sequence[JobReturn]:
        with signals_to_workers(self.stop_file):
            runs = super().launch(job_overrides, initial_job_idx)
        done = [r.return_value for r in runs if r.status == JobStatus.COMPLETED]
        exits = [value.code for value in done if isinstance(value, JobExit)]
        if any(exits):
            sys.exit(max(exits))
        return runs
