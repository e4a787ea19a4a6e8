"""Helpers for the reliability tests: real subprocesses, real signals, a real MLflow server."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

import pytest

from cdqn.tracking import Recorder
from cdqn.trainer import EpisodeStats


def run_cli(
    module: str, args: list[str], cwd: Path, timeout: float = 300.0
) -> subprocess.CompletedProcess[str]:
    """``python -m <module> <args>`` in ``cwd``; output captured as text."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    env.pop("HYDRA_FULL_ERROR", None)
    return subprocess.run(
        [sys.executable, "-m", module, *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def signals_after_episode(monkeypatch: pytest.MonkeyPatch) -> Callable[..., None]:
    """``arm(k, SIGTERM, ...)``: once episode ``k`` is recorded, this process sends itself
    those signals (real signals, handled by the training run's handlers); for a fixture."""
    armed: dict[str, object] = {}
    original = Recorder.log_episode

    def log_episode(self: Recorder, stats: EpisodeStats) -> None:
        original(self, stats)
        if armed.get("episode") == stats.episode:
            signals = armed.pop("signals")
            armed.clear()
            for sig in signals:  # type: ignore[attr-defined]
                os.kill(os.getpid(), sig)

    monkeypatch.setattr(Recorder, "log_episode", log_episode)

    def arm(episode: int, *signals: int) -> None:
        armed.update(episode=episode, signals=signals or (signal.SIGTERM,))

    return arm


@contextmanager
def mlflow_server(root: Path, start_timeout: float = 180.0) -> Iterator[str]:
    """A real ``mlflow server`` on 127.0.0.1 (sqlite backend, artifacts served from
    ``root/artifacts``); yields its URI and stops the server (its whole process group)."""
    port = free_port()
    log = (root / "server.log").open("w")
    proc = subprocess.Popen(
        [
            str(Path(sys.executable).with_name("mlflow")),
            "server",
            "--backend-store-uri",
            f"sqlite:///{root / 'server.db'}",
            "--artifacts-destination",
            str(root / "artifacts"),
            "--serve-artifacts",
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--workers",
            "1",
        ],
        cwd=root,
        stdout=log,
        stderr=subprocess.STDOUT,
        env={**os.environ, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"},
        start_new_session=True,  # its own process group: stopped together below
    )
    uri = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + start_timeout
        while True:
            try:
                with urllib.request.urlopen(f"{uri}/health", timeout=2) as resp:
                    if resp.read().strip() == b"OK":
                        break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                log.flush()
                raise RuntimeError(
                    f"mlflow server did not come up: {(root / 'server.log').read_text()[-2000:]}"
                )
            time.sleep(0.5)
        yield uri
    finally:
        for sig, wait in ((signal.SIGTERM, 20.0), (signal.SIGKILL, 10.0)):
            try:  # the whole group: the CLI, uvicorn and anything they started
                os.killpg(proc.pid, sig)
            except ProcessLookupError:
                break
            with suppress(subprocess.TimeoutExpired):
                proc.wait(wait)
        log.close()
