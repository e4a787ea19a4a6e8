"""Every option of every config group composes, validates and builds."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from cdqn.agents import DDQNAgent, make_agent
from cdqn.config import Config, validate
from cdqn.control.factory import make_controller
from cdqn.envs import env_sizes, make_env
from cdqn.network import NetworkSpec, QNetwork
from tests.conftest import CONF_DIR, compose_config


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


def test_defaults_are_the_paper_settings() -> None:
    cfg = compose_config()
    assert cfg.env.id == "CartPole-v1" and cfg.env.max_episode_steps == 200
    assert cfg.controller.name == "hinf"
    assert cfg.network.width == 2500 and cfg.network.dtype == "float64"
    assert cfg.train.lr == 5e-5 and cfg.train.discount == 1.0
    assert cfg.tracking.experiment == "cdqn"
    assert cfg.weights.name == "cartpole"


@pytest.mark.parametrize("group", ["env", "controller", "weights", "network", "tracking", "train"])
def test_every_option_composes_and_validates(group: str) -> None:
    options = _options(group)
    assert options
    for option in options:
        cfg = compose_config([f"{group}={option}", *_own_agent(group, option)])
        conf: Config = OmegaConf.to_object(cfg)
        validate(conf)


def _own_agent(group: str, option: str) -> list[str]:
    """A tuned weights preset carries its agent's settings: it composes with that agent
    (``extra.tuned.agent``), as its header says."""
    if group != "weights" or not option.startswith("tuned_"):
        return []
    preset = OmegaConf.load(CONF_DIR / "weights" / f"{option}.yaml")
    return [f"controller={preset.extra.tuned.agent}"]


@pytest.mark.parametrize("env", _options("env"))
@pytest.mark.parametrize("controller", _options("controller"))
def test_every_env_and_controller_builds(env: str, controller: str) -> None:
    cfg = compose_config([f"env={env}", f"controller={controller}", "network=small"])
    conf: Config = OmegaConf.to_object(cfg)
    gym_env = make_env(conf.env)
    n_obs, n_actions = env_sizes(gym_env)
    if conf.env.obs_indices is not None:
        assert n_obs == len(conf.env.obs_indices)
    net = QNetwork(NetworkSpec(n_obs, n_actions, conf.network.width, conf.network.dtype))
    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
    agent = make_agent(conf.controller, conf.train, net, setup, np.random.default_rng(0))
    obs, _ = gym_env.reset(seed=0)
    action = agent.act(obs)
    next_obs, reward, terminated, _, _ = gym_env.step(action)
    rec = agent.update(obs, action, float(reward), next_obs, terminated)
    assert np.isfinite(rec.q1) and rec.theta1 > 0
    gym_env.close()


def test_weights_follow_the_env_choice() -> None:
    for env in ("cartpole", "acrobot", "mountaincar"):
        assert compose_config([f"env={env}"]).weights.name == env
    cfg = compose_config(["env=acrobot", "weights=cartpole"])
    assert cfg.weights.h2.w_c == 20000.0


def test_exploration_schedule_follows_the_env_unless_train_sets_it() -> None:
    def schedule(*overrides: str) -> tuple[float, str]:
        conf: Config = OmegaConf.to_object(compose_config(list(overrides)))
        return conf.train.eps_dec, conf.train.eps_schedule

    research = (1e-4, "random_action")
    assert schedule("env=cartpole") == schedule("env=mountaincar") == research
    assert schedule("env=cartpole_pole") == schedule("env.id=LunarLander-v3") == research
    assert schedule("env=acrobot") == (9.3e-4, "episode")  # docs/research/learning.md, section 5
    assert schedule("env=acrobot", "train.eps_dec=3e-4") == (3e-4, "episode")
    assert schedule("env=acrobot", "train.eps_schedule=step") == (9.3e-4, "step")
    assert schedule("env=cartpole", "env.eps_dec=2e-5", "env.eps_schedule=step") == (2e-5, "step")


def test_double_dqn_takes_its_environments_settings_unless_overridden() -> None:
    """``weights.ddqn`` (conf/weights) gives Double DQN's α, target period and observations
    per environment; the agent steps with that α."""

    def settings(*overrides: str) -> tuple[float, int, bool]:
        conf: Config = OmegaConf.to_object(compose_config(["controller=ddqn", *overrides]))
        env = make_env(conf.env)
        net = QNetwork(NetworkSpec(*env_sizes(env), 8))
        env.close()
        agent = make_agent(conf.controller, conf.train, net, None, np.random.default_rng(0))
        assert isinstance(agent, DDQNAgent)
        return agent.lr, agent.cfg.target_update, conf.env.normalize

    assert settings("env=cartpole") == (5e-5, 500, False)  # the paper's α and observations
    assert settings("env=acrobot") == (5e-5, 500, False)
    assert settings("env=mountaincar") == (1e-3, 125, True)  # conf/weights/mountaincar.yaml
    assert settings("env=mountaincar", "controller.lr=2e-4", "controller.target_update=500",
                    "env.normalize=false") == (2e-4, 500, False)  # fmt: skip
    assert settings("env=cartpole", "train.lr=1e-4") == (1e-4, 500, False)
    assert compose_config(["controller=hinf_f", "env=acrobot"]).env.normalize  # the NTK box's


def test_mountain_car_features_shared_and_integrator_kept_by_the_controlled_agents() -> None:
    """Every Mountain car agent sees 6 x 6 radial basis features (conf/env/mountaincar.yaml;
    Double DQN through weights.ddqn.rbf_centres); the controlled agents keep x_e across
    episodes (conf/weights/mountaincar.yaml); elsewhere x_e is reset as the research code
    does."""

    def inputs_and_reset(*overrides: str) -> tuple[int, bool]:
        conf: Config = OmegaConf.to_object(compose_config(list(overrides)))
        env = make_env(conf.env)
        size = env_sizes(env)[0]
        env.close()
        return size, conf.controller.reset_integrator

    for ctrl in ("h2", "hinf", "hinf_f"):
        assert inputs_and_reset("env=mountaincar", f"controller={ctrl}") == (36, False)
        assert inputs_and_reset("env=acrobot", f"controller={ctrl}") == (6, True)
        assert inputs_and_reset("env=cartpole", f"controller={ctrl}") == (4, True)
    assert inputs_and_reset("env=mountaincar", "controller=ddqn")[0] == 36
    assert inputs_and_reset("env=acrobot", "controller=ddqn")[0] == 6
    assert (
        inputs_and_reset("env=mountaincar", "controller=ddqn", "weights.ddqn.rbf_centres=null")[0]
        == 2
    )
    assert inputs_and_reset("env=mountaincar", "controller=ddqn", "env.rbf_centres=4")[0] == 16
    assert inputs_and_reset("env=mountaincar", "controller=h2", "env.rbf_centres=null",
                            "controller.reset_integrator=true") == (2, True)  # fmt: skip


def test_any_discrete_gymnasium_id_runs_through_env_id() -> None:
    cfg = compose_config(["env.id=CartPole-v0", "env.max_episode_steps=null"])
    env = make_env(OmegaConf.to_object(cfg).env)
    assert env.spec is not None and env.spec.max_episode_steps == 200
    env.close()


def test_network_dtype_option() -> None:
    net = QNetwork(NetworkSpec(2, 2, 8, "float32"))
    assert net.hidden.weight.dtype == torch.float32


TUNED_PRESET_KEYS = {"weights", "env", "train", "controller", "network", "extra"}
"""The groups a tuned weights preset (``_global_``) may set: those a study tunes, and the
network it was tuned on."""


def _group_files() -> list[tuple[str, Path]]:
    """Every config of a ``conf/`` group (``conf/<group>/.../<option>.yaml``) with its
    package, the group's path dotted (``hydra/help/train.yaml``: ``hydra.help``)."""
    return [
        (".".join(path.relative_to(CONF_DIR).parent.parts), path)
        for path in sorted(CONF_DIR.glob("*/**/*.yaml"))
    ]


def _package(text: str) -> str | None:
    """The ``# @package`` header of a config file's text, if any."""
    found = re.search(r"^#\s*@package\s+(\S+)", text, re.MULTILINE)
    return found[1] if found else None


@pytest.mark.parametrize("package, path", _group_files(), ids=lambda v: str(v)[-40:])
def test_every_group_file_writes_only_its_own_keys(package: str, path: Path) -> None:
    """Each file of a ``conf/`` group writes only its group's keys: a ``# @package`` header,
    if any, names its own package (``_group_`` or the group's dotted path); its defaults list
    extends configs of its own group only (plain names: no ``@package``, ``override`` or
    ``group: option`` entries); and no top-level key is named like another group (``env:`` in
    a controller file is a write meant for another group).  A setting that depends on another
    group reads it through an interpolation in the group that owns the key (``env.normalize:
    ${cdqn.agent:normalize,...}`` for Double DQN's weights).

    The one exception, by design: a tuned weights preset (``conf/weights/tuned_*.yaml``,
    written by ``python -m cdqn.tune``, :mod:`cdqn.tuning.presets`) is ``_global_``.  It is one
    trial's settings in every group the study tuned, so that ``weights=<preset>`` trains that
    trial again; it names itself (``weights.name``), records its study (``extra.tuned``) and
    sets only the tuned groups (:data:`TUNED_PRESET_KEYS`).  Configs outside ``conf/``
    groups (the primary configs ``conf/*.yaml``, the experiments in ``sweeps/``) set whatever
    they compose."""
    text = path.read_text()
    node = OmegaConf.load(path)
    header = _package(text)
    if package == "weights" and path.stem.startswith("tuned_"):
        assert header == "_global_", f"{path}: a tuned preset is _global_"
        assert set(node) <= TUNED_PRESET_KEYS, f"{path}: sets {sorted(set(node))}"
        assert node.weights.name == path.stem and "tuned" in node.extra
        return
    assert header in (None, "_group_", package), f"{path}: # @package {header}"
    for entry in node.get("defaults", []):
        assert isinstance(entry, str) and not re.search(r"[@:/]|^override ", entry), (
            f"{path}: defaults entry {entry!r} places a config outside {package}"
        )
    group = package.split(".")[0]
    groups = {f.name for f in dataclasses.fields(Config)} | {
        d.name for d in CONF_DIR.iterdir() if d.is_dir()
    }
    others = sorted((groups - {group}) & set(node))
    assert not others, f"{path}: top-level keys {others} belong to other groups"
