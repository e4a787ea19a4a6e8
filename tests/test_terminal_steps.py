"""Termination is not truncation: no bootstrap when the MDP ends, a bootstrap at the time
limit (gymnasium's ``terminated`` / ``truncated``), in single runs and populations."""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf

from cdqn.envs import make_env
from cdqn.training.build import build
from cdqn.training.loop import TrainState, train
from cdqn.training.signals import SignalBuffer
from tests.conftest import compose_config

COLS = {"reward": 2, "q1": 3, "q2": 4, "loss": 9}


def _last_rows(overrides: list[str]) -> tuple[np.ndarray, list[float]]:
    """The last signal row of every episode of a short ``none`` run (u = 0, so
    loss = ½ (r + γ Q̂2 − Q1)²)."""
    conf = OmegaConf.to_object(
        compose_config(["controller=none", "network.width=32", "train.progress=false", *overrides])
    )
    env = make_env(conf.env)
    job = build(conf, env)
    signals, state = SignalBuffer(), TrainState()
    train(env, job.agent, episodes=conf.train.episodes, seed=0, discount=1.0, q_limit=1e6,
          signals=signals, state=state, progress=False)  # fmt: skip
    rows = signals.state()
    last = np.flatnonzero(np.diff(rows[:, 0], append=rows[-1, 0] + 1))
    return rows[last], state.returns


def _bootstrapped(row: np.ndarray) -> bool:
    r, q1, q2, loss = (row[COLS[k]] for k in ("reward", "q1", "q2", "loss"))
    with_q2, without = 0.5 * (r + q2 - q1) ** 2, 0.5 * (r - q1) ** 2
    assert with_q2 != pytest.approx(without, rel=1e-6)  # the two targets differ
    if loss == pytest.approx(with_q2, rel=1e-9):
        return True
    assert loss == pytest.approx(without, rel=1e-9)
    return False


def test_terminal_steps_do_not_bootstrap_and_truncated_steps_do() -> None:
    # CartPole's pole falls within 200 steps under random play: every episode terminates
    rows, returns = _last_rows(["train.episodes=4", "env.max_episode_steps=200"])
    assert max(returns) < 200
    assert not any(_bootstrapped(r) for r in rows)
    # a cap of 5 steps truncates every episode before the pole falls
    rows, returns = _last_rows(["train.episodes=4", "env.max_episode_steps=5"])
    assert returns == [5.0] * 4
    assert all(_bootstrapped(r) for r in rows)


def test_research_code_bootstrap_at_terminal_steps_is_an_option() -> None:
    rows, returns = _last_rows(["train.episodes=3", "train.bootstrap_terminal=true"])
    assert max(returns) < 200
    assert all(_bootstrapped(r) for r in rows)
