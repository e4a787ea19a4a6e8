"""Vectorised environments for populations: ``K`` copies of one environment stepped as one.

Each member keeps its own gymnasium environment from :func:`cdqn.envs.make_env`; resets
go through it (its own seeded ``np_random``), so every episode starts where a single run
with that seed starts.  Steps go through one of two implementations:

* :class:`ClassicControlTwin` — for CartPole, Acrobot and MountainCar: gymnasium's
  dynamics on ``K`` states, written operation for operation as gymnasium writes them for
  one (same order of floating-point operations, ``cos``/``sin`` and ``x**2`` through the
  same libm routines), so each member's trajectory is bit-identical to the environment's
  own (``tests/test_population.py`` checks this).  Each is a compiled loop over the
  members (numba, strict IEEE arithmetic).  Acrobot's ``x**2`` must be libm's ``pow``
  (not ``x*x``, which differs in the last bit for about 1 in 1000 values): the exponent is
  passed in at run time so that the compiler keeps the call.  Acrobot's twin is used where
  the compiled ``cos``/``sin``/``pow`` agree with NumPy's scalar ones, which
  :func:`compiled_math_matches_numpy` checks once per process.
* :class:`GymLoop` — any other environment: a loop over the members' environments.

Both count steps and truncate at the environment's ``TimeLimit`` as gymnasium does.

Checkpoints: a twin's member, and a :class:`GymLoop` member of a classic control
environment, is captured between any two steps (:meth:`VectorEnv.state_dict`).  Any other
environment is captured at its episode boundaries (:meth:`VectorEnv.boundary_state`): after
an episode ended and before the reset that starts the next, what the next episodes depend on
is the environment's ``np_random``, from which gymnasium environments draw their resets
(LunarLander's terrain and initial push, for example); a freshly made environment given that
generator resets and steps as the original does (``tests/test_resume.py``).
"""

from __future__ import annotations

import functools
import math
from math import pi
from typing import Any, NamedTuple, Protocol

import gymnasium as gym
import numpy as np
from gymnasium.envs.classic_control.acrobot import AcrobotEnv
from gymnasium.envs.classic_control.cartpole import CartPoleEnv
from gymnasium.envs.classic_control.mountain_car import MountainCarEnv
from gymnasium.wrappers import OrderEnforcing, PassiveEnvChecker, TimeLimit
from numba import njit

from cdqn.envs import ObservationScale, ObservationSubset, RadialFeatures


class VectorStep(NamedTuple):
    """One step of all members: observations ``(K, n_obs)`` and ``(K,)`` arrays."""

    obs: np.ndarray
    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray


class VectorEnv(Protocol):
    """What a population needs from its environments."""

    envs: list[gym.Env]

    def reset(self, i: int, seed: int | None) -> np.ndarray:
        """Reset member ``i`` (seeded when ``seed`` is given) and return its observation."""
        ...

    def step(self, actions: np.ndarray) -> VectorStep: ...

    def select(self, keep: np.ndarray) -> None:
        """Keep only the members ``keep`` (indices, in that order)."""
        ...

    @property
    def checkpointable(self) -> bool:
        """Whether :meth:`state_dict` captures every member between two steps."""
        ...

    def state_dict(self, i: int) -> dict[str, Any]:
        """Member ``i``'s environment state between two steps (for checkpoints)."""
        ...

    def load_state_dict(self, i: int, state: dict[str, Any]) -> None: ...

    def boundary_state(self, i: int) -> dict[str, Any]:
        """Member ``i``'s environment between two episodes (any environment)."""
        ...

    def load_boundary_state(self, i: int, state: dict[str, Any]) -> None:
        """Put member ``i`` of fresh environments into ``state``; its next call is a reset."""
        ...


def boundary_state(env: gym.Env) -> dict[str, Any]:
    """``env`` after an episode ended and before the next reset: its ``np_random`` state
    (module docstring)."""
    return {"np_random": _rng_state(env)}


def load_boundary_state(env: gym.Env, state: dict[str, Any]) -> None:
    """Inverse of :func:`boundary_state`, into a freshly made ``env``."""
    _set_rng_state(env, state["np_random"])


class _Wrappers(NamedTuple):
    """What :func:`_unwrap` finds around a member's environment."""

    base: gym.Env
    indices: np.ndarray | None
    cap: int | None
    known: bool
    """Every wrapper is one the twin reproduces or a no-op."""
    scaling: ObservationScale | None
    features: RadialFeatures | None


def _unwrap(env: gym.Env) -> _Wrappers:
    """The base environment and the wrappers a :class:`ClassicControlTwin` reproduces."""
    indices, cap, known, scaling, features = None, None, True, None, None
    while isinstance(env, gym.Wrapper):
        if isinstance(env, ObservationSubset):
            indices = env.indices
        elif isinstance(env, ObservationScale):
            scaling = env
        elif isinstance(env, RadialFeatures):
            features = env
        elif isinstance(env, TimeLimit):
            cap = env._max_episode_steps
        elif not isinstance(env, OrderEnforcing | PassiveEnvChecker):
            known = False
        env = env.env
    return _Wrappers(env, indices, cap, known, scaling, features)


_PHYSICS = {
    CartPoleEnv: ("gravity", "masscart", "masspole", "length", "force_mag", "tau",
                  "kinematics_integrator", "x_threshold", "theta_threshold_radians",
                  "_sutton_barto_reward"),
    AcrobotEnv: ("dt", "torque_noise_max", "book_or_nips", "AVAIL_TORQUE", "LINK_LENGTH_1",
                 "LINK_MASS_1", "LINK_MASS_2", "LINK_COM_POS_1", "LINK_COM_POS_2", "LINK_MOI",
                 "MAX_VEL_1", "MAX_VEL_2"),
    MountainCarEnv: ("min_position", "max_position", "max_speed", "goal_position",
                     "goal_velocity", "force", "gravity"),
}  # fmt: skip


def _physics(env: gym.Env) -> tuple:
    """The parameters a :class:`ClassicControlTwin` reads from a member's environment."""
    return tuple(getattr(env, name, None) for name in _PHYSICS.get(type(env), ()))


class GymLoop:
    """Members stepped one after another through their own environments."""

    def __init__(self, envs: list[gym.Env]) -> None:
        self.envs = list(envs)

    def reset(self, i: int, seed: int | None) -> np.ndarray:
        return self.envs[i].reset(seed=seed)[0]

    def step(self, actions: np.ndarray) -> VectorStep:
        out = [env.step(int(a)) for env, a in zip(self.envs, actions, strict=True)]
        obs, reward, terminated, truncated, _ = zip(*out, strict=True)
        return VectorStep(
            np.stack(obs), np.array(reward, dtype=float), np.array(terminated), np.array(truncated)
        )

    def select(self, keep: np.ndarray) -> None:
        self.envs = [self.envs[i] for i in keep]

    @property
    def checkpointable(self) -> bool:
        """Whether :meth:`state_dict` can capture the members mid-episode (the classic
        control environments, whose whole state is ``state`` and the step count); every
        member can be captured at its episode boundaries (:meth:`boundary_state`)."""
        return all(type(_unwrap(env).base) in ClassicControlTwin.KINDS for env in self.envs)

    def boundary_state(self, i: int) -> dict[str, Any]:
        return boundary_state(self.envs[i])

    def load_boundary_state(self, i: int, state: dict[str, Any]) -> None:
        load_boundary_state(self.envs[i], state)

    def state_dict(self, i: int) -> dict[str, Any]:
        """Member ``i``'s environment between two steps (classic control only)."""
        env = self.envs[i]
        base = _classic(env)
        out = {"state": np.array(base.state, dtype=np.float64), "np_random": _rng_state(env),
               "elapsed": int(getattr(_time_limit(env), "_elapsed_steps", 0) or 0)}  # fmt: skip
        if isinstance(base, CartPoleEnv):  # the one of the three that counts steps beyond
            out["beyond"] = (
                -1 if base.steps_beyond_terminated is None else int(base.steps_beyond_terminated)
            )
        return out

    def load_state_dict(self, i: int, state: dict[str, Any]) -> None:
        env = self.envs[i]
        base = _classic(env)
        _set_rng_state(env, state["np_random"])
        base.state = np.array(state["state"], dtype=np.float64)
        if "beyond" in state and isinstance(base, CartPoleEnv):
            base.steps_beyond_terminated = None if state["beyond"] < 0 else state["beyond"]
        limit = _time_limit(env)
        if limit is not None:
            limit._elapsed_steps = state["elapsed"]
        _mark_reset(env)


def _classic(env: gym.Env) -> CartPoleEnv | AcrobotEnv | MountainCarEnv:
    """``env``'s classic control environment, whose whole state is ``state``."""
    base = env.unwrapped
    if not isinstance(base, ClassicControlTwin.KINDS):
        raise TypeError(f"{type(base).__name__} cannot be captured between two steps")
    return base


def _time_limit(env: gym.Env) -> TimeLimit | None:
    while isinstance(env, gym.Wrapper):
        if isinstance(env, TimeLimit):
            return env
        env = env.env
    return None


def _mark_reset(env: gym.Env) -> None:
    """Let a restored environment step without a reset (``OrderEnforcing``; the passive
    checker's first-step checks, which compare with the reset's data, are skipped)."""
    while isinstance(env, gym.Wrapper):
        if isinstance(env, OrderEnforcing):
            env._has_reset = True
        if isinstance(env, PassiveEnvChecker):
            env.checked_step = env.checked_data_reuse = True
        env = env.env


def _rng_state(env: gym.Env) -> dict[str, Any]:
    return dict(env.unwrapped.np_random.bit_generator.state)


def _set_rng_state(env: gym.Env, state: dict[str, Any]) -> None:
    bit_generator = getattr(np.random, state["bit_generator"])()
    bit_generator.state = state
    env.unwrapped.np_random = np.random.Generator(bit_generator)


class ClassicControlTwin:
    """CartPole, Acrobot or MountainCar dynamics on ``K`` states at once (module docstring)."""

    KINDS = (CartPoleEnv, AcrobotEnv, MountainCarEnv)

    def __init__(self, envs: list[gym.Env]) -> None:
        self.envs = list(envs)
        found = [_unwrap(env) for env in envs]
        self.bases = [w.base for w in found]
        w = found[0]
        self.base, self.indices, self.cap = w.base, w.indices, w.cap
        self.scaling, self.features = w.scaling, w.features
        self.kind = type(self.base)
        self._arrays: TwinArrays | None = None
        self.state = np.zeros((len(envs), {CartPoleEnv: 4, AcrobotEnv: 4}.get(self.kind, 2)))
        self.elapsed = np.zeros(len(envs), dtype=np.int64)
        e = self.base
        if isinstance(e, CartPoleEnv):
            self.params = np.array([
                e.force_mag, e.gravity, e.masspole, e.total_mass, e.length, e.polemass_length,
                e.tau, e.kinematics_integrator == "euler", e.x_threshold,
                e.theta_threshold_radians,
            ], dtype=np.float64)  # fmt: skip
        elif isinstance(e, AcrobotEnv):
            self.params = np.array([
                e.LINK_MASS_1, e.LINK_MASS_2, e.LINK_LENGTH_1, e.LINK_COM_POS_1,
                e.LINK_COM_POS_2, e.LINK_MOI, e.dt, e.MAX_VEL_1, e.MAX_VEL_2,
                e.book_or_nips == "nips", *e.AVAIL_TORQUE,
            ], dtype=np.float64)  # fmt: skip
        elif isinstance(e, MountainCarEnv):
            self.params = np.array([
                e.force, e.gravity, e.max_speed, e.min_position, e.max_position,
                e.goal_position, e.goal_velocity,
            ], dtype=np.float64)  # fmt: skip

    @classmethod
    def supports(cls, envs: list[gym.Env]) -> bool:
        """True when every member is a default-parameter instance of a supported kind."""
        found = [_unwrap(env) for env in envs]
        base = found[0].base
        if not all(w.known for w in found) or type(base) not in cls.KINDS:
            return False
        bases = [w.base for w in found]
        if any(type(b) is not type(base) or b.render_mode is not None for b in bases):
            return False
        if any(_physics(b) != _physics(base) for b in bases):
            return False
        if any(b.spec is None or b.spec.kwargs != gym.spec(b.spec.id).kwargs for b in bases):
            return False  # made with env.kwargs: the twin reimplements the default physics
        if isinstance(base, CartPoleEnv):
            return base.kinematics_integrator in ("euler", "semi-implicit") and not getattr(
                base, "_sutton_barto_reward", False
            )
        if isinstance(base, AcrobotEnv):
            return (
                base.torque_noise_max == 0.0
                and base.book_or_nips in ("book", "nips")
                and len(base.AVAIL_TORQUE) == 3
                and compiled_math_matches_numpy()
            )
        return True

    def reset(self, i: int, seed: int | None) -> np.ndarray:
        obs = self.envs[i].reset(seed=seed)[0]
        self.state[i] = _classic(self.envs[i]).state
        self.elapsed[i] = 0
        return obs

    def select(self, keep: np.ndarray) -> None:
        self.envs = [self.envs[i] for i in keep]
        self.bases = [self.bases[i] for i in keep]
        self.state, self.elapsed = self.state[keep], self.elapsed[keep]
        self._arrays = None

    checkpointable = True

    def state_dict(self, i: int) -> dict[str, Any]:
        """Member ``i``'s environment between two steps: the twin's state and step count and
        the member's ``np_random`` (which draws the next episode's start)."""
        return {"state": self.state[i].copy(), "elapsed": int(self.elapsed[i]),
                "np_random": _rng_state(self.envs[i])}  # fmt: skip

    def load_state_dict(self, i: int, state: dict[str, Any]) -> None:
        self.state[i], self.elapsed[i] = state["state"], state["elapsed"]
        _set_rng_state(self.envs[i], state["np_random"])

    def boundary_state(self, i: int) -> dict[str, Any]:
        return boundary_state(self.envs[i])

    def load_boundary_state(self, i: int, state: dict[str, Any]) -> None:
        load_boundary_state(self.envs[i], state)

    @property
    def _raw_size(self) -> int:
        return 6 if self.kind is AcrobotEnv else self.state.shape[1]

    @property
    def compiled(self) -> bool:
        """Whether :func:`twin_step` computes the members' whole observations (every wrapper
        but radial features, whose ``np.exp`` is NumPy's)."""
        return self.features is None

    def arrays(self) -> TwinArrays:
        """The twin as :func:`twin_step` takes it (its arrays, until :meth:`select`)."""
        if self._arrays is None:
            self._arrays = self._bundle()
        return self._arrays

    def _bundle(self) -> TwinArrays:
        k, d = len(self.state), self._raw_size
        none = np.zeros(0, np.float32)
        offset, scale = (
            (self.scaling.offset, self.scaling.scale) if self.scaling is not None else (none, none)
        )
        return TwinArrays(
            self.KINDS.index(self.kind), self.state, self.params, 2.0, self.elapsed,
            -1 if self.cap is None else self.cap,
            np.arange(d) if self.indices is None else np.asarray(self.indices, np.int64),
            offset, scale, self.features is None, np.empty((k, d), np.float32),
        )  # fmt: skip

    def outputs(self) -> VectorStep:
        """Arrays for one step of every member (:func:`twin_step` writes them)."""
        k = len(self.state)
        d = self._raw_size if self.indices is None else len(self.indices)
        return VectorStep(np.empty((k, d), np.float32), np.empty(k), np.empty(k, bool),
                          np.empty(k, bool))  # fmt: skip

    def step(self, actions: np.ndarray) -> VectorStep:
        out = self.outputs()
        twin_step(tuple(self.arrays()), np.ascontiguousarray(actions, np.int64), tuple(out))
        if self.features is None:
            return out
        return out._replace(obs=self._observation_maps(out.obs))

    def _observation_maps(self, obs: np.ndarray) -> np.ndarray:
        """The members' :class:`ObservationScale` and :class:`RadialFeatures` on all rows at
        once: one compiled pass (:func:`_scale_and_exponents`) and, for features, one
        ``np.exp`` (NumPy's, as the wrapper's)."""
        none = np.zeros(0, obs.dtype)
        offset, scale = (
            (self.scaling.offset, self.scaling.scale) if self.scaling is not None else (none, none)
        )
        if self.features is None:
            out = np.empty_like(obs)
            _scale_and_exponents(obs, offset, scale, np.zeros((0, 0), obs.dtype), none, out)
            return out
        f = self.features
        out = np.empty((len(obs), len(f.centres)), f.dtype)
        _scale_and_exponents(obs, offset, scale, f.centres, f.sigma, out)
        return np.exp(out)


@njit(cache=True)  # strict IEEE arithmetic, in the wrappers' dtype (float32)
def _scale_and_exponents(obs, offset, scale, centres, sigma, out):
    """Per row of ``obs``: ``s = (obs − offset) ⊙ scale`` (:class:`ObservationScale`; skipped
    when ``offset`` is empty), then, when there are ``centres``, the exponents
    ``−½ Σ_i ((s_i − c_ji)/σ_i)²`` of :meth:`RadialFeatures.features` (summed in index
    order, in the observation's dtype, as NumPy sums the last axis), else ``s`` itself."""
    n, d = obs.shape
    s = np.empty(d, obs.dtype)
    half = obs.dtype.type(-0.5)
    for k in range(n):
        for i in range(d):
            s[i] = (obs[k, i] - offset[i]) * scale[i] if offset.shape[0] else obs[k, i]
        if centres.shape[0] == 0:
            for i in range(d):
                out[k, i] = s[i]
            continue
        for j in range(centres.shape[0]):
            acc = obs.dtype.type(0.0)
            for i in range(d):
                z = (s[i] - centres[j, i]) / sigma[i]
                acc += z * z
            out[k, j] = half * acc


class TwinArrays(NamedTuple):
    """A :class:`ClassicControlTwin` as :func:`twin_step` takes it."""

    kind: int
    """Index of the environment class in :attr:`ClassicControlTwin.KINDS`."""
    state: np.ndarray
    params: np.ndarray
    two: float
    """2.0, given at run time (Acrobot's ``x**2`` stays libm's ``pow``, module docstring)."""
    elapsed: np.ndarray
    cap: int
    """Episode cap (−1: none)."""
    indices: np.ndarray
    """The observation's entries the members see (:class:`ObservationSubset`)."""
    offset: np.ndarray
    scale: np.ndarray
    """:class:`ObservationScale` (empty: none)."""
    maps: bool
    """Whether :func:`twin_step` applies the scaling (False: radial features follow, which
    scale on their way)."""
    raw: np.ndarray
    """The environment's own observations ``(K, ·)``, float32."""


@njit(cache=True)
def twin_step(tw, actions, out):
    """One step of every member into ``out`` (:class:`VectorStep`; bundles as plain
    tuples): gymnasium's dynamics (:func:`_cartpole_kernel`, :func:`_acrobot_rk4`,
    :func:`_mountaincar_kernel`), ``TimeLimit`` (:func:`_count_steps`), then the entries
    ``indices`` of each observation, scaled when ``maps``."""
    tw, out = TwinArrays(*tw), VectorStep(*out)
    if tw.kind == 0:
        _cartpole_kernel(tw.state, actions, tw.params, tw.raw, out.reward, out.terminated)
    elif tw.kind == 1:
        _acrobot_rk4(tw.state, actions, tw.params, tw.two, tw.raw, out.reward, out.terminated)
    else:
        _mountaincar_kernel(tw.state, actions, tw.params, tw.raw, out.reward, out.terminated)
    _count_steps(tw.elapsed, tw.cap, out.truncated)
    for k in range(tw.raw.shape[0]):
        for i in range(tw.indices.shape[0]):
            out.obs[k, i] = tw.raw[k, tw.indices[i]]
    if tw.maps and tw.offset.shape[0]:
        _scale_and_exponents(out.obs, tw.offset, tw.scale, np.zeros((0, 0), out.obs.dtype),
                             tw.offset[:0], out.obs)  # fmt: skip


@njit(cache=True)
def _count_steps(elapsed, cap, truncated):
    """gymnasium's ``TimeLimit``: count the step, truncate at ``cap`` (−1: no limit)."""
    for k in range(elapsed.shape[0]):
        elapsed[k] += 1
        truncated[k] = cap >= 0 and elapsed[k] >= cap


@njit(cache=True)  # strict IEEE arithmetic (no fastmath), libm cos/sin as gymnasium's NumPy
def _cartpole_kernel(state, action, params, obs, reward, terminated):
    """gymnasium ``CartPoleEnv.step`` on each row of ``state`` (in place), operation for
    operation in gymnasium's order; ``params`` as :class:`ClassicControlTwin` packs them."""
    force_mag, gravity, masspole, total_mass = params[0], params[1], params[2], params[3]
    length, polemass_length, tau, euler = params[4], params[5], params[6], params[7] != 0.0
    x_threshold, theta_threshold = params[8], params[9]
    for k in range(state.shape[0]):
        x, x_dot, theta, theta_dot = state[k, 0], state[k, 1], state[k, 2], state[k, 3]
        force = force_mag if action[k] == 1 else -force_mag
        costheta = math.cos(theta)
        sintheta = math.sin(theta)
        temp = (force + polemass_length * (theta_dot * theta_dot) * sintheta) / total_mass
        thetaacc = (gravity * sintheta - costheta * temp) / (
            length * (4.0 / 3.0 - masspole * (costheta * costheta) / total_mass)
        )
        xacc = temp - polemass_length * thetaacc * costheta / total_mass
        if euler:
            x = x + tau * x_dot
            x_dot = x_dot + tau * xacc
            theta = theta + tau * theta_dot
            theta_dot = theta_dot + tau * thetaacc
        else:  # semi-implicit euler
            x_dot = x_dot + tau * xacc
            x = x + tau * x_dot
            theta_dot = theta_dot + tau * thetaacc
            theta = theta + tau * theta_dot
        state[k, 0], state[k, 1], state[k, 2], state[k, 3] = x, x_dot, theta, theta_dot
        for i in range(4):
            obs[k, i] = state[k, i]
        terminated[k] = (
            x < -x_threshold
            or x > x_threshold
            or theta < -theta_threshold
            or theta > theta_threshold
        )
        reward[k] = 1.0


@njit(cache=True)  # strict IEEE arithmetic (no fastmath), libm cos as gymnasium's math.cos
def _mountaincar_kernel(state, action, params, obs, reward, terminated):
    """gymnasium ``MountainCarEnv.step`` on each row of ``state`` (in place), operation for
    operation in gymnasium's order (``np.clip`` as min/max)."""
    force, gravity, max_speed, min_position = params[0], params[1], params[2], params[3]
    max_position, goal_position, goal_velocity = params[4], params[5], params[6]
    for k in range(state.shape[0]):
        position, velocity = state[k, 0], state[k, 1]
        velocity = velocity + ((action[k] - 1) * force + math.cos(3 * position) * (-gravity))
        velocity = min(max(velocity, -max_speed), max_speed)
        position = position + velocity
        position = min(max(position, min_position), max_position)
        if position == min_position and velocity < 0:
            velocity = 0.0
        terminated[k] = position >= goal_position and velocity >= goal_velocity
        state[k, 0], state[k, 1] = position, velocity
        obs[k, 0], obs[k, 1] = position, velocity
        reward[k] = -1.0


@njit(cache=True)
def _acrobot_dsdt(y, c, two, out):
    """gymnasium ``AcrobotEnv._dsdt`` at ``y = [θ1, θ2, θ̇1, θ̇2, torque]`` into ``out``,
    operation for operation (``x ** two`` is libm ``pow(x, 2)``, as NumPy's and Python's
    scalar ``x**2``; ``two`` is an argument so that the compiler cannot turn it into x*x)."""
    m1, m2, l1, lc1, lc2 = c[0], c[1], c[2], c[3], c[4]
    I1 = I2 = c[5]
    g = 9.8
    a = y[4]
    theta1, theta2, dtheta1, dtheta2 = y[0], y[1], y[2], y[3]
    d1 = m1 * lc1**two + m2 * (l1**two + lc2**two + 2 * l1 * lc2 * math.cos(theta2)) + I1 + I2
    d2 = m2 * (lc2**two + l1 * lc2 * math.cos(theta2)) + I2
    phi2 = m2 * lc2 * g * math.cos(theta1 + theta2 - pi / 2.0)
    phi1 = (
        -m2 * l1 * lc2 * dtheta2**two * math.sin(theta2)
        - 2 * m2 * l1 * lc2 * dtheta2 * dtheta1 * math.sin(theta2)
        + (m1 * lc1 + m2 * l1) * g * math.cos(theta1 - pi / 2)
        + phi2
    )
    if c[9] != 0.0:  # "nips"
        ddtheta2 = (a + d2 / d1 * phi1 - phi2) / (m2 * lc2**two + I2 - d2**two / d1)
    else:  # "book"
        ddtheta2 = (a + d2 / d1 * phi1 - m2 * l1 * lc2 * dtheta1**two * math.sin(theta2) - phi2) / (
            m2 * lc2**two + I2 - d2**two / d1
        )
    ddtheta1 = -(d2 * ddtheta2 + phi1) / d1
    out[0], out[1], out[2], out[3], out[4] = dtheta1, dtheta2, ddtheta1, ddtheta2, 0.0


@njit(cache=True)
def _acrobot_rk4(state, action, params, two, obs, reward, terminated):
    c = params
    dt = c[6] - 0  # gymnasium integrates over t = [0, dt]
    dt2 = dt / 2.0
    y0, y = np.empty(5), np.empty(5)
    k1, k2, k3, k4 = np.empty(5), np.empty(5), np.empty(5), np.empty(5)
    for k in range(state.shape[0]):
        for i in range(4):
            y0[i] = state[k, i]
        y0[4] = c[10 + action[k]]
        _acrobot_dsdt(y0, c, two, k1)
        for i in range(5):
            y[i] = y0[i] + dt2 * k1[i]
        _acrobot_dsdt(y, c, two, k2)
        for i in range(5):
            y[i] = y0[i] + dt2 * k2[i]
        _acrobot_dsdt(y, c, two, k3)
        for i in range(5):
            y[i] = y0[i] + dt * k3[i]
        _acrobot_dsdt(y, c, two, k4)
        for i in range(4):
            y[i] = y0[i] + dt / 6.0 * (k1[i] + 2 * k2[i] + 2 * k3[i] + k4[i])
        for i in range(2):  # gymnasium's wrap(x, -pi, pi)
            while y[i] > pi:
                y[i] = y[i] - (pi - -pi)
            while y[i] < -pi:
                y[i] = y[i] + (pi - -pi)
        y[2] = min(max(y[2], -c[7]), c[7])  # bound
        y[3] = min(max(y[3], -c[8]), c[8])
        for i in range(4):
            state[k, i] = y[i]
        s0, s1 = y[0], y[1]
        terminated[k] = -math.cos(s0) - math.cos(s1 + s0) > 1.0
        reward[k] = 0.0 if terminated[k] else -1.0
        obs[k, 0], obs[k, 1] = math.cos(s0), math.sin(s0)
        obs[k, 2], obs[k, 3] = math.cos(s1), math.sin(s1)
        obs[k, 4], obs[k, 5] = y[2], y[3]


@functools.cache
def compiled_math_matches_numpy(samples: int = 4000) -> bool:
    """Whether this machine's compiled ``cos``, ``sin`` and ``pow(x, 2)`` (libm, as numba
    calls them) return what NumPy's scalar ``cos``, ``sin`` and ``x**2`` return, which
    gymnasium's Acrobot uses: checked on ``samples`` angles and velocities.  (NumPy may
    dispatch to its own SIMD routines on some CPUs; there Acrobot populations step the
    members' own environments.)"""
    gen = np.random.default_rng(0)
    x = np.concatenate([gen.uniform(-8.0, 8.0, samples), gen.normal(0.0, 1e-2, samples // 4)])
    out = np.empty((len(x), 3))
    _libm(x, 2.0, out)
    for i, v in enumerate(x.tolist()):
        s = np.float64(v)
        if (np.cos(s), np.sin(s), s**2) != tuple(out[i]):
            return False
    return True


@njit(cache=True)
def _libm(x, two, out):
    for i in range(x.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = math.cos(x[i]), math.sin(x[i]), x[i] ** two


def make_vector_env(envs: list[gym.Env]) -> VectorEnv:
    """The fastest exact implementation for these members' environments."""
    if ClassicControlTwin.supports(envs):
        return ClassicControlTwin(envs)
    return GymLoop(envs)
