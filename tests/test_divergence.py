"""A diverging run ends FAILED with its reason and keeps everything recorded up to then;
in a multirun the other jobs go on and the sweep ends with a summary."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from mlflow.tracking import MlflowClient

from cdqn.agents.base import StepRecord
from cdqn.network import load_network
from cdqn.training.callbacks import JOB_FILE, format_summary, summarize
from cdqn.training.divergence import check_step, failure_reason, is_divergence
from cdqn.training.loop import DivergenceError, train
from cdqn.training.run import run
from cdqn.training.signals import SignalBuffer
from tests.conftest import TINY, compose_config
from tests.helpers import run_cli

DIVERGES = ["controller=none", "train.lr=0.05", "train.episodes=50"]
"""Plain semi-gradient Q-learning with a large step: |Q| > 1e6 in the third episode."""


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> str:
    return f"sqlite:///{tmp_path_factory.mktemp('store') / 'mlflow.db'}"


def _where(reason: str) -> tuple[int, int]:
    m = re.search(r"\(episode (\d+), step (\d+)\)", reason)
    assert m, reason
    return int(m[1]), int(m[2])


def test_diverged_run_is_failed_and_keeps_everything(store: str) -> None:
    result = run(compose_config([*TINY, *DIVERGES, f"tracking.uri={store}"]), False)
    assert result.status == "FAILED"
    client = MlflowClient(store)
    info = client.get_run(result.run_id)
    assert info.info.status == "FAILED"
    reason = info.data.tags["failure_reason"]
    assert reason.startswith("diverged: |Q| = ") and "above train.q_limit=1e+06" in reason
    episode, step = _where(reason)
    assert episode >= 1

    # metrics of every completed episode were flushed
    history = client.get_metric_history(result.run_id, "episode_return")
    assert sorted(m.step for m in history) == list(range(episode))
    # per-step signals up to and including the diverging step
    steps = pd.read_parquet(client.download_artifacts(result.run_id, "signals/steps.parquet"))
    lengths = [m.value for m in client.get_metric_history(result.run_id, "episode_length")]
    assert len(steps) == sum(lengths) + step + 1
    last = steps.iloc[-1]
    assert (last["episode"], last["step"]) == (episode, step)
    assert max(abs(last["q1"]), abs(last["q2"])) > 1e6
    assert client.download_artifacts(result.run_id, "signals/fft.parquet")
    # and the network as it was when learning blew up
    net = load_network(Path(client.download_artifacts(result.run_id, "model")))
    assert net.spec.width == 32


@pytest.mark.filterwarnings("ignore:overflow:RuntimeWarning")
def test_non_finite_values_are_divergence(store: str) -> None:
    overrides = [*TINY, "controller=none", "train.lr=1e3", "train.q_limit=inf"]
    result = run(compose_config([*overrides, f"tracking.uri={store}"]), False)
    info = MlflowClient(store).get_run(result.run_id)
    assert info.info.status == "FAILED"
    assert info.data.tags["failure_reason"].startswith("diverged: non-finite")


class ScriptedAgent:
    """Replays a list of step records; one action, no learning."""

    def __init__(self, records: list[StepRecord], x_c: np.ndarray | None = None) -> None:
        self.records = iter(records)
        self.epsilon = 0.0
        self.controller = type("Ctrl", (), {"x": x_c})()

    def act(self, obs: np.ndarray) -> int:
        return 0

    def update(self, *args: Any) -> StepRecord:
        return next(self.records)

    def start_episode(self) -> None:
        pass

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        pass


def _rec(loss: float = 1.0, q: float = 1.0, u: float = 0.0, x_e: float = 0.0) -> StepRecord:
    return StepRecord(loss, q, q, u, x_e, 1.0, 1.0)


def _train(records: list[StepRecord], x_c: np.ndarray | None = None, episodes: int = 1):
    import gymnasium as gym

    env = gym.make("CartPole-v1", max_episode_steps=len(records) // episodes)
    try:
        return train(
            env,
            ScriptedAgent(records, x_c),
            episodes=episodes,
            seed=0,
            discount=1.0,
            q_limit=100.0,
            signals=SignalBuffer(),
            progress=False,
        )
    finally:
        env.close()


@pytest.mark.parametrize(
    ("records", "message"),
    [
        ([_rec(), _rec(q=float("nan"))], "non-finite Q1 = nan"),
        ([_rec(), _rec(u=float("inf"))], "non-finite u = inf"),
        ([_rec(), _rec(x_e=float("-inf"))], "non-finite x_e = -inf"),
        ([_rec(), _rec(loss=float("inf"))], "non-finite loss = inf"),
        ([_rec(), _rec(loss=float("nan"))], "non-finite loss = nan"),
        ([_rec(), _rec(q=-101.0)], "|Q| = 101 above train.q_limit=100"),
    ],
)
def test_each_divergence_signal_is_caught(records: list[StepRecord], message: str) -> None:
    with pytest.raises(DivergenceError, match=re.escape(message)) as exc:
        _train([*records, _rec(), _rec()])
    assert (exc.value.episode, exc.value.step) == (0, 1)


def test_nan_loss_before_any_update_is_not_divergence() -> None:
    nan = float("nan")
    state = _train([_rec(loss=nan), _rec(loss=nan), _rec(), _rec()])  # Double DQN warm-up
    assert state.episode == 1


def test_non_finite_controller_state_is_divergence() -> None:
    with pytest.raises(DivergenceError, match="non-finite controller state"):
        _train([_rec(), _rec()], x_c=np.array([0.0, np.nan]))
    assert _train([_rec(), _rec()], x_c=np.zeros(2)).episode == 1


def test_one_check_for_every_run() -> None:
    """The step test a single run and a population member share: a NaN loss passes only
    before the first finite one, and a run it fails is the one resume refuses."""
    fine = StepRecord(0.5, 1.0, 1.0, 0.0, 0.0, 1.0, 1.0)
    no_update = fine._replace(loss=float("nan"))
    assert check_step(no_update, 1e6, False, 0, 0) is False
    assert check_step(fine, 1e6, False, 0, 1) is True
    with pytest.raises(
        DivergenceError, match=r"non-finite loss = nan \(episode 0, step 2\)"
    ) as exc:
        check_step(no_update, 1e6, True, 0, 2)
    reason = failure_reason(exc.value)
    assert is_divergence("FAILED", reason)
    assert not is_divergence("KILLED", reason)
    assert not is_divergence("FAILED", "RuntimeError: boom")


def test_summary_lists_failed_jobs_with_reasons(tmp_path: Path) -> None:
    outcomes = [
        ("FINISHED", "r0", None, ["seed=0"]),
        ("FAILED", "r1", "diverged: |Q| = 2e+06 above train.q_limit=1e+06 (episode 3, step 9)", []),
        ("REFUSED", None, "invalid configuration: network.width=0", ["network.width=0"]),
    ]
    for num, (status, run_id, reason, overrides) in enumerate(outcomes):
        job = tmp_path / str(num)
        (job / ".hydra").mkdir(parents=True)
        (job / JOB_FILE).write_text(
            json.dumps(
                {
                    "job": num,
                    "overrides": overrides,
                    "status": status,
                    "run_id": run_id,
                    "reason": reason,
                    "final_score": None,
                }
            )
        )
    (tmp_path / "3" / ".hydra").mkdir(parents=True)  # a job that never wrote its result
    (tmp_path / "3" / ".hydra" / "overrides.yaml").write_text("- seed=3\n")
    jobs = summarize(tmp_path)
    assert [j["status"] for j in jobs] == ["FINISHED", "FAILED", "REFUSED", "UNKNOWN"]
    text = format_summary(jobs, tmp_path)
    assert text.splitlines()[0] == (
        f"cdqn multirun {tmp_path}: 4 jobs: 1 FAILED, 1 FINISHED, 1 REFUSED, 1 UNKNOWN"
    )
    assert "-> diverged: |Q| = 2e+06" in text and "-> invalid configuration" in text
    assert "seed=3" in text and "no result" in text


@pytest.mark.slow
def test_multirun_goes_on_and_summarises_failures(tmp_path: Path) -> None:
    sweep = tmp_path / "sweep"
    proc = run_cli(
        "cdqn.train",
        [
            "-m",
            "train.lr=0.05,5e-5",
            "controller=none",
            "network.width=32",
            "train.episodes=20",
            "train.progress=false",
            f"hydra.sweep.dir={sweep}",
        ],
        tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout
    assert f"cdqn multirun {sweep}: 2 jobs: 1 FAILED, 1 FINISHED" in out
    score = r"score +-?\d+\.\d\d \((not solved|solved at episode \d+)\)"
    assert re.search(rf"0  FAILED    run \w+  {score}  train.lr=0.05 controller=none", out), out
    assert "-> diverged: |Q| = " in out
    assert re.search(rf"1  FINISHED  run \w+  {score}  train.lr=5e-0?5 controller=none", out), out

    jobs = json.loads((sweep / "summary.json").read_text())
    assert [j["status"] for j in jobs] == ["FAILED", "FINISHED"]
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    for job in jobs:
        info = client.get_run(job["run_id"])
        assert info.info.status == job["status"]
    assert client.get_run(jobs[0]["run_id"]).data.tags["failure_reason"] == jobs[0]["reason"]


@pytest.mark.slow
def test_cli_single_diverged_run_exits_1(tmp_path: Path) -> None:
    proc = run_cli("cdqn.train", [*TINY, *DIVERGES], tmp_path)
    assert proc.returncode == 1, proc.stderr[-3000:]
    out = proc.stdout + proc.stderr
    assert re.search(r"run \w+ FAILED: diverged: \|Q\| = \S+ above train.q_limit=1e\+06", out), out
    assert "Traceback" not in out
