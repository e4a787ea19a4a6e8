"""The training loop: environment steps, agent updates, per-step and per-episode records."""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import gymnasium as gym
import numpy as np
from numba import njit
from tqdm.auto import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from cdqn.agents.base import Agent, ReplayAgent
from cdqn.config import ReplayConfig
from cdqn.control.box import Box
from cdqn.records import Signal, column
from cdqn.training.divergence import DivergenceError as DivergenceError
from cdqn.training.divergence import check_controller, check_replayed, check_step
from cdqn.training.signals import SignalBuffer

if TYPE_CHECKING:  # loaded for a run with episodic replay
    from cdqn.agents.episodic_replay import EpisodeTail

RATE_WINDOW = 20
"""Episodes over which the progress bar's steps/s is measured (wall time, everything in)."""


_LOSS, _U, _THETA1, _THETA2 = map(column, (Signal.LOSS, Signal.U, Signal.THETA1, Signal.THETA2))
"""Indices of the signal columns the episode summaries read (compile-time constants)."""


@dataclass
class EpisodeStats:
    """Per-episode metrics, logged to MLflow with step = episode index."""

    episode: int
    episode_return: float
    return_ma100: float
    episode_length: int
    loss_mean: float
    u_abs_mean: float
    theta1_mean: float
    unstable_fraction: float
    """Share of the episode's steps with Θ1 < γ Θ2 (the nominal model unstable)."""
    replay_updates: int = 0
    """Updates of episodic replay after the episode (:mod:`cdqn.agents.episodic_replay`)."""
    theta1_outside_box: float | None = None
    """Share of the episode's steps with Θ1 outside the Θ1 range of the NTK box the design
    was certified on; ``None`` (not logged) for an agent without a box."""
    ratio_below_box: float | None = None
    """Share of the episode's steps with Θ2/Θ1 below the box's ratio range (those whose next
    greedy action differs from ``a`` among them); ``None`` (not logged) without a box."""
    ratio_above_box: float | None = None
    """Share of the episode's steps with Θ2/Θ1 above the box's ratio range, the side the
    loop's stability bound limits; ``None`` (not logged) without a box."""

    def metrics(self) -> dict[str, float]:
        return {k: float(v) for k, v in vars(self).items() if k != "episode" and v is not None}


@dataclass
class TrainState:
    """What the loop carries across episodes (and what a checkpoint must restore)."""

    episode: int = 0
    returns: list[float] = field(default_factory=list)
    total_steps: int = 0


def episode_stats(
    episode: int,
    rows: np.ndarray,
    returns: list[float],
    discount: float,
    replay_updates: int = 0,
    box: Box | None = None,
) -> EpisodeStats:
    """Summarise one episode's rows of the signal table (columns of
    :mod:`cdqn.training.signals`); ``box``: the design's NTK box, for
    ``theta1_outside_box``, ``ratio_below_box`` and ``ratio_above_box``."""
    loss_mean, u_abs_mean, theta1_mean, unstable = _episode_means(rows, discount)
    outside = (None,) * 3 if box is None else _outside_shares(rows, *box[0], *box[1])
    return EpisodeStats(
        episode=episode,
        episode_return=returns[-1],
        return_ma100=float(np.mean(returns[-100:])),
        episode_length=len(rows),
        loss_mean=loss_mean,
        u_abs_mean=u_abs_mean,
        theta1_mean=theta1_mean,
        unstable_fraction=unstable,
        replay_updates=replay_updates,
        theta1_outside_box=outside[0],
        ratio_below_box=outside[1],
        ratio_above_box=outside[2],
    )


@njit(cache=True)
def _episode_means(rows, discount):
    """Mean of the finite losses (NaN if none), of |u| and of Θ1, and the share of steps
    with Θ1 < γ Θ2; one pass over the rows, sums in row order."""
    loss = u = theta1 = 0.0
    n_loss = unstable = 0
    for r in range(rows.shape[0]):
        if math.isfinite(rows[r, _LOSS]):
            loss += rows[r, _LOSS]
            n_loss += 1
        u += abs(rows[r, _U])
        theta1 += rows[r, _THETA1]
        if rows[r, _THETA1] < discount * rows[r, _THETA2]:
            unstable += 1
    n = rows.shape[0]
    return loss / n_loss if n_loss else math.nan, u / n, theta1 / n, unstable / n


@njit(cache=True)
def _outside_shares(rows, theta1_lo, theta1_hi, ratio_lo, ratio_hi):
    """Shares of the rows whose kernel leaves the box (paper Sec. 3, "Boundedness of the
    parametric uncertainty"): Θ1 ∉ [Θ1_lo, Θ1_hi], ρ = Θ2/Θ1 < ρ_lo and ρ > ρ_hi.

    The box is measured on the initial network and the design certified over it
    (docs/synthesis.md).  Θ1 grows as the weights learn.  ρ lies below the box on the
    transitions whose next greedy action differs from ``a`` (Θ2 ≈ 0 at initialisation, left
    out of the measured ratio range): Q2 moves less there, and a static loop is further from
    its bound ``(1 + k1)Θ1 > (γ − k2)Θ2`` (:mod:`cdqn.control.plant`).  ρ above the box is
    the side that bound limits."""
    theta1_out = below = above = 0
    for r in range(rows.shape[0]):
        t1, t2 = rows[r, _THETA1], rows[r, _THETA2]
        if not theta1_lo <= t1 <= theta1_hi:
            theta1_out += 1
        if t2 < ratio_lo * t1:
            below += 1
        elif t2 > ratio_hi * t1:
            above += 1
    n = rows.shape[0]
    return (theta1_out / n, below / n, above / n) if n else (math.nan, math.nan, math.nan)


def train(
    env: gym.Env,
    agent: Agent,
    *,
    episodes: int,
    seed: int,
    discount: float,
    q_limit: float,
    signals: SignalBuffer,
    state: TrainState | None = None,
    on_episode: Callable[[EpisodeStats, TrainState], None] | None = None,
    progress: bool = True,
    desc: str = "",
    should_stop: Callable[[], bool] | None = None,
    replay: ReplayConfig | None = None,
    box: Box | None = None,
) -> TrainState:
    """Run ``episodes`` episodes (from ``state.episode`` on) and return the final state.

    The environment is seeded with ``seed`` at the first episode of a fresh run.  Raises
    :class:`DivergenceError` when a step fails the divergence check of
    :mod:`cdqn.training.divergence` (loss, Q-values, control u or integrator x_e non-finite,
    ``|Q|`` above ``q_limit``, the controller's state non-finite at the end of an episode);
    everything up to that step is in ``signals``.  ``should_stop`` is asked after each
    episode; when it answers True the loop returns early, at an episode boundary.
    ``replay``: episodic replay of the controlled agents
    (:mod:`cdqn.agents.episodic_replay`) after each qualifying episode; an agent built with
    sampled replay (:mod:`cdqn.agents.replay`) replays after each step.  ``box``: the
    design's NTK box, for the per-episode ``theta1_outside_box``, ``ratio_below_box`` and
    ``ratio_above_box``.
    """
    state = state or TrainState()
    tail = None
    if replay is not None and replay.repeats > 0:
        from cdqn.agents.episodic_replay import EpisodeTail

        tail = EpisodeTail(replay)
    run = _Episodes(env, agent, signals, seed, discount, q_limit, replay, tail, box)
    bar = _Bar(episodes, state, desc, progress)
    try:
        while state.episode < episodes:
            stats = run.episode(state)
            if on_episode is not None:
                on_episode(stats, state)
            bar.update(state, stats, agent.epsilon)
            if should_stop is not None and should_stop():
                break
    finally:
        bar.close()
    return state


@dataclass
class _Episodes:
    """The episodes of one run: steps, updates, signal rows, replay and divergence checks."""

    env: gym.Env
    agent: Agent
    signals: SignalBuffer
    seed: int
    discount: float
    q_limit: float
    replay: ReplayConfig | None
    tail: EpisodeTail | None
    box: Box | None
    loss_seen: bool = False
    """A finite loss was seen (a NaN loss before that means "no update yet")."""

    def __post_init__(self) -> None:
        sampled = getattr(self.agent, "memory", None) is not None
        self.replay_sampled = getattr(self.agent, "replay_sampled", None) if sampled else None
        """The agent's sampled replay after each step (:mod:`cdqn.agents.replay`), if on."""

    def episode(self, state: TrainState) -> EpisodeStats:
        """Play episode ``state.episode`` to its end and advance ``state``; its metrics."""
        env, agent, signals, tail, q_limit = (
            self.env, self.agent, self.signals, self.tail, self.q_limit
        )  # fmt: skip
        ep = state.episode
        obs, _ = env.reset(seed=self.seed if ep == 0 else None)
        agent.start_episode()
        start_row, ret = signals.n, 0.0
        if tail is not None:
            tail.clear()
        for t in range(1_000_000_000):
            action = agent.act(obs)
            next_obs, reward, terminated, truncated, _ = env.step(action)
            rec = agent.update(obs, action, float(reward), next_obs, bool(terminated))
            if tail is not None:
                tail.append(obs, action, float(reward), next_obs, bool(terminated))
            signals.append(ep, t, float(reward), rec)
            self.loss_seen = check_step(rec, q_limit, self.loss_seen, ep, t)
            if self.replay_sampled is not None:
                done = bool(terminated)
                for sampled_rec in self.replay_sampled(obs, action, float(reward), next_obs, done):
                    check_replayed(sampled_rec, q_limit, ep, t)
            ret += float(reward)
            obs = next_obs
            if terminated or truncated:
                break
        replayed = self._replay(bool(terminated), bool(truncated), ret, ep, t)
        check_controller(getattr(getattr(agent, "controller", None), "x", None), ep, t)
        state.returns.append(ret)
        state.total_steps += signals.n - start_row
        state.episode += 1
        rows = signals.rows(start_row)
        return episode_stats(ep, rows, state.returns, self.discount, replayed, self.box)

    def _replay(self, terminated: bool, truncated: bool, ret: float, ep: int, t: int) -> int:
        """Episodic replay of the episode that ended, if it qualifies; the updates made."""
        replay, tail = self.replay, self.tail
        if tail is None or replay is None:
            return 0
        from cdqn.agents.episodic_replay import qualifies  # loaded with the tail

        if not qualifies(replay, terminated, truncated, ret):
            return 0
        agent = self.agent
        if not isinstance(agent, ReplayAgent):
            raise TypeError(f"{type(agent).__name__} has no episodic replay")
        replayed = 0
        for rec in agent.replay(tail.transitions(), replay.repeats):
            check_replayed(rec, self.q_limit, ep, t)
            replayed += 1
        return replayed


class _Bar:
    """The progress bar: episodes, return, MA100, ε and steps/s over the last
    :data:`RATE_WINDOW` episodes; log lines go above it instead of breaking it."""

    def __init__(self, episodes: int, state: TrainState, desc: str, progress: bool) -> None:
        self.redirect = (
            logging_redirect_tqdm(_console_loggers()) if progress else contextlib.nullcontext()
        )
        self.redirect.__enter__()
        self.bar = tqdm(total=episodes, initial=state.episode, desc=desc, disable=not progress,
                        unit="ep", dynamic_ncols=True, leave=True)  # fmt: skip
        self.recent = deque([(state.total_steps, time.perf_counter())], maxlen=RATE_WINDOW + 1)

    def update(self, state: TrainState, stats: EpisodeStats, epsilon: float) -> None:
        self.recent.append((state.total_steps, time.perf_counter()))
        steps = self.recent[-1][0] - self.recent[0][0]
        secs = self.recent[-1][1] - self.recent[0][1]
        self.bar.set_postfix(
            ret=f"{stats.episode_return:.0f}",
            ma100=f"{stats.return_ma100:.1f}",
            eps=f"{epsilon:.2f}",
            sps=f"{steps / max(secs, 1e-9):.0f}",
            refresh=False,
        )
        self.bar.update(1)

    def close(self) -> None:
        self.bar.close()
        self.redirect.__exit__(None, None, None)


def _console_loggers() -> list[logging.Logger]:
    """The root logger and the loggers with console handlers of their own (MLflow's)."""
    named = [logging.getLogger(n) for n in ("mlflow",)]
    return [logging.getLogger(), *[lg for lg in named if lg.handlers]]
