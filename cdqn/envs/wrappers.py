"""Wrappers: what the network sees of an environment's observation, and its actions.

:func:`cdqn.envs.make.make_env` numbers the actions from 0 (:class:`ActionStart`) and
applies the observation maps in the order one-hot encoding (a ``Discrete``,
``MultiDiscrete``, or a ``Tuple`` or ``Dict`` of them) or flattening (a ``Box`` of another
shape, a ``MultiBinary``, a ``Tuple`` or ``Dict`` with ``Box`` parts), feature subset,
scaling, radial basis features.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium.spaces import Box, Dict, Discrete, MultiBinary, MultiDiscrete, Space, Tuple


def real_dtype(space: Box) -> np.dtype:
    """The dtype of a map of ``space``'s observations: its own when it is a floating one, else
    float32 (an integer ``Box``, e.g. cell counts or a RAM state, scaled in integers would
    round every feature to 0)."""
    dtype = np.dtype(space.dtype)
    return dtype if np.issubdtype(dtype, np.floating) else np.dtype(np.float32)


class OneHot(gym.ObservationWrapper):
    """A ``Discrete(n)`` observation as the one-hot vector ``e_s`` of length ``n``; a
    ``MultiDiscrete`` one, or a ``Tuple`` or ``Dict`` of such spaces, as the concatenation of
    the one-hot vectors of its parts (in the order of the flattened ``nvec``, of the
    ``Tuple``, of the ``Dict``'s keys: ``gymnasium.spaces.flatten``'s order).

    A state index fed as a number would be read as a magnitude (Taxi's state 400 "larger"
    than state 4).  With ``e_s`` every state has its own input direction: in the NTK of
    :mod:`cdqn.network`, ``Θ((x,a),(y,b)) = [a=b](h·g + 1) + (x·y + 1) Σ_j …``, two distinct
    states have ``x·y = 0`` (one ``Discrete``), so the hidden-layer term of Θ2 counts the
    bias only, and a step at ``s`` moves Q at other states less than at ``s``."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        parts = self.parts(env.observation_space)
        assert parts is not None
        self.sizes = [n for n, _ in parts]
        self.starts = np.array([start for _, start in parts], dtype=np.int64)
        self.first = int(self.starts[0])
        self.offsets = np.concatenate([[0], np.cumsum(self.sizes)[:-1]]).astype(np.int64)
        self.width = int(sum(self.sizes))
        self.raw = env.observation_space
        self.nested = _nested(self.raw)
        self.observation_space = Box(0.0, 1.0, (self.width,), dtype=np.float32)

    @staticmethod
    def encodes(space: Space) -> bool:
        """Whether :class:`OneHot` encodes ``space`` (class docstring)."""
        return OneHot.parts(space) is not None

    @staticmethod
    def parts(space: Space) -> list[tuple[int, int]] | None:
        """Size ``n`` and first value ``start`` of each discrete part of ``space``, or None
        when ``space`` is not made of discrete parts only."""
        if isinstance(space, Discrete):
            return [(int(space.n), int(space.start))]
        if isinstance(space, MultiDiscrete):
            sizes, starts = space.nvec.reshape(-1), np.asarray(space.start).reshape(-1)
            return [(int(n), int(s)) for n, s in zip(sizes, starts, strict=True)] or None
        if isinstance(space, Tuple | Dict) and space.spaces:
            each = [OneHot.parts(s) for s in _parts(space)]
            return None if any(p is None for p in each) else [x for p in each if p for x in p]
        return None

    def observation(self, observation: object) -> np.ndarray:
        out = np.zeros(self.width, dtype=np.float32)
        if isinstance(observation, int | np.integer):  # one Discrete
            out[int(observation) - self.first] = 1.0
            return out
        if self.nested:  # a Dict, or a Tuple with Tuple or Dict parts: gymnasium's order
            return np.asarray(gym.spaces.flatten(self.raw, observation), dtype=np.float32)
        parts = observation if isinstance(observation, tuple) else (observation,)
        values = np.concatenate([np.asarray(v, dtype=np.int64).reshape(-1) for v in parts])
        out[self.offsets + values - self.starts] = 1.0
        return out


def _parts(space: Tuple | Dict) -> list[Space]:
    """The parts of a ``Tuple``, or of a ``Dict`` in its keys' order."""
    return list(space.spaces.values() if isinstance(space, Dict) else space.spaces)


def _nested(space: Space) -> bool:
    """Whether ``space`` is a ``Dict``, or a ``Tuple`` with a ``Tuple`` or ``Dict`` part."""
    return isinstance(space, Dict) or (
        isinstance(space, Tuple) and any(isinstance(s, Tuple | Dict) for s in space.spaces)
    )


def _feature_parts(space: Space) -> bool:
    """Whether ``space`` is made of ``Box``, ``Discrete``, ``MultiDiscrete`` and
    ``MultiBinary`` parts only (nested in ``Tuple`` and ``Dict``): the spaces whose
    flattening is a vector of numbers (a ``Text`` or ``Graph`` part is not)."""
    if isinstance(space, Tuple | Dict):
        return bool(space.spaces) and all(_feature_parts(s) for s in _parts(space))
    return isinstance(space, Box | Discrete | MultiDiscrete | MultiBinary)


def flattens(space: Space, most: int) -> bool:
    """Whether :func:`cdqn.envs.make.make_env` flattens ``space`` into a flat ``Box``
    (``gymnasium.wrappers.FlattenObservation``): a ``Box`` of another shape, a
    ``MultiBinary``, or a ``Tuple`` or ``Dict`` of feature parts (:class:`OneHot` takes those
    of discrete parts only; ``flatten`` sends a ``Discrete`` part to its one-hot vector in
    [0, 1] and keeps a ``Box`` part's bounds), of at most ``most`` entries (an image of
    96 × 96 × 3 is not a feature vector for a two-layer network)."""
    shaped = isinstance(space, Box) and len(space.shape) != 1
    composite = isinstance(space, Tuple | Dict) and _feature_parts(space)
    flat = shaped or composite or isinstance(space, MultiBinary)
    return flat and 0 < gym.spaces.flatdim(space) <= most


class ActionStart(gym.ActionWrapper):
    """A ``Discrete(n, start)`` action space as ``Discrete(n)``: the agents choose an index
    ``a`` in ``0 … n−1`` (the column of Q), the environment receives ``start + a``."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        space = env.action_space
        assert isinstance(space, Discrete)
        self.start = int(space.start)
        self.action_space = Discrete(int(space.n))

    def action(self, action: int) -> int:
        return self.start + int(action)


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
        lo, hi = np.where(finite, low, -1.0), np.where(finite, high, 1.0)  # no inf arithmetic
        dtype = real_dtype(space)
        self.offset = np.where(finite, 0.5 * (lo + hi), 0.0).astype(dtype)
        self.scale = np.where(finite, 2.0 * w / (hi - lo), 1.0).astype(dtype)
        self.observation_space = Box(
            np.where(finite, -w, low).astype(dtype),
            np.where(finite, w, high).astype(dtype),
            dtype=dtype,
        )

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return (np.asarray(observation, self.offset.dtype) - self.offset) * self.scale


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
    no features, and a step mostly moves Q near the state it learns from (docs/research/learning.md,
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
        self.dtype = real_dtype(space)
        self.centres = np.stack(mesh, axis=-1).reshape(-1, len(low)).astype(self.dtype)
        self.sigma = (width * (high - low) / (centres - 1)).astype(self.dtype)
        self.observation_space = Box(0.0, 1.0, (len(self.centres),), dtype=self.dtype)

    def features(self, obs: np.ndarray) -> np.ndarray:
        """``φ`` of each row of ``obs`` ``(K, d)``: ``(K, n^d)``; the population's
        environments call this on all members at once, with the same result per row."""
        z = (np.asarray(obs, self.dtype)[:, None, :] - self.centres[None, :, :]) / self.sigma
        return np.exp(-0.5 * (z * z).sum(axis=-1)).astype(self.dtype)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return self.features(np.asarray(observation)[None, :])[0]
