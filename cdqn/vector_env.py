"""Vectorised environments for populations: ``K`` copies of one environment stepped as one.

Each member keeps its own gymnasium environment from :func:`cdqn.envs.make_env`; resets
go through it (its own seeded ``np_random``), so every episode starts where a single run
with that seed starts.  Steps go through one of two implementations:

* :class:`ClassicControlTwin` — for CartPole, Acrobot and MountainCar: gymnasium's
  dynamics on ``K`` states, written operation for operation as gymnasium writes them for
  one (same order of floating-point operations, ``cos``/``sin`` and ``x**2`` through the
  same libm routines), so each member's trajectory is bit-identical to the environment's
  own (``tests/test_population.py`` checks this).  CartPole and MountainCar are compiled
  loops (numba, strict IEEE arithmetic); Acrobot's RK4 stays in NumPy, because its
  ``x**2`` must be libm's ``pow`` (not ``x*x``), which a compiler may rewrite.
* :class:`GymLoop` — any other environment: a loop over the members' environments.

Both count steps and truncate at the environment's ``TimeLimit`` as gymnasium does.
"""

from __future__ import annotations

import math
from math import pi
from typing import NamedTuple, Protocol

import gymnasium as gym
import numpy as np
from gymnasium.envs.classic_control.acrobot import AcrobotEnv
from gymnasium.envs.classic_control.cartpole import CartPoleEnv
from gymnasium.envs.classic_control.mountain_car import MountainCarEnv
from gymnasium.wrappers import OrderEnforcing, PassiveEnvChecker, TimeLimit
from numba import njit

from cdqn.envs import ObservationSubset


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


def _unwrap(env: gym.Env) -> tuple[gym.Env, np.ndarray | None, int | None, bool]:
    """(base env, observation indices, step cap, whether every wrapper is a known no-op)."""
    indices, cap, known = None, None, True
    while isinstance(env, gym.Wrapper):
        if isinstance(env, ObservationSubset):
            indices = env.indices
        elif isinstance(env, TimeLimit):
            cap = env._max_episode_steps
        elif not isinstance(env, OrderEnforcing | PassiveEnvChecker):
            known = False
        env = env.env
    return env, indices, cap, known


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


class ClassicControlTwin:
    """CartPole, Acrobot or MountainCar dynamics on ``K`` states at once (module docstring)."""

    KINDS = (CartPoleEnv, AcrobotEnv, MountainCarEnv)

    def __init__(self, envs: list[gym.Env]) -> None:
        self.envs = list(envs)
        self.bases = [_unwrap(env)[0] for env in envs]
        base, self.indices, cap, _ = _unwrap(envs[0])
        self.base = base
        self.cap = cap
        self.kind = type(base)
        self.state = np.zeros((len(envs), {CartPoleEnv: 4, AcrobotEnv: 4}.get(self.kind, 2)))
        self.elapsed = np.zeros(len(envs), dtype=np.int64)
        self._two = np.full(len(envs), 2.0)
        e = base
        if self.kind is CartPoleEnv:
            self.params = np.array([
                e.force_mag, e.gravity, e.masspole, e.total_mass, e.length, e.polemass_length,
                e.tau, e.kinematics_integrator == "euler", e.x_threshold,
                e.theta_threshold_radians,
            ], dtype=np.float64)  # fmt: skip
        elif self.kind is MountainCarEnv:
            self.params = np.array([
                e.force, e.gravity, e.max_speed, e.min_position, e.max_position,
                e.goal_position, e.goal_velocity,
            ], dtype=np.float64)  # fmt: skip

    @classmethod
    def supports(cls, envs: list[gym.Env]) -> bool:
        """True when every member is a default-parameter instance of a supported kind."""
        bases = [_unwrap(env) for env in envs]
        base = bases[0][0]
        if not all(known for *_, known in bases) or type(base) not in cls.KINDS:
            return False
        if any(type(b) is not type(base) or b.render_mode is not None for b, *_ in bases):
            return False
        if any(_physics(b) != _physics(base) for b, *_ in bases):
            return False
        if isinstance(base, CartPoleEnv):
            return base.kinematics_integrator in ("euler", "semi-implicit") and not getattr(
                base, "_sutton_barto_reward", False
            )
        if isinstance(base, AcrobotEnv):
            return base.torque_noise_max == 0.0 and base.book_or_nips in ("book", "nips")
        return True

    def reset(self, i: int, seed: int | None) -> np.ndarray:
        obs = self.envs[i].reset(seed=seed)[0]
        self.state[i] = self.bases[i].state
        self.elapsed[i] = 0
        return obs

    def select(self, keep: np.ndarray) -> None:
        self.envs = [self.envs[i] for i in keep]
        self.bases = [self.bases[i] for i in keep]
        self.state, self.elapsed = self.state[keep], self.elapsed[keep]
        self._two = self._two[keep]

    def step(self, actions: np.ndarray) -> VectorStep:
        k = len(actions)
        if self.kind is AcrobotEnv:
            obs, reward, terminated = self._acrobot(np.asarray(actions))
            self.elapsed += 1
            truncated = self.elapsed >= self.cap if self.cap is not None else np.zeros(k, bool)
        else:
            obs = np.empty(self.state.shape, np.float32)
            reward, terminated, truncated = np.empty(k), np.empty(k, bool), np.empty(k, bool)
            kernel = _cartpole_kernel if self.kind is CartPoleEnv else _mountaincar_kernel
            kernel(self.state, np.ascontiguousarray(actions, np.int64), self.params, obs, reward,
                   terminated)  # fmt: skip
            _count_steps(self.elapsed, -1 if self.cap is None else self.cap, truncated)
        if self.indices is not None:
            obs = obs[:, self.indices]
        return VectorStep(obs, reward, terminated, truncated)

    def _dsdt(self, s: np.ndarray) -> np.ndarray:
        """gymnasium ``AcrobotEnv._dsdt`` on rows ``[θ1, θ2, θ̇1, θ̇2, torque]``."""
        e = self.base
        m1, m2 = e.LINK_MASS_1, e.LINK_MASS_2
        l1 = e.LINK_LENGTH_1
        lc1, lc2 = e.LINK_COM_POS_1, e.LINK_COM_POS_2
        I1 = I2 = e.LINK_MOI
        g = 9.8
        a = s[:, 4]
        theta1, theta2, dtheta1, dtheta2 = s[:, 0], s[:, 1], s[:, 2], s[:, 3]
        two = self._two  # x**2 of a NumPy scalar is libm pow(x, 2), not x*x
        d1 = m1 * lc1**2 + m2 * (l1**2 + lc2**2 + 2 * l1 * lc2 * np.cos(theta2)) + I1 + I2
        d2 = m2 * (lc2**2 + l1 * lc2 * np.cos(theta2)) + I2
        phi2 = m2 * lc2 * g * np.cos(theta1 + theta2 - pi / 2.0)
        phi1 = (
            -m2 * l1 * lc2 * np.power(dtheta2, two) * np.sin(theta2)
            - 2 * m2 * l1 * lc2 * dtheta2 * dtheta1 * np.sin(theta2)
            + (m1 * lc1 + m2 * l1) * g * np.cos(theta1 - pi / 2)
            + phi2
        )
        if e.book_or_nips == "nips":
            ddtheta2 = (a + d2 / d1 * phi1 - phi2) / (m2 * lc2**2 + I2 - np.power(d2, two) / d1)
        else:
            ddtheta2 = (
                a + d2 / d1 * phi1 - m2 * l1 * lc2 * np.power(dtheta1, two) * np.sin(theta2) - phi2
            ) / (m2 * lc2**2 + I2 - np.power(d2, two) / d1)
        ddtheta1 = -(d2 * ddtheta2 + phi1) / d1
        return np.stack([dtheta1, dtheta2, ddtheta1, ddtheta2, np.zeros_like(a)], axis=1)

    def _acrobot(self, action: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """gymnasium ``AcrobotEnv.step`` (one RK4 step of ``dt``, wrap, bound), vectorised."""
        e = self.base
        torque = np.asarray(e.AVAIL_TORQUE, dtype=np.float64)[action]
        y0 = np.concatenate([self.state, torque[:, None]], axis=1)
        dt = e.dt - 0
        dt2 = dt / 2.0
        k1 = self._dsdt(y0)
        k2 = self._dsdt(y0 + dt2 * k1)
        k3 = self._dsdt(y0 + dt2 * k2)
        k4 = self._dsdt(y0 + dt * k3)
        ns = y0 + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        for j in (0, 1):  # wrap to [-pi, pi] as gymnasium's wrap()
            col = ns[:, j]
            while (col > pi).any():
                col = np.where(col > pi, col - 2 * pi, col)
            while (col < -pi).any():
                col = np.where(col < -pi, col + 2 * pi, col)
            ns[:, j] = col
        ns[:, 2] = np.minimum(np.maximum(ns[:, 2], -e.MAX_VEL_1), e.MAX_VEL_1)
        ns[:, 3] = np.minimum(np.maximum(ns[:, 3], -e.MAX_VEL_2), e.MAX_VEL_2)
        self.state = ns[:, :4]
        s = self.state
        terminated = -np.cos(s[:, 0]) - np.cos(s[:, 1] + s[:, 0]) > 1.0
        obs = np.stack(
            [np.cos(s[:, 0]), np.sin(s[:, 0]), np.cos(s[:, 1]), np.sin(s[:, 1]), s[:, 2], s[:, 3]],
            axis=1,
        ).astype(np.float32)
        return obs, np.where(terminated, 0.0, -1.0), terminated


@njit(cache=True)
def _count_steps(elapsed, cap, truncated):  # noqa: ANN001, ANN202
    """gymnasium's ``TimeLimit``: count the step, truncate at ``cap`` (−1: no limit)."""
    for k in range(elapsed.shape[0]):
        elapsed[k] += 1
        truncated[k] = cap >= 0 and elapsed[k] >= cap


@njit(cache=True)  # strict IEEE arithmetic (no fastmath), libm cos/sin as gymnasium's NumPy
def _cartpole_kernel(state, action, params, obs, reward, terminated):  # noqa: ANN001, ANN202
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
def _mountaincar_kernel(state, action, params, obs, reward, terminated):  # noqa: ANN001, ANN202
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


def make_vector_env(envs: list[gym.Env]) -> VectorEnv:
    """The fastest exact implementation for these members' environments."""
    if ClassicControlTwin.supports(envs):
        return ClassicControlTwin(envs)
    return GymLoop(envs)
