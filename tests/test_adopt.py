"""A run of an environment no preset names is that environment's, whatever the entry point:
adoption (:func:`cdqn.envs.adopt`), ``<module>:<Id>`` ids, ``env.kwargs``, the episode-cap
rule and discrete observations.  The toy environments are registered by the package
``tests.toy_envs`` when it is imported, as a user's own package would; the commands are the
real ``python -m cdqn.*`` in subprocesses, on a real SQLite store."""

from __future__ import annotations

import itertools
import json
import re
import tempfile
from pathlib import Path
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest
import torch
from mlflow.tracking import MlflowClient
from omegaconf import OmegaConf

from cdqn.cli import EXIT_CONFIG, check_overrides
from cdqn.config import EnvConfig
from cdqn.control.factory import make_controller
from cdqn.envs import adopt, env_label, env_presets, env_sizes, make_env
from cdqn.envs.adopt import GENERIC, command_line, shipped_weights
from cdqn.network import NetworkSpec, QNetwork
from cdqn.ntk_bounds import measured_box
from cdqn.training.run import run
from cdqn.training.sweep import config_hash
from cdqn.tuning.presets import write_preset
from cdqn.vector_env import ClassicControlTwin, GymLoop, make_vector_env
from tests.conftest import compose_config
from tests.helpers import episode_returns, run_cli, runs_of, signals_after_episode
from tests.test_population import BASE, _population, _single

TOY = "tests.toy_envs:CdqnChain-v0"
"""Registered on import of ``tests.toy_envs``: cap 50 steps, reward threshold −12."""
LABEL = "CdqnChain-v0"
KWARGS_LABEL = f"{LABEL}.step_reward--2.0"
"""The label of the toy id with the constructor argument ``step_reward=-2.0``."""
NO_CAP = "tests.toy_envs:CdqnChainNoCap-v0"
SMALL = ["network=small", "train.episodes=3", "train.progress=false"]


# --- adoption ------------------------------------------------------------------------------


def test_an_id_no_preset_names_is_adopted_once() -> None:
    cfg = compose_config([f"env.id={TOY}"])
    adopted = adopt(cfg)
    env = adopted.cfg.env
    assert (env.name, env.max_episode_steps, env.solve_threshold) == (LABEL, 50, -12.0)
    assert adopted.box_source == "measured"  # weights=cartpole are another id's
    assert adopted.change == (
        f"env.id={TOY} is not env=cartpole's CartPole-v1: named {LABEL}, episode cap 50 (its "
        "registration), solve threshold -12.0 (its registration), weights=generic in place of "
        "CartPole-v1's weights=cartpole, NTK box measured (weights=generic have none)"
    )
    assert adopted.cfg.weights == shipped_weights(GENERIC)
    assert cfg.env.name == "cartpole" and cfg.env.max_episode_steps == 200  # a new object
    again = adopt(adopted.cfg)
    assert again.change is None and again.cfg == adopted.cfg


def test_values_set_explicitly_stay() -> None:
    adopted = adopt(
        compose_config([f"env.id={TOY}", "env.max_episode_steps=30", "env.solve_threshold=-9"])
    )
    assert (adopted.conf.env.max_episode_steps, adopted.conf.env.solve_threshold) == (30, -9.0)


def test_labels_are_safe_in_file_names() -> None:
    assert env_label(TOY) == LABEL
    assert env_label("ALE/Pong-v5") == "ALE-Pong-v5"
    assert env_label("CartPole-v1") == "CartPole-v1"
    assert env_label("CartPole-v1", {}, cap=500) == "CartPole-v1-cap500"


def test_constructor_arguments_make_the_label_distinct_and_deterministic() -> None:
    """Keys sorted, values as on the command line; a value that is not short safe text (a
    list, a string with spaces) by its hash."""
    lake = "FrozenLake-v1"
    slip = {"map_name": "8x8", "is_slippery": False}
    assert env_label(lake, slip) == "FrozenLake-v1.is_slippery-false.map_name-8x8"
    assert env_label(lake, dict(reversed(slip.items()))) == env_label(lake, slip)
    assert env_label(lake, {"map_name": "4x4"}) == "FrozenLake-v1.map_name-4x4"
    assert env_label(TOY, {"step_reward": -2.0, "length": 4}) == (
        f"{LABEL}.length-4.step_reward--2.0"
    )
    assert env_label("CartPole-v1", {"x": None}, cap=500) == "CartPole-v1-cap500.x-null"
    desc = env_label(lake, {"desc": ["SF", "HG"]})
    assert desc != env_label(lake, {"desc": ["SF", "GH"]})
    assert re.fullmatch(r"FrozenLake-v1\.desc-[0-9a-f]{8}", desc)
    assert env_label(lake, {"render_mode": "a b"}) != env_label(lake, {"render_mode": "a_b"})
    names = set()
    for kwargs in ({}, {"map_name": "8x8"}, {"map_name": "8x8", "is_slippery": False}):
        over = [f"+env.kwargs.{k}={str(v).lower()}" for k, v in kwargs.items()]
        name = adopt(compose_config(["env.id=FrozenLake-v1", *over])).conf.env.name
        assert name == env_label(lake, kwargs) and re.fullmatch(r"[A-Za-z0-9_.+-]+", name)
        names.add(name)
    assert len(names) == 3


@pytest.mark.parametrize("env", ["cartpole", "cartpole_pole"])
def test_a_presets_own_id_with_constructor_arguments_is_labelled_by_them(env: str) -> None:
    """``env=cartpole +env.kwargs.sutton_barto_reward=true`` is not ``cartpole``: its label
    carries the arguments as an adopted id's does; the preset's cap, threshold, weights and
    box stay."""
    given = [f"env={env}", "+env.kwargs.sutton_barto_reward=true"]
    with command_line(given):
        adopted = adopt(compose_config(given))
    label = f"{env}.sutton_barto_reward-true"
    preset = env_presets()[env]
    conf = adopted.conf
    assert conf.env.name == label and adopted.box_source == "config"
    assert (conf.env.max_episode_steps, conf.env.solve_threshold) == (200, 195.0)
    assert (conf.env.obs_indices, conf.weights.name) == (preset.obs_indices, env)
    assert adopted.change == f"env={env} with constructor arguments env.kwargs: named {label}"
    assert adopt(adopted.cfg).change is None
    assert check_overrides(given) == []


@pytest.mark.parametrize(
    ("preset", "env_id", "key", "value"),
    [
        ("acrobot", "CartPole-v1", "normalize_scale", [1.0, 1.0, 1.0, 1.0, 2.0, 2.0]),
        ("cartpole_pole", "Acrobot-v1", "obs_indices", [2, 3]),
    ],
)
def test_another_id_drops_the_presets_features_by_index(
    preset: str, env_id: str, key: str, value: list
) -> None:
    """``env.obs_indices`` and ``env.normalize_scale`` name the preset's own observation
    features: a run of another id sees its own observation, unless the command line sets
    them.  (``cartpole_pole``'s weights preset, built on ``cartpole``'s, is read as Hydra
    composes it.)"""
    given = [f"env={preset}", f"env.id={env_id}"]
    with command_line(given):
        adopted = adopt(compose_config(given))
    assert OmegaConf.select(adopted.cfg, f"env.{key}") is None
    assert adopted.change is not None and f"env.{key}=null (not {preset}'s {value})" in (
        adopted.change
    )
    assert adopted.conf.weights.name == GENERIC and adopt(adopted.cfg).change is None
    assert check_overrides(given) == []
    own = [*given, f"env.{key}=[1,1]"]
    with command_line(own):
        kept = adopt(compose_config(own)).cfg
    assert OmegaConf.to_container(kept.env)[key] == [1, 1]


@pytest.mark.parametrize("env", sorted(env_presets()))
def test_presets_are_left_as_they_are_and_hash_as_before(env: str) -> None:
    cfg = compose_config([f"env={env}"])
    adopted = adopt(cfg)
    assert adopted.change is None and adopted.cfg == cfg
    assert adopted.box_source == "config"
    tree = OmegaConf.to_container(cfg, resolve=True)
    del tree["env"]["kwargs"]  # as recorded before env.kwargs existed
    assert config_hash(tree) == config_hash(cfg)
    given = compose_config([f"env={env}", "+env.kwargs.render_mode=rgb_array"])
    assert config_hash(given) != config_hash(cfg)


# --- the weights of an environment without a preset ------------------------------------------


def test_an_adopted_id_learns_with_the_generic_weights_and_keeps_what_the_run_sets() -> None:
    """Another environment's shipped preset, composed by default (``weights: ${env}``), is
    replaced by ``weights=generic``; values of ``weights.*`` set for the run stay, given on
    the command line (even at the replaced preset's value) or set in a configuration
    composed in code."""
    generic = shipped_weights(GENERIC)
    assert generic.paper.hinf_f is None  # no environment's research-code gains
    given = [
        f"env.id={TOY}",
        "controller=hinf_f",
        "weights.hinf_f.w_delta=0.5",
        "weights.target.step_scale=[0.3,0.4]",
        "weights.paper.hinf_f=[-0.379,2.82,0.1937]",  # cartpole's research-code gains
    ]
    with command_line(given):
        adopted = adopt(compose_config(given))
    w = adopted.conf.weights
    assert w.name == GENERIC and adopted.box_source == "measured"
    assert (w.hinf_f.w_delta, w.target.step_scale) == (0.5, [0.3, 0.4])  # the run's
    assert w.paper.hinf_f == [-0.379, 2.82, 0.1937]
    assert w.target.gamma_eff == list(generic.target.gamma_eff)  # generic's
    cfg = compose_config([f"env.id={TOY}", "weights.replay.repeats=4"])  # composed in code
    adopted = adopt(cfg)
    assert adopted.conf.weights.replay.repeats == 4 and adopted.conf.weights.paper.hinf_f is None
    assert OmegaConf.masked_copy(adopted.cfg.weights, ["target", "hinf_f", "hinf", "h2"]) == (
        OmegaConf.masked_copy(generic, ["target", "hinf_f", "hinf", "h2"])
    )


def test_a_weights_preset_chosen_for_the_run_is_kept(tmp_path: Path) -> None:
    """``weights=cartpole`` on the command line (its box measured) and a user's own preset
    (its box kept) are the run's choice; a preset's own id keeps its preset."""
    chosen = [f"env.id={TOY}", "weights=cartpole"]
    with command_line(chosen):
        adopted = adopt(compose_config(chosen))
    assert adopted.conf.weights.name == "cartpole" and adopted.box_source == "measured"
    assert adopted.change is not None and "weights=generic" not in adopted.change
    (tmp_path / "weights").mkdir()
    mine = OmegaConf.merge(shipped_weights("cartpole"), {"name": "mine"})
    mine.target.gamma_eff = [0.5, 0.6]
    OmegaConf.save(mine, tmp_path / "weights" / "mine.yaml")
    own = [f"env.id={TOY}", "weights=mine", f"hydra.searchpath=[file://{tmp_path}]"]
    for line in ((), own):  # on the command line or composed in code
        with command_line(list(line)):
            adopted = adopt(compose_config(own))
        assert adopted.conf.weights.name == "mine" and adopted.box_source == "config"
        assert adopted.conf.weights.target.gamma_eff == [0.5, 0.6]
    for cap in (["env=cartpole", "env.max_episode_steps=500"], ["env=acrobot"]):
        adopted = adopt(compose_config(cap))
        assert adopted.conf.weights.name == cap[0].removeprefix("env=")
        assert adopted.box_source == "config"


def test_a_tuned_preset_on_another_id_is_that_ids_run(tmp_path: Path) -> None:
    """A tuned preset sets the environment it was tuned on (id, kwargs, cap, threshold, box);
    with another ``env.id`` the run is that id's: its label, cap and threshold, no foreign
    kwargs, a measured box, the preset's exploration kept; other kwargs on its own id
    relabel it; its own id is left as it is.  A preset written without ``extra.tuned.env_id``
    is read by its label's id."""
    tuned_on = [f"env.id={TOY}", "+env.kwargs.step_reward=-2.0", "controller=hinf_f"]
    with command_line(tuned_on):
        cfg = adopt(compose_config(tuned_on)).cfg
    cfg.train.eps_dec = 0.0123  # as a study writes it: the box its design was certified on
    cfg.controller.synthesis.ntk_bounds = "config"
    cfg.weights.theta_bounds.theta1 = [3.0, 4.0]
    best = SimpleNamespace(number=3, value=-20.0, params={})
    tune = SimpleNamespace(study=f"{KWARGS_LABEL}-hinf_f", trials=1, seeds=1, seed=100, space={})
    path = write_preset(cfg, "tuned_toy", tmp_path, best, tune)
    text = path.read_text()  # a preset written before the id was recorded
    assert f"    env_id: {TOY}\n" in text
    path.with_name("tuned_old.yaml").write_text(text.replace(f"    env_id: {TOY}\n", ""))
    cases = [
        ([], KWARGS_LABEL),
        (["env.kwargs.step_reward=-3.0"], f"{LABEL}.step_reward--3.0"),
        (["env.id=Acrobot-v1"], "Acrobot-v1"),
        (["env.id=Acrobot-v1", "env.max_episode_steps=40"], "Acrobot-v1-cap40"),
    ]
    for preset, (extra, name) in itertools.product(["tuned_toy", "tuned_old"], cases):
        base = ["controller=hinf_f", f"weights={preset}", f"hydra.searchpath=[file://{tmp_path}]"]
        with command_line(base + extra):
            adopted = adopt(compose_config(base + extra))
            assert adopt(adopted.cfg).change is None  # idempotent
        conf = adopted.conf
        assert conf.env.name == name and conf.train.eps_dec == 0.0123, extra
        own_id = not any(e.startswith("env.id") for e in extra)
        assert (adopted.change is None) == (extra == [])
        assert adopted.box_source == ("config" if own_id else "measured")
        if not own_id:
            assert conf.env.kwargs == {} and conf.env.solve_threshold == -100.0
            assert conf.env.max_episode_steps == (40 if len(extra) == 2 else 500)
            tuned_on = TOY if preset == "tuned_toy" else LABEL
            assert adopted.change.startswith(f"weights=tuned_toy was tuned on {tuned_on}: ")


def test_generic_weights_on_a_presets_id_measure_their_box() -> None:
    adopted = adopt(compose_config(["env=cartpole", "weights=generic"]))
    assert adopted.box_source == "measured" and adopted.conf.env.name == "cartpole"
    assert adopted.change == "NTK box measured (weights=generic have none)"


# --- module:Id, kwargs, refusals -------------------------------------------------------------


def test_kwargs_reach_the_constructor_and_keep_the_twin_away() -> None:
    conf = adopt(
        compose_config([f"env.id={TOY}", "+env.kwargs.length=4", "+env.kwargs.step_reward=-2.0"])
    ).conf
    env = make_env(conf.env)
    assert (env.unwrapped.length, env.unwrapped.step_reward) == (4, -2.0)
    assert isinstance(
        make_vector_env([make_env(EnvConfig()) for _ in range(2)]), ClassicControlTwin
    )
    given = EnvConfig(kwargs={"sutton_barto_reward": False})  # the default value, still given
    assert isinstance(make_vector_env([make_env(given) for _ in range(2)]), GymLoop)


REFUSED = [
    (
        ["env.id=tests.no_such_module:Chain-v0"],
        "env.id='tests.no_such_module:Chain-v0': cannot import module 'tests.no_such_module' "
        "(ModuleNotFoundError: No module named 'tests.no_such_module'); give an importable "
        "module that registers 'Chain-v0' (<module>:<Id>)",
    ),
    (
        ["env.id=tests.toy_envs:Nope-v0"],
        "env.id='tests.toy_envs:Nope-v0' is not a registered gymnasium environment; importing "
        "'tests.toy_envs' did not register 'Nope-v0'",
    ),
    (
        [f"env.id={TOY}", "+env.kwargs.size=3"],
        "env.kwargs={'size': 3}: CdqnChain-v0's constructor refused them",
    ),
    (
        [f"env.id={TOY}", "env.kwargs.length=4"],
        "env.kwargs.length: env.kwargs has no such key yet; add it with +env.kwargs.length=<value>",
    ),
    (
        [f"env.id={NO_CAP}"],
        f"env.max_episode_steps=null: {NO_CAP} is registered without an episode cap "
        "(max_episode_steps) and none was given; give one, env.max_episode_steps=<steps>",
    ),
    (
        ["env.id=Blackjack-v1"],
        "env.max_episode_steps=null: Blackjack-v1 is registered without an episode cap",
    ),
    (  # gymnasium registers it with an entry point that raises ImportError
        ["env.id=HalfCheetah-v2", "env.max_episode_steps=10"],
        "env.id='HalfCheetah-v2' cannot be made here: its entry point "
        "gymnasium.envs:_raise_mujoco_py_error failed to import (ImportError: The mujoco v2 "
        "and v3 based environments have been moved to the gymnasium-robotics project",
    ),
    (  # an image: not flattened into the network's input
        ["env.id=CarRacing-v3", "+env.kwargs.continuous=false"],
        "env.id='CarRacing-v3' with env.kwargs={'continuous': False}: cdqn's network takes "
        "at most 1024 inputs from a Box observation (flattened), a MultiBinary one, discrete "
        "ones one-hot (Discrete, MultiDiscrete), or a Tuple or Dict of these; got "
        "Box(0, 255, (96, 96, 3), uint8) (27648 inputs)",
    ),
    (  # cells 1..600 either side, one-hot: 1200 inputs
        [f"env.id={TOY}", "+env.kwargs.form=multi_discrete", "+env.kwargs.length=600"],
        f"env.id='{TOY}' with env.kwargs={{'form': 'multi_discrete', 'length': 600}}: cdqn's "
        "network takes at most 1024 inputs",
    ),
    (  # a Text part: no vector of numbers
        [f"env.id={TOY}", "+env.kwargs.form=text"],
        f"env.id='{TOY}' with env.kwargs={{'form': 'text'}}: cdqn's network takes at most 1024",
    ),
    (  # a continuous variant chosen by a constructor argument
        ["env.id=LunarLander-v3", "+env.kwargs.continuous=true"],
        "env.id='LunarLander-v3' with env.kwargs={'continuous': True} has action space Box(",
    ),
    (  # a one-hot observation of 500 features: the grid's size as an order of magnitude
        ["env.id=Taxi-v4", "env.rbf_centres=4"],
        "env.rbf_centres=4: 4^500 = about 10^301 features, more than 4096; use fewer centres",
    ),
]


@pytest.mark.parametrize(("overrides", "expected"), REFUSED, ids=[" ".join(o) for o, _ in REFUSED])
def test_refused_with_one_line(overrides: list[str], expected: str) -> None:
    errors = check_overrides(overrides)
    assert len(errors) == 1 and errors[0].startswith(expected), errors


def test_a_cap_or_threshold_given_on_the_command_line_stays_at_the_presets_value() -> None:
    """``env.max_episode_steps=200`` is also ``env=cartpole``'s cap: given on the command
    line, it is the user's, not a leftover of the preset (CliffWalking is not refused,
    FrozenLake keeps 200 steps and the threshold given)."""
    assert check_overrides(["env.id=CliffWalking-v1", "env.max_episode_steps=200"]) == []
    given = ["env.id=FrozenLake-v1", "env.max_episode_steps=200", "env.solve_threshold=195"]
    with command_line(given):
        env = adopt(compose_config(given)).conf.env
    assert (env.max_episode_steps, env.solve_threshold) == (200, 195.0)
    assert env.name == "FrozenLake-v1-cap200"  # not its registration's 100: another task
    for other in (["env=acrobot", "env.max_episode_steps=100"], ["env.id=Acrobot-v1",
                  "env.max_episode_steps=100"]):  # fmt: skip
        with command_line(other):
            assert adopt(compose_config(other)).conf.env.name == "Acrobot-v1-cap100"
    for cap in (200, 100):  # registered without a cap: each given one is its own task
        no_cap = ["env.id=CliffWalking-v1", f"env.max_episode_steps={cap}"]
        with command_line(no_cap):
            assert adopt(compose_config(no_cap)).conf.env.name == f"CliffWalking-v1-cap{cap}"
    env = adopt(compose_config(given)).conf.env  # composed in code: the preset's values
    assert (env.max_episode_steps, env.solve_threshold) == (100, 0.7)


@pytest.mark.slow
def test_a_hydra_job_keeps_the_cap_its_command_line_gives(tmp_path: Path) -> None:
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    args = ["env.id=FrozenLake-v1", "env.max_episode_steps=200", *SMALL, "controller=none",
            f"tracking.uri={uri}"]  # fmt: skip
    proc = run_cli("cdqn.train", args, tmp_path)
    assert proc.returncode == 0, proc.stderr
    (run_,) = runs_of(uri)
    assert run_.data.params["env.max_episode_steps"] == "200"
    assert run_.data.params["env.solve_threshold"] == "0.7"  # not given: its registration's


def test_an_id_registered_without_a_reward_threshold_has_no_solve_threshold() -> None:
    adopted = adopt(compose_config(["env.id=CliffWalking-v1", "env.max_episode_steps=100"]))
    assert adopted.conf.env.solve_threshold is None
    assert adopted.change is not None
    assert "no solve threshold (none registered; env.solve_threshold=<return> sets one)" in (
        adopted.change
    )


def test_a_cap_given_or_registered_passes() -> None:
    assert check_overrides([f"env.id={NO_CAP}", "env.max_episode_steps=20"]) == []
    assert check_overrides([f"env.id={TOY}", "+env.kwargs.length=4"]) == []
    for env_id in ("Taxi-v4", "FrozenLake-v1"):
        assert check_overrides([f"env.id={env_id}"]) == []


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        ([f"env.id={NO_CAP}"], REFUSED[4][1]),
        (["env.id=tests.no_such_module:Chain-v0"], REFUSED[0][1]),
    ],
)
def test_cli_refuses_with_one_line_and_exit_2(
    overrides: list[str], expected: str, tmp_path: Path
) -> None:
    proc = run_cli("cdqn.train", [*overrides, f"tracking.uri=sqlite:///{tmp_path}/m.db"], tmp_path)
    assert proc.returncode == EXIT_CONFIG, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        "cdqn: invalid configuration, nothing was started:",
        f"  - {expected}",
    ]
    assert "Traceback" not in proc.stdout and not (tmp_path / "m.db").exists()


def test_an_entry_point_that_fails_to_import_is_one_line_and_exit_2(tmp_path: Path) -> None:
    """gymnasium registers HalfCheetah-v2 with an entry point that raises ImportError (as a
    missing jax or shimmy does for other ids): refused before anything starts.  gymnasium's
    own warning that the version is out of date may come first."""
    args = [
        "env.id=HalfCheetah-v2",
        "env.max_episode_steps=10",
        f"tracking.uri=sqlite:///{tmp_path}/m.db",
    ]
    proc = run_cli("cdqn.train", args, tmp_path)
    assert proc.returncode == EXIT_CONFIG, proc.stderr
    *_, head, line = proc.stderr.strip().splitlines()
    assert head == "cdqn: invalid configuration, nothing was started:"
    assert line.startswith(f"  - {REFUSED[6][1]}") and line.endswith("or choose another id")
    assert "Traceback" not in proc.stdout + proc.stderr and not (tmp_path / "m.db").exists()


# --- discrete observations -----------------------------------------------------------------


@pytest.mark.parametrize(
    ("env_id", "sizes"),
    [("Taxi-v4", [500]), ("FrozenLake-v1", [16]), ("CliffWalking-v1", [48]),
     ("Blackjack-v1", [32, 11, 2])],
)  # fmt: skip
def test_discrete_observations_are_one_hot(env_id: str, sizes: list[int]) -> None:
    env = make_env(EnvConfig(id=env_id, max_episode_steps=20))
    raw = gym.make(env_id, max_episode_steps=20)
    assert env_sizes(env)[0] == sum(sizes)
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    obs, state = env.reset(seed=3)[0], raw.reset(seed=3)[0]
    for t in range(30):
        parts = state if isinstance(state, tuple) else (state,)
        assert obs.dtype == np.float32 and obs.sum() == len(sizes)
        hot = [int(o + s) for o, s in zip(offsets, parts, strict=True)]
        assert np.flatnonzero(obs).tolist() == hot
        action = t % int(env.action_space.n)
        obs, _, term, trunc, _ = env.step(action)
        state, _, raw_term, raw_trunc, _ = raw.step(action)
        assert (term, trunc) == (raw_term, raw_trunc)
        if term or trunc:
            obs, state = env.reset(seed=t)[0], raw.reset(seed=t)[0]


def test_an_integer_box_observation_is_scaled_and_featured_in_floats() -> None:
    """An integer ``Box`` (cells to either side of the walker, 0..4) mapped to [−1, 1] and
    to radial features in float32: in the Box's own integer dtype every scaled feature was
    0 and every feature 0 or 1."""
    base = dict(id=TOY, kwargs={"cells": True, "length": 5}, max_episode_steps=50)
    raw = make_env(EnvConfig(**base))
    assert raw.reset(seed=0)[0].tolist() == [0, 4]
    scaled = make_env(EnvConfig(**base, normalize=True))
    obs = scaled.reset(seed=0)[0]
    assert obs.dtype == scaled.observation_space.dtype == np.float32
    assert obs.tolist() == [-1.0, 1.0]
    featured = make_env(EnvConfig(**base, rbf_centres=3))
    phi = featured.reset(seed=0)[0]
    assert phi.dtype == featured.observation_space.dtype == np.float32
    assert phi[2] == 1.0 and phi[1] == pytest.approx(np.exp(-0.5))  # centres (0, 4), (0, 2)


def test_actions_numbered_from_another_start_reach_the_environment_shifted() -> None:
    """``Discrete(2, start=-1)`` (action 0 moves right): the agents' indices 0, 1 reach the
    environment as −1, 0; a single run and a population train (the index 1 was refused)."""
    conf = EnvConfig(id=TOY, kwargs={"action_start": -1, "slip": 0.0, "cells": True},
                     max_episode_steps=50)  # fmt: skip
    env = make_env(conf)
    assert env.action_space == gym.spaces.Discrete(2)
    env.reset(seed=0)
    assert env.step(1)[0].tolist() == [1, 6] and env.step(0)[0].tolist() == [0, 7]
    overrides = [*BASE, f"env.id={TOY}", "+env.kwargs.action_start=-1", "controller=ddqn"]
    assert _single(overrides)[0] == "FINISHED"
    assert len(_population(overrides, [3, 4])[1].returns) == 6


@pytest.mark.parametrize(
    ("form", "first", "width"),
    [("column", [0.0, 1.0], 2),  # a (2, 1) Box, flattened
     ("multi_discrete", [1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1], 16),  # cells 1 | 7
     ("multi_binary", [1, 0, 0, 0, 0, 0, 0, 0], 8),  # position 0 of 8
     ("dict", [1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1], 16),  # left 1 | right 7
     ("mixed", [1, 0, 0, 0, 0, 0, 0, 0, 0.0], 9)],  # cell 0 of 8 | x (keys in order)
)  # fmt: skip
def test_other_observation_spaces_are_flattened_or_one_hot(
    form: str, first: list[float], width: int
) -> None:
    """A ``Box`` of another shape, a ``MultiBinary`` and a ``Dict`` with a ``Box`` part are
    flattened, a ``MultiDiscrete`` (values from its ``start``) and a ``Dict`` of ``Discrete``
    go in one-hot per part; a population of them trains as the single runs of its seeds."""
    env = make_env(EnvConfig(id=TOY, kwargs={"form": form}, max_episode_steps=50))
    assert env.observation_space.shape == (width,)
    assert env.reset(seed=0)[0].tolist() == first
    overrides = [*BASE, f"env.id={TOY}", f"+env.kwargs.form={form}", "controller=ddqn"]
    members = _population(overrides, [3, 4])
    for m in members:
        status, _, returns, rows = _single([*overrides, f"seed={m.seed}"])
        assert m.status == status == "FINISHED" and m.returns == returns
        assert np.array_equal(m.signals.state(), rows, equal_nan=True)  # loss: NaN at first


@pytest.mark.parametrize("controller", ["none", "h2"])
def test_population_on_discrete_observations_equals_single_runs(controller: str) -> None:
    """A population of FrozenLake (one-hot, its members' own environments) learns, member
    by member, what the single run of each seed learns, bit for bit."""
    overrides = [*BASE, "env.id=FrozenLake-v1", "env.max_episode_steps=100",
                 f"controller={controller}"]  # fmt: skip
    members = _population(overrides, [3, 4])
    for m in members:
        status, _, returns, rows = _single([*overrides, f"seed={m.seed}"])
        assert m.status == status == "FINISHED"
        assert m.returns == returns
        assert np.array_equal(m.signals.state(), rows)
        if controller == "h2":
            assert np.abs(rows[:, 5]).sum() > 0  # u acted


@pytest.mark.parametrize("env_id", ["FrozenLake-v1", "Taxi-v4"])
def test_ntk_box_is_measured_on_discrete_observations(env_id: str) -> None:
    conf = adopt(compose_config([f"env.id={env_id}", "controller=hinf_f", "network=small"])).conf
    assert conf.controller.synthesis.ntk_bounds == "measured"
    env = make_env(conf.env)
    n_obs, n_actions = env_sizes(env)
    torch.manual_seed(0)
    box = measured_box(conf, QNetwork(NetworkSpec(n_obs, n_actions, 64, "float64")))
    assert box is not None and box.source == "measured"
    assert 0 < box.theta1[0] <= box.theta1[1] and 0 < box.ratio[0] <= box.ratio[1]


@pytest.mark.slow
@pytest.mark.parametrize("controller", ["hinf", "hinf_f"])
@pytest.mark.parametrize(
    "overrides",
    [
        ["env.id=FrozenLake-v1"],
        ["env.id=Taxi-v4"],
        ["env.id=CliffWalking-v1", "env.max_episode_steps=100"],
    ],
)
def test_default_designs_are_certified_on_one_hot_boxes(
    overrides: list[str], controller: str
) -> None:
    """``python -m cdqn.train env.id=<a toy-text id>`` (default width, generic weights): the
    box measured on one-hot observations gets a certified design."""
    cfg = compose_config(
        [*overrides, f"controller={controller}", "controller.synthesis.cache=false"]
    )
    conf = adopt(cfg).conf
    env = make_env(conf.env)
    n_obs, n_actions = env_sizes(env)
    torch.manual_seed(conf.seed)
    net = QNetwork(NetworkSpec(n_obs, n_actions, conf.network.width, conf.network.dtype))
    box = measured_box(conf, net)
    assert box is not None
    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr, box)
    assert setup.source == "synthesized" and setup.design["certificate"]["passed"]


# --- every entry point, on an id no preset names -----------------------------------------------


class Store:
    """The runs the entry points wrote into one SQLite store."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.uri = f"sqlite:///{folder / 'mlflow.db'}"
        self.client = MlflowClient(self.uri)

    def run(self, name: str):
        found = [r for r in runs_of(self.uri) if r.info.run_name == name]
        assert len(found) == 1, [r.info.run_name for r in runs_of(self.uri)]
        return found[0]

    def artifact(self, run_id: str, path: str) -> Path:
        return Path(self.client.download_artifacts(run_id, path, tempfile.mkdtemp()))


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Store:
    """A single run (synthesised hinf_f, constructor argument step_reward=−2), then a multirun
    of a single run and a population of two, all ``env.id=tests.toy_envs:CdqnChain-v0``."""
    st = Store(tmp_path_factory.mktemp("adopt"))
    common = [f"env.id={TOY}", *SMALL, f"tracking.uri={st.uri}",
              f"controller.synthesis.cache_dir={st.folder / 'designs'}"]  # fmt: skip
    single = run_cli(
        "cdqn.train", [*common, "controller=hinf_f", "+env.kwargs.step_reward=-2.0"], st.folder
    )
    assert single.returncode == 0, single.stderr
    assert f"named {KWARGS_LABEL}, episode cap 50" in single.stdout + single.stderr
    multi = run_cli(
        "cdqn.train",
        ["-m", *common, "controller=none", "seed=10", "train.population=1,2"],
        st.folder,
    )
    assert multi.returncode == 0, multi.stderr
    return st


def _assert_adopted(run, controller: str, label: str = LABEL) -> None:
    tags, params = run.data.tags, run.data.params
    assert (tags["env"], tags["env_id"], tags["controller"]) == (label, TOY, controller)
    assert params["env.name"] == label
    assert params["env.max_episode_steps"] == "50"  # the registration's, not CartPole's 200
    assert params["env.solve_threshold"] == "-12.0"  # not CartPole's 195
    assert params["controller.synthesis.ntk_bounds"] == "measured"
    assert params["weights.name"] == GENERIC  # not weights=cartpole's CartPole target
    target = shipped_weights(GENERIC).target
    assert params["weights.target.gamma_eff"] == str(list(target.gamma_eff))


@pytest.mark.slow
def test_single_run_is_the_environments_with_its_kwargs(store: Store) -> None:
    run_ = store.run(f"{KWARGS_LABEL}-hinf_f-w64-e3-s0")
    _assert_adopted(run_, "hinf_f", KWARGS_LABEL)
    assert run_.data.params["env.kwargs.step_reward"] == "-2.0"
    design = json.loads(store.artifact(run_.info.run_id, "design/controller.json").read_text())
    assert design["box_source"] == "measured"
    returns = episode_returns(store.client, run_.info.run_id)
    lengths = [m.value for m in store.client.get_metric_history(run_.info.run_id, "episode_length")]
    assert returns == [-2.0 * n for n in lengths]  # step_reward=-2 reached the constructor


@pytest.mark.slow
def test_multirun_and_population_runs_are_the_environments(store: Store) -> None:
    runs = runs_of(store.uri)
    names = sorted(r.info.run_name for r in runs)
    assert names == sorted(
        [f"{KWARGS_LABEL}-hinf_f-w64-e3-s0", *[f"{LABEL}-none-w64-e3-s{s}" for s in (10, 10, 11)]]
    )
    members = [r for r in runs if "population" in r.data.tags]
    assert sorted(r.data.tags["seed"] for r in members) == ["10", "11"]
    for r in runs:
        if r.data.tags["controller"] == "none":
            _assert_adopted(r, "none")
            assert r.data.params["env.kwargs"] == "{}"


@pytest.mark.slow
def test_a_presets_own_id_with_constructor_arguments_runs_under_their_label(
    tmp_path: Path,
) -> None:
    """``python -m cdqn.train -m env=cartpole +env.kwargs.sutton_barto_reward=true`` with a
    single run and a population of two: every run is named and tagged by the label with the
    argument, which reached the constructor (Sutton and Barto's reward: 0 a step, −1 at
    the fall)."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    label = "cartpole.sutton_barto_reward-true"
    args = ["-m", "env=cartpole", "+env.kwargs.sutton_barto_reward=true", *SMALL,
            "controller=none", "seed=0", "train.population=1,2", f"tracking.uri={uri}"]  # fmt: skip
    proc = run_cli("cdqn.train", args, tmp_path)
    assert proc.returncode == 0, proc.stderr
    runs = runs_of(uri)
    assert sorted(r.info.run_name for r in runs) == [f"{label}-none-w64-e3-s{s}" for s in (0, 0, 1)]
    client = MlflowClient(uri)
    for r in runs:
        assert (r.data.tags["env"], r.data.tags["env_id"]) == (label, "CartPole-v1")
        assert r.data.params["env.max_episode_steps"] == "200"
        assert r.data.params["weights.name"] == "cartpole"
        assert set(episode_returns(client, r.info.run_id)) <= {0.0, -1.0}


@pytest.mark.slow
def test_evaluate_builds_the_stored_environment(store: Store) -> None:
    run_id = store.run(f"{KWARGS_LABEL}-hinf_f-w64-e3-s0").info.run_id
    args = [f"run_id={run_id}", "episodes=3", f"tracking.uri={store.uri}"]
    proc = run_cli("cdqn.evaluate", args, store.folder)
    assert proc.returncode == 0, proc.stderr
    assert f"run {run_id} on {TOY}: greedy return" in proc.stdout
    table = pd.read_csv(store.artifact(run_id, "evaluation/returns-seed1000000-n3.csv"))
    assert (table["return"] == -2.0 * table["length"]).all()  # its env.kwargs, its module


@pytest.mark.slow
def test_synthesize_designs_on_the_environments_own_box(tmp_path: Path) -> None:
    args = [f"env.id={TOY}", "controller=hinf_f", "network=small", f"out={tmp_path / 'out'}",
            f"controller.synthesis.cache_dir={tmp_path / 'designs'}"]  # fmt: skip
    proc = run_cli("cdqn.synthesize", args, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert f"named {LABEL}, episode cap 50" in proc.stdout + proc.stderr
    design = json.loads((tmp_path / "out" / "controller.json").read_text())
    assert design["box_source"] == "measured"
    target = shipped_weights(GENERIC).target  # as cdqn.train designs it
    assert design["learning_target"]["target"] == {
        "gamma_eff": list(target.gamma_eff),
        "step_scale": list(target.step_scale),
    }


@pytest.mark.slow
def test_bench_takes_an_id(tmp_path: Path) -> None:
    args = ["--env", TOY, "--controllers", "none", "--width", "16", "--steps", "60", "--warmup",
            "20", "--repeats", "1", "--population", "2", "--no-estimate", "--json"]  # fmt: skip
    proc = run_cli("cdqn.bench", args, tmp_path)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout[proc.stdout.index("{") :])
    assert (result["env"], result["env_id"]) == (LABEL, TOY)
    assert result["controllers"]["none"]["steps_per_s"] > 0


@pytest.mark.slow
def test_resume_continues_the_environments_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A run of the toy id stopped by SIGTERM after its first episode, then continued by
    ``python -m cdqn.train resume=<id>`` in a new process (which imports the module again)."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    arm = signals_after_episode(monkeypatch)
    arm(1)
    stopped = run(
        compose_config([f"env.id={TOY}", *SMALL, "controller=none", f"tracking.uri={uri}"]),
        progress=False,
    )
    assert stopped.status == "KILLED"
    proc = run_cli("cdqn.train", [f"resume={stopped.run_id}", f"tracking.uri={uri}"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    resumed = MlflowClient(uri).get_run(stopped.run_id)
    assert resumed.info.status == "FINISHED" and resumed.info.run_name == f"{LABEL}-none-w64-e3-s0"
    _assert_adopted(resumed, "none")
    assert len(episode_returns(MlflowClient(uri), stopped.run_id)) == 3


@pytest.mark.slow
def test_tune_studies_the_environment_as_itself(tmp_path: Path) -> None:
    """``python -m cdqn.tune env.id=<module>:<Id> +env.kwargs.<k>=<v>``: the study, its preset,
    its trial and member runs are the environment's (label with its constructor argument, cap,
    threshold), the search starts from the generic weights (the target is its own dimension),
    every design is certified on a box measured on the environment's own network and
    observation map, and the preset, named by the label, trains that environment again."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    label = f"{LABEL}.length-6"
    args = [f"env.id={TOY}", "+env.kwargs.length=6", "controller=hinf_f", "network=small",
            f"tracking.uri={uri}", f"tune.storage=sqlite:///{tmp_path / 'optuna.db'}",
            f"tune.preset_dir={tmp_path / 'presets'}", "tune.trials=1", "tune.seeds=2",
            "tune.episodes=4", "tune.eval_seeds=0", "tune.pruner.kind=none",
            "tune.space.gamma_eff.choices=[-2.0]",  # certified on every map's box
            f"controller.synthesis.cache_dir={tmp_path / 'designs'}"]  # fmt: skip
    proc = run_cli("cdqn.tune", args, tmp_path)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout + proc.stderr
    assert f"named {label}, episode cap 50" in out and f"study {label}-hinf_f" in out
    assert "weights=generic in place of CartPole-v1's weights=cartpole" in out
    assert "study cartpole" not in out and "(cartpole," not in out  # no member named so
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name("cdqn-tune")
    runs = client.search_runs([exp.experiment_id])
    parent = next(r for r in runs if r.data.tags.get("kind") == "tune")
    assert parent.info.run_name == f"tune-{label}-hinf_f" and parent.data.tags["env"] == label
    members = [r for r in runs if "population" in r.data.tags]
    names = sorted(r.info.run_name for r in members)
    assert [n.rsplit("-", 1)[1] for n in names] == ["s100", "s101"]
    assert all(n.startswith(f"{label}-hinf_f-w64-e4") for n in names)
    for r in members:
        assert (r.data.tags["env"], r.data.tags["env_id"]) == (label, TOY)
        assert r.data.params["env.max_episode_steps"] == "50"
        assert r.data.params["env.solve_threshold"] == "-12.0"
        assert r.data.params["weights.name"] == GENERIC
        # the box measured once for the study, written into the design's configuration
        assert r.data.params["controller.synthesis.ntk_bounds"] == "config"
    preset = tmp_path / "presets" / "weights" / f"tuned_{label}-hinf_f.yaml"
    tuned = OmegaConf.load(preset)
    assert (tuned.env.id, tuned.env.name, tuned.env.kwargs) == (TOY, label, {"length": 6})
    assert (tuned.env.max_episode_steps, tuned.env.solve_threshold) == (50, -12.0)
    generic = shipped_weights(GENERIC)
    assert tuned.weights.h2 == generic.h2 and tuned.weights.paper == generic.paper
    assert tuned.weights.hinf_f.w_delta == generic.hinf_f.w_delta
    again = run_cli("cdqn.train", [f"weights=tuned_{label}-hinf_f", "controller=hinf_f",
                                   "network=small", "train.episodes=2", "train.progress=false",
                                   f"hydra.searchpath=[file://{tmp_path / 'presets'}]",
                                   f"tracking.uri=sqlite:///{tmp_path / 'train.db'}",
                                   f"controller.synthesis.cache_dir={tmp_path / 'designs'}"],
                    tmp_path)  # fmt: skip
    assert again.returncode == 0, again.stderr
    (trained,) = runs_of(f"sqlite:///{tmp_path / 'train.db'}")
    name = trained.info.run_name  # the tuned α in it: <label>-hinf_f-w64-e2-lr<α>-s0
    assert name.startswith(f"{label}-hinf_f-w64-e2-lr") and name.endswith("-s0")
    assert trained.data.tags["env"] == label and trained.data.params["env.kwargs.length"] == "6"
    assert trained.data.params["weights.name"] == f"tuned_{label}-hinf_f"
