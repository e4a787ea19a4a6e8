"""``tracking=server``: a real MLflow tracking server takes whole runs, checkpoints and
resumes; an unreachable or wrong URI is refused at start, within seconds."""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Callable, Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pandas as pd
import pytest
from mlflow.tracking import MlflowClient

from cdqn.config import EvaluateConfig, TrackingConfig
from cdqn.evaluate import evaluate
from cdqn.training.run import run
from cdqn.training.tracking import TrackingError, check_tracking
from tests.conftest import TINY, compose_config
from tests.helpers import (
    MlflowServer,
    assert_same_run,
    episode_returns,
    finish,
    free_port,
    member_runs,
    mlflow_server,
    read_until,
    run_cli,
    signals_after_episode,
    start_cli,
)


class _NotMlflow(BaseHTTPRequestHandler):
    """Some other web service: 404 everywhere, or 200 with a page that is not MLflow's."""

    status = 404

    def do_GET(self) -> None:
        self.send_response(self.status)
        self.end_headers()
        self.wfile.write(b"<html>hello</html>")

    def log_message(self, *args: object) -> None:
        pass


@pytest.fixture
def other_service() -> Iterator[Callable[[int], str]]:
    servers: list[ThreadingHTTPServer] = []

    def start(status: int) -> str:
        handler = type("Handler", (_NotMlflow,), {"status": status})
        server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        servers.append(server)
        return f"http://127.0.0.1:{server.server_address[1]}"

    yield start
    for server in servers:
        server.shutdown()
        server.server_close()


def test_unreachable_server_refused_within_seconds(tmp_path: Path) -> None:
    uri = f"http://127.0.0.1:{free_port()}"
    t0 = time.monotonic()
    with pytest.raises(TrackingError) as exc:
        check_tracking(uri, timeout=2.0)
    assert time.monotonic() - t0 < 5
    msg = str(exc.value)
    assert msg.startswith(f"tracking.uri='{uri}': no MLflow tracking server reachable")
    assert "Connection refused" in msg and "mlflow server" in msg

    cfg = compose_config([*TINY, "tracking=server", f"tracking.uri={uri}"])
    t0 = time.monotonic()
    with pytest.raises(TrackingError, match="no MLflow tracking server reachable"):
        run(cfg, progress=False)
    assert time.monotonic() - t0 < 5  # refused before anything is built or trained


@pytest.mark.parametrize("status", [404, 200])
def test_wrong_uri_refused(other_service: Callable[[int], str], status: int) -> None:
    uri = other_service(status)
    with pytest.raises(TrackingError, match="not an MLflow tracking server"):
        check_tracking(uri, timeout=2.0)


def test_unwritable_local_store_refused(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(TrackingError, match="cannot create"):
        check_tracking(f"sqlite:///{blocker}/sub/mlflow.db")


def test_cli_unreachable_server_exit_2(tmp_path: Path) -> None:
    port = free_port()
    proc = run_cli(
        "cdqn.train", [*TINY, "tracking=server", f"tracking.uri=http://127.0.0.1:{port}"], tmp_path
    )
    assert proc.returncode == 2, proc.stderr[-2000:]
    out = proc.stdout + proc.stderr
    assert f"tracking.uri='http://127.0.0.1:{port}': no MLflow tracking server reachable" in out
    assert "Traceback" not in out


def test_server_uri_from_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://127.0.0.1:5999")
    assert compose_config(["tracking=server"]).tracking.uri == "http://127.0.0.1:5999"


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Path]]:
    root = tmp_path_factory.mktemp("mlflow-server")
    with mlflow_server(root) as uri:
        yield uri, root


@pytest.fixture
def signal_at(monkeypatch: pytest.MonkeyPatch) -> Callable[..., None]:
    return signals_after_episode(monkeypatch)


@pytest.mark.slow
def test_training_against_a_real_server(server: tuple[str, Path]) -> None:
    uri, root = server
    overrides = [*TINY, "train.episodes=5", "train.checkpoint_every=2", "controller=hinf_f"]
    result = run(compose_config([*overrides, "tracking=server", f"tracking.uri={uri}"]))
    assert result.status == "FINISHED"
    client = MlflowClient(uri)
    info = client.get_run(result.run_id)
    assert info.info.status == "FINISHED"
    assert info.data.params["tracking.uri"] == uri
    assert len(client.get_metric_history(result.run_id, "episode_return")) == 5
    steps = pd.read_parquet(client.download_artifacts(result.run_id, "signals/steps.parquet"))
    assert steps["episode"].max() == 4
    # artifacts went through the server into its artifact root
    (run_dir,) = (root / "artifacts").rglob(result.run_id)  # <experiment>/<run id>/artifacts
    for name in (
        "config.yaml",
        "model/q_network.pt",
        "model/spec.json",
        "signals/steps.parquet",
    ):
        assert (run_dir / "artifacts" / name).is_file(), name
    # checkpoints were written (every 2 episodes) and deleted through the server once the run
    # FINISHED: there is nothing left to resume
    assert not list((run_dir / "artifacts").rglob("state.pt"))
    assert client.list_artifacts(result.run_id, "checkpoint") == []

    evaluation = evaluate(
        EvaluateConfig(run_id=result.run_id, episodes=3, tracking=TrackingConfig(uri=uri))
    )
    assert len(evaluation.returns) == 3
    metrics = client.get_run(result.run_id).data.metrics
    assert metrics["eval_return_mean"] == pytest.approx(evaluation.mean)


@pytest.mark.slow
def test_interrupt_and_resume_through_the_server(
    server: tuple[str, Path], signal_at: Callable[..., None]
) -> None:
    uri, _ = server
    overrides = [*TINY, "train.episodes=8", "controller=hinf", "seed=2", f"tracking.uri={uri}"]
    signal_at(2, signal.SIGINT)
    killed = run(compose_config(overrides), progress=False)
    assert killed.status == "KILLED"
    resumed = run(compose_config([f"resume={killed.run_id}", f"tracking.uri={uri}"]))
    assert resumed.status == "FINISHED"
    reference = run(compose_config(overrides), progress=False)
    client = MlflowClient(uri)

    def returns(run_id: str) -> list[float]:
        history = client.get_metric_history(run_id, "episode_return")
        return [m.value for m in sorted(history, key=lambda m: m.step)]

    assert returns(killed.run_id) == returns(reference.run_id)
    assert len(returns(killed.run_id)) == 8


OUTAGE = [
    "network=small",
    "controller=hinf",
    "train.episodes=400",
    "train.progress=false",
    "train.checkpoint_every=50",
    "seed=5",
]


@pytest.mark.slow
def test_a_server_that_goes_away_and_comes_back(tmp_path: Path) -> None:
    """A real server stopped during a run: for less than ``tracking.retry_s`` the run waits
    and loses nothing; for longer, it checkpoints locally, exits 75 naming the server and
    the file, and ``resume=`` (server back) continues it to the uninterrupted result."""
    with MlflowServer(tmp_path / "server") as server:
        uri = server.uri
        # 1. an outage within tracking.retry_s=120, until the run has met it: the run
        # finishes, nothing lost
        args = [*OUTAGE, f"tracking.uri={uri}", "tracking.retry_s=120"]
        args.append("hydra.verbose=cdqn")  # checkpoints are logged at DEBUG
        proc, seen = start_cli("cdqn.train", args, tmp_path), []
        try:
            read_until(proc, "checkpoint at episode 50", seen)
            server.stop()
            read_until(proc, f"tracking server {uri} not answering", seen)
            server.start()
        finally:
            output = finish(proc, seen, timeout=300)
        assert proc.returncode == 0, output[-3000:]
        assert f"tracking server {uri} not answering" in output
        client = MlflowClient(uri)
        (blinked,) = client.search_runs(["1"])
        assert blinked.info.status == "FINISHED"
        assert len(episode_returns(client, blinked.info.run_id)) == 400

        # 2. an outage longer than tracking.retry_s=3: local checkpoint, exit 75, resume
        local = tmp_path / "local-checkpoints"
        args = [
            *OUTAGE,
            "seed=6",
            f"tracking.uri={uri}",
            "tracking.retry_s=3",
            f"tracking.local_checkpoints={local}",
        ]
        args.append("hydra.verbose=cdqn")  # checkpoints are logged at DEBUG
        proc, seen = start_cli("cdqn.train", args, tmp_path), []
        try:
            read_until(proc, "checkpoint at episode 50", seen)
            run_id = next(
                r.info.run_id for r in client.search_runs(["1"]) if r.data.tags["seed"] == "6"
            )
            server.stop()
        finally:
            output = finish(proc, seen)
        assert proc.returncode == 75, output[-3000:]
        path = local / run_id / "state.pt"
        assert f"the tracking server {uri} did not answer" in output
        assert f"written locally to {path}" in output and path.is_file()
        assert f"resume={run_id}" in output and "Traceback" not in output
        server.start()
        assert client.get_run(run_id).info.status == "RUNNING"
        resumed = run_cli(
            "cdqn.train",
            [f"resume={run_id}", f"tracking.uri={uri}", f"tracking.local_checkpoints={local}"],
            tmp_path,
        )
        assert resumed.returncode == 0, resumed.stderr[-3000:]
        assert "continuing from the local checkpoint" in resumed.stdout + resumed.stderr
        assert not path.exists()
        reference = run(
            compose_config([*OUTAGE, "seed=6", "train.checkpoint_every=0", f"tracking.uri={uri}"])
        )
        assert_same_run(client, run_id, reference.run_id)
        record = client.get_run(run_id)
        print(
            "outage run:",
            record.info.status,
            sorted(record.data.tags),
            {k: len(client.get_metric_history(run_id, k)) for k in record.data.metrics},
        )


POPULATION_OUTAGE = [*OUTAGE, "train.population=3", "train.checkpoint_every=10", "seed=7"]


@pytest.mark.slow
def test_a_population_whose_server_stays_away(tmp_path: Path) -> None:
    """A real server stopped during a population for longer than ``tracking.retry_s``: the
    population stops at the end of a step, writes every member's checkpoint locally, ends
    with one message naming the server and the local checkpoints, exits 75 with its runs
    RUNNING; ``resume=`` (server back) continues every member from the local checkpoints to
    the returns and signal rows of an uninterrupted population."""
    with MlflowServer(tmp_path / "server") as server:
        uri = server.uri
        local = tmp_path / "local-checkpoints"
        args = [
            *POPULATION_OUTAGE,
            f"tracking.uri={uri}",
            "tracking.retry_s=3",
            f"tracking.local_checkpoints={local}",
        ]
        args.append("hydra.verbose=cdqn")  # checkpoints are logged at DEBUG
        proc, seen = start_cli("cdqn.train", args, tmp_path), []
        try:
            read_until(proc, "checkpoint at episode", seen)  # the population's first
            client = MlflowClient(uri)
            ids = sorted(r.info.run_id for r in client.search_runs(["1"]))
            first = member_runs(client, ids)["7"]  # the message names the first seed's run
            server.stop()
        finally:
            output = finish(proc, seen)
        assert proc.returncode == 75, output[-3000:]
        assert len(ids) == 3 and "Traceback" not in output
        (message,) = [line for line in output.splitlines() if "did not answer" in line]
        assert f"the tracking server {uri} did not answer" in message
        assert f"written locally to {local.resolve()}/<run id>/" in message
        assert (
            f"resume={first} tracking.uri={uri} "
            f"tracking.local_checkpoints={local.resolve()}" in message
        )
        written = {p.parent.name for p in local.glob("*/*.pt")}
        assert written == set(ids), (written, output[-3000:])

        server.start()
        assert {client.get_run(r).info.status for r in ids} == {"RUNNING"}
        stored = {r: len(episode_returns(client, r)) for r in ids}
        resumed = run_cli(
            "cdqn.train",
            # any member continues the whole population
            [f"resume={ids[1]}", f"tracking.uri={uri}", f"tracking.local_checkpoints={local}"],
            tmp_path,
        )
        out = resumed.stdout + resumed.stderr
        assert resumed.returncode == 0, out[-3000:]
        assert "from its local checkpoints" in out or "closing run" in out, out[-3000:]
        assert not list(local.glob("*/*.pt"))
        reference = run(
            compose_config([*POPULATION_OUTAGE, "train.checkpoint_every=0", f"tracking.uri={uri}"])
        )
        ours = member_runs(client, ids)
        theirs = member_runs(client, reference.run_id.split(","))
        assert sorted(ours) == sorted(theirs) == ["7", "8", "9"]
        for seed, run_id in ours.items():
            assert len(episode_returns(client, run_id)) == 400 > stored[run_id]
            assert_same_run(client, run_id, theirs[seed])
            assert client.get_run(run_id).data.tags["resume_count"] == "1"
        print("population outage:", message)
