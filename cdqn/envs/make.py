"""Building an environment from ``env.*``: any gymnasium id with a discrete action space.

``env.id`` is a registered id (``CartPole-v1``, ``ALE/Pong-v5``) or, as in
``gymnasium.make``, ``<module>:<Id>``: the module is imported first and registers ``<Id>``
(``env.id=my_package.envs:Chain-v0``).  ``env.kwargs`` go to the environment's constructor.
Every problem is one :class:`ConfigError` line naming the key, the value and what to do.
"""

from __future__ import annotations

import difflib
import hashlib
import importlib
import json
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.envs.registration import EnvSpec
from gymnasium.spaces import Box, Discrete
from gymnasium.wrappers import FlattenObservation

from cdqn.config import ConfigError, EnvConfig, of_kind
from cdqn.envs.wrappers import (
    ActionStart,
    ObservationScale,
    ObservationSubset,
    OneHot,
    RadialFeatures,
    flattens,
)

MAX_FLAT_INPUTS = 1024
"""The most network inputs :func:`make_env` gives an observation: the entries of a ``Box``
(flattened when of another shape, or a ``MultiBinary``), or the one-hot values of discrete
ones (a ``Discrete(n)`` is ``n`` inputs)."""

EXTRAS = {
    "box2d": 'pip install "gymnasium[box2d]"',
    "mujoco": 'pip install "gymnasium[mujoco]"',
}
"""Install commands of gymnasium's optional environment families."""


@dataclass(frozen=True)
class EnvId:
    """``env.id`` taken apart: ``<module>:<name>`` or ``<name>``."""

    module: str | None
    """The module that registers ``name`` when imported (None: gymnasium's own ids)."""
    name: str
    """The registered id, e.g. ``Chain-v0`` or ``ALE/Pong-v5``."""

    @classmethod
    def parse(cls, env_id: str) -> EnvId:
        module, sep, name = env_id.rpartition(":")
        return cls(module if sep else None, name)

    @property
    def label(self) -> str:
        """A name safe in file names, run names and tags: the id without its module,
        ``/`` replaced by ``-`` (``ALE/Pong-v5`` → ``ALE-Pong-v5``)."""
        return self.name.replace("/", "-")


SAFE_TEXT = re.compile(r"[A-Za-z0-9_+.-]{1,32}")
"""Text a label carries as it is: safe in a Hydra override value, a file name, an MLflow run
name or tag and an Optuna study name."""


def env_label(env_id: str, kwargs: Mapping[str, Any] | None = None, cap: int | None = None) -> str:
    """The label of a run's environment (``env.name`` of an adopted id):
    ``<id>[-cap<N>][.<key>-<value>...]``.

    ``<id>`` is :attr:`EnvId.label`; ``-cap<N>`` an episode cap its registration does not
    have; then one ``.<key>-<value>`` per constructor argument (``env.kwargs``), keys sorted:
    ``FrozenLake-v1.is_slippery-false.map_name-8x8``, ``CdqnChain-v0.step_reward--2.0``.  A value
    is written as on the command line (``true``, ``null``, ``-2.0``, ``8x8``) when that text is
    at most 32 characters of ``[A-Za-z0-9_+.-]``; any other (a list, a dict, a string with
    spaces) as the first 8 hex digits of the SHA-256 of its JSON (``desc-3f9a0c1e``).  The label
    is then safe wherever it is used: ``weights=tuned_<label>-<agent>``, file names, MLflow
    run names and tags, Optuna study names."""
    label = EnvId.parse(env_id).label + ("" if cap is None else f"-cap{cap}")
    return label + kwargs_label(kwargs)


def kwargs_label(kwargs: Mapping[str, Any] | None) -> str:
    """The part of a label that names constructor arguments (:func:`env_label`): one
    ``.<key>-<value>`` per argument, keys sorted; empty without arguments.  A preset's own id
    with arguments is ``<preset><this>`` (``cartpole.sutton_barto_reward-true``)."""
    args = dict(kwargs or {})
    return "".join(f".{_label_text(key)}-{_label_text(args[key])}" for key in sorted(args))


def _label_text(value: Any) -> str:
    """``value`` as a label writes it (:func:`env_label`)."""
    if isinstance(value, bool) or value is None:
        text = {True: "true", False: "false", None: "null"}[value]
    else:
        text = str(value) if isinstance(value, (int, float, str)) else ""
    if SAFE_TEXT.fullmatch(text):
        return text
    plain = json.dumps(value, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(plain.encode()).hexdigest()[:8]


def registration(env_id: str) -> EnvSpec:
    """The gymnasium registration of ``env_id``, after importing its module (``<module>:``);
    an import failure or an unknown id is a :class:`ConfigError`."""
    parsed = EnvId.parse(env_id)
    if parsed.module is not None:
        try:
            importlib.import_module(parsed.module)
        except Exception as err:  # any failure of the user's module is one line
            raise ConfigError(
                f"env.id={env_id!r}: cannot import module {parsed.module!r} "
                f"({type(err).__name__}: {err}); give an importable module that registers "
                f"{parsed.name!r} (<module>:<Id>)"
            ) from None
    spec = gym.registry.get(parsed.name)
    if spec is None:
        raise _unknown_id(env_id, parsed)
    return spec


def _unknown_id(env_id: str, parsed: EnvId) -> ConfigError:
    """The error for an unregistered id, with the nearest registered ids."""
    ids = [k for k in gym.registry if "/" not in k]
    base = parsed.name.rsplit("-v", 1)[0]
    near = sorted(k for k in ids if k.rsplit("-v", 1)[0] == base)
    near += [
        k for k in difflib.get_close_matches(parsed.name, ids, n=3, cutoff=0.6) if k not in near
    ]
    hint = (
        f"did you mean {', '.join(near)}?"
        if near
        else f"e.g. {', '.join(sorted(ids)[:12])}, ... (python -c 'import gymnasium; "
        "gymnasium.pprint_registry()' lists them all)"
    )
    if parsed.module is not None:
        hint = f"importing {parsed.module!r} did not register {parsed.name!r}; " + hint
    return ConfigError(f"env.id={env_id!r} is not a registered gymnasium environment; {hint}")


def _make(env_id: str, kwargs: dict[str, Any], cap: int | None) -> gym.Env:
    """``gymnasium.make`` of a registered id, with a missing optional dependency or
    constructor arguments it refuses as a :class:`ConfigError`."""
    spec = registration(env_id)
    extra: dict[str, Any] = {} if cap is None else {"max_episode_steps": cap}
    try:
        return gym.make(spec.id, **extra, **kwargs)
    except gym.error.DependencyNotInstalled as err:
        entry = str(spec.entry_point)
        family = next((f for f in EXTRAS if f".{f}." in entry), None)
        fix = EXTRAS[family] if family else f"install what it names ({err})"
        raise ConfigError(
            f"env.id={env_id!r} needs an optional package that is not installed; {fix}"
        ) from None
    except ImportError as err:  # a missing package of the entry point (jax, shimmy, ...)
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(
            f"env.id={env_id!r} cannot be made here: its entry point {_entry_text(spec)} "
            f"failed to import ({type(err).__name__}: {first}); install what it needs or "
            "choose another id"
        ) from None
    except Exception as err:  # with env.kwargs: the constructor's refusal is one line
        if not kwargs:
            raise
        first = str(err).split(" was raised from the environment creator")[0]
        raise ConfigError(
            f"env.kwargs={kwargs}: {spec.id}'s constructor refused them "
            f"({type(err).__name__}: {first}); give arguments and values it takes"
        ) from None


def _entry_text(spec: EnvSpec) -> str:
    """A registration's entry point as ``module:name`` (it may be a string or a callable)."""
    entry = spec.entry_point
    if callable(entry):
        return f"{entry.__module__}:{getattr(entry, '__qualname__', entry)}"
    return str(entry)


def episode_cap(env: EnvConfig) -> int | None:
    """The episode cap of ``env``: ``env.max_episode_steps``, else its id's registration's
    (``env=acrobot`` leaves it to Acrobot-v1's 500); None where neither has one."""
    if env.max_episode_steps is not None:
        return int(env.max_episode_steps)
    return registration(str(env.id)).max_episode_steps


def make_env(cfg: EnvConfig) -> gym.Env:
    """Build the environment of ``cfg``: gymnasium id (its module imported first), its
    constructor arguments ``env.kwargs``, episode cap, actions numbered from 0, one-hot
    encoding of a discrete observation or flattening of another shape, feature subset,
    scaling (``env.normalize``) and radial basis features (``env.rbf_centres``), in that
    order."""
    env = _make(cfg.id, dict(cfg.kwargs or {}), cfg.max_episode_steps)
    if not isinstance(env.action_space, Discrete):
        env.close()
        raise ConfigError(
            f"env.id={cfg.id!r}{_with_kwargs(cfg)} has action space {env.action_space}; "
            "cdqn needs a Discrete one"
        )
    if env.action_space.start != 0:
        env = ActionStart(env)
    raw = env.observation_space
    if OneHot.encodes(raw):
        env = OneHot(env)
    elif flattens(raw, MAX_FLAT_INPUTS):  # an image is refused below, not copied flat
        env = FlattenObservation(env)
    space = env.observation_space
    if not isinstance(space, Box) or len(space.shape) != 1 or space.shape[0] > MAX_FLAT_INPUTS:
        env.close()
        inputs = f" ({gym.spaces.flatdim(space)} inputs)" if isinstance(space, Box) else ""
        raise ConfigError(
            f"env.id={cfg.id!r}{_with_kwargs(cfg)}: cdqn's network takes at most "
            f"{MAX_FLAT_INPUTS} inputs from a Box observation (flattened), a MultiBinary one, "
            f"discrete ones one-hot (Discrete, MultiDiscrete), or a Tuple or Dict of these; got "
            f"{raw}{inputs}"
        )
    if cfg.obs_indices is not None:
        bad = [i for i in cfg.obs_indices if not 0 <= i < space.shape[0]]
        if bad or not cfg.obs_indices:
            env.close()
            raise ConfigError(
                f"env.obs_indices={list(cfg.obs_indices)}: indices must lie in "
                f"[0, {space.shape[0]}) for {cfg.id}"
            )
        env = ObservationSubset(env, list(cfg.obs_indices))
    if cfg.normalize:
        widths = cfg.normalize_scale
        n = of_kind(env.observation_space, Box).shape[0]
        if widths is not None and (len(widths) != n or not all(w > 0 for w in widths)):
            env.close()
            raise ConfigError(
                f"env.normalize_scale={list(widths)}: give {n} half-widths > 0, one per "
                f"observed feature of {cfg.id}, or null"
            )
        env = ObservationScale(env, widths)
    if cfg.rbf_centres is not None:
        env = _radial_features(env, cfg)
    return env


def _with_kwargs(cfg: EnvConfig) -> str:
    """`` with env.kwargs={...}`` when the constructor got arguments (they may be the cause)."""
    return f" with env.kwargs={dict(cfg.kwargs)}" if cfg.kwargs else ""


def _radial_features(env: gym.Env, cfg: EnvConfig) -> RadialFeatures:
    """:class:`RadialFeatures` of ``cfg``, refused on an unbounded or too large box."""
    space = env.observation_space
    assert isinstance(space, Box) and cfg.rbf_centres is not None
    finite = np.isfinite(space.low) & np.isfinite(space.high)
    unbounded = [int(i) for i in np.flatnonzero(~finite)]
    count = cfg.rbf_centres ** space.shape[0]
    problem = None
    if unbounded:
        problem = (
            f"observed features {unbounded} of {cfg.id} have no finite bounds to place centres "
            "on (choose features with env.obs_indices)"
        )
    elif count > RadialFeatures.MAX_FEATURES:
        problem = (
            f"{cfg.rbf_centres}^{space.shape[0]} = {_count_text(count)} features, more than "
            f"{RadialFeatures.MAX_FEATURES}; use fewer centres or features (env.obs_indices)"
        )
    if problem is not None:
        env.close()
        raise ConfigError(f"env.rbf_centres={cfg.rbf_centres}: {problem}")
    return RadialFeatures(env, cfg.rbf_centres, cfg.rbf_width)


def _count_text(count: int) -> str:
    """``count`` as written in a message: in full up to 10^9, else its order of magnitude
    (a one-hot observation of 500 features has 4^500 grid points)."""
    return str(count) if count <= 10**9 else f"about 10^{len(str(count)) - 1}"


def env_sizes(env: gym.Env) -> tuple[int, int]:
    """(observation size, number of actions)."""
    assert isinstance(env.action_space, Discrete)
    return int(of_kind(env.observation_space, Box).shape[0]), int(env.action_space.n)
