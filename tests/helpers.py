"""Helpers for the reliability tests: real subprocesses, real signals, a real MLflow server."""

from __future__ import annotations

import atexit
import json
import logging
import os
import random
import select
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

import pandas as pd
import pytest
from mlflow.tracking import MlflowClient

from cdqn.training.loop import EpisodeStats
from cdqn.training.tracking import Recorder
from tests.cli_server import SERVED

ROOT = Path(__file__).resolve().parents[1]
"""The checkout these tests belong to."""


def run_cli(
    module: str, args: list[str], cwd: Path, timeout: float = 300.0
) -> subprocess.CompletedProcess[str]:
    """``python -m <module> <args>`` in ``cwd``, with this checkout's ``cdqn`` and ``tests``
    importable (:data:`ROOT` on ``PYTHONPATH``); output captured as text.

    cdqn's command lines start as children of a process that has their imports done
    (:mod:`tests.cli_server`); each is its own process, with its own working folder,
    environment, arguments and exit code."""
    env = _cli_env()
    if module in SERVED:
        return _server().run({"module": module}, args, cwd, env, timeout)
    return subprocess.run(
        [sys.executable, "-m", module, *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def run_script(
    script: Path, args: list[str], cwd: Path, timeout: float = 300.0
) -> subprocess.CompletedProcess[str]:
    """``python <script> <args>`` in ``cwd`` (an ``analysis/`` script, as a user runs it:
    nothing added to ``PYTHONPATH``), started as :func:`run_cli` starts cdqn's commands."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return _server().run({"script": str(script)}, args, cwd, env, timeout)


def _cli_env() -> dict[str, str]:
    """This process's environment with :data:`ROOT` first on ``PYTHONPATH``, unbuffered."""
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": path}
    env.pop("HYDRA_FULL_ERROR", None)
    return env


class _CliServer:
    """The running :mod:`tests.cli_server` of this test process, and its commands."""

    def __init__(self, env: dict[str, str]) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, str(ROOT / "tests" / "cli_server.py")],
            cwd=ROOT,
            env=env,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
        )
        self.lock = threading.Lock()
        self.pending = b""
        self._answer("ready", 300.0)
        atexit.register(self.close)

    def run(
        self,
        command: dict[str, str],
        args: list[str],
        cwd: Path,
        env: dict[str, str],
        timeout: float,
    ) -> subprocess.CompletedProcess[str]:
        """``command`` (``{"module": …}`` or ``{"script": …}``) with ``args`` in a child."""
        head = ["-m", command["module"]] if "module" in command else [command["script"]]
        cmd = [sys.executable, *head, *args]
        with self.lock, tempfile.TemporaryDirectory() as tmp:
            out, err = Path(tmp) / "stdout", Path(tmp) / "stderr"
            request = {**command, "args": args, "cwd": str(cwd), "env": env,
                       "stdout": str(out), "stderr": str(err)}  # fmt: skip
            assert self.proc.stdin is not None
            self.proc.stdin.write(json.dumps(request).encode() + b"\n")
            self.proc.stdin.flush()
            pid = self._answer("pid", 60.0)
            try:
                code = self._answer("returncode", timeout)
            except subprocess.TimeoutExpired:
                os.kill(pid, signal.SIGKILL)
                self._answer("returncode", 60.0)
                raise subprocess.TimeoutExpired(
                    cmd, timeout, output=_text(out), stderr=_text(err)
                ) from None
            return subprocess.CompletedProcess(cmd, code, _text(out), _text(err))

    def _answer(self, key: str, timeout: float) -> int:
        """The next answer of the server, which must hold ``key``."""
        assert self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        deadline = time.monotonic() + timeout
        while b"\n" not in self.pending:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                raise subprocess.TimeoutExpired(str(self.proc.args), timeout)
            chunk = os.read(fd, 4096)
            if not chunk:
                raise RuntimeError(f"tests/cli_server.py ended (exit {self.proc.wait()})")
            self.pending += chunk
        line, _, self.pending = self.pending.partition(b"\n")
        return int(json.loads(line)[key])

    def close(self) -> None:
        if self.proc.poll() is None:
            assert self.proc.stdin is not None
            self.proc.stdin.close()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()


_SERVER: list[_CliServer] = []


def _server() -> _CliServer:
    """This test process's server (started with this checkout on ``PYTHONPATH``, as
    :func:`run_cli`'s commands are)."""
    if not _SERVER or _SERVER[0].proc.poll() is not None:
        _SERVER[:] = [_CliServer(_cli_env())]
    return _SERVER[0]


def _text(path: Path) -> str:
    return path.read_text(encoding="utf-8", errors="replace") if path.exists() else ""


def start_cli(
    module: str, args: list[str], cwd: Path, env: dict[str, str] | None = None
) -> subprocess.Popen[str]:
    """``python -m <module> <args>`` in ``cwd``, running; stdout and stderr in one text pipe,
    unbuffered (read it with :func:`read_until`)."""
    return subprocess.Popen(
        [sys.executable, "-m", module, *args],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, **(env or {}), "PYTHONUNBUFFERED": "1"},
    )


def read_until(
    proc: subprocess.Popen[str], text: str, seen: list[str], timeout: float = 240.0
) -> None:
    """Read ``proc``'s output (kept in ``seen``) up to the first line containing ``text``."""
    deadline = time.monotonic() + timeout
    assert proc.stdout is not None
    for line in proc.stdout:
        seen.append(line)
        if text in line:
            return
        assert time.monotonic() < deadline, "".join(seen)[-3000:]
    raise AssertionError(f"{text!r} never printed:\n{''.join(seen)[-3000:]}")


def finish(proc: subprocess.Popen[str], seen: list[str], timeout: float = 120.0) -> str:
    """Wait for ``proc`` to end (killed if it does not) and return all it printed."""
    try:
        rest, _ = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    return "".join(seen) + (rest or "")


def runs_of(uri: str) -> list:
    """Every run in the store at ``uri``."""
    client = MlflowClient(uri)
    return client.search_runs([e.experiment_id for e in client.search_experiments()])


def episode_returns(client: MlflowClient, run_id: str) -> list[float]:
    """The run's ``episode_return`` by episode; each episode logged once."""
    history = client.get_metric_history(run_id, "episode_return")
    assert len({m.step for m in history}) == len(history), "an episode was logged twice"
    return [m.value for m in sorted(history, key=lambda m: m.step)]


def signal_table(client: MlflowClient, run_id: str) -> pd.DataFrame:
    """The run's ``signals/steps.parquet``."""
    with tempfile.TemporaryDirectory() as tmp:
        return pd.read_parquet(client.download_artifacts(run_id, "signals/steps.parquet", tmp))


def member_runs(client: MlflowClient, run_ids: list[str]) -> dict[str, str]:
    """seed -> run id of a population's member runs."""
    return {client.get_run(r).data.tags["seed"]: r for r in run_ids}


def assert_same_run(
    client: MlflowClient, run_id: str, reference: str, other: MlflowClient | None = None
) -> None:
    """``run_id`` FINISHED with the returns and signal rows of ``reference`` (in the store of
    ``other``, default the same)."""
    other = other or client
    assert client.get_run(run_id).info.status == "FINISHED"
    assert episode_returns(client, run_id) == episode_returns(other, reference)
    pd.testing.assert_frame_equal(signal_table(client, run_id), signal_table(other, reference))


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _below_ephemeral() -> range:
    """Ports the kernel does not hand out on its own: below its ephemeral range
    (``net.ipv4.ip_local_port_range``, from which it picks the local port of every outgoing
    connection and of a bind to port 0), down to half its start."""
    try:
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        low = 32768  # Linux's default start
    return range(max(1024, low // 2), low)


def server_port() -> int:
    """A free TCP port on 127.0.0.1 for a server that is stopped and started again on it.

    While such a server is down its port must stay free.  One from :func:`free_port` could
    meanwhile become the local port of any outgoing connection, or another test's
    :func:`free_port`; this one is below the kernel's ephemeral range, in the share of it that
    belongs to this pytest-xdist worker (``PYTEST_XDIST_WORKER=gw<i>``), so no other worker
    picks it either."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    index = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw"))
    share = _below_ephemeral()[index::workers]
    for port in random.sample(share, min(200, len(share))):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue  # taken by something else on the machine
            return port
    raise RuntimeError(f"no free port among 200 tried of {share}")


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
            for sig in signals:
                os.kill(os.getpid(), sig)

    monkeypatch.setattr(Recorder, "log_episode", log_episode)

    def arm(episode: int, *signals: int) -> None:
        armed.update(episode=episode, signals=signals or (signal.SIGTERM,))

    return arm


def signals_after_checkpoint(monkeypatch: pytest.MonkeyPatch) -> Iterator[Callable[..., None]]:
    """``arm(n, SIGINT, ...)``: once the ``n``-th checkpoint is logged ("checkpoint at ..."
    on the ``cdqn`` logger; a population's logs one line per checkpoint), this process sends
    itself those signals when the next episode is recorded; for a fixture."""
    armed: dict[str, object] = {}
    original = Recorder.log_episode

    class Seen(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if armed and record.getMessage().startswith("checkpoint at"):
                armed["left"] = int(armed["left"]) - 1

    def log_episode(self: Recorder, stats: EpisodeStats) -> None:
        original(self, stats)
        if armed and int(armed["left"]) <= 0:
            signals = armed.pop("signals")
            armed.clear()
            for sig in signals:
                os.kill(os.getpid(), sig)

    handler = Seen(logging.DEBUG)  # checkpoints are logged at DEBUG
    logger = logging.getLogger("cdqn")
    logger.addHandler(handler)
    level = logger.level
    logger.setLevel(logging.DEBUG)
    monkeypatch.setattr(Recorder, "log_episode", log_episode)

    def arm(checkpoints: int, *signals: int) -> None:
        armed.update(left=checkpoints, signals=signals or (signal.SIGTERM,))

    yield arm
    logger.removeHandler(handler)
    logger.setLevel(level)


class MlflowServer:
    """A real ``mlflow server`` on 127.0.0.1 (sqlite backend, artifacts served from
    ``root/artifacts``) that can be stopped and started again on the same port, with the
    same store (a server that goes away during a run and comes back)."""

    def __init__(self, root: Path, port: int | None = None) -> None:
        root.mkdir(parents=True, exist_ok=True)
        self.root = root
        self.port = port or server_port()
        self.uri = f"http://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen[bytes] | None = None
        self._log = None

    def start(self, timeout: float = 180.0) -> None:
        self._log = (self.root / "server.log").open("a")
        self.proc = subprocess.Popen(
            [
                str(Path(sys.executable).with_name("mlflow")),
                "server",
                "--backend-store-uri",
                f"sqlite:///{self.root / 'server.db'}",
                "--artifacts-destination",
                str(self.root / "artifacts"),
                "--serve-artifacts",
                "--host",
                "127.0.0.1",
                "--port",
                str(self.port),
                "--workers",
                "1",
            ],
            cwd=self.root,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            env={**os.environ, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"},
            start_new_session=True,  # its own process group: stopped together below
        )
        deadline = time.monotonic() + timeout
        while True:
            try:
                with urllib.request.urlopen(f"{self.uri}/health", timeout=2) as resp:
                    if resp.read().strip() == b"OK":
                        return
            except OSError:
                pass
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self._log.flush()
                log = (self.root / "server.log").read_text()[-2000:]
                self.stop()
                raise RuntimeError(f"mlflow server did not come up: {log}")
            time.sleep(0.5)

    def __enter__(self) -> MlflowServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stop(self) -> None:
        """Stop the server's whole process group (the CLI, uvicorn and its workers)."""
        if self.proc is None:
            return
        for sig, wait in ((signal.SIGTERM, 20.0), (signal.SIGKILL, 10.0)):
            try:
                os.killpg(self.proc.pid, sig)
            except ProcessLookupError:
                break
            with suppress(subprocess.TimeoutExpired):
                self.proc.wait(wait)
                break
        self.proc = None
        if self._log is not None:
            self._log.close()
            self._log = None


@contextmanager
def mlflow_server(root: Path, start_timeout: float = 180.0) -> Iterator[str]:
    """A real ``mlflow server`` on 127.0.0.1 (:class:`MlflowServer`); yields its URI and
    stops the server (its whole process group)."""
    server = MlflowServer(root)
    server.start(start_timeout)
    try:
        yield server.uri
    finally:
        server.stop()
