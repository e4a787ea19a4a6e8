"""Episodic replay: which episodes qualify, how many updates run, and that they are the
controlled update itself (recorded per episode in MLflow)."""

from __future__ import annotations

import numpy as np
import pytest
from mlflow.tracking import MlflowClient

from cdqn.agents.episodic_replay import EpisodeTail, PopulationTail, qualifies
from cdqn.config import ReplayConfig
from cdqn.training.run import run
from tests.conftest import compose_config


@pytest.mark.parametrize(
    ("cfg", "ends", "expected"),
    [
        (ReplayConfig(repeats=0), (True, False, 0.0), False),
        (ReplayConfig(repeats=5), (True, False, 0.0), True),
        (ReplayConfig(repeats=5), (False, True, 0.0), False),
        (ReplayConfig(repeats=5, when="truncated"), (False, True, 0.0), True),
        (ReplayConfig(repeats=5, when="truncated"), (True, True, 0.0), False),
        (ReplayConfig(repeats=5, when="any"), (False, True, -3.0), True),
        (ReplayConfig(repeats=5, min_return=-480.0), (True, False, -490.0), False),
        (ReplayConfig(repeats=5, min_return=-480.0), (True, False, -300.0), True),
    ],
)
def test_which_episodes_qualify(cfg: ReplayConfig, ends: tuple, expected: bool) -> None:
    assert qualifies(cfg, *ends) is expected


def test_tails_keep_the_last_transitions_in_order() -> None:
    tail = EpisodeTail(ReplayConfig(repeats=1, last=2))
    ring = PopulationTail(k=2, n_obs=1, capacity=3)
    for t in range(4):
        tail.append(np.array([t]), t % 2, -1.0, np.array([t + 1]), t == 3)
        ring.append(np.array([[t], [10 + t]]), np.array([t % 2, 1]), np.array([-1.0, 0.0]),
                    np.array([[t + 1], [11 + t]]), np.array([t == 3, False]))  # fmt: skip
    got = tail.transitions()
    assert got.obs[:, 0].tolist() == [2.0, 3.0] and got.terminated.tolist() == [False, True]
    member = ring.transitions(1, 2)
    assert member.obs[:, 0].tolist() == [12.0, 13.0] and member.next_obs[-1, 0] == 14.0
    assert ring.transitions(0, 2).actions.tolist() == [0, 1]


def test_replayed_updates_are_recorded_and_change_learning(tracking_uri: str) -> None:
    base = ["controller=hinf_f", "network.width=32", "train.episodes=4", "train.progress=false",
            "tracking.log_model=false", f"tracking.uri={tracking_uri}"]  # fmt: skip
    # CartPole's episodes end by the pole falling (terminated) under random play
    replay = ["weights.replay.repeats=3", "weights.replay.last=2", "weights.replay.when=terminated"]
    with_replay = run(compose_config([*base, *replay]), progress=False)
    without = run(compose_config(base), progress=False)
    client = MlflowClient(tracking_uri)
    hist = client.get_metric_history(with_replay.run_id, "replay_updates")
    assert [m.value for m in sorted(hist, key=lambda m: m.step)] == [6.0] * 4
    assert {m.value for m in client.get_metric_history(without.run_id, "replay_updates")} == {0.0}
    q1 = [
        np.array([m.value for m in client.get_metric_history(r.run_id, "loss_mean")])
        for r in (with_replay, without)
    ]
    assert q1[0][0] == q1[1][0]  # the first episode is the same: replay comes after it
    assert not np.array_equal(q1[0][1:], q1[1][1:])
