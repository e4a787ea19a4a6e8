"""Where a population's member-step goes: shares of the time per part.

    python -m cdqn.profile                                     # CartPole, hinf, K = 10
    python -m cdqn.profile --env mountaincar --controller h2 --steps 3000
    python -m cdqn.profile --controller ddqn                   # Double DQN

Trains a population (:func:`cdqn.training.population_loop.train_population`, one thread,
no tracking store) step by step and times, per population step, what the loop calls: the environment
twin's step and resets (:mod:`cdqn.vector_env`), the exploration plan, the act call's
forward passes, the update kernel, and the recording (signal rows moved into each member's
buffer, episode statistics).  The rest of the loop's time is its own Python.  The update
kernel's controller arithmetic (:mod:`cdqn.control.kernels`) is timed apart afterwards on
the members' controller arrays and subtracted from the update, which leaves the network's
share (forward pass at s', Θ1/Θ2, SGD step) with the step's signal row.  Times are CPU
seconds of this process; the first ``--warmup`` population steps are not counted.
A controlled population on CartPole or Acrobot trains several steps per compiled call
(:meth:`cdqn.agents.controlled_population.ControlledPopulation.run`), whose parts cannot be
timed apart; its time per member-step is measured on its own (``as trained``).

Double DQN (:mod:`cdqn.agents.ddqn_population`) has no controller; its update is timed as
two parts, the per-step kernel (pass at s', Θ1/Θ2, signal row, replay buffer) and the
minibatch steps, the rest of it (minibatch index draws, target copies) going to the loop's
share.  Its warm-up should pass ``learning_starts`` (``--warmup 1200``).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable, Iterator  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402
from numba import njit  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from cdqn.agents import ddqn_population  # noqa: E402
from cdqn.agents.controlled_population import (  # noqa: E402
    SCHEDULED_LQR,
    STATE_SPACE,
    STATIC_GAIN,
    ControlledPopulation,
    ControllerArrays,
    ControllerView,
)
from cdqn.agents.ddqn_population import DDQNPopulation  # noqa: E402
from cdqn.config import Config, register_configs, to_schema  # noqa: E402
from cdqn.control.factory import make_controller  # noqa: E402
from cdqn.control.kernels import scheduled_lqr_step, state_space_step, static_gain_u  # noqa: E402
from cdqn.envs import adopt, env_presets  # noqa: E402
from cdqn.training import population_loop  # noqa: E402
from cdqn.training.build import build_population, member_config  # noqa: E402
from cdqn.training.member import Member  # noqa: E402
from cdqn.training.population_loop import train_population  # noqa: E402
from cdqn.training.signals import SignalBuffer  # noqa: E402

PARTS = ("environment", "exploration", "act (forward at s after a reset, argmax)", "network",
         "controller", "recording", "loop (Python)")  # fmt: skip
DDQN_PARTS = ("environment", "exploration", "act (pass at s after a reset or minibatch)",
              "pass at s', Θ1, Θ2, replay buffer", "minibatch step", "recording",
              "loop (Python)")  # fmt: skip
clock = time.process_time
CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


@dataclass
class Profile:
    """Seconds per part over ``member_steps`` timed member-steps."""

    member_steps: int = 0
    seconds: dict[str, float] = field(default_factory=lambda: dict.fromkeys(PARTS, 0.0))
    """Per part (:data:`PARTS`, or :data:`DDQN_PARTS` for Double DQN)."""
    total: float = 0.0
    trained: float | None = None
    """µs per member-step of the loop as it trains (several steps per compiled call), where
    it differs from step by step."""

    @property
    def us_per_member_step(self) -> float:
        return 1e6 * self.total / self.member_steps

    def shares(self) -> dict[str, float]:
        return {k: v / self.total for k, v in self.seconds.items()}


class _Timers:
    """Accumulates the CPU time of wrapped calls per part while ``on`` is set."""

    def __init__(self, profile: Profile) -> None:
        self.profile, self.on = profile, False

    def wrap(self, part: str, fn: Callable[..., Any], inner: str | None = None) -> Callable:
        """``fn`` timed into ``part``; time spent in ``inner`` during the call is not."""
        seconds = self.profile.seconds

        def timed(*args: Any, **kwargs: Any) -> Any:
            if not self.on:
                return fn(*args, **kwargs)
            before = seconds[inner] if inner else 0.0
            t0 = clock()
            out = fn(*args, **kwargs)
            seconds[part] += clock() - t0 - ((seconds[inner] - before) if inner else 0.0)
            return out

        return timed

    def instrument(self, obj: object, method: str, part: str, inner: str | None = None) -> None:
        """Replace ``obj``'s ``method`` (on this instance only) by :meth:`wrap` of it."""
        setattr(obj, method, self.wrap(part, getattr(obj, method), inner))


class _TimedSignals(SignalBuffer):
    timers: _Timers

    def extend(self, rows: np.ndarray) -> None:
        self.timers.wrap("recording", super().extend)(rows)


@contextmanager
def _timed_episode_stats(timers: _Timers) -> Iterator[None]:
    original = population_loop.episode_stats
    population_loop.episode_stats = timers.wrap("recording", original)
    try:
        yield
    finally:
        population_loop.episode_stats = original


def fresh_population(conf: Config, k: int) -> tuple[Any, Any, list[Member]]:
    """Seeds ``conf.seed … conf.seed+k−1`` of ``conf`` as a new population: its agent,
    vectorised environments and members (no tracking store)."""
    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
    seeds = list(range(conf.seed, conf.seed + k))
    agent, venv = build_population(conf, setup, seeds)
    cfg = OmegaConf.structured(conf)
    return agent, venv, [Member(s, member_config(cfg, s)) for s in seeds]


def profile_population(conf: Config, k: int, steps: int, warmup: int) -> Profile:
    """Train seeds ``conf.seed … conf.seed+k−1`` as a population for ``warmup + steps``
    population steps and time its parts (module docstring)."""
    torch.set_num_threads(1)
    agent, venv, members = fresh_population(conf, k)
    ddqn = isinstance(agent, DDQNPopulation)
    prof = Profile(seconds=dict.fromkeys(DDQN_PARTS if ddqn else PARTS, 0.0))
    timers = _Timers(prof)
    for m in members:
        m.signals = _TimedSignals()
        m.signals.timers = timers
    timers.instrument(venv, "step", "environment")
    timers.instrument(venv, "reset", "environment")
    if isinstance(agent, ControlledPopulation):
        timers.instrument(agent.explore, "next", "exploration")
        timers.instrument(agent, "act", PARTS[2], "exploration")
        timers.instrument(agent, "update", "network")
    count = {"steps": 0, "t0": 0.0}

    def tick() -> bool:
        count["steps"] += 1
        if count["steps"] == warmup:
            timers.on, count["t0"] = True, clock()
        elif count["steps"] > warmup:
            prof.member_steps += len(members) - sum(m.status != "RUNNING" for m in members)
        if count["steps"] == warmup + steps:
            prof.total = clock() - count["t0"]
            return True
        return False

    with _timed_episode_stats(timers), _timed_ddqn(agent, timers):
        train_population(agent, venv, members, episodes=10**9, discount=conf.train.discount,
                         q_limit=conf.train.q_limit, should_stop=tick,
                         step_by_step=True)  # fmt: skip
    prof.total = prof.total or clock() - count["t0"]
    if isinstance(agent, ControlledPopulation):
        control = controller_seconds(agent.controller, prof.member_steps)
        prof.seconds["controller"] = control
        prof.seconds["network"] -= control
    prof.seconds["loop (Python)"] = prof.total - sum(prof.seconds.values())
    if isinstance(agent, ControlledPopulation) and getattr(venv, "compiled", False):
        prof.trained = trained_us_per_member_step(conf, k, steps, warmup)
    return prof


def trained_us_per_member_step(conf: Config, k: int, steps: int, warmup: int) -> float:
    """µs per member-step of the population as it trains: the CPU time of ``warmup + steps``
    population steps less that of ``warmup``, each from a fresh population."""

    def seconds(n: int) -> float:
        agent, venv, members = fresh_population(conf, k)
        t0 = clock()
        train_population(agent, venv, members, episodes=10**9, discount=conf.train.discount,
                         q_limit=conf.train.q_limit, max_steps=n)  # fmt: skip
        return clock() - t0

    seconds(1)  # compiled (or loaded) before it is timed
    return 1e6 * (seconds(warmup + steps) - seconds(warmup)) / (steps * k)


@contextmanager
def _timed_ddqn(agent: Any, timers: _Timers) -> Iterator[None]:
    """A Double DQN population's parts timed (:data:`DDQN_PARTS`); nothing for another."""
    if not isinstance(agent, DDQNPopulation):
        yield
        return
    for explorer in agent.explorers:
        timers.instrument(explorer, "explore", "exploration")
    timers.instrument(agent, "act", DDQN_PARTS[2], "exploration")
    names = {"_record_kernel": DDQN_PARTS[3], "double_dqn_learn": DDQN_PARTS[4]}
    originals = {name: getattr(ddqn_population, name) for name in names}
    for name, part in names.items():
        setattr(ddqn_population, name, timers.wrap(part, originals[name]))
    try:
        yield
    finally:
        for name, fn in originals.items():
            setattr(ddqn_population, name, fn)


def controller_seconds(c: ControllerArrays, member_steps: int) -> float:
    """CPU seconds of ``member_steps`` controller steps on copies of ``c``'s arrays."""
    v = c.view
    k = len(v.loss_weight)
    copies = v._replace(gains=v.gains.copy(), loss_weight=v.loss_weight.copy(),
                        x=np.zeros_like(v.x), unsolved=v.unsolved.copy())  # fmt: skip
    _controller_loop(1, tuple(copies))  # compiled (or loaded) before it is timed
    t0 = clock()
    _controller_loop(member_steps // k, tuple(copies))
    return clock() - t0


@njit(cache=True)
def _controller_loop(n, controller):
    """``n`` steps of every member's controller (a :class:`ControllerView` as a tuple) on
    representative signals (Θ1 = 300, Θ2 = 290, Q1 = 1, Q2 = 1.01, x_e = 1e-3)."""
    c = ControllerView(*controller)
    kind, gains, loss_weight, xc, unsolved = c.kind, c.gains, c.loss_weight, c.x, c.unsolved
    Ad, Bd, C, D, w_x, w_c = c.Ad, c.Bd, c.C, c.D, c.w_x, c.w_c
    research, target = c.research, c.target
    acc = 0.0
    for step in range(n):
        for k in range(gains.shape[0]):
            xe, q1, q2 = 1e-3 * (step % 7), 1.0, 1.01
            if kind == STATIC_GAIN:
                u = static_gain_u(gains[k, 0], gains[k, 1], gains[k, 2], xe, q1, q2)
            elif kind == STATE_SPACE:
                u = state_space_step(Ad, Bd, C, D, xc[k], xe, q1, q2)
                xc[k, :] = 0.0
            elif kind == SCHEDULED_LQR:
                u, loss_weight[k], solved = scheduled_lqr_step(
                    300.0 + step % 3, 290.0, 1.0, w_x, w_c, research, target, gains[k], xe, q1, q2
                )
                unsolved[k] += not solved
            else:
                u = 0.0
            acc += u
    return acc


def format_profile(name: str, prof: Profile) -> str:
    lines = [f"{name}: {prof.us_per_member_step:.2f} µs per member-step "
             f"({prof.member_steps} member-steps)"]  # fmt: skip
    for part, share in prof.shares().items():
        lines.append(f"  {part:<42}{100 * share:>6.1f} %")
    if prof.trained is not None:
        lines.append(f"as trained (several steps per compiled call): {prof.trained:.2f} µs per "
                     "member-step")  # fmt: skip
    return "\n".join(lines)


def profile_config(env: str, controller: str, width: int) -> Config:
    """What ``python -m cdqn.train env=<env> controller=<controller> network.width=<width>``
    trains (``env``: a preset or a gymnasium id), adopted by its environment."""
    register_configs()
    overrides = [
        f"env={env}" if env in env_presets() else f"env.id={env}",
        f"controller={controller}",
        f"network.width={width}",
        "train.progress=false",
    ]
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        return to_schema(adopt(compose("config", overrides=overrides)).cfg, Config)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m cdqn.profile",
                                     description=__doc__.split("\n")[0])  # fmt: skip
    parser.add_argument("--env", default="cartpole")
    controllers = sorted(p.stem for p in (CONF_DIR / "controller").glob("*.yaml"))
    parser.add_argument("--controller", default="hinf", choices=controllers)
    parser.add_argument("--width", type=int, default=2500)
    parser.add_argument("--population", type=int, default=10)
    parser.add_argument("--steps", type=int, default=3000, help="timed population steps")
    parser.add_argument(
        "--warmup", type=int, default=200, help="untimed population steps (ddqn: 1200)"
    )
    args = parser.parse_args(argv)
    conf = profile_config(args.env, args.controller, args.width)
    prof = profile_population(conf, args.population, args.steps, args.warmup)
    print(format_profile(f"{args.env} {args.controller} K={args.population}", prof))
    return {"us_per_member_step": prof.us_per_member_step, "shares": prof.shares(),
            "trained_us_per_member_step": prof.trained}  # fmt: skip


if __name__ == "__main__":
    from cdqn.cli import run_command

    run_command(main)
