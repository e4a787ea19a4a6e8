"""SIGINT/SIGTERM stop a run at an episode boundary with a checkpoint (status KILLED);
``resume=<run_id>`` continues it to a result equal to an uninterrupted run."""

from __future__ import annotations

import signal
import tempfile
from collections.abc import Callable
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

from cdqn.config import ConfigError
from cdqn.training.checkpoint import CheckpointStore
from cdqn.training.run import run
from cdqn.training.tracking import TrackingError
from tests.conftest import compose_config
from tests.helpers import (
    assert_same_run,
    episode_returns,
    finish,
    member_runs,
    read_until,
    run_cli,
    signal_table,
    signals_after_episode,
    start_cli,
)

CONTROLLED = [
    "controller=hinf",
    "controller.reset_state=false",  # controller state x_c carried across episodes
    "controller.reset_integrator=false",  # and so is x_e
    "network.width=32",
    "train.episodes=12",
    "train.progress=false",
    "seed=3",
]
DDQN = [
    "controller=ddqn",
    "controller.buffer_size=100",  # wraps around before the interruption
    "controller.learning_starts=20",
    "controller.batch_size=8",
    "controller.target_update=30",
    "network.width=32",
    "train.episodes=12",
    "train.progress=false",
    "seed=4",
]


@pytest.fixture
def signal_at(monkeypatch: pytest.MonkeyPatch) -> Callable[..., None]:
    return signals_after_episode(monkeypatch)


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> str:
    return f"sqlite:///{tmp_path_factory.mktemp('store') / 'mlflow.db'}"


@pytest.mark.parametrize(
    "overrides",
    [
        CONTROLLED,
        [*CONTROLLED, "weights.replay.sample=2", "weights.replay.buffer=64"],
        DDQN,
        [*DDQN, "network.dtype=float32"],
    ],
    ids=["hinf", "hinf-sampled", "ddqn", "ddqn-float32"],
)
def test_signal_checkpoint_resume_equals_uninterrupted(
    store: str, overrides: list[str], signal_at: Callable[..., None]
) -> None:
    client = MlflowClient(store)
    cfg = compose_config([*overrides, f"tracking.uri={store}", "train.checkpoint_every=0"])
    signal_at(4, signal.SIGTERM)
    killed = run(cfg, progress=False)
    assert (killed.status, killed.signum) == ("KILLED", signal.SIGTERM)
    info = client.get_run(killed.run_id)
    assert info.info.status == "KILLED"
    assert info.data.tags["failure_reason"].startswith("SIGTERM after episode 5 of 12")
    assert len(episode_returns(client, killed.run_id)) == 5
    assert len(signal_table(client, killed.run_id)) > 0  # flushed at the interruption
    ckpt = CheckpointStore(client, killed.run_id).load()
    assert ckpt is not None and ckpt.episode == 5

    resumed = run(compose_config([f"resume={killed.run_id}", f"tracking.uri={store}"]), False)
    assert (resumed.run_id, resumed.status) == (killed.run_id, "FINISHED")
    tags = client.get_run(killed.run_id).data.tags
    assert tags["resumed_from_episode"] == "5" and "failure_reason" not in tags
    assert tags["previous_failure_reason"].startswith("SIGTERM")

    reference = run(compose_config([*overrides, f"tracking.uri={store}"]), progress=False)
    assert_same_run(client, killed.run_id, reference.run_id)


def test_second_signal_stops_at_once_and_resumes_from_periodic_checkpoint(
    store: str, signal_at: Callable[..., None]
) -> None:
    client = MlflowClient(store)
    cfg = compose_config([*CONTROLLED, f"tracking.uri={store}", "train.checkpoint_every=2"])
    signal_at(6, signal.SIGINT, signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        run(cfg, progress=False)
    killed = client.search_runs(
        [client.get_experiment_by_name("cdqn").experiment_id],
        "attributes.status = 'KILLED'",
        order_by=["attributes.start_time DESC"],
    )[0]
    reason = killed.data.tags["failure_reason"]
    assert "the last checkpoint is at episode 6" in reason, reason
    assert len(episode_returns(client, killed.info.run_id)) == 7  # more than the checkpoint holds

    # slots a, b, a took episodes 2, 4, 6; spoil the newest (as a write cut short by a hard
    # kill would): resume falls back to the other slot
    with tempfile.TemporaryDirectory() as tmp:
        bad = Path(tmp) / "state.pt"
        bad.write_bytes(b"truncated")
        client.log_artifact(killed.info.run_id, str(bad), "checkpoint/slot-a")
    ckpt = CheckpointStore(client, killed.info.run_id).load()
    assert ckpt is not None and ckpt.episode == 4

    run(compose_config([f"resume={killed.info.run_id}", f"tracking.uri={store}"]), False)
    reference = run(compose_config([*CONTROLLED, f"tracking.uri={store}"]), progress=False)
    assert_same_run(client, killed.info.run_id, reference.run_id)


def test_resume_refuses_what_cannot_be_continued(store: str) -> None:
    finished = run(compose_config([*CONTROLLED, "train.episodes=2", f"tracking.uri={store}"]))
    with pytest.raises(ConfigError, match="FINISHED; there is nothing to continue"):
        run(compose_config([f"resume={finished.run_id}", f"tracking.uri={store}"]))
    with pytest.raises(TrackingError, match="resume=0123456789abcdef: no such run"):
        run(compose_config(["resume=0123456789abcdef", f"tracking.uri={store}"]))
    diverged = run(
        compose_config(
            ["controller=none", "train.lr=0.05", "network.width=32", f"tracking.uri={store}"]
        ),
        progress=False,
    )
    assert diverged.status == "FAILED"
    with pytest.raises(ConfigError, match="would diverge again"):
        run(compose_config([f"resume={diverged.run_id}", f"tracking.uri={store}"]))


@pytest.mark.slow
def test_sigterm_to_training_process_then_cli_resume(tmp_path: Path, store: str) -> None:
    """The real thing end to end: a training subprocess gets SIGTERM, a second process
    resumes it from the store, and the returns equal an uninterrupted run's."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    args = [*CONTROLLED, "train.episodes=400", "train.checkpoint_every=25", f"tracking.uri={uri}"]
    args.append("hydra.verbose=cdqn")  # checkpoints are logged at DEBUG
    proc, seen = start_cli("cdqn.train", args, tmp_path), []
    try:
        read_until(proc, "checkpoint at episode 25", seen)  # the first periodic checkpoint
        proc.send_signal(signal.SIGTERM)
    finally:
        output = finish(proc, seen)
    assert proc.returncode == 128 + signal.SIGTERM, output
    client = MlflowClient(uri)
    (killed,) = client.search_runs(["1"])
    assert killed.info.status == "KILLED"
    stopped_at = len(episode_returns(client, killed.info.run_id))
    assert 25 <= stopped_at < 400, output

    resumed = run_cli(
        "cdqn.train", [f"resume={killed.info.run_id}", f"tracking.uri={uri}"], tmp_path
    )
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"resuming MLflow run {killed.info.run_id} at episode {stopped_at} of 400" in (
        resumed.stdout + resumed.stderr
    )
    reference = run(compose_config([*args[:-1], "train.checkpoint_every=0", f"tracking.uri={uri}"]))
    assert_same_run(client, killed.info.run_id, reference.run_id)


POPULATION = [*CONTROLLED, "train.population=3", "train.episodes=300"]


@pytest.mark.slow
def test_sigterm_to_population_process_then_resume_equals_uninterrupted(tmp_path: Path) -> None:
    """A real population process gets SIGTERM after its first checkpoint; every member is
    closed KILLED with the resume command; ``resume=<one member>`` continues all of them, and
    every member's returns and signal rows equal those of an uninterrupted population."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    args = [*POPULATION, "train.checkpoint_every=20", f"tracking.uri={uri}", "hydra.verbose=cdqn"]
    proc, seen = start_cli("cdqn.train", args, tmp_path), []
    try:
        read_until(proc, "checkpoint at episode", seen)  # the first population checkpoint
        proc.send_signal(signal.SIGTERM)
    finally:
        output = finish(proc, seen)
    assert proc.returncode == 128 + signal.SIGTERM, output
    client = MlflowClient(uri)
    killed = client.search_runs(["1"])
    assert len(killed) == 3 and {r.info.status for r in killed} == {"KILLED"}, output
    for r in killed:
        reason = r.data.tags["failure_reason"]
        assert reason.startswith("SIGTERM during episode"), reason
        assert f"checkpoint written, continue the population with resume={r.info.run_id}" in (
            reason
        )
        assert len(episode_returns(client, r.info.run_id)) < 300
    pid = {r.data.tags["population_id"] for r in killed}
    assert len(pid) == 1

    first = killed[0].info.run_id
    resumed = run_cli("cdqn.train", [f"resume={first}", f"tracking.uri={uri}"], tmp_path)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    for r in killed:
        assert f"resuming MLflow run {r.info.run_id}" in resumed.stdout + resumed.stderr

    reference = run(
        compose_config([*POPULATION, "train.checkpoint_every=0", f"tracking.uri={uri}"])
    )
    assert reference.status == "FINISHED"
    ours = member_runs(client, [r.info.run_id for r in killed])
    theirs = member_runs(client, reference.run_id.split(","))
    assert sorted(ours) == sorted(theirs) == ["3", "4", "5"]
    for seed, run_id in ours.items():
        assert len(episode_returns(client, run_id)) == 300
        assert_same_run(client, run_id, theirs[seed])
        tags = client.get_run(run_id).data.tags
        assert tags["resume_count"] == "1" and "failure_reason" not in tags


@pytest.mark.parametrize(
    ("seed", "settings"),
    [
        (11, CONTROLLED),
        # episodic replay of every episode: a mid-episode checkpoint holds the episode so far
        (
            21,
            [
                *CONTROLLED,
                "weights.replay.repeats=2",
                "weights.replay.last=null",
                "weights.replay.when=any",
            ],
        ),
        (31, DDQN),  # a Double DQN population: buffers, target networks, cached passes
        # sampled replay: each member's buffer and its sampling stream
        (51, [*CONTROLLED, "weights.replay.sample=2", "weights.replay.buffer=64"]),
        # ε per episode: the draws made ahead but not yet taken are part of the checkpoint
        (41, [*CONTROLLED, "train.eps_schedule=episode", "train.eps_dec=0.05"]),
    ],
)
def test_population_resumes_from_a_periodic_checkpoint(
    store: str, signal_at: Callable[..., None], seed: int, settings: list[str]
) -> None:
    """Two signals stop a population at once (mid-step, no checkpoint then): resume goes
    back to the last periodic checkpoint, whose members are mid-episode, and still equals
    an uninterrupted population."""
    client = MlflowClient(store)
    base = [*settings, "train.population=3", f"seed={seed}", f"tracking.uri={store}"]
    signal_at(7, signal.SIGINT, signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        run(compose_config([*base, "train.checkpoint_every=2"]), progress=False)
    exp = client.get_experiment_by_name("cdqn").experiment_id
    killed = client.search_runs([exp], f"tags.seed = '{seed}' and attributes.status = 'KILLED'")
    assert len(killed) == 1
    reason = killed[0].data.tags["failure_reason"]
    assert "the last checkpoint is at episode" in reason, reason
    resumed = run(compose_config([f"resume={killed[0].info.run_id}", f"tracking.uri={store}"]))
    assert resumed.status == "FINISHED"
    reference = run(compose_config([*base, "train.checkpoint_every=0"]), progress=False)
    ours = member_runs(client, resumed.run_id.split(","))
    theirs = member_runs(client, reference.run_id.split(","))
    assert sorted(ours) == sorted(theirs) == [str(seed + i) for i in range(3)]
    for seed, run_id in ours.items():
        assert_same_run(client, run_id, theirs[seed])
