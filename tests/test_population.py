"""A population trains each of its seeds exactly as a single run of that seed does."""

from __future__ import annotations

import signal

import numpy as np
import pandas as pd
import pytest
from mlflow.tracking import MlflowClient
from omegaconf import OmegaConf

from cdqn.agents.base import EpsilonGreedy
from cdqn.agents.controlled_population import ExplorationPlan
from cdqn.config import EPS_SCHEDULES, EnvConfig, TrainConfig
from cdqn.control.factory import make_controller
from cdqn.envs import make_env
from cdqn.training.build import build, build_population, member_seeds
from cdqn.training.loop import DivergenceError, TrainState, train
from cdqn.training.member import Member
from cdqn.training.population_loop import train_population
from cdqn.training.run import run, run_population
from cdqn.training.signals import SignalBuffer
from cdqn.vector_env import (
    ClassicControlTwin,
    GymLoop,
    compiled_math_matches_numpy,
    make_vector_env,
)
from tests.conftest import compose_config
from tests.helpers import runs_of, signals_after_episode

ENVS = {
    "CartPole-v1": EnvConfig(),
    "CartPole obs[2:4]": EnvConfig(obs_indices=[2, 3]),
    "Acrobot-v1": EnvConfig(name="acrobot", id="Acrobot-v1", max_episode_steps=None),
    "MountainCar-v0": EnvConfig(name="mountaincar", id="MountainCar-v0"),
    "MountainCar-v0 radial features": EnvConfig(
        name="mountaincar", id="MountainCar-v0", normalize=True, rbf_centres=6, rbf_width=0.7
    ),
}


@pytest.mark.parametrize("name", list(ENVS))
def test_vectorised_classic_control_steps_equal_gymnasium(name: str) -> None:
    """Observations, rewards, terminations and truncations of every member equal those of
    its own gymnasium environment, bit for bit, across resets."""
    cfg = ENVS[name]
    k = 3
    reference = [make_env(cfg) for _ in range(k)]
    venv = make_vector_env([make_env(cfg) for _ in range(k)])
    # Acrobot's twin needs this machine's compiled cos/sin/pow to be NumPy's
    twin = cfg.name != "acrobot" or compiled_math_matches_numpy()
    assert isinstance(venv, ClassicControlTwin if twin else GymLoop)
    obs = np.stack([env.reset(seed=10 + i)[0] for i, env in enumerate(reference)])
    assert np.array_equal(obs, np.stack([venv.reset(i, 10 + i) for i in range(k)]))
    gen = np.random.default_rng(0)
    n_actions = int(reference[0].action_space.n)
    episodes = 0
    for _ in range(1500):
        actions = gen.integers(n_actions, size=k)
        out = [env.step(int(a)) for env, a in zip(reference, actions, strict=True)]
        step = venv.step(actions)
        assert np.array_equal(np.stack([o[0] for o in out]), step.obs)
        assert np.array_equal(np.array([o[1] for o in out]), step.reward)
        assert np.array_equal(np.array([o[2] for o in out]), step.terminated)
        assert np.array_equal(np.array([o[3] for o in out]), step.truncated)
        for i in np.flatnonzero(step.terminated | step.truncated):
            episodes += 1
            assert np.array_equal(reference[i].reset()[0], venv.reset(i, None))
    assert episodes > 0


def test_other_environments_step_through_their_own_envs() -> None:
    envs = [make_env(EnvConfig(name="pendulum", id="CartPole-v1")) for _ in range(2)]
    envs[1].unwrapped.kinematics_integrator = "rk4"  # not a dynamics the twin knows
    assert isinstance(make_vector_env(envs), GymLoop)


def _frame(client: MlflowClient, run_id: str, path: str) -> pd.DataFrame:
    return pd.read_parquet(client.download_artifacts(run_id, path))


def _metrics(client: MlflowClient, run_id: str) -> dict[str, list[tuple[int, float]]]:
    keys = client.get_run(run_id).data.metrics
    return {k: [(m.step, m.value) for m in client.get_metric_history(run_id, k)] for k in keys}


def _artifacts(client: MlflowClient, run_id: str, path: str | None = None) -> list[str]:
    out = []
    for item in client.list_artifacts(run_id, path):
        out += _artifacts(client, run_id, item.path) if item.is_dir else [item.path]
    return sorted(out)


BASE = [
    "network.width=48",
    "train.episodes=6",
    "train.progress=false",
    "train.checkpoint_every=0",
    "train.eps_dec=0.02",  # greedy actions early, so that learning shapes the returns
]


def _single(overrides: list[str]) -> tuple[str, str | None, list[float], np.ndarray]:
    """(status, failure reason, returns, signal rows) of a single run's loop for one seed."""
    conf = OmegaConf.to_object(compose_config(overrides))
    env = make_env(conf.env)
    job = build(conf, env)
    signals, state = SignalBuffer(), TrainState()
    status, reason = "FINISHED", None
    try:
        train(
            env,
            job.agent,
            episodes=conf.train.episodes,
            seed=conf.seed,
            discount=conf.train.discount,
            q_limit=conf.train.q_limit,
            signals=signals,
            state=state,
            progress=False,
            replay=conf.weights.replay,
        )
    except DivergenceError as err:
        status, reason = "FAILED", f"diverged: {err}"
    return status, reason, state.returns, signals.state()


def _population(overrides: list[str], seeds: list[int]) -> list[Member]:
    conf = OmegaConf.to_object(compose_config(overrides))
    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
    agent, venv = build_population(conf, setup, seeds)
    members = [Member(s, None) for s in seeds]
    train_population(
        agent,
        venv,
        members,
        episodes=conf.train.episodes,
        discount=conf.train.discount,
        q_limit=conf.train.q_limit,
        replay=conf.weights.replay,
    )
    return members


@pytest.mark.parametrize(
    ("env", "controller", "extra"),
    [
        ("cartpole", "none", []),
        ("cartpole", "hinf_f", []),
        ("cartpole", "h2", []),
        ("acrobot", "hinf", []),
        ("mountaincar", "hinf", ["network.dtype=float32"]),
        (
            "cartpole",
            "h2",
            [
                "controller.design=paper",
                "controller.h2_gain_map=paper",
                "train.bootstrap_terminal=true",
            ],
        ),
        (
            "cartpole",
            "hinf_f",
            ["weights.replay.repeats=3", "weights.replay.when=any", "weights.replay.last=4"],
        ),
        ("cartpole", "h2", ["weights.replay.repeats=2", "weights.replay.last=null"]),
        ("cartpole", "hinf", ["controller.reset_integrator=false"]),
        ("cartpole", "hinf_f", ["train.eps_schedule=step"]),
        ("cartpole", "h2", ["train.eps_schedule=episode", "train.eps_dec=0.1"]),
        (
            "mountaincar",
            "hinf",
            ["weights.replay.repeats=2", "weights.replay.when=truncated", "weights.replay.last=3"],
        ),
        # sampled replay, its buffer wrapping around, beside episodic replay
        (
            "cartpole",
            "hinf_f",
            ["weights.replay.sample=2", "weights.replay.buffer=50", "weights.replay.repeats=1"],
        ),
        ("mountaincar", "hinf", ["weights.replay.sample=1", "network.dtype=float32"]),
    ],
)
def test_population_members_step_exactly_as_single_runs(
    env: str, controller: str, extra: list[str]
) -> None:
    """Every per-step signal (Q1, Q2, u, x_e, Θ1, Θ2, loss) and every return of a member
    equals the single run of its seed, bit for bit (episodic and sampled replay included)."""
    overrides = [*BASE, f"env={env}", f"controller={controller}", *extra]
    if env == "acrobot":
        overrides += ["train.episodes=2"]
    members = _population(overrides, [3, 4, 5])
    for m in members:
        status, _, returns, rows = _single([*overrides, f"seed={m.seed}"])
        assert m.status == status == "FINISHED"
        assert m.returns == returns
        assert np.array_equal(m.signals.state(), rows)
        if controller != "none":
            assert np.abs(rows[:, 5]).sum() > 0  # u acted


def test_members_stepping_their_own_environments_equal_single_runs(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The population loop on :class:`GymLoop` (environments the twin does not know)."""
    monkeypatch.setattr(ClassicControlTwin, "supports", classmethod(lambda cls, envs: False))
    overrides = [*BASE, "env=mountaincar", "controller=hinf_f", "train.episodes=2"]
    members = _population(overrides, [3, 4])
    for m in members:
        status, _, returns, rows = _single([*overrides, f"seed={m.seed}"])
        assert m.status == status == "FINISHED"
        assert m.returns == returns
        assert np.array_equal(m.signals.state(), rows)


@pytest.mark.parametrize("n_actions", [2, 3])
@pytest.mark.parametrize("schedule", EPS_SCHEDULES)
def test_exploration_drawn_ahead_equals_epsilon_greedy(n_actions: int, schedule: str) -> None:
    """Decisions drawn ahead in blocks (populations) are the decisions, and leave the
    generator in the state, of one ``EpsilonGreedy.explore`` call per step (single runs)."""
    cfg = TrainConfig(eps_start=1.0, eps_end=0.05, eps_dec=2e-3, eps_schedule=schedule)
    if schedule == "episode":
        cfg.eps_dec = 0.02
    steps = 2000
    explorer = EpsilonGreedy(cfg, n_actions, np.random.default_rng(7))
    plan = ExplorationPlan(cfg, n_actions, [np.random.default_rng(7)], block=300)
    expected, drawn = [], []
    for t in range(steps):
        if t % 37 == 0:  # episodes of 37 steps: ε falls at their starts (episode schedule)
            explorer.start_episode()
            plan.start_episode(0)
        expected.append(explorer.explore())
        drawn.append(int(plan.next()[0]))
    assert drawn == [-1 if a is None else a for a in expected]
    assert 0 < sum(a is None for a in expected) < steps  # both kinds of decision occur
    # the plan has drawn to the end of its block (2100 decisions): so has the explorer
    tail = [explorer.explore() for _ in range(100)]
    ahead = plan.plan[200:, 0]
    if schedule == "episode":  # drawn ahead: the uniform and the action, decided with ε now
        ahead = np.where(plan.uniform[200:, 0] <= plan.epsilon[0], ahead, -1)
    assert [-1 if a is None else a for a in tail] == ahead.tolist()
    assert explorer.rng.bit_generator.state == plan.rngs[0].bit_generator.state
    assert explorer.epsilon == plan.epsilon[0] < cfg.eps_start


def test_diverging_members_fail_as_their_single_runs_do() -> None:
    overrides = [*BASE, "controller=none", "train.lr=0.05", "train.q_limit=50"]
    members = _population(overrides, [0, 1, 2])
    statuses = []
    for m in members:
        status, reason, returns, rows = _single([*overrides, f"seed={m.seed}"])
        assert (m.status, m.reason, m.returns) == (status, reason, returns)
        assert np.array_equal(m.signals.state(), rows)
        statuses.append(status)
    assert "FAILED" in statuses


def test_population_member_is_recorded_as_its_single_run(tracking_uri: str) -> None:
    """Same metrics, params, tags (plus ``population``) and artifacts (signals, model,
    config, design) as the single run of its seed."""
    base = [*BASE, "controller=hinf", "train.episodes=3", f"tracking.uri={tracking_uri}"]
    singles = [run(compose_config([*base, f"seed={s}"]), progress=False) for s in (3, 4)]
    population = run_population(compose_config([*base, "seed=3", "train.population=2"]))
    client = MlflowClient(tracking_uri)
    for single, member in zip(singles, population.members, strict=True):
        assert single.status == member.status == "FINISHED"
        for path in ("signals/steps.parquet", "signals/fft.parquet"):
            pd.testing.assert_frame_equal(
                _frame(client, single.run_id, path),
                _frame(client, member.run_id, path),
                check_exact=True,
            )
        assert _metrics(client, single.run_id) == _metrics(client, member.run_id)
        assert {"theta1_outside_box", "ratio_below_box", "ratio_above_box"} <= set(
            _metrics(client, member.run_id)
        )
        ra, rb = client.get_run(single.run_id).data, client.get_run(member.run_id).data
        assert ra.params == rb.params
        tags_a = {k: v for k, v in ra.tags.items() if not k.startswith("mlflow.")}
        tags_b = {k: v for k, v in rb.tags.items() if not k.startswith("mlflow.")}
        assert tags_b.pop("population") == "3-4"
        assert len(tags_b.pop("population_id")) == 32  # what resume= finds the members by
        assert tags_a == tags_b
        assert _artifacts(client, single.run_id) == _artifacts(client, member.run_id)
        assert single.final_score == member.final_score


def test_double_dqn_population_records_each_seed_as_its_run(tracking_uri: str) -> None:
    cfg = compose_config(
        [
            "controller=ddqn",
            "network.width=16",
            "train.episodes=2",
            "controller.learning_starts=10",
            "train.progress=false",
            f"tracking.uri={tracking_uri}",
            "seed=5",
            "train.population=2",
        ]
    )
    result = run_population(cfg)
    client = MlflowClient(tracking_uri)
    seeds = [client.get_run(r.run_id).data.tags["seed"] for r in result.members]
    assert seeds == ["5", "6"] and member_seeds(5, 2) == [5, 6]
    assert {r.status for r in result.members} == {"FINISHED"}
    assert result.summary().status == "FINISHED"


def test_a_signal_stops_a_population_trained_one_member_after_another(
    tracking_uri: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``train.fast_path=false`` trains the members one after another; SIGTERM during the
    first member stops the population (that member KILLED, resumable), not only the member:
    no later member starts."""
    arm = signals_after_episode(monkeypatch)
    arm(2)
    cfg = compose_config(
        [
            *BASE,
            "controller=hinf_f",
            "train.fast_path=false",
            f"tracking.uri={tracking_uri}",
            "seed=0",
            "train.population=3",
        ]  # fmt: skip
    )
    result = run_population(cfg)
    assert [r.status for r in result.members] == ["KILLED"]
    assert result.signum == signal.SIGTERM and result.summary().status == "KILLED"
    assert [r.data.tags["seed"] for r in runs_of(tracking_uri)] == ["0"]


@pytest.mark.parametrize("twin", [True, False], ids=["twin", "gym-loop"])
def test_environment_state_between_two_steps_round_trips(twin: bool) -> None:
    """A member's environment captured mid-episode (``state_dict``) and loaded into freshly
    made environments continues with the same observations, rewards and resets."""
    cfg = ENVS["CartPole-v1"]

    def make() -> object:
        envs = [make_env(cfg) for _ in range(2)]
        return ClassicControlTwin(envs) if twin else GymLoop(envs)

    venv, copy_ = make(), make()
    assert venv.checkpointable
    for i in range(2):
        venv.reset(i, 20 + i)
    gen = np.random.default_rng(1)
    for _ in range(7):
        venv.step(gen.integers(2, size=2))
    for i in range(2):
        copy_.load_state_dict(i, venv.state_dict(i))
    for _ in range(400):
        actions = gen.integers(2, size=2)
        a, b = venv.step(actions), copy_.step(actions)
        for x, y in zip(a, b, strict=True):
            assert np.array_equal(x, y)
        for i in np.flatnonzero(a.terminated | a.truncated):
            assert np.array_equal(venv.reset(i, None), copy_.reset(i, None))
