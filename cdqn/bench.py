"""Training throughput: every controller against the autograd floor, populations, and the
paper sweep's wall time on this machine.

    python -m cdqn.bench                                  # CartPole, width 2500, all controllers
    python -m cdqn.bench --env acrobot --controllers h2,hinf --steps 5000
    python -m cdqn.bench --json                           # machine-readable, see below

For each controller it measures environment steps per second of the real training code
path with logging on: the agent's step (NTK Θ1 and Θ2, controller, SGD step or Double DQN's
minibatch step), :func:`cdqn.training.loop.train` with its per-step :class:`SignalBuffer`
appends, divergence checks and episode statistics, and the MLflow :class:`Recorder`
receiving every episode's metrics (a store in a temporary folder).  In the same process,
interleaved with those measurements, it measures the **floor**: a bare online Q-learning
step on the same network with torch autograd (forward on s, forward on s', TD loss,
backward, SGD step) plus the environment step.  Each controller's cost is printed as a
ratio to the floor's (``ratio_to_floor = floor steps/s ÷ controller steps/s``; ≤ 1 means
no slower than the floor).  Numbers are medians over ``--repeats`` interleaved rounds, so
that other load on the machine affects all of them alike, in CPU seconds of this process
(``--clock wall`` for wall-clock seconds).  The recorder's batched writes of the episode
metrics to the store cost the same per episode in every mode; they are kept out of the
timed windows, timed apart in one flush of 300 episodes (wall clock,
:func:`metric_write_seconds_per_episode`), printed below the table and included in the
estimate.

Beside each agent's microseconds per step (single run) or per member-step (population) it
prints its **limit**: the multiply-adds of one environment step of that agent, counted from
the shapes of its matrix products (:func:`agent_products`), at one thread's measured peak
(:func:`peak_macs_per_s`, a 512² torch matmul in the configured dtype, best of 20 in CPU
seconds of the thread), and the ratio.  Below the table: the same products as torch matmuls
of their shapes (:func:`torch_seconds`), far slower than the limit for such thin products.
``--dtype float32`` measures everything with ``network.dtype=float32``.

The population section trains ``K`` seeds as one batch (:mod:`cdqn.training.population`) for
``--steps`` population steps (``K × steps`` member-steps) and reports member-steps per
second against the single run's steps per second of the same controller (the throughput of
``K`` sequential runs); its ``speedup`` is the ratio.

The estimate section measures the throughput of every environment and controller of the
paper's sweep (populations of 10, Double DQN's included), adds the measured costs of opening
and closing a run and of writing metrics and signals, and schedules the sweep's 12 jobs on
``--workers`` parallel workers in launch order
(Hydra's joblib launcher):

    wall ≈ makespan over jobs of  Σ_seeds (episodes × L_env × (1 / steps_per_s + signal write)
                                         + episodes × metric write + run overhead)

``L_env`` is the mean episode length over training, an assumption stated in the output
(``--episode-lengths``); the upper bound uses every episode at its cap.

``--json`` prints ``{"floor": {"steps_per_s": …}, "controllers": {"<name>": {"steps_per_s":
…, "ratio_to_floor": …, "us_per_step": …, "limit_us": …, "ratio_to_limit": …}}, "limits":
{"<name>": {"macs_per_step": …, "peak_macs_per_s": …, "limit_us": …, "torch_us": …}},
"population": {"k": 10, "speedup": …, "by_controller": {…}}, "estimate": {…}}``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core, as each job of a sweep gets

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import uuid  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import torch  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from cdqn.agents.base import EpsilonGreedy  # noqa: E402
from cdqn.config import CONF_DIR, Config, register_configs, to_schema  # noqa: E402
from cdqn.control.factory import make_controller  # noqa: E402
from cdqn.envs import adopt, env_presets, env_sizes, make_env  # noqa: E402
from cdqn.network import NetworkSpec, QNetwork  # noqa: E402
from cdqn.records import EPISODE_METRICS, Signal, Tag, column  # noqa: E402
from cdqn.training.build import build, build_population, member_config  # noqa: E402
from cdqn.training.lifecycle import RunLifecycle  # noqa: E402
from cdqn.training.loop import DivergenceError, EpisodeStats, TrainState, train  # noqa: E402
from cdqn.training.member import Member  # noqa: E402
from cdqn.training.population_checkpoint import MemberCheckpoint  # noqa: E402
from cdqn.training.population_loop import train_population  # noqa: E402
from cdqn.training.signals import (  # noqa: E402
    COLUMNS,
    SignalBuffer,
    amplitude_spectra,
    signal_series,
)
from cdqn.training.tracking import Recorder  # noqa: E402

CONTROLLERS = ("none", "h2", "hinf", "hinf_f", "ddqn")
PAPER_ENVS = ("cartpole", "acrobot", "mountaincar")
PAPER_CONTROLLERS = ("h2", "hinf", "hinf_f", "ddqn")
SWEEP_ORDER = tuple(
    (env, ctrl)
    for ctrl in ("ddqn", "h2", "hinf", "hinf_f")
    for env in ("mountaincar", "acrobot", "cartpole")
)
"""The order in which ``sweeps/paper.yaml`` starts its jobs (Hydra's sweeper takes the product
of its parameters in the order written): the longest jobs (Double DQN, Mountain car) first,
so that two workers finish together instead of one waiting on a long job started last."""
PAPER_SEEDS = 10
PAPER_EPISODES = 2000
EPISODE_CAP = {"cartpole": 200, "acrobot": 500, "mountaincar": 200}
EPISODE_LENGTH = {"cartpole": 150, "acrobot": 150, "mountaincar": 170}
"""Assumed mean episode length over 2000 training episodes (early episodes near the cap for
Acrobot and Mountain car, near 20 for CartPole; final returns of the paper's table)."""

log = logging.getLogger("cdqn")

CLOCKS = {"cpu": time.process_time, "wall": time.perf_counter}
clock = time.process_time
"""Training seconds are CPU seconds of this process by default (``--clock cpu``): on an
otherwise idle core they equal wall-clock seconds, and other load on a shared machine barely
moves them.  Writes to the tracking store (metrics, opening and closing runs) wait for the
disk and are always timed in wall-clock seconds."""


@dataclass
class Throughput:
    steps: int
    seconds: float

    @property
    def steps_per_s(self) -> float:
        return self.steps / self.seconds if self.seconds > 0 else float("nan")


@dataclass(frozen=True)
class Product:
    """A matrix product ``(rows × inner) @ (inner × cols)`` an agent computes ``per_step``
    times per environment step."""

    rows: int
    inner: int
    cols: int
    per_step: float

    @property
    def macs(self) -> float:
        return self.rows * self.inner * self.cols * self.per_step


def agent_products(conf: Config, n_obs: int, n_actions: int) -> list[Product]:
    """The arithmetic of one environment step of ``conf``'s agent on the two-layer network
    (width ``W``, ``n`` inputs, or the nonzero ones of :func:`nonzero_inputs`, ``m``
    actions), as matrix products.

    Every agent: the pass at ``s'`` (``(1×n)(n×W)``, ``(1×W)(W×m)``) and the NTK's four sums
    over hidden units (Θ1, Θ2).  Double DQN also the pass at ``s`` (its act), and every
    ``train_freq`` steps a minibatch step (:func:`cdqn.ddqn_kernels.minibatch_macs`): three
    passes over ``B`` samples, then ``∂L/∂W_2``, ``∂L/∂h`` and ``∂L/∂W_1``.  A controlled
    agent's SGD step: ``W_1 += s g x^⊤``, ``b_1``, ``W_2[a]`` and its pass at ``s'`` with
    the new parameters from the old one."""
    w, n, m = conf.network.width, n_obs, n_actions
    step = [Product(1, n, w, 1), Product(1, w, m, 1), Product(1, w, 1, 4)]
    if conf.controller.name != "ddqn":
        return [*step, Product(n, 1, w, 1), Product(1, 1, w, 3), Product(1, w, m, 1)]
    b, every = conf.controller.batch_size, 1 / conf.controller.train_freq
    return [
        *step,
        Product(1, n, w, 1),  # the act's pass at s
        Product(1, w, m, 1),
        Product(b, n, w, 3 * every),  # Q(s, ·), Q(s', ·), Q̄(s', ·)
        Product(b, w, m, 3 * every),
        Product(m, b, w, every),  # ∂L/∂W_2
        Product(b, m, w, every),  # ∂L/∂h
        Product(n, b, w, every),  # ∂L/∂W_1
    ]


def nonzero_inputs(env: Any, steps: int = 50) -> int:
    """The inputs the first layer's products run over (:mod:`cdqn.network`, zero inputs):
    the mean number of nonzero entries of the observations of ``steps`` random steps,
    rounded (1 for a one-hot state, every input of a dense observation)."""
    rng = np.random.default_rng(0)
    obs, counts = env.reset(seed=0)[0], []
    for _ in range(steps):
        counts.append(np.count_nonzero(obs))
        obs, _, terminated, truncated, _ = env.step(int(rng.integers(env.action_space.n)))
        if terminated or truncated:
            obs = env.reset()[0]
    return max(1, round(float(np.mean(counts))))


def _best_seconds(fn: Any, repeats: int) -> float:
    """The fastest of ``repeats`` calls, in CPU seconds of this thread (other load on a
    shared machine takes the core away without counting)."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.thread_time()
        fn()
        best = min(best, time.thread_time() - t0)
    return best


def peak_macs_per_s(dtype: str, size: int = 512, repeats: int = 20) -> float:
    """Multiply-adds per second of one thread at its peak: a ``size``² matrix product in
    ``dtype`` through torch (MKL), best of ``repeats``."""
    a = torch.randn(size, size, dtype=getattr(torch, dtype))
    return size**3 / _best_seconds(lambda: a @ a, repeats)


def torch_seconds(products: list[Product], dtype: str, repeats: int = 50) -> float:
    """Seconds per environment step of the same products as torch matrix products of their
    shapes (one call each), best of ``repeats``."""
    t = getattr(torch, dtype)
    pairs = [(torch.randn(p.rows, p.inner, dtype=t), torch.randn(p.inner, p.cols, dtype=t))
             for p in products]  # fmt: skip
    return sum(
        p.per_step * _best_seconds(lambda a=a, b=b: a @ b, repeats)
        for p, (a, b) in zip(products, pairs, strict=True)
    )


def measure_limits(cfgs: dict[str, DictConfig]) -> dict[str, dict[str, float]]:
    """Per controller: the multiply-adds of an environment step, the **limit** (those at one
    thread's measured peak, µs) and the same products through torch (µs)."""
    out: dict[str, dict[str, float]] = {}
    peak: dict[str, float] = {}
    for c, cfg in cfgs.items():
        conf = _conf(cfg)
        env = make_env(conf.env)
        products = agent_products(conf, nonzero_inputs(env), env_sizes(env)[1])
        env.close()
        dtype = conf.network.dtype
        if dtype not in peak:
            peak[dtype] = peak_macs_per_s(dtype)
        macs = sum(p.macs for p in products)
        out[c] = {
            "macs_per_step": macs,
            "peak_macs_per_s": peak[dtype],
            "limit_us": 1e6 * macs / peak[dtype],
            "torch_us": 1e6 * torch_seconds(products, dtype),
        }
    return out


def compose_config(overrides: list[str]) -> DictConfig:
    """The configuration ``python -m cdqn.train <overrides>`` would run, adopted by its
    environment (:func:`cdqn.envs.adopt`)."""
    register_configs()
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        return adopt(compose("config", overrides=overrides)).cfg


def _conf(cfg: DictConfig) -> Config:
    return to_schema(cfg, Config)


def measure_floor(cfg: DictConfig, steps: int, warmup: int) -> Throughput:
    """Bare online Q-learning with torch autograd on the same network, plus the env step."""
    conf = _conf(cfg)
    env = make_env(conf.env)
    n_obs, n_actions = env_sizes(env)
    torch.manual_seed(conf.seed)
    net = QNetwork(NetworkSpec(n_obs, n_actions, conf.network.width, conf.network.dtype))
    opt = torch.optim.SGD(net.parameters(), lr=conf.train.lr)
    explorer = EpsilonGreedy(conf.train, n_actions, np.random.default_rng(conf.seed))
    dtype, gamma = net.hidden.weight.dtype, conf.train.discount
    obs, _ = env.reset(seed=conf.seed)
    t0 = clock()
    for i in range(warmup + steps):
        if i == warmup:
            t0 = clock()
        q = net(torch.as_tensor(obs, dtype=dtype))  # forward on s
        action = explorer.explore()
        if action is None:
            action = int(torch.argmax(q))
        next_obs, reward, terminated, truncated, _ = env.step(action)
        with torch.no_grad():  # forward on s'
            q_next = net(torch.as_tensor(next_obs, dtype=dtype)).max()
        loss = 0.5 * (float(reward) + gamma * q_next - q[action]) ** 2  # TD loss
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        obs = next_obs
        if terminated or truncated:
            obs, _ = env.reset()
    seconds = clock() - t0
    env.close()
    return Throughput(steps, seconds)


def measure_single(cfg: DictConfig, uri: str, steps: int, warmup: int) -> Throughput:
    """One run's training loop (agent, trainer, signals, episode statistics handed to the
    MLflow recorder) for ``warmup + steps`` environment steps; only whole episodes after the
    warm-up are timed, and a diverged run is replaced by another seed's.  The recorder's
    batched metric writes are left out (:func:`metric_write_seconds_per_episode`)."""
    conf = _conf(cfg)
    total = Throughput(0, 0.0)
    done, seed = 0, conf.seed
    while done < warmup + steps:
        conf.seed = seed
        env = make_env(conf.env)
        job = build(conf, env)
        recorder = Recorder.start(uri, conf.tracking.experiment, f"bench-s{seed}", {}, {})
        recorder.flush_seconds = float("inf")  # written outside the window
        state = TrainState()
        window: list[tuple[int, float]] = []  # (steps, time) at its edges

        def on_episode(
            stats: EpisodeStats,
            st: TrainState,
            rec: Recorder = recorder,
            window: list[tuple[int, float]] = window,
            before: int = done,
        ) -> None:
            rec.log_episode(stats)
            if before + st.total_steps >= warmup:
                if not window:
                    rec.flush()  # the warm-up's metrics
                window[1:] = [(st.total_steps, clock())]

        def should_stop(st: TrainState = state, before: int = done) -> bool:
            return before + st.total_steps >= warmup + steps

        try:
            train(
                env,
                job.agent,
                episodes=10**9,
                seed=seed,
                discount=conf.train.discount,
                q_limit=conf.train.q_limit,
                signals=SignalBuffer(),
                state=state,
                on_episode=on_episode,
                progress=False,
                should_stop=should_stop,
            )
        except DivergenceError:
            seed += 1_000
        finally:
            recorder.finish()
            env.close()
        if len(window) == 2:
            (s0, t0), (s1, t1) = window
            total = Throughput(total.steps + s1 - s0, total.seconds + t1 - t0)
        done += state.total_steps
    return total


@dataclass
class PopulationThroughput:
    member_steps: Throughput
    run_overhead_s: float
    """Seconds to open and close one member's run (params, config, signals, model)."""


def measure_population(
    cfg: DictConfig, uri: str, k: int, steps: int, warmup: int
) -> PopulationThroughput:
    """``k`` seeds as one batch for ``warmup + steps`` population steps, with each member's
    MLflow run receiving its metrics, then its signals and model.

    Only steps with all ``k`` members in the batch are timed: when a member diverges the
    window closes there, and the measurement goes on with ``k`` other seeds until
    ``steps`` population steps are timed (like :func:`measure_single`, which replaces a
    diverged run)."""
    total, overheads, seed = Throughput(0, 0.0), [], _conf(cfg).seed
    for _ in range(8):
        window, overhead = _population_window(cfg, uri, k, steps - total.steps // k, warmup, seed)
        total = Throughput(total.steps + window.steps, total.seconds + window.seconds)
        overheads.append(overhead)
        if total.steps >= k * steps:
            break
        seed += 1_000
    return PopulationThroughput(total, float(np.mean(overheads)))


def _population_window(
    cfg: DictConfig, uri: str, k: int, steps: int, warmup: int, seed: int
) -> tuple[Throughput, float]:
    """Seeds ``seed … seed+k−1`` as one batch: (the timed window, seconds to open and
    close one member's run)."""
    conf = _conf(cfg)
    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
    seeds = list(range(seed, seed + k))
    agent, venv = build_population(conf, setup, seeds)
    members = [Member(s, member_config(cfg, s)) for s in seeds]
    life = RunLifecycle(conf, uri, MemberCheckpoint)
    tags = {Tag.POPULATION: f"{seeds[0]}-{seeds[-1]}", Tag.POPULATION_ID: uuid.uuid4().hex}
    t_open = time.perf_counter()
    for m in members:
        life.open(m, setup, tags)
    t_open = time.perf_counter() - t_open
    timer: dict[str, float] = {"steps": 0, "member_steps": 0}
    ended: list[float] = []
    for m in members:
        assert m.recorder is not None
        m.recorder.flush_seconds = float("inf")  # written at the end, outside the window

    def count(taken: int) -> None:  # population steps since the last call
        timer["steps"] += taken
        if "t0" in timer:
            timer["member_steps"] += taken * k

    def tick() -> bool:  # called after each call of the loop, after its episode ends
        if "t0" not in timer and timer["steps"] >= warmup:
            for m in members:  # the warm-up's metrics
                if m.recorder is not None:
                    m.recorder.flush()
            timer["t0"] = clock()
        all_in = all(m.status == "RUNNING" for m in members)
        if timer["steps"] >= warmup + steps or not all_in:
            if "t0" in timer:
                timer["t1"] = clock()
            return True
        return False

    def on_episode(m: Member, stats: Any) -> None:
        assert m.recorder is not None
        m.recorder.log_episode(stats)

    def on_member_end(m: Member, pop: Any, j: int) -> None:
        assert m.recorder is not None
        m.recorder.flush()
        t = time.perf_counter()
        life.close(m, pop.network(j))
        ended.append(time.perf_counter() - t)

    train_population(
        agent,
        venv,
        members,
        episodes=10**9,
        discount=conf.train.discount,
        q_limit=conf.train.q_limit,
        on_episode=on_episode,
        on_member_end=on_member_end,
        should_stop=tick,
        on_steps=count,
    )
    for env in venv.envs:
        env.close()
    diverged = sum(m.status == "FAILED" for m in members)
    if diverged:
        log.info("%d of %d members diverged; timed until the first did", diverged, k)
    if "t1" not in timer:  # a member left during the warm-up: nothing timed
        return Throughput(0, 0.0), (t_open + sum(ended)) / k
    seconds = timer["t1"] - timer["t0"]
    return Throughput(int(timer["member_steps"]), seconds), (t_open + sum(ended)) / k


def _pop_warmup(controller: str, warmup: int, k: int) -> int:
    """Untimed population steps before a population's timed window: ``warmup`` member-steps
    in all, but Double DQN's members each take ``warmup`` steps (past ``learning_starts``)."""
    return warmup if controller == "ddqn" else warmup // k + 1


def _median(values: list[float]) -> float:
    finite = [v for v in values if np.isfinite(v)]
    return statistics.median(finite) if finite else float("nan")


def makespan(durations: list[float], workers: int) -> float:
    """Wall time of jobs started in this order on ``workers`` workers (list scheduling)."""
    free = [0.0] * workers
    for d in durations:
        i = int(np.argmin(free))
        free[i] += d
    return max(free)


def estimate_paper_sweep(
    uri: str,
    width: int,
    steps: int,
    warmup: int,
    workers: int,
    k: int,
    metric_s: float,
    episodes: int = PAPER_EPISODES,
    lengths: dict[str, float] | None = None,
) -> dict[str, Any]:
    """Measured throughput of every environment × controller of the paper's sweep and the
    resulting wall time (module docstring); ``metric_s`` is the measured cost of writing one
    episode's metrics, ``lengths`` the assumed mean episode lengths."""
    lengths = dict(EPISODE_LENGTH if lengths is None else lengths)
    rates: dict[str, dict[str, float]] = {}
    overhead: list[float] = []
    for env in PAPER_ENVS:
        rates[env] = {}
        for ctrl in PAPER_CONTROLLERS:
            cfg = compose_config(_overrides(env, ctrl, width, uri))
            pop = measure_population(cfg, uri, k, steps // k + 1, _pop_warmup(ctrl, warmup, k))
            measured = pop.member_steps
            overhead.append(pop.run_overhead_s)
            rates[env][ctrl] = measured.steps_per_s
    per_run = _median(overhead)
    signal_s = signal_write_seconds_per_step(uri)
    jobs: dict[str, list[float]] = {"expected": [], "upper": []}
    for env, ctrl in SWEEP_ORDER:
        for kind, length in (("expected", lengths[env]), ("upper", EPISODE_CAP[env])):
            steps_per_run = episodes * length
            run_s = (
                steps_per_run * (1.0 / rates[env][ctrl] + signal_s) + episodes * metric_s + per_run
            )
            jobs[kind].append(PAPER_SEEDS * run_s)
    total_steps = sum(
        PAPER_SEEDS * episodes * lengths[e] * len(PAPER_CONTROLLERS) for e in PAPER_ENVS
    )
    return {
        "steps_per_s": rates,
        "run_overhead_s": per_run,
        "metric_write_s_per_episode": metric_s,
        "signal_write_s_per_step": signal_s,
        "episodes": episodes,
        "episode_length": lengths,
        "episode_cap": dict(EPISODE_CAP),
        "workers": workers,
        "expected_env_steps": total_steps,
        "expected_hours": makespan(jobs["expected"], workers) / 3600,
        "upper_bound_hours": makespan(jobs["upper"], workers) / 3600,
    }


def synthetic_signals(rows: int) -> np.ndarray:
    """``rows`` rows of the signal table (:data:`cdqn.records.STEP_COLUMNS`): episodes of 150
    steps, normal noise in the other columns, Θ1 > 0 (so that Θ2/Θ1 is defined)."""
    table = np.random.default_rng(0).normal(size=(rows, len(COLUMNS)))
    table[:, column(Signal.EPISODE)] = np.arange(rows) // 150
    table[:, column(Signal.STEP)] = np.arange(rows) % 150
    table[:, column(Signal.THETA1)] = np.abs(table[:, column(Signal.THETA1)]) * 300.0
    return table


def metric_write_seconds_per_episode(uri: str, episodes: int = 300) -> float:
    """Wall-clock seconds per episode of writing a run's episode metrics
    (:data:`cdqn.records.EPISODE_METRICS`) as the recorder does, in one flush of
    ``episodes`` episodes: about what a CartPole member logs between two flushes
    (every 5 s)."""
    recorder = Recorder.start(uri, "bench", "bench-metrics", {}, {})
    recorder.add_pending(
        [(str(key), float(ep), 0, ep) for ep in range(episodes) for key in EPISODE_METRICS]
    )
    t0 = time.perf_counter()
    recorder.flush()
    seconds = time.perf_counter() - t0
    recorder.finish()
    return seconds / episodes


def signal_write_seconds_per_step(uri: str, rows: int = 100_000) -> float:
    """Wall-clock seconds per step of writing a run's per-step signals at its end
    (``signals/steps.parquet`` and ``signals/fft.parquet``), from ``rows`` synthetic rows."""
    recorder = Recorder.start(uri, "bench", "bench-signals", {}, {})
    signals = SignalBuffer()
    signals.extend(synthetic_signals(rows))
    t0 = time.perf_counter()
    recorder.log_signals(signals, 5e-5)
    seconds = time.perf_counter() - t0
    recorder.finish()
    return seconds / rows


def signal_series_cost(uri: str, rows: int = 300_000, repeats: int = 3) -> dict[str, float]:
    """Wall-clock and CPU seconds of turning a run's ``rows`` per-step signals and spectra
    into metric series and writing them in one batch (:meth:`Recorder.log_series`), medians
    of ``repeats`` runs; 300,000 rows are a 2000-episode CartPole run at 150 steps."""
    table = synthetic_signals(rows)
    spectra = amplitude_spectra(pd.DataFrame(table, columns=list(COLUMNS)), 5e-5)
    box = ((200.0, 500.0), (0.8, 1.2))
    wall, cpu, points = [], [], 0
    for i in range(repeats):
        recorder = Recorder.start(uri, "bench", f"bench-series-{i}", {}, {})
        t0, c0 = time.perf_counter(), time.process_time()
        series = signal_series(table, spectra, box)
        recorder.log_series(series)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        points = len(series)
        recorder.finish()
    return {"seconds": _median(wall), "cpu_seconds": _median(cpu), "metrics": points,
            "rows": rows}  # fmt: skip


def _overrides(env: str, controller: str, width: int, uri: str) -> list[str]:
    """``--env`` is a preset (``env=<preset>``) or any id (``env.id=<id>``)."""
    return [
        f"env={env}" if env in env_presets() else f"env.id={env}",
        f"controller={controller}",
        f"network.width={width}",
        f"tracking.uri={uri}",
        "tracking.experiment=bench",
        "train.progress=false",
    ]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m cdqn.bench", description=__doc__.split("\n")[0]
    )
    parser.add_argument(
        "--env", default="cartpole", help="env preset or gymnasium id (default cartpole)"
    )
    parser.add_argument("--controllers", default=",".join(CONTROLLERS))
    parser.add_argument("--width", type=int, default=2500, help="hidden units (paper: 2500)")
    parser.add_argument(
        "--dtype", choices=("float64", "float32"), default="float64", help="network.dtype"
    )
    parser.add_argument("--steps", type=int, default=5000, help="timed steps per measurement")
    parser.add_argument(
        "--warmup", type=int, default=1200, help="untimed steps first (> DDQN's learning_starts)"
    )
    parser.add_argument("--repeats", type=int, default=3, help="interleaved rounds; medians")
    parser.add_argument("--population", type=int, default=10, help="K of the population (0: skip)")
    parser.add_argument("--workers", type=int, default=2, help="parallel sweep workers")
    parser.add_argument("--no-estimate", action="store_true", help="skip the sweep estimate")
    parser.add_argument(
        "--only-estimate", action="store_true", help="only the sweep estimate (no table)"
    )
    parser.add_argument("--episodes", type=int, default=PAPER_EPISODES, help="episodes per run")
    parser.add_argument(
        "--episode-lengths",
        default=",".join(f"{k}={v}" for k, v in EPISODE_LENGTH.items()),
        help="assumed mean episode length per environment, e.g. cartpole=150,acrobot=150",
    )
    parser.add_argument(
        "--clock", choices=sorted(CLOCKS), default="cpu", help="cpu or wall seconds"
    )
    parser.add_argument("--json", action="store_true", help="print JSON instead of tables")
    return parser


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = _parser().parse_args(argv)
    global clock
    clock = CLOCKS[args.clock]
    logging.basicConfig(level=logging.ERROR)
    logging.getLogger("cdqn").setLevel(logging.ERROR)
    torch.set_num_threads(1)
    controllers = [] if args.only_estimate else [c for c in args.controllers.split(",") if c]
    lengths = {k: float(v) for k, v in (kv.split("=") for kv in args.episode_lengths.split(","))}
    with tempfile.TemporaryDirectory() as tmp:
        uri = f"sqlite:///{Path(tmp) / 'bench.db'}"
        extra = [f"network.dtype={args.dtype}"]
        cfgs = {
            c: compose_config(_overrides(args.env, c, args.width, uri) + extra) for c in controllers
        }
        base = (
            cfgs[controllers[0]]
            if controllers
            else compose_config(_overrides(args.env, "none", args.width, uri) + extra)
        )
        result = _measure_table(args, cfgs, base, uri)
        result["signal_series"] = signal_series_cost(uri)
        if not args.no_estimate:
            result["estimate"] = estimate_paper_sweep(
                uri,
                args.width,
                args.steps,
                args.warmup,
                args.workers,
                max(args.population, 1),
                result["metric_write_s_per_episode"],
                args.episodes,
                lengths,
            )
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        print(format_report(result))
    return result


def _measure_table(
    args: argparse.Namespace, cfgs: dict[str, DictConfig], base: DictConfig, uri: str
) -> dict[str, Any]:
    """The floor, each controller's single run and population, interleaved over
    ``args.repeats`` rounds (medians), and each controller's limit."""
    controllers, k = list(cfgs), args.population
    floor: list[float] = []
    single: dict[str, list[float]] = {c: [] for c in controllers}
    pop: dict[str, list[float]] = {c: [] for c in controllers}

    for _ in range(0 if args.only_estimate else args.repeats):
        floor.append(measure_floor(base, args.steps, args.warmup).steps_per_s)
        for c in controllers:
            single[c].append(measure_single(cfgs[c], uri, args.steps, args.warmup).steps_per_s)
            if k > 1:
                p = measure_population(cfgs[c], uri, k, args.steps, _pop_warmup(c, args.warmup, k))
                pop[c].append(p.member_steps.steps_per_s)
    limits = measure_limits(cfgs)
    floor_sps = _median(floor)
    result: dict[str, Any] = {
        "env": str(base.env.name),
        "env_id": str(base.env.id),
        "width": args.width,
        "dtype": args.dtype,
        "clock": args.clock,
        "floor": {"steps_per_s": floor_sps},
        "controllers": {
            c: {"steps_per_s": _median(v), "ratio_to_floor": floor_sps / _median(v)}
            | _against_limit(_median(v), limits[c])
            for c, v in single.items()
        },
        "limits": limits,
        "metric_write_s_per_episode": metric_write_seconds_per_episode(uri),
    }
    if k > 1 and pop:
        by = {
            c: {"steps_per_s": _median(v), "speedup": _median(v) / _median(single[c])}
            | _against_limit(_median(v), limits[c])
            for c, v in pop.items()
        }
        main_ctrl = "hinf" if "hinf" in by else next(iter(by))
        result["population"] = {
            "k": k,
            "controller": main_ctrl,
            "speedup": by[main_ctrl]["speedup"],
            "by_controller": by,
        }
    return result


def _against_limit(steps_per_s: float, limit: dict[str, float]) -> dict[str, float]:
    """Microseconds per (member-)step, the limit's and their ratio."""
    us = 1e6 / steps_per_s
    return {
        "us_per_step": us,
        "limit_us": limit["limit_us"],
        "ratio_to_limit": us / limit["limit_us"],
    }


def _limit_lines(r: dict[str, Any]) -> list[str]:
    """How the limit column was measured, and the same products through torch."""
    limits = r["limits"]
    peak = next(iter(limits.values()))["peak_macs_per_s"]
    return [
        f"(limit: the step's multiply-adds at one thread's measured peak, "
        f"{peak / 1e9:.1f} G/s in {r['dtype']}; the same products as torch matmuls of their "
        "shapes: " + ", ".join(f"{c} {v['torch_us']:.1f} µs" for c, v in limits.items()) + ")"
    ]


def format_report(r: dict[str, Any]) -> str:
    lines = [
        f"cdqn.bench: {r['env']}, width {r['width']}, {r['dtype']}, one core, logging on "
        f"({r['clock']} seconds)",
    ]
    if r["controllers"]:
        lines += [
            "",
            f"{'':<24}{'steps/s':>9}{'cost / floor':>13}{'µs/step':>9}{'limit µs':>10}"
            f"{'x limit':>9}",
            f"{'floor (torch autograd)':<24}{r['floor']['steps_per_s']:>9.0f}{1.0:>13.2f}",
        ]
        for name, c in r["controllers"].items():
            lines.append(
                f"{name:<24}{c['steps_per_s']:>9.0f}{c['ratio_to_floor']:>13.2f}"
                f"{c['us_per_step']:>9.1f}{c['limit_us']:>10.1f}{c['ratio_to_limit']:>9.2f}"
            )
        lines.append(
            f"(MLflow episode metrics: {1e3 * r['metric_write_s_per_episode']:.1f} ms per "
            "episode and run, written in batches, timed apart)"
        )
        lines += _limit_lines(r)
    if "signal_series" in r:
        ss = r["signal_series"]
        lines.append(
            f"(MLflow signal series: {1e3 * ss['seconds']:.1f} ms wall, "
            f"{1e3 * ss['cpu_seconds']:.1f} ms CPU per run for {ss['metrics']} points in one "
            f"batch at its end, from {ss['rows']} steps)"
        )
    if "population" in r:
        p = r["population"]
        lines += [
            "",
            f"population K={p['k']} (member-steps/s, speed-up over sequential runs)",
            f"{'':<24}{'steps/s':>9}{'speed-up':>13}{'µs/step':>9}{'limit µs':>10}{'x limit':>9}",
        ]
        for name, c in p["by_controller"].items():
            lines.append(
                f"{name:<24}{c['steps_per_s']:>9.0f}{c['speedup']:>12.2f}x"
                f"{c['us_per_step']:>9.1f}{c['limit_us']:>10.1f}{c['ratio_to_limit']:>9.2f}"
            )
    if "estimate" in r:
        e = r["estimate"]
        lines += [
            "",
            f"sweep: 3 envs x 4 controllers x {PAPER_SEEDS} seeds x {e['episodes']} episodes, "
            f"width {r['width']}, populations of {PAPER_SEEDS}, {e['workers']} workers",
            f"{'steps/s':<14}" + "".join(f"{c:>10}" for c in PAPER_CONTROLLERS),
        ]
        for env, row in e["steps_per_s"].items():
            lines.append(f"{env:<14}" + "".join(f"{row[c]:>10.0f}" for c in PAPER_CONTROLLERS))
        lengths = ", ".join(f"{k} {v:g}" for k, v in e["episode_length"].items())
        lines += [
            f"per run: {e['run_overhead_s']:.2f} s to open and close it, "
            f"{1e3 * e['metric_write_s_per_episode']:.1f} ms per episode of metrics, "
            f"{1e6 * e['signal_write_s_per_step']:.1f} µs per step of signals",
            f"assumed mean episode length: {lengths} -> "
            f"{e['expected_env_steps'] / 1e6:.2f} M env steps",
            f"estimated wall time: {e['expected_hours']:.2f} h = "
            f"{60 * e['expected_hours']:.1f} min (every episode at its cap: "
            f"{e['upper_bound_hours']:.2f} h)",
        ]
    return "\n".join(lines)


if __name__ == "__main__":
    from cdqn.cli import run_command

    run_command(main)
