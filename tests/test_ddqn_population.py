"""Double DQN: no bootstrap at termination, a bootstrap at the time limit; a population
trains each of its seeds exactly as the single run of that seed does."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient
from omegaconf import OmegaConf

from cdqn.agents.ddqn_population import DDQNPopulation
from cdqn.control.factory import make_controller
from cdqn.ddqn_kernels import double_dqn_step
from cdqn.envs import make_env
from cdqn.network import FastTwoLayer, NetworkSpec, QNetwork
from cdqn.training.build import build, build_population
from cdqn.training.loop import TrainState, train
from cdqn.training.member import Member
from cdqn.training.population_loop import train_population
from cdqn.training.run import run_population
from cdqn.training.signals import SignalBuffer
from tests.conftest import compose_config
from tests.test_population import _artifacts, _frame, _metrics


def _nets(seed: int, n_obs: int = 4, n_actions: int = 2) -> tuple[FastTwoLayer, FastTwoLayer]:
    torch.manual_seed(seed)
    online = QNetwork(NetworkSpec(n_obs, n_actions, 24))
    target = QNetwork(NetworkSpec(n_obs, n_actions, 24))  # a different target network
    return FastTwoLayer(online), FastTwoLayer(target)


@pytest.mark.parametrize("terminated", [1.0, 0.0], ids=["terminated", "truncated"])
def test_target_bootstraps_at_the_time_limit_and_not_at_termination(terminated: float) -> None:
    """The minibatch loss of one transition is ½(r − Q(s,a))² when the MDP ended, and
    ½(r + γ Q̄(s', argmax_a Q(s', a)) − Q(s,a))² when the episode was cut short."""
    online, target = _nets(0)
    rng = np.random.default_rng(1)
    s, s2 = rng.normal(size=(1, 4)), rng.normal(size=(1, 4))
    q_s, q_next, q_tgt = online.forward(s[0]).q, online.forward(s2[0]).q, target.forward(s2[0]).q
    bootstrap = 0.9 * q_tgt[int(np.argmax(q_next))]
    assert abs(bootstrap) > 1e-6
    loss = double_dqn_step(
        online, target, s, np.array([1]), np.array([0.5]), s2, np.array([terminated]), 0.9, 0.0
    )
    expected = 0.5 + (0.0 if terminated else bootstrap) - q_s[1]
    assert loss == pytest.approx(0.5 * expected**2, rel=1e-12)


class _Flags(gym.Wrapper):
    """Records each step's (terminated, truncated)."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.flags: list[tuple[bool, bool]] = []

    def step(self, action):
        out = self.env.step(action)
        self.flags.append((bool(out[2]), bool(out[3])))
        return out


def test_replay_stores_termination_not_the_time_limit() -> None:
    """A real CartPole with a 20-step limit: transitions that end an episode by the time
    limit are stored with d = 0 (they bootstrap), those that end it by failure with d = 1."""
    cfg = compose_config(
        ["controller=ddqn", "network.width=16", "env.max_episode_steps=20",
         "controller.learning_starts=10000", "train.progress=false"]
    )  # fmt: skip
    conf = OmegaConf.to_object(cfg)
    env = _Flags(make_env(conf.env))
    job = build(conf, env)
    train(env, job.agent, episodes=60, seed=0, discount=1.0, q_limit=1e6, signals=SignalBuffer(),
          progress=False)  # fmt: skip
    terminated, truncated = np.array(env.flags).T
    buf = job.agent.buffer
    assert (truncated & ~terminated).sum() > 5 and terminated.sum() > 5
    assert np.array_equal(buf.terminated[: buf.size], terminated.astype(float))


BASE = [
    "controller=ddqn",
    "network.width=40",
    "train.episodes=8",
    "train.progress=false",
    "train.checkpoint_every=0",
    "train.eps_dec=0.02",
    "controller.learning_starts=40",
    "controller.batch_size=8",
    "controller.buffer_size=150",  # wraps around
    "controller.target_update=25",
    "controller.train_freq=2",
    "train.lr=1e-3",
]


def _single(overrides: list[str]) -> tuple[list[float], np.ndarray, dict]:
    conf = OmegaConf.to_object(compose_config(overrides))
    env = make_env(conf.env)
    job = build(conf, env)
    signals, state = SignalBuffer(), TrainState()
    train(env, job.agent, episodes=conf.train.episodes, seed=conf.seed,
          discount=conf.train.discount, q_limit=conf.train.q_limit, signals=signals,
          state=state, progress=False)  # fmt: skip
    return state.returns, signals.state(), job.agent.state_dict()


def _population(overrides: list[str], seeds: list[int]) -> tuple[list[Member], DDQNPopulation]:
    conf = OmegaConf.to_object(compose_config(overrides))
    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
    agent, venv = build_population(conf, setup, seeds)
    assert isinstance(agent, DDQNPopulation)
    members = [Member(s, None) for s in seeds]
    states: dict[int, dict] = {}
    train_population(
        agent, venv, members, episodes=conf.train.episodes, discount=conf.train.discount,
        q_limit=conf.train.q_limit,
        on_member_end=lambda m, pop, j: states.__setitem__(m.seed, pop.member_state(j)),
    )  # fmt: skip
    for m in members:
        m.cfg = states[m.seed]  # the member's final state
    return members, agent


@pytest.mark.parametrize(
    ("env", "extra"),
    [("cartpole", []), ("acrobot", ["train.episodes=2"]),
     ("mountaincar", ["train.episodes=2", "network.dtype=float32"]),
     ("cartpole", ["controller.discount=0.9"]),
     ("cartpole", ["train.eps_schedule=episode", "train.eps_dec=0.1"])],
)  # fmt: skip
def test_ddqn_population_members_step_exactly_as_single_runs(env: str, extra: list[str]) -> None:
    """Returns, every per-step signal (Q1, Q2, Θ1, Θ2, loss) and the final state (networks,
    target networks, buffer, generator, ε, step count) of each member equal the single run
    of its seed, bit for bit."""
    overrides = [*BASE, f"env={env}", *extra]
    members, _ = _population(overrides, [3, 4, 5])
    for m in members:
        returns, rows, state = _single([*overrides, f"seed={m.seed}"])
        assert m.status == "FINISHED"
        assert m.returns == returns
        assert np.array_equal(m.signals.state(), rows, equal_nan=True)
        assert np.isfinite(rows[:, 9]).sum() > 20  # it learned
        got = m.cfg
        for key in ("net", "target"):
            for name, value in state[key].items():
                assert torch.equal(got[key][name], value), (key, name)
        for name, value in state["buffer"].items():
            if isinstance(value, np.ndarray):
                assert np.array_equal(got["buffer"][name], value), name
            else:
                assert got["buffer"][name] == value, name
        assert (got["epsilon"], got["steps"]) == (state["epsilon"], state["steps"])
        assert np.array_equal(got["last_loss"], state["last_loss"], equal_nan=True)


def test_ddqn_population_state_round_trip() -> None:
    """population_state/load_population_state carry a population's networks, targets, buffers,
    generators, ε and step counters: a restored population continues identically."""
    conf = OmegaConf.to_object(compose_config([*BASE, "train.episodes=3"]))
    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)

    def trained(steps: int, load: dict | None = None) -> DDQNPopulation:
        agent, venv = build_population(conf, setup, [0, 1])
        if load is not None:
            agent.load_population_state(load)
        if steps:
            members = [Member(s, None) for s in (0, 1)]
            train_population(agent, venv, members, episodes=10**6, discount=1.0, q_limit=1e6,
                             max_steps=steps)  # fmt: skip
        return agent

    first = trained(300)  # past learning_starts, the buffer wrapped around
    state = first.population_state()
    assert [m["steps"] for m in state["members"]] == [300, 300]
    restored = trained(0, load=state)  # built afresh, then loaded: the same state
    _assert_same_state(restored.population_state(), state)
    again, control = trained(50, load=state), trained(50, load=first.population_state())
    _assert_same_state(again.population_state(), control.population_state())
    assert [m["steps"] for m in again.population_state()["members"]] == [350, 350]


def _assert_same_state(a: dict, b: dict) -> None:
    assert np.array_equal(a["loss_seen"], b["loss_seen"])
    for x, y in zip(a["members"], b["members"], strict=True):
        for key in ("net", "target"):
            assert all(torch.equal(x[key][k], y[key][k]) for k in x[key])
        for k, v in x["buffer"].items():
            assert (
                np.array_equal(v, y["buffer"][k])
                if isinstance(v, np.ndarray)
                else v == y["buffer"][k]
            )
        assert (x["epsilon"], x["steps"]) == (y["epsilon"], y["steps"])
        assert np.array_equal(x["last_loss"], y["last_loss"], equal_nan=True)


def test_ddqn_population_member_is_recorded_as_its_single_run(tracking_uri: str) -> None:
    from cdqn.training.run import run

    base = [*BASE, "train.episodes=4", f"tracking.uri={tracking_uri}"]
    singles = [run(compose_config([*base, f"seed={s}"]), progress=False) for s in (3, 4)]
    population = run_population(compose_config([*base, "seed=3", "train.population=2"]))
    client = MlflowClient(tracking_uri)
    for single, member in zip(singles, population.members, strict=True):
        assert single.status == member.status == "FINISHED"
        a = _frame(client, single.run_id, "signals/steps.parquet")
        b = _frame(client, member.run_id, "signals/steps.parquet")
        assert a.equals(b)
        ma, mb = _metrics(client, single.run_id), _metrics(client, member.run_id)
        assert ma.keys() == mb.keys()
        assert all(np.array_equal(ma[k], mb[k], equal_nan=True) for k in ma)  # NaN: no loss yet
        assert _artifacts(client, single.run_id) == _artifacts(client, member.run_id)
        assert single.final_score == member.final_score


def test_controller_discount_sets_the_double_dqn_target_discount() -> None:
    """``controller.discount`` (γ of Double DQN's target, 0.99 by default) in single runs and
    populations; null leaves ``train.discount``."""
    for extra, gamma in (([], 0.99), (["controller.discount=null"], 1.0)):
        conf = OmegaConf.to_object(compose_config([*BASE, *extra]))
        job = build(conf, make_env(conf.env))
        setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
        agent, _ = build_population(conf, setup, [0, 1])
        assert job.agent.discount == agent.hyper[1] == gamma
