"""Adoption: a composed configuration made a run *of its environment*, once per entry point.

Every command (``cdqn.train`` for a single run, a population or a multirun job,
``cdqn.synthesize``, ``cdqn.tune``, ``cdqn.evaluate``, ``cdqn.bench``, the check before Hydra
starts) calls :func:`adopt` on its configuration before anything is built, and reads the
result.

The presets of ``conf/env/`` name one gymnasium id each, with its episode cap and solve
threshold.  When ``env.id`` is not the id of the preset named ``env.name``
(``env=cartpole env.id=Acrobot-v1``, or the default preset with ``env.id=<module>:<Id>``):

* ``env.name`` becomes the id's label (:func:`cdqn.envs.make.env_label`: the id without
  its module, ``/`` → ``-``, ``-cap<N>`` when ``env.max_episode_steps`` is not the cap of its
  registration (always for an id registered without one), then ``.<key>-<value>`` per
  constructor argument ``env.kwargs``, keys sorted), so the run is named
  ``<label>-<controller>-s<seed>``, tagged ``env=<label>`` and grouped under it by the
  analysis and the tuner;
* ``env.obs_indices`` and ``env.normalize_scale`` (:data:`FEATURE_KEYS`: the preset's
  features by index) become null unless the command line gives them;
* ``env.max_episode_steps`` and ``env.solve_threshold`` come from the id's registration
  (``max_episode_steps``, ``reward_threshold``) unless the command line gives them, or
  they were set to something other than the preset's values (a configuration composed in
  code); an id registered without a ``reward_threshold`` has no solve threshold (null: no
  run is judged solved) unless ``env.solve_threshold`` gives one;
* a ``weights`` preset shipped for an environment preset of another id — the one
  ``weights: ${env}`` composes by default — is replaced by ``weights=generic``
  (``conf/weights/generic.yaml``: the research code's design weights and a learning target
  chosen for environments without a preset, docs/research/learning.md), keeping every
  ``weights.*`` value set for the run (given on the command line, or unlike the replaced
  preset's).  A preset named on the command line (``weights=cartpole``) or one of the user's
  own (not shipped, e.g. a tuned preset) is kept.

A preset's own id with another episode cap (``env=cartpole env.max_episode_steps=500``) is
another task: it is labelled by the id (``CartPole-v1``, or ``CartPole-v1-cap300`` for a cap
its registration does not have) and, at the registration's cap, takes its threshold unless one
was set; it keeps the preset's weights.  A preset's own id with constructor arguments at its
cap is the preset's task on another environment instance: labelled ``<preset>.<key>-<value>``
(``env=cartpole +env.kwargs.sutton_barto_reward=true``:
``cartpole.sutton_barto_reward-true``, :func:`cdqn.envs.make.kwargs_label`), with the
preset's cap, threshold and weights.

A tuned preset (``weights=tuned_<label>-<agent>``, which sets the environment it was tuned
on) with another ``env.id`` on the command line is that id's run: labelled by it, its
features by index and ``env.kwargs`` dropped, cap and solve threshold from its registration
and the NTK box measured, each unless the command line gives it; the preset's observation maps,
exploration and learning settings stay.  With other constructor arguments or another cap
on its own id, it is relabelled.

``controller.synthesis.ntk_bounds`` becomes ``measured`` when the weights carry no box of this
environment: ``weights=generic`` (on any id), or, for a run of an id no preset names, a
weights preset of an environment preset of another id — unless ``weights.theta_bounds`` was
set for the run.  A robust design is never built on another environment's NTK box.  A weights
preset of the user's own keeps its box.  A run of a preset's own id with its own weights is
left as it is.

Refused, one line each: an id that cannot be imported or is not registered, and an
environment registered without an episode cap when ``env.max_episode_steps`` is not given
(an episode must end for the run to make progress).
"""

from __future__ import annotations

import copy
import functools
import re
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path

import yaml
from gymnasium.envs.registration import EnvSpec
from omegaconf import DictConfig, OmegaConf, read_write

from cdqn.config import (
    CONF_DIR,
    Config,
    ConfigError,
    EnvConfig,
    WeightsConfig,
    merged,
    to_schema,
    validate,
)
from cdqn.envs.make import EnvId, env_label, kwargs_label, registration

_COMMAND_LINE: ContextVar[tuple[str, ...] | None] = ContextVar("cdqn_overrides", default=None)
GENERIC = "generic"
"""The shipped weights preset of an environment without one of its own
(``conf/weights/generic.yaml``)."""
FEATURE_KEYS = ("obs_indices", "normalize_scale")
"""Settings of an environment preset that name its observation's features one by one: a
run of another id drops them unless it sets them (:func:`adopt`)."""
BOX_SOURCES = ("config", "measured")
"""Where the robust designs' NTK box comes from (``controller.synthesis.ntk_bounds``)."""


@dataclass(frozen=True)
class Adopted:
    """A configuration adopted by its environment (:func:`adopt`)."""

    cfg: DictConfig
    """The adopted configuration: a new object, the input is left unchanged."""
    conf: Config
    """``cfg`` as the schema's typed object, validated (:func:`cdqn.config.validate`)."""
    change: str | None
    """One line saying what adoption changed; None when nothing did."""

    @property
    def box_source(self) -> str:
        """``measured`` (rollout of the run's own network) or ``config``
        (``weights.theta_bounds``); recorded as the param ``controller.synthesis.ntk_bounds``."""
        return str(self.conf.controller.synthesis.ntk_bounds)


def adopt(cfg: DictConfig) -> Adopted:
    """``cfg`` as a run of its environment (module docstring); idempotent under the same
    command line: ``adopt(adopt(cfg).cfg).change is None``.  Raises :class:`ConfigError` for
    an id that cannot be made, an environment without an episode cap, or any value
    :func:`cdqn.config.validate` refuses."""
    out = copy.deepcopy(cfg)
    env = out.env
    spec = registration(str(env.id))  # imports <module>: of <module>:<Id>
    preset = env_presets().get(str(env.name))
    changed: list[str] = []
    overrides = _overrides()
    given = _given(out, overrides)
    tuned_on = None if preset is not None else _tuned_elsewhere(out, spec, given)
    with read_write(out):
        if preset is not None and preset.id != env.id:
            changed += _take_registration(env, preset, spec, given)
        elif preset is not None and env.max_episode_steps != preset.max_episode_steps:
            changed += _other_cap(env, preset, spec, given)
        elif preset is not None and _kwargs(env):
            env.name = preset.name + kwargs_label(_kwargs(env))
            changed.append(f"named {env.name}")
        elif tuned_on is not None:
            changed += _leave_tuned_env(out, spec, given, tuned_on, _keys(overrides))
        if preset is None or preset.id != env.id:
            changed += _weights_of_its_own(out, given, "weights" in _keys(overrides))
        if preset is None or preset.id != env.id or out.weights.name == GENERIC:
            changed += _box_of_its_own(out)
    if env.max_episode_steps is None and spec.max_episode_steps is None:
        raise ConfigError(
            f"env.max_episode_steps=null: {env.id} is registered without an episode cap "
            "(max_episode_steps) and none was given; give one, env.max_episode_steps=<steps>"
        )
    conf = to_schema(out, Config)
    validate(conf)
    head = ""
    if preset is not None and preset.id != env.id:
        head = f"env.id={env.id} is not env={preset.name}'s {preset.id}: "
    elif preset is not None and env.max_episode_steps != preset.max_episode_steps:
        head = f"env={preset.name} at another episode cap: "
    elif preset is not None and _kwargs(env):
        head = f"env={preset.name} with constructor arguments env.kwargs: "
    elif tuned_on is not None:
        head = f"weights={out.weights.name} was tuned on {tuned_on}: "
    return Adopted(out, conf, head + ", ".join(changed) if changed else None)


@functools.lru_cache(maxsize=4)
def env_presets(conf_dir: Path = CONF_DIR) -> dict[str, EnvConfig]:
    """The environment presets shipped in ``conf_dir/env/*.yaml`` (``cartpole``, ``acrobot``,
    ...) by their ``name``."""
    folder = conf_dir / "env"
    out: dict[str, EnvConfig] = {}
    for path in sorted(folder.glob("*.yaml")):
        preset = merged(OmegaConf.structured(EnvConfig), _group_file(folder, path.stem))
        env = to_schema(preset, EnvConfig)
        out[env.name] = env
    return out


def _group_file(folder: Path, stem: str) -> DictConfig:
    """``folder/<stem>.yaml`` over the files its ``defaults`` list names in the same group
    (``cartpole_pole`` over ``cartpole``), as Hydra composes it."""
    node = OmegaConf.load(folder / f"{stem}.yaml")
    assert isinstance(node, DictConfig)
    bases = [d for d in node.pop("defaults", []) if d != "_self_"]
    return merged(*[_group_file(folder, b) for b in bases], node)


@contextmanager
def command_line(overrides: list[str]) -> Iterator[None]:
    """Within the block, :func:`adopt` takes ``overrides`` as the command line (the check
    before Hydra starts composes without a Hydra job)."""
    token = _COMMAND_LINE.set(tuple(overrides))
    try:
        yield
    finally:
        _COMMAND_LINE.reset(token)


def _overrides() -> tuple[str, ...]:
    """The command line: that of :func:`command_line`, else the running Hydra job's overrides
    (none for a configuration composed in code)."""
    overrides = _COMMAND_LINE.get()
    if overrides is None:
        from hydra.core.hydra_config import HydraConfig

        overrides = tuple(HydraConfig.get().overrides.task) if HydraConfig.initialized() else ()
    return overrides


def _keys(overrides: tuple[str, ...]) -> frozenset[str]:
    """The keys (and config groups) the command line sets."""
    return frozenset(text.lstrip("+~").partition("=")[0] for text in overrides)


def _given(cfg: DictConfig, overrides: tuple[str, ...]) -> frozenset[str]:
    """The keys of ``env.*`` and ``weights.*`` the command line gives their present value."""
    out = set()
    for text in overrides:
        key, eq, value = text.lstrip("+~").partition("=")
        if (
            eq
            and key.startswith(("env.", "weights."))
            and OmegaConf.select(cfg, key) == _value(value)
        ):
            out.add(key)
    return frozenset(out)


def _value(text: str) -> object:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def _take_registration(
    env: DictConfig, preset: EnvConfig, spec: EnvSpec, given: frozenset[str]
) -> list[str]:
    """Name, cap and threshold of ``env.id`` (registered as ``spec``) in place of
    ``preset``'s unless given; what changed."""
    cap, threshold = spec.max_episode_steps, spec.reward_threshold
    changed: list[str] = []
    plain = OmegaConf.to_container(env, resolve=True)
    assert isinstance(plain, dict)
    for key in FEATURE_KEYS:  # indices and widths of the preset's observation, not this one's
        value = plain[key]
        if value is not None and value == getattr(preset, key) and f"env.{key}" not in given:
            env[key] = None
            changed.append(f"env.{key}=null (not {preset.name}'s {value})")
    if env.max_episode_steps == preset.max_episode_steps and "env.max_episode_steps" not in given:
        env.max_episode_steps = cap
        changed.append(f"episode cap {cap} (its registration)")
    other = env.max_episode_steps not in (None, cap)  # always for ids registered without one
    env.name = env_label(str(env.id), _kwargs(env), env.max_episode_steps if other else None)
    changed.insert(0, f"named {env.name}")
    if env.solve_threshold == preset.solve_threshold and "env.solve_threshold" not in given:
        env.solve_threshold = threshold
        changed.append(
            f"solve threshold {threshold} (its registration)"
            if threshold is not None
            else "no solve threshold (none registered; env.solve_threshold=<return> sets one)"
        )
    return changed


def _other_cap(
    env: DictConfig, preset: EnvConfig, spec: EnvSpec, given: frozenset[str]
) -> list[str]:
    """A preset's id with another episode cap is another task (CartPole-v1 at 500 steps is
    not the 200-step ``cartpole``): labelled by the id, with ``-cap<N>`` unless the cap is the
    registration's, whose solve threshold it then takes unless one was set."""
    cap = env.max_episode_steps
    label = env_label(str(env.id), _kwargs(env), None if cap == spec.max_episode_steps else cap)
    env.name = label
    changed = [f"named {label} (episode cap {cap}, not {preset.name}'s {preset.max_episode_steps})"]
    same = env.solve_threshold == preset.solve_threshold and "env.solve_threshold" not in given
    if same and cap == spec.max_episode_steps:
        env.solve_threshold = spec.reward_threshold
        changed.append(f"solve threshold {spec.reward_threshold} (its registration)")
    return changed


def _label(env: DictConfig, spec: EnvSpec) -> str:
    """The label of ``env`` as it stands (:func:`cdqn.envs.make.env_label`)."""
    cap = env.max_episode_steps
    other = cap not in (None, spec.max_episode_steps)
    return env_label(str(env.id), _kwargs(env), cap if other else None)


def _tuned_elsewhere(cfg: DictConfig, spec: EnvSpec, given: frozenset[str]) -> str | None:
    """The environment a tuned preset (``extra.tuned``, :mod:`cdqn.tuning.presets`) was tuned
    on, when the run is not that environment (the command line gives another ``env.id``,
    constructor arguments or cap): its ``env.id``, or for a preset that does not record the
    id, the id's part of its label (``FrozenLake-v1`` of ``FrozenLake-v1-cap50.is_slippery-false``).
    None for any other configuration, or when ``env.name`` is given."""
    tuned = OmegaConf.select(cfg, "extra.tuned", default=None)
    if not OmegaConf.is_dict(tuned) or "env.name" in given or cfg.env.name == _label(cfg.env, spec):
        return None
    return str(tuned.get("env_id") or re.sub(r"-cap\d+$", "", str(cfg.env.name).split(".")[0]))


def _leave_tuned_env(
    cfg: DictConfig, spec: EnvSpec, given: frozenset[str], tuned_on: str, keys: frozenset[str]
) -> list[str]:
    """A tuned preset's settings on another environment: labelled by this one.  On another id
    (not only other constructor arguments or cap), the preset's environment-specific settings
    give way to this id's unless the command line gives them: features by index and
    ``env.kwargs`` are dropped, cap and solve threshold come from the registration, and the
    design's NTK box is measured (the preset's is ``tuned_on``'s).  Its observation maps,
    exploration and learning settings stay.  What changed."""
    env = cfg.env
    changed: list[str] = []
    if EnvId.parse(tuned_on).label != EnvId.parse(str(env.id)).label:
        for key in FEATURE_KEYS:
            if env[key] is not None and f"env.{key}" not in given:
                env[key] = None
                changed.append(f"env.{key}=null")
        if _kwargs(env) and not any(k.startswith("env.kwargs") for k in given):
            env.kwargs = {}
            changed.append("env.kwargs={}")
        if "env.max_episode_steps" not in given:
            env.max_episode_steps = spec.max_episode_steps
            changed.append(f"episode cap {spec.max_episode_steps} (its registration)")
        if "env.solve_threshold" not in given:
            env.solve_threshold = spec.reward_threshold
            changed.append(f"solve threshold {spec.reward_threshold} (its registration)")
        box = {"controller.synthesis.ntk_bounds", "weights.theta_bounds"}
        if not any(k.startswith(tuple(box)) for k in keys):
            cfg.controller.synthesis.ntk_bounds = "measured"
            changed.append("NTK box measured")
    env.name = _label(env, spec)
    return [f"named {env.name}", *changed]


def _kwargs(env: DictConfig) -> dict[str, object]:
    """``env.kwargs`` as plain values."""
    kwargs = OmegaConf.to_container(env.kwargs, resolve=True) if env.get("kwargs") else {}
    assert isinstance(kwargs, dict)
    return {str(k): v for k, v in kwargs.items()}


def shipped_weights(name: str) -> DictConfig:
    """The shipped weights preset ``conf/weights/<name>.yaml`` over the schema's defaults, as
    composing ``weights=<name>`` gives it."""
    node = OmegaConf.merge(
        OmegaConf.structured(WeightsConfig), _group_file(CONF_DIR / "weights", name)
    )
    assert isinstance(node, DictConfig)
    return node


def _leaves(node: object, prefix: str) -> dict[str, object]:
    """The values of a plain tree by dotted key (a list is one value)."""
    if not isinstance(node, dict):
        return {prefix: node}
    out: dict[str, object] = {}
    for key, value in node.items():
        out.update(_leaves(value, f"{prefix}.{key}"))
    return out


def _weights_of_its_own(cfg: DictConfig, given: frozenset[str], chosen: bool) -> list[str]:
    """``weights=generic`` in place of another environment's shipped weights preset, unless
    the command line chose that preset (``weights=cartpole``).  A value of ``weights.*`` set
    for this run (on the command line, or unlike the preset's) is kept over generic's."""
    name = str(cfg.weights.name)
    weights_env = env_presets().get(name)
    if weights_env is None or weights_env.id == cfg.env.id or chosen:
        return []
    own = _leaves(OmegaConf.to_container(cfg.weights, resolve=True), "weights")
    shipped = _leaves(OmegaConf.to_container(shipped_weights(name), resolve=True), "weights")
    generic = shipped_weights(GENERIC)
    for key, value in own.items():
        if key != "weights.name" and (key in given or value != shipped.get(key)):
            OmegaConf.update(generic, key.removeprefix("weights."), value, merge=False)
    cfg.weights = generic
    return [f"weights={GENERIC} in place of {weights_env.id}'s weights={name}"]


def _box_of_its_own(cfg: DictConfig) -> list[str]:
    """``ntk_bounds=measured`` when the box is not this environment's: the weights preset is
    :data:`GENERIC` or belongs to an environment preset of another id, and
    ``weights.theta_bounds`` is still that preset's box (a box set for this run, e.g. one a
    study measured, stays)."""
    name = str(cfg.weights.name)
    weights_env = env_presets().get(name)
    syn = cfg.controller.synthesis
    foreign = name == GENERIC or (weights_env is not None and weights_env.id != cfg.env.id)
    if not foreign or syn.ntk_bounds == "measured":
        return []
    shipped = shipped_weights(name).theta_bounds
    if OmegaConf.to_container(cfg.weights.theta_bounds) != OmegaConf.to_container(shipped):
        return []
    syn.ntk_bounds = "measured"
    whose = "have none" if weights_env is None else f"are {weights_env.id}'s"
    return [f"NTK box measured (weights={name} {whose})"]
