"""The training loop: environment steps, agent updates, per-step and per-episode records."""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np
from numba import njit
from tqdm.auto import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from cdqn.agents.base import Agent, StepRecord
from cdqn.agents.episodic_replay import EpisodeTail, qualifies
from cdqn.config import ReplayConfig
from cdqn.control.box import Box
from cdqn.records import Signal, column
from cdqn.training.signals import SignalBuffer

RATE_WINDOW = 20
"""Episodes over which the progress bar's steps/s is measured (wall time, everything in)."""


class DivergenceError(RuntimeError):
    """Learning diverged: a non-finite or too large value in the loss, Q or controller."""

    def __init__(self, reason: str, episode: int, step: int) -> None:
        super().__init__(f"{reason} (episode {episode}, step {step})")
        self.reason, self.episode, self.step = reason, episode, step


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
    :class:`DivergenceError` when a step's loss, Q-values, control u or integrator x_e are
    non-finite, ``|Q|`` exceeds ``q_limit``, or the controller's state is non-finite at the
    end of an episode; everything up to that step is in ``signals``.  A NaN loss before the
    first finite one means "no update yet" (Double DQN before ``learning_starts``).
    ``should_stop`` is asked after each episode; when it answers True the loop returns
    early, at an episode boundary.  ``replay``: episodic replay of the controlled agents
    (:mod:`cdqn.agents.episodic_replay`) after each qualifying episode.  ``box``: the
    design's NTK box, for the per-episode ``theta1_outside_box``, ``ratio_below_box`` and
    ``ratio_above_box``.
    """
    state = state or TrainState()
    redirect = logging_redirect_tqdm(_console_loggers()) if progress else contextlib.nullcontext()
    redirect.__enter__()  # log lines go above the bar instead of breaking it
    bar = tqdm(
        total=episodes,
        initial=state.episode,
        desc=desc,
        disable=not progress,
        unit="ep",
        dynamic_ncols=True,
        leave=True,
    )
    recent = deque([(state.total_steps, time.perf_counter())], maxlen=RATE_WINDOW + 1)
    controller = getattr(agent, "controller", None)
    loss_seen = False
    tail = EpisodeTail(replay) if replay is not None and replay.repeats > 0 else None
    try:
        while state.episode < episodes:
            ep = state.episode
            obs, _ = env.reset(seed=seed if ep == 0 else None)
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
                if not (
                    abs(rec.q1) <= q_limit
                    and abs(rec.q2) <= q_limit
                    and math.isfinite(rec.u + rec.x_e)
                    and (math.isfinite(rec.loss) or (not loss_seen and math.isnan(rec.loss)))
                ):
                    _diagnose(rec, q_limit, ep, t)
                loss_seen = loss_seen or not math.isnan(rec.loss)
                ret += float(reward)
                obs = next_obs
                if terminated or truncated:
                    break
            replayed = 0
            if tail is not None and qualifies(replay, bool(terminated), bool(truncated), ret):
                for rec in agent.replay(tail.transitions(), replay.repeats):
                    if not _healthy(rec, q_limit):
                        _diagnose(rec, q_limit, ep, t)
                    replayed += 1
            x_c = getattr(controller, "x", None)
            if x_c is not None and not np.all(np.isfinite(x_c)):
                raise DivergenceError(f"non-finite controller state x_c = {x_c}", ep, t)
            state.returns.append(ret)
            length = signals.n - start_row
            state.total_steps += length
            state.episode += 1
            stats = episode_stats(
                ep, signals.rows(start_row), state.returns, discount, replayed, box
            )
            if on_episode is not None:
                on_episode(stats, state)
            recent.append((state.total_steps, time.perf_counter()))
            steps, secs = recent[-1][0] - recent[0][0], recent[-1][1] - recent[0][1]
            bar.set_postfix(
                ret=f"{ret:.0f}",
                ma100=f"{stats.return_ma100:.1f}",
                eps=f"{agent.epsilon:.2f}",
                sps=f"{steps / max(secs, 1e-9):.0f}",
                refresh=False,
            )
            bar.update(1)
            if should_stop is not None and should_stop():
                break
    finally:
        bar.close()
        redirect.__exit__(None, None, None)
    return state


def _healthy(rec: StepRecord, q_limit: float) -> bool:
    """The divergence test of a replayed update (every one has a finite loss)."""
    return (
        abs(rec.q1) <= q_limit
        and abs(rec.q2) <= q_limit
        and math.isfinite(rec.u + rec.x_e + rec.loss)
    )


def _console_loggers() -> list[logging.Logger]:
    """The root logger and the loggers with console handlers of their own (MLflow's)."""
    named = [logging.getLogger(n) for n in ("mlflow",)]
    return [logging.getLogger(), *[lg for lg in named if lg.handlers]]


def _diagnose(rec: StepRecord, q_limit: float, ep: int, t: int) -> None:
    """Raise the :class:`DivergenceError` that names what went wrong in ``rec``."""
    for name, value in (("Q1", rec.q1), ("Q2", rec.q2), ("u", rec.u), ("x_e", rec.x_e)):
        if not math.isfinite(value):
            raise DivergenceError(f"non-finite {name} = {value}", ep, t)
    if not math.isfinite(rec.loss):
        raise DivergenceError(f"non-finite loss = {rec.loss}", ep, t)
    q = max(abs(rec.q1), abs(rec.q2))
    raise DivergenceError(f"|Q| = {q:.3g} above train.q_limit={q_limit:g}", ep, t)
