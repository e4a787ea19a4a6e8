"""``python -m cdqn.evaluate``: the stored network, greedy, its own seeds, logged to the run."""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest
import torch
from mlflow.tracking import MlflowClient

from cdqn.config import ConfigError, EvaluateConfig, TrackingConfig
from cdqn.evaluate import evaluate
from cdqn.network import load_network
from cdqn.training.run import run
from cdqn.training.tracking import TrackingError
from tests.conftest import TINY, compose_config
from tests.helpers import run_cli


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, str]:
    """(store URI, run id) of a short run on CartPole with only the pole features."""
    store = f"sqlite:///{tmp_path_factory.mktemp('store') / 'mlflow.db'}"
    overrides = [*TINY, "env=cartpole_pole", "controller=hinf_f", f"tracking.uri={store}"]
    return store, run(compose_config(overrides), progress=False).run_id


def _config(store: str, run_id: str, **kw: object) -> EvaluateConfig:
    return EvaluateConfig(run_id=run_id, tracking=TrackingConfig(uri=store), **kw)


def test_greedy_returns_of_the_stored_network(trained: tuple[str, str]) -> None:
    store, run_id = trained
    result = evaluate(_config(store, run_id, episodes=4, seed=123, log=False))
    # the same episodes by hand: stored network, argmax Q, env of the run, seeds 123..126
    client = MlflowClient(store)
    with tempfile.TemporaryDirectory() as tmp:
        net = load_network(Path(client.download_artifacts(run_id, "model", tmp)))
    env = gym.make("CartPole-v1", max_episode_steps=200)
    expected = []
    for seed in range(123, 127):
        obs, _ = env.reset(seed=seed)
        total, done = 0.0, False
        while not done:
            x = torch.as_tensor(obs[[2, 3]], dtype=torch.float64)  # env.obs_indices of the run
            obs, reward, terminated, truncated, _ = env.step(int(net(x).argmax()))
            total, done = total + float(reward), terminated or truncated
        expected.append(total)
    np.testing.assert_array_equal(result.returns, expected)
    assert result.summary().startswith(f"run {run_id} on CartPole-v1: greedy return ")


def test_evaluation_logged_to_the_same_run(trained: tuple[str, str]) -> None:
    store, run_id = trained
    result = evaluate(_config(store, run_id, episodes=5, seed=7))
    assert np.array_equal(
        result.returns, evaluate(_config(store, run_id, episodes=5, seed=7, log=False)).returns
    )
    client = MlflowClient(store)
    info = client.get_run(run_id)
    assert info.info.status == "FINISHED"  # unchanged
    assert info.data.metrics["eval_return_mean"] == pytest.approx(result.mean)
    assert info.data.metrics["eval_return_std"] == pytest.approx(result.std)
    assert info.data.metrics["eval_episodes"] == 5
    assert info.data.tags["eval_seed"] == "7"
    (step,) = {m.step for m in client.get_metric_history(run_id, "eval_return_mean")}
    assert step == 3  # the training episodes
    with tempfile.TemporaryDirectory() as tmp:
        frame = pd.read_csv(
            client.download_artifacts(run_id, "evaluation/returns-seed7-n5.csv", tmp)
        )
    assert frame["seed"].tolist() == [7, 8, 9, 10, 11]
    np.testing.assert_array_equal(frame["return"], result.returns)


def test_refuses_unknown_run_and_bad_settings(trained: tuple[str, str]) -> None:
    store, _ = trained
    with pytest.raises(TrackingError, match="run_id=nope: no such run"):
        evaluate(_config(store, "nope"))
    with pytest.raises(ConfigError, match="episodes=0: must be > 0"):
        evaluate(_config(store, "x", episodes=0))


@pytest.mark.slow
def test_cli(trained: tuple[str, str], tmp_path: Path) -> None:
    store, run_id = trained
    proc = run_cli(
        "cdqn.evaluate", [f"run_id={run_id}", "episodes=3", f"tracking.uri={store}"], tmp_path
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    pattern = rf"run {run_id} on CartPole-v1: greedy return \d+\.\d\d ± \d+\.\d\d over 3 episodes"
    assert re.search(pattern, proc.stdout), proc.stdout
    missing = run_cli("cdqn.evaluate", ["episodes=3"], tmp_path)
    assert missing.returncode == 2
    assert "run_id: required, give run_id=<value>" in missing.stderr
