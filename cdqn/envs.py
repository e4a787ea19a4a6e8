"""Environments: any gymnasium id with a discrete action space.

The presets of ``conf/env/`` (``cartpole``, ``acrobot``, ...) name one gymnasium id each,
with its episode cap and solve threshold.  ``env.id=<id>`` on top of a preset trains that
other environment: :func:`adopt_env_id` then takes its name, cap and threshold from the
id's own registration, so the run is labelled and judged as what it trains.
"""

from __future__ import annotations

import difflib
import functools
import logging
from pathlib import Path

import gymnasium as gym
import numpy as np
from gymnasium.spaces import Box, Discrete
from omegaconf import DictConfig, OmegaConf, read_write

from cdqn.config import ConfigError, EnvConfig

log = logging.getLogger("cdqn")

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
"""The Hydra config folder shipped with cdqn."""
EXTRAS = {
    "box2d": 'pip install swig, then pip install "gymnasium[box2d]"',
    "mujoco": 'pip install "gymnasium[mujoco]"',
}
"""Install commands of gymnasium's optional environment families."""


@functools.lru_cache(maxsize=4)
def env_presets(conf_dir: Path = CONF_DIR) -> dict[str, EnvConfig]:
    """The environment presets of ``conf_dir/env/*.yaml`` by their ``name``."""
    folder = conf_dir / "env"

    def load(stem: str) -> DictConfig:
        node = OmegaConf.load(folder / f"{stem}.yaml")
        assert isinstance(node, DictConfig)
        bases = [d for d in node.pop("defaults", []) if d != "_self_"]
        return OmegaConf.merge(*[load(b) for b in bases], node)  # type: ignore[return-value]

    out: dict[str, EnvConfig] = {}
    for path in sorted(folder.glob("*.yaml")):
        preset = OmegaConf.merge(OmegaConf.structured(EnvConfig), load(path.stem))
        env: EnvConfig = OmegaConf.to_object(preset)  # type: ignore[assignment]
        out[env.name] = env
    return out


def adopt_env_id(cfg: DictConfig) -> str | None:
    """Make a run whose ``env.id`` is not its preset's id a run of that id, in place.

    The preset is the one named ``env.name``.  When ``env.id`` differs from the preset's id
    (``env=cartpole env.id=Acrobot-v1``):

    * ``env.name`` becomes the id, so the run is named ``<id>-<controller>-s<seed>`` and
      tagged ``env=<id>``;
    * ``env.max_episode_steps`` and ``env.solve_threshold`` come from the id's registration
      (``gymnasium.spec(id)``: ``max_episode_steps``, ``reward_threshold``) unless they were
      set to something other than the preset's values;
    * ``controller.synthesis.ntk_bounds`` becomes ``measured`` unless the selected
      ``weights`` preset belongs to an environment preset of this id: a robust design is
      never built on another environment's NTK box.

    Returns one line saying what changed, or None when nothing did (a preset's own id, a
    name no preset has, an id gymnasium does not know: :func:`make_env` refuses that).
    """
    presets = env_presets()
    env = cfg.env
    preset = presets.get(str(env.name))
    if preset is None or env.id == preset.id or env.id not in gym.registry:
        return None
    spec = gym.spec(env.id)
    changed = [f"named {env.id}"]
    with read_write(cfg):
        env.name = env.id
        if env.max_episode_steps == preset.max_episode_steps:
            env.max_episode_steps = spec.max_episode_steps
            changed.append(f"episode cap {spec.max_episode_steps} (its registration)")
        if env.solve_threshold == preset.solve_threshold:
            env.solve_threshold = spec.reward_threshold
            changed.append(f"solve threshold {spec.reward_threshold} (its registration)")
        weights_env = presets.get(str(cfg.weights.name))
        if weights_env is None or weights_env.id != env.id:
            cfg.controller.synthesis.ntk_bounds = "measured"
            ctrl = cfg.controller
            if ctrl.design == "synthesize" and ctrl.name in ("hinf", "hinf_f"):
                changed.append(
                    f"NTK box measured (weights={cfg.weights.name} are another environment's)"
                )
    return f"env.id={env.id} is not env={preset.name}'s {preset.id}: " + ", ".join(changed)


def _unknown_id(env_id: str) -> ConfigError:
    """The error for an unregistered id, with the nearest registered ids."""
    ids = [k for k in gym.registry if "/" not in k]
    base = env_id.rsplit("-v", 1)[0]
    near = sorted(k for k in ids if k.rsplit("-v", 1)[0] == base)
    near += [k for k in difflib.get_close_matches(env_id, ids, n=3, cutoff=0.6) if k not in near]
    hint = (
        f"did you mean {', '.join(near)}?"
        if near
        else f"e.g. {', '.join(sorted(ids)[:12])}, ... (python -c 'import gymnasium; "
        "gymnasium.pprint_registry()' lists them all)"
    )
    return ConfigError(f"env.id={env_id!r} is not a registered gymnasium environment; {hint}")


def _make(env_id: str, **kwargs: object) -> gym.Env:
    """``gymnasium.make``, with a missing optional dependency as a :class:`ConfigError`."""
    try:
        return gym.make(env_id, **kwargs)
    except gym.error.DependencyNotInstalled as err:
        entry = str(gym.spec(env_id).entry_point)
        family = next((f for f in EXTRAS if f".{f}." in entry), None)
        fix = EXTRAS[family] if family else f"install what it names ({err})"
        raise ConfigError(
            f"env.id={env_id!r} needs an optional package that is not installed; {fix}"
        ) from None


class ObservationSubset(gym.ObservationWrapper):
    """Keep only the observation features ``indices`` (e.g. pole angle and velocity)."""

    def __init__(self, env: gym.Env, indices: list[int]) -> None:
        super().__init__(env)
        space = env.observation_space
        assert isinstance(space, Box)
        self.indices = np.asarray(indices, dtype=np.int64)
        self.observation_space = Box(
            space.low[self.indices], space.high[self.indices], dtype=space.dtype
        )

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return observation[self.indices]


class ObservationScale(gym.ObservationWrapper):
    """Map each observation feature affinely from its ``[low, high]`` to ``[−1, 1]``
    (``env.normalize``), or to ``[−w, w]`` with per-feature half-widths ``widths``
    (``env.normalize_scale``); features with an infinite bound are passed through unchanged.

    A wide network's NTK compares inputs through ``x·y`` and its ReLU pattern: features on
    very different scales (Mountain car's velocity is a hundredth of its position) leave
    the kernel blind to the small ones, so every state looks alike to the learning update
    (Θ2/Θ1 within 1 ± 0.007 on Mountain car)."""

    def __init__(self, env: gym.Env, widths: list[float] | None = None) -> None:
        super().__init__(env)
        space = env.observation_space
        assert isinstance(space, Box)
        low, high = space.low.astype(np.float64), space.high.astype(np.float64)
        w = np.ones(low.shape) if widths is None else np.asarray(widths, dtype=np.float64)
        finite = np.isfinite(low) & np.isfinite(high) & (high > low)
        self.offset = np.where(finite, 0.5 * (low + high), 0.0).astype(space.dtype)
        self.scale = np.where(finite, 2.0 * w / np.where(finite, high - low, 1.0), 1.0).astype(
            space.dtype
        )
        self.observation_space = Box(
            np.where(finite, -w, low).astype(space.dtype),
            np.where(finite, w, high).astype(space.dtype),
            dtype=space.dtype,
        )

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return (observation - self.offset) * self.scale


class RadialFeatures(gym.ObservationWrapper):
    """Gaussian radial basis features of the observation (``env.rbf_centres``).

    With ``n`` centres per feature on a grid over the observation box ``[low, high]`` (the
    scaled box when ``env.normalize`` is on), the network sees, instead of ``s``,

    .. math::  \\phi_j(s) = \\exp\\Big(-\\tfrac12 \\sum_i
               \\big((s_i - c_{ji})/\\sigma_i\\big)^2\\Big),
               \\qquad \\sigma_i = w\\,(\\mathrm{high}_i - \\mathrm{low}_i)/(n - 1),

    ``n^d`` features for ``d`` observed features (``w``: ``env.rbf_width``, in grid spacings).
    The NTK of the two-layer ReLU network compares inputs through ``x·y`` and the angle
    between them: on raw or scaled observations every pair of states is similar to it, so one
    online step moves Q over the whole state space alike.  On ``φ`` two states far apart share
    no features, and a step mostly moves Q near the state it learns from (docs/learning.md,
    §6: Mountain car's controlled agents learn with them)."""

    MAX_FEATURES = 4096
    """The largest n^d accepted (the network's input size)."""

    def __init__(self, env: gym.Env, centres: int, width: float) -> None:
        super().__init__(env)
        space = env.observation_space
        assert isinstance(space, Box)
        low, high = space.low.astype(np.float64), space.high.astype(np.float64)
        grid = [np.linspace(lo, hi, centres) for lo, hi in zip(low, high, strict=True)]
        mesh = np.meshgrid(*grid, indexing="ij")
        self.dtype = space.dtype
        self.centres = np.stack(mesh, axis=-1).reshape(-1, len(low)).astype(self.dtype)
        self.sigma = (width * (high - low) / (centres - 1)).astype(self.dtype)
        self.observation_space = Box(0.0, 1.0, (len(self.centres),), dtype=self.dtype)

    def features(self, obs: np.ndarray) -> np.ndarray:
        """``φ`` of each row of ``obs`` ``(K, d)``: ``(K, n^d)``; the population's
        environments call this on all members at once, with the same result per row."""
        z = (obs[:, None, :] - self.centres[None, :, :]) / self.sigma
        return np.exp(-0.5 * (z * z).sum(axis=-1)).astype(self.dtype)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return self.features(np.asarray(observation)[None, :])[0]


def make_env(cfg: EnvConfig) -> gym.Env:
    """Build the environment of ``cfg``: gymnasium id, episode cap, feature subset, scaling
    (``env.normalize``) and radial basis features (``env.rbf_centres``), in that order."""
    if cfg.id not in gym.registry:
        raise _unknown_id(cfg.id)
    kwargs = {} if cfg.max_episode_steps is None else {"max_episode_steps": cfg.max_episode_steps}
    env = _make(cfg.id, **kwargs)
    if not isinstance(env.action_space, Discrete):
        env.close()
        raise ConfigError(
            f"env.id={cfg.id!r} has action space {env.action_space}; cdqn needs a Discrete one"
        )
    space = env.observation_space
    if not isinstance(space, Box) or len(space.shape) != 1:
        env.close()
        raise ConfigError(f"env.id={cfg.id!r}: cdqn needs a flat Box observation, got {space}")
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
        n = env.observation_space.shape[0]  # type: ignore[index]
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
            f"{cfg.rbf_centres}^{space.shape[0]} = {count} features, more than "
            f"{RadialFeatures.MAX_FEATURES}; use fewer centres or features (env.obs_indices)"
        )
    if problem is not None:
        env.close()
        raise ConfigError(f"env.rbf_centres={cfg.rbf_centres}: {problem}")
    return RadialFeatures(env, cfg.rbf_centres, cfg.rbf_width)


def env_sizes(env: gym.Env) -> tuple[int, int]:
    """(observation size, number of actions)."""
    assert isinstance(env.action_space, Discrete)
    return int(env.observation_space.shape[0]), int(env.action_space.n)
