"""ε-greedy exploration schedules (:class:`cdqn.agents.base.EpsilonGreedy`)."""

from __future__ import annotations

import numpy as np
import pytest

from cdqn.agents.base import EpsilonGreedy
from cdqn.config import TrainConfig


def _explore(schedule: str, steps: int, **train: float) -> tuple[np.ndarray, int, float]:
    """ε before each of ``steps`` steps, the number of random actions, and ε after them."""
    cfg = TrainConfig(eps_schedule=schedule, **{"eps_end": 0.05, "eps_dec": 1e-3, **train})
    explorer = EpsilonGreedy(cfg, 3, np.random.default_rng(0))
    eps, random = np.empty(steps), 0
    for t in range(steps):
        eps[t] = explorer.epsilon
        random += explorer.explore() is not None
    return eps, random, explorer.epsilon


def test_step_schedule_is_linear_in_steps_down_to_its_floor() -> None:
    eps, random, last = _explore("step", 2000)
    np.testing.assert_allclose(eps, np.maximum(0.05, 1.0 - 1e-3 * np.arange(2000)), atol=1e-12)
    assert last == 0.05
    assert 0 < random < 2000


def test_random_action_schedule_falls_only_with_random_actions() -> None:
    """The research code's schedule: greedy steps leave ε where it is, so it falls more slowly
    than the step schedule with the same eps_dec."""
    eps, random, last = _explore("random_action", 500)
    assert random < 500
    assert last == pytest.approx(1.0 - 1e-3 * random)
    assert last > _explore("step", 500)[2]
    assert np.count_nonzero(np.diff(np.append(eps, last))) == random  # one fall per random action


@pytest.mark.parametrize("schedule", ["random_action", "step", "episode"])
def test_share_of_random_actions_is_epsilon(schedule: str) -> None:
    """With ε held at 0.3 (start = floor), 30 % of the actions are random under every schedule."""
    _, random, last = _explore(schedule, 20000, eps_start=0.3, eps_end=0.3, eps_dec=0.0)
    assert last == 0.3
    assert random / 20000 == pytest.approx(0.3, abs=0.01)


def test_step_schedule_does_not_raise_epsilon_to_its_floor() -> None:
    eps, random, last = _explore("step", 100, eps_start=0.0)
    assert last == 0.0 and random == 0 and not eps.any()


def test_episode_schedule_is_linear_in_episodes_whatever_their_length() -> None:
    """ε is held through an episode and falls by eps_dec at each episode start, so a seed
    with long episodes explores for as many episodes as one with short episodes."""
    cfg = TrainConfig(eps_schedule="episode", eps_end=0.05, eps_dec=0.1)
    explorer = EpsilonGreedy(cfg, 3, np.random.default_rng(0))
    lengths = [500, 3, 120, 7, 300, 1, 1, 40, 60, 9, 200, 5]
    random = np.zeros(len(lengths))
    for e, n in enumerate(lengths):
        explorer.start_episode()
        expected = max(0.05, 1.0 - 0.1 * (e + 1))
        assert explorer.epsilon == pytest.approx(expected)
        random[e] = sum(explorer.explore() is not None for _ in range(n))
        assert explorer.epsilon == pytest.approx(expected)  # steps leave ε where it is
    assert explorer.epsilon == 0.05
    assert random[0] / 500 == pytest.approx(0.9, abs=0.05)  # ε = 0.9 in the first episode
    assert random[10] / 200 == pytest.approx(0.05, abs=0.05)
