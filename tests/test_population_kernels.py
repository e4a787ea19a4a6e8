"""The population's step kernels compute a single run's numbers by other routes: the deferred
``W_1`` update and the blocked forward pass (:mod:`cdqn.network`), the compiled observation
maps of the environment twin (:mod:`cdqn.vector_env`), several steps in one compiled call;
and the profile adds up."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from numba import njit

from cdqn.config import EnvConfig
from cdqn.envs import make_env
from cdqn.network import (
    _JIT,
    Forward,
    Params,
    Pending,
    apply_pending_row,
    forward_pending_row,
    forward_row,
    output_row,
    sgd_deferred_row,
    sgd_row,
)
from cdqn.profile import DDQN_PARTS, PARTS, fresh_population, profile_config, profile_population
from cdqn.training.member import Member
from cdqn.training.population_loop import train_population
from cdqn.vector_env import ClassicControlTwin, make_vector_env


@njit(**_JIT)
def _unblocked_forward(w1t, b1, w2, b2, x, p, q):
    """The forward pass one input at a time over all hidden units (no blocks)."""
    for j in range(w1t.shape[1]):
        p[j] = b1[j]
    for i in range(w1t.shape[0]):
        for j in range(w1t.shape[1]):
            p[j] += w1t[i, j] * x[i]
    output_row(w2, b2, p, q)


@pytest.mark.parametrize(("n_obs", "n_actions", "width"), [(4, 2, 2500), (36, 3, 700), (6, 3, 33)])
def test_deferred_step_equals_the_immediate_step_bit_for_bit(
    n_obs: int, n_actions: int, width: int
) -> None:
    """Step, then forward pass at the next input: the single run's route (``sgd_row``, then
    ``forward_row``) and the population's (``sgd_deferred_row``, then ``forward_pending_row``
    or ``apply_pending_row``) leave the same parameters and passes; the blocked forward
    pass equals the unblocked one."""
    gen = np.random.default_rng(n_obs)
    for _ in range(10):
        params = [
            gen.normal(size=s) for s in ((n_obs, width), width, (n_actions, width), n_actions)
        ]
        x, x2, x3 = (gen.normal(size=n_obs) for _ in range(3))
        p, q = np.empty(width), np.empty(n_actions)
        forward_row(Params(*params), Forward(x, p, q))
        p_ref, q_ref = np.empty(width), np.empty(n_actions)
        _unblocked_forward(*params, x, p_ref, q_ref)
        assert np.array_equal(p, p_ref) and np.array_equal(q, q_ref)
        p2, q2 = np.empty(width), np.empty(n_actions)
        forward_row(Params(*params), Forward(x2, p2, q2))
        g, s = np.where(p > 0.0, params[2][1], 0.0), gen.normal() * 1e-3
        immediate, deferred = [a.copy() for a in params], [a.copy() for a in params]
        p_i, q_i = np.empty(width), np.empty(n_actions)
        p_d, q_d = np.empty(width), np.empty(n_actions)
        sgd_row(Params(*immediate), Forward(x, p, q), 1, s, g, Forward(x2, p2, q2),
                Forward(x2, p_i, q_i))  # fmt: skip
        sx = np.empty(n_obs)
        sgd_deferred_row(Params(*deferred), Forward(x, p, q), 1, s, Forward(x2, p2, q2),
                         Forward(x2, p_d, q_d), Pending(sx, g, False))  # fmt: skip
        assert np.array_equal(p_i, p_d) and np.array_equal(q_i, q_d)
        applied = [a.copy() for a in deferred]
        apply_pending_row(applied[0], sx, g)
        p3, q3 = np.empty(width), np.empty(n_actions)
        p4, q4 = np.empty(width), np.empty(n_actions)
        forward_row(Params(*immediate), Forward(x3, p3, q3))
        forward_pending_row(Params(*deferred), Forward(x3, p4, q4), Pending(sx, g, True))
        assert np.array_equal(p3, p4) and np.array_equal(q3, q4)
        for a, b, c in zip(immediate, deferred, applied, strict=True):
            assert np.array_equal(a, b) and np.array_equal(a, c)


@pytest.mark.parametrize(
    "cfg",
    [
        EnvConfig(name="mountaincar", id="MountainCar-v0", normalize=True, rbf_centres=6),
        EnvConfig(name="mountaincar", id="MountainCar-v0", rbf_centres=5, rbf_width=0.5),
        EnvConfig(
            name="acrobot", id="Acrobot-v1", normalize=True, normalize_scale=[1, 1, 1, 1, 2, 2]
        ),
    ],
    ids=["scaled-features", "features", "scaled"],
)
def test_compiled_observation_maps_equal_the_wrappers(cfg: EnvConfig) -> None:
    """The twin's compiled scaling and radial features equal the members' own wrappers, bit
    for bit, on observations spread over the whole box."""
    venv = make_vector_env([make_env(cfg) for _ in range(2)])
    if not isinstance(venv, ClassicControlTwin):
        pytest.skip("this machine steps Acrobot through its own environments")
    space = venv.base.observation_space
    obs = np.random.default_rng(1).uniform(space.low, space.high, (5000, space.shape[0]))
    obs = obs.astype(space.dtype)
    expected = obs if venv.scaling is None else venv.scaling.observation(obs)
    if venv.features is not None:
        expected = venv.features.features(expected)
    got = venv._observation_maps(obs)
    assert got.dtype == expected.dtype and np.array_equal(got, expected)


def test_profile_shares_add_up() -> None:
    prof = profile_population(profile_config("cartpole", "hinf", 32), k=3, steps=200, warmup=20)
    assert prof.member_steps == 600
    assert set(prof.shares()) == set(PARTS)
    assert sum(prof.shares().values()) == pytest.approx(1.0)
    assert all(prof.seconds[p] > 0 for p in ("environment", "network", "loop (Python)"))


def test_double_dqn_profile_shares_add_up() -> None:
    """Double DQN's profile times its minibatch steps apart from its per-step kernel."""
    conf = profile_config("cartpole", "ddqn", 32)
    conf.controller.learning_starts = 10
    prof = profile_population(conf, k=3, steps=100, warmup=20)
    assert prof.member_steps == 300
    assert set(prof.shares()) == set(DDQN_PARTS)
    assert sum(prof.shares().values()) == pytest.approx(1.0)
    assert all(prof.seconds[p] > 0 for p in DDQN_PARTS[:5])


def _trained(env: str, controller: str, step_by_step: bool) -> tuple[list[Member], Any, list]:
    """Seeds 0–2 trained 25 episodes as a population (width 32): the members, the agent and
    the population steps of each call of the loop."""
    conf = profile_config(env, controller, 32)
    agent, venv, members = fresh_population(conf, 3)
    if not isinstance(venv, ClassicControlTwin):
        pytest.skip("this machine steps Acrobot through its own environments")
    calls: list[int] = []
    train_population(agent, venv, members, episodes=25, discount=conf.train.discount,
                     q_limit=conf.train.q_limit, step_by_step=step_by_step,
                     on_steps=calls.append)  # fmt: skip
    return members, agent, calls


@pytest.mark.parametrize(("env", "controller"), [("cartpole", "hinf"), ("acrobot", "h2")])
def test_steps_run_ahead_in_one_call_as_step_by_step(env: str, controller: str) -> None:
    """A controlled population on a twin takes several steps per compiled call
    (``ControlledPopulation.run``), with the numbers of one step per call: the same returns,
    signal rows, parameters and exploration (CartPole's ε per random action, Acrobot's per
    episode and its scaled observations)."""
    ahead, agent, calls = _trained(env, controller, step_by_step=False)
    single, reference, steps = _trained(env, controller, step_by_step=True)
    assert set(steps) == {1} and max(calls) > 1 and sum(calls) == sum(steps)
    for a, b in zip(ahead, single, strict=True):
        assert a.status == b.status == "FINISHED"
        assert a.returns == b.returns and len(a.returns) == 25
        assert np.array_equal(a.signals.rows(0), b.signals.rows(0))
    agent.flush()
    reference.flush()
    for a, b in zip(agent.net.params, reference.net.params, strict=True):
        assert np.array_equal(a, b)
    assert np.array_equal(agent.epsilon, reference.epsilon)
