"""Populations: ``K`` seeds of one configuration trained in one process as one batch.

``python -m cdqn.train train.population=10 seed=0`` trains seeds 0, 1, …, 9 together.  The
members' networks are stacked and each step of all of them (forward passes, NTK,
controllers, SGD steps, signal rows) is two compiled calls built from the row functions a
single run uses (:mod:`cdqn.population_step`); their environments step as one
(:mod:`cdqn.vector_env`).  So the per-step Python of the trainer, the environment and the
bookkeeping is paid once for ``K`` members.

Each member is still its own MLflow run with the content of a single run of its seed
(params with ``seed`` set to the member's seed and ``train.population=1``, the same tags
plus ``population``, per-episode metrics, ``signals/steps.parquet``, ``signals/fft.parquet``,
``config.yaml`` and the model), and learns what that single run learns: every array
operation acts on each member's row alone, through the kernels a single run uses, so the
numbers are bit-identical (``tests/test_population.py``).

:class:`ControlledPopulation` is the batched :class:`cdqn.agents.ControlledAgent` (fast path)
for ``none``, ``h2``, ``hinf`` and ``hinf_f``.  Double DQN and ``train.fast_path=false`` fall
back to training the members one after another in the same process (Double DQN's cost is
its minibatch step, which batching the seeds would not make cheaper).  Members write no
checkpoints: an interrupted population marks its unfinished members KILLED, and a restarted
sweep with ``tracking.skip_finished=true`` trains exactly those again.
"""

from __future__ import annotations

import copy
import logging
import math
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf, read_write
from tqdm.auto import tqdm

from cdqn.agents.base import StepRecord
from cdqn.agents.episodic_replay import PopulationTail, qualifies
from cdqn.config import Config, ReplayConfig, resolve_tracking_uri, validate
from cdqn.control.factory import ControllerSetup, make_controller
from cdqn.envs import env_sizes, make_env
from cdqn.interrupt import GracefulStop
from cdqn.network import NetworkSpec, QNetwork, save_network
from cdqn.population_step import CHECK, DONE, ControlledPopulation
from cdqn.signals import COLUMNS, SignalBuffer
from cdqn.sweep import config_hash, ensure_store, final_score, find_finished
from cdqn.tracking import Recorder, check_tracking, flatten, git_commit
from cdqn.trainer import DivergenceError, _diagnose, episode_stats
from cdqn.vector_env import VectorEnv, make_vector_env

log = logging.getLogger("cdqn")


def member_seeds(seed: int, population: int) -> list[int]:
    """Seeds of a population: ``seed, seed+1, …, seed+population−1``."""
    return [seed + i for i in range(population)]


def member_config(cfg: DictConfig, seed: int) -> DictConfig:
    """The configuration of the single run a member stands for."""
    out = copy.deepcopy(cfg)
    with read_write(out):
        out.seed = seed
        out.train.population = 1
    return out


@dataclass
class Member:
    """One seed of a population and its bookkeeping."""

    seed: int
    cfg: DictConfig
    recorder: Recorder | None = None
    signals: SignalBuffer = field(default_factory=SignalBuffer)
    returns: list[float] = field(default_factory=list)
    episode: int = 0
    status: str = "RUNNING"
    reason: str | None = None

    @property
    def score(self) -> float:
        return float(np.mean(self.returns[-100:])) if self.returns else float("nan")


class _Staging:
    """Per-step signal rows of all active members, written as one ``(K, 10)`` block per
    step and moved into each member's :class:`SignalBuffer` in blocks."""

    def __init__(self, k: int, capacity: int = 2048) -> None:
        self.data = np.empty((capacity, k, len(COLUMNS)))
        self.n = 0
        self.flushed = np.zeros(k, dtype=np.int64)

    def next_block(self, members: list[Member]) -> np.ndarray:
        """The ``(K, 10)`` block of this step's rows, to be written in place."""
        if self.n == len(self.data):
            self.flush_all(members)
        self.n += 1
        return self.data[self.n - 1]

    def flush(self, j: int, member: Member) -> None:
        member.signals.extend(self.data[self.flushed[j] : self.n, j])
        self.flushed[j] = self.n

    def flush_all(self, members: list[Member]) -> None:
        for j, member in enumerate(members):
            self.flush(j, member)
        self.n = 0
        self.flushed[:] = 0

    def select(self, keep: np.ndarray, members: list[Member]) -> None:
        self.flush_all(members)
        self.data = np.empty((len(self.data), len(keep), len(COLUMNS)))
        self.flushed = np.zeros(len(keep), dtype=np.int64)


def train_population(
    agent: ControlledPopulation,
    venv: VectorEnv,
    members: list[Member],
    *,
    episodes: int,
    discount: float,
    q_limit: float,
    on_episode: Callable[[Member, object], None] | None = None,
    on_member_end: Callable[[Member, ControlledPopulation, int], None] | None = None,
    progress: bool = False,
    should_stop: Callable[[], bool] | None = None,
    max_steps: int | None = None,
    replay: ReplayConfig | None = None,
) -> None:
    """The training loop of :func:`cdqn.trainer.train` for all members at once.

    Each member's environment is seeded with its seed at its first episode.  A member that
    finishes its ``episodes`` or diverges leaves the batch (``on_member_end`` is called with
    the member, the agent and its row, before the row is dropped).  ``max_steps`` (for the
    benchmark) ends the loop after that many population steps.  ``replay``: episodic replay
    after each member's qualifying episode, as :func:`cdqn.trainer.train` does it.
    """
    members = list(members)
    obs = np.stack([venv.reset(j, m.seed) for j, m in enumerate(members)])
    for j in range(len(members)):
        agent.start_episode(j)
    t = np.zeros(len(members), dtype=np.int64)
    ret = np.zeros(len(members))
    ep = np.array([m.episode for m in members], dtype=float)
    staging = _Staging(len(members))
    tail = None
    if replay is not None and replay.repeats > 0:
        cap = replay.last or getattr(venv.envs[0].spec, "max_episode_steps", None) or 10_000
        tail = PopulationTail(len(members), obs.shape[1], cap)
    bar = tqdm(total=episodes * len(members), disable=not progress, unit="ep", leave=True)
    steps = 0
    try:
        while members:
            actions = agent.act(obs)
            out = venv.step(actions)
            rows = staging.next_block(members)
            flagged = agent.update(actions, out, ep, t, ret, rows, q_limit)
            if tail is not None:
                tail.append(obs, actions, out.reward, out.obs, out.terminated)
            obs = out.obs
            leaving: list[int] = []
            if flagged:
                flags = agent.flags
                for j in np.flatnonzero(flags == CHECK):  # the trainer's exact test
                    row = rows[j].tolist()
                    r = StepRecord(row[9], *row[3:9])
                    if (
                        abs(r.q1) <= q_limit
                        and abs(r.q2) <= q_limit
                        and math.isfinite(r.u + r.x_e)
                        and (
                            math.isfinite(r.loss) or (not agent.loss_seen[j] and math.isnan(r.loss))
                        )
                    ):
                        agent.loss_seen[j] |= not math.isnan(r.loss)
                        flags[j] = DONE if out.terminated[j] or out.truncated[j] else 0
                        continue
                    try:
                        _diagnose(r, q_limit, members[j].episode, int(t[j] - 1))
                    except DivergenceError as err:
                        members[j].status, members[j].reason = "FAILED", f"diverged: {err}"
                    leaving.append(j)
                for j in np.flatnonzero(flags == DONE):
                    m = members[j]
                    staging.flush(j, m)
                    replayed = 0
                    end = (bool(out.terminated[j]), bool(out.truncated[j]), float(ret[j]))
                    if tail is not None and qualifies(replay, *end):  # type: ignore[arg-type]
                        steps_j = min(int(t[j]), replay.last or int(t[j]))  # type: ignore[union-attr]
                        replayed = agent.replay(
                            j,
                            tail.transitions(j, steps_j),
                            replay.repeats,
                            q_limit,  # type: ignore[union-attr]
                        )
                        if replayed < 0:
                            err = DivergenceError(
                                f"update {-replayed - 1} of episodic replay failed the divergence "
                                "test",
                                m.episode,
                                int(t[j] - 1),
                            )
                            m.status, m.reason = "FAILED", f"diverged: {err}"
                            leaving.append(j)
                            continue
                    x_c = agent.controller.state(j)
                    if x_c is not None and not np.all(np.isfinite(x_c)):
                        err = DivergenceError(
                            f"non-finite controller state x_c = {x_c}", m.episode, int(t[j] - 1)
                        )
                        m.status, m.reason = "FAILED", f"diverged: {err}"
                        leaving.append(j)
                        continue
                    m.returns.append(float(ret[j]))
                    start = m.signals.n - int(t[j])
                    stats = episode_stats(
                        m.episode, m.signals.rows(start), m.returns, discount, replayed
                    )
                    m.episode += 1
                    if on_episode is not None:
                        on_episode(m, stats)
                    bar.update(1)
                    if m.episode >= episodes:
                        m.status = "FINISHED"
                        leaving.append(j)
                        continue
                    obs[j] = venv.reset(j, None)
                    agent.start_episode(j)
                    t[j], ret[j], ep[j] = 0, 0.0, m.episode
            steps += 1
            stop = should_stop is not None and should_stop()
            if stop or (max_steps is not None and steps >= max_steps):
                for m in members:
                    if m.status == "RUNNING":
                        m.status = "KILLED"
                leaving = list(range(len(members)))
            if leaving:
                staging.flush_all(members)
                for j in sorted(set(leaving)):
                    if on_member_end is not None:
                        on_member_end(members[j], agent, j)
                keep = np.array([j for j in range(len(members)) if j not in set(leaving)])
                members = [members[j] for j in keep]
                if not members:
                    break
                agent.select(keep)
                venv.select(keep)
                if tail is not None:
                    tail.select(keep)
                staging.select(keep, members)
                obs, t, ret, ep = obs[keep], t[keep], ret[keep], ep[keep]
    finally:
        bar.close()


def build_population(
    conf: Config, setup: ControllerSetup, seeds: list[int]
) -> tuple[ControlledPopulation, VectorEnv]:
    """Agent and environments of a population, with the calls of ``cdqn.train.build`` per
    member (network initialised under ``torch.manual_seed(seed)``, exploration from
    ``np.random.default_rng(seed)``)."""
    envs = [make_env(conf.env) for _ in seeds]
    n_obs, n_actions = env_sizes(envs[0])
    nets, rngs = [], []
    for seed in seeds:
        torch.manual_seed(seed)
        rngs.append(np.random.default_rng(seed))
        nets.append(QNetwork(NetworkSpec(n_obs, n_actions, conf.network.width, conf.network.dtype)))
    agent = ControlledPopulation(
        nets, setup.controller, conf.train, conf.controller.reset_integrator, rngs
    )
    return agent, make_vector_env(envs)


def batchable(conf: Config) -> bool:
    """Whether :class:`ControlledPopulation` can train this configuration (its controllers
    are the runtime controllers :class:`cdqn.population_step.ControllerArrays` knows)."""
    return conf.controller.name != "ddqn" and conf.train.fast_path


@dataclass
class PopulationResult:
    """Outcome of :func:`run_population`: one ``cdqn.train.RunResult`` per member."""

    members: list
    signum: int | None = None

    def summary(self):  # -> cdqn.train.RunResult
        """One result for the Hydra job: the worst status, the mean final score."""
        from cdqn.train import RunResult  # noqa: PLC0415

        order = {"FINISHED": 0, "KILLED": 1, "FAILED": 2}
        worst = max(self.members, key=lambda r: order.get(r.status, 3))
        scores = [r.final_score for r in self.members if math.isfinite(r.final_score)]
        failed = [f"{r.run_id}: {r.reason}" for r in self.members if r.status != "FINISHED"]
        return RunResult(
            ",".join(r.run_id for r in self.members),
            worst.status,
            float(np.mean(scores)) if scores else float("nan"),
            "; ".join(failed) or None,
            self.signum,
        )


def run_population(
    cfg: DictConfig,
    progress: bool = True,
    observe: Callable[[Member], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> PopulationResult:
    """Train seeds ``seed … seed+population−1`` of ``cfg``, each as its own MLflow run
    (module docstring).  ``observe(member)`` is called after each recorded episode and a
    true ``should_stop()`` ends the population as a signal does (members KILLED); both
    serve :mod:`cdqn.tune` (intermediate values, pruning) on the batched path."""
    from cdqn.train import RunResult, run  # noqa: PLC0415

    conf: Config = OmegaConf.to_object(cfg)  # type: ignore[assignment]
    validate(conf)
    uri = resolve_tracking_uri(conf.tracking.uri)
    check_tracking(uri, conf.tracking.timeout)
    ensure_store(uri, conf.tracking.experiment)
    members = [
        Member(s, member_config(cfg, s)) for s in member_seeds(conf.seed, conf.train.population)
    ]
    results: dict[int, RunResult] = {}
    if conf.tracking.skip_finished:
        from mlflow.tracking import MlflowClient  # noqa: PLC0415

        client = MlflowClient(uri)
        for m in members:
            done = find_finished(client, conf.tracking.experiment, config_hash(m.cfg))
            if done is not None:
                log.info(
                    "skipping %s/%s seed %d: run %s already FINISHED with this configuration",
                    conf.env.name, conf.controller.name, m.seed, done.info.run_id,
                )  # fmt: skip
                results[m.seed] = RunResult(
                    done.info.run_id, "FINISHED", final_score(client, done), "skipped"
                )
        members = [m for m in members if m.seed not in results]
    if not members:
        return PopulationResult([results[s] for s in sorted(results)])
    if not batchable(conf):
        log.info("population of %s: members trained one after another", conf.controller.name)
        for m in members:
            results[m.seed] = run(m.cfg, progress=progress)
        return PopulationResult([results[s] for s in sorted(results)])
    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)

    agent, venv = build_population(conf, setup, [m.seed for m in members])
    envs = list(venv.envs)
    seeds = member_seeds(conf.seed, conf.train.population)
    for m in members:
        m.recorder = start_member_run(m, conf, setup, uri, f"{seeds[0]}-{seeds[-1]}")

    def on_episode(m: Member, stats: object) -> None:
        assert m.recorder is not None
        m.recorder.log_episode(stats)  # type: ignore[arg-type]
        if observe is not None:
            observe(m)

    stop = GracefulStop()

    def on_member_end(m: Member, pop: ControlledPopulation, j: int) -> None:
        if m.status == "KILLED":
            m.reason = (
                f"{stop.name or 'stopped'} during episode {m.episode} of {conf.train.episodes}; "
                "populations write no checkpoints: a restarted sweep with "
                "tracking.skip_finished=true trains this seed again"
            )
        finish_member(m, pop.network(j), conf)
        assert m.recorder is not None
        results[m.seed] = RunResult(m.recorder.run_id, m.status, m.score, m.reason)

    with stop:
        try:
            train_population(
                agent,
                venv,
                members,
                episodes=conf.train.episodes,
                discount=conf.train.discount,
                q_limit=conf.train.q_limit,
                on_episode=on_episode,
                on_member_end=on_member_end,
                progress=progress and conf.train.progress,
                should_stop=stop.requested
                if should_stop is None
                else lambda: stop.requested() or should_stop(),
                replay=conf.weights.replay,
            )
        except BaseException as err:  # close the members' runs that are still open
            for m in members:
                if m.seed not in results and m.recorder is not None:
                    m.status = "KILLED" if isinstance(err, KeyboardInterrupt) else "FAILED"
                    m.reason = f"{type(err).__name__}: {err}"
                    finish_member(m, None, conf)
            raise
        finally:
            for env in envs:
                env.close()
    return PopulationResult([results[s] for s in sorted(results)], stop.signum)


def start_member_run(
    m: Member, conf: Config, setup: ControllerSetup, uri: str, population: str
) -> Recorder:
    """Open member ``m``'s MLflow run with the params, tags and artifacts of a single run."""
    container = OmegaConf.to_container(m.cfg, resolve=True)
    tags = {
        "env": conf.env.name,
        "env_id": conf.env.id,
        "controller": conf.controller.name,
        "seed": str(m.seed),
        "git_commit": git_commit(),
        "design_source": setup.source,
        "config_hash": config_hash(m.cfg),
        "population": population,
    }
    rec = Recorder.start(
        uri,
        conf.tracking.experiment,
        f"{conf.env.name}-{conf.controller.name}-s{m.seed}",
        flatten(container),  # type: ignore[arg-type]
        tags,
        config=container,  # type: ignore[arg-type]
    )
    if setup.design:
        rec.log_dict(setup.design, "design/controller.json")
    if setup.artifacts is not None:
        rec.log_dir(setup.artifacts, "design")
    log.info(
        "MLflow run %s (%s, %s, seed %d)", rec.run_id, conf.env.name, conf.controller.name, m.seed
    )
    return rec


def finish_member(m: Member, net: QNetwork | None, conf: Config) -> None:
    """Signals, model and status of member ``m``'s run, as a single run writes them."""
    rec = m.recorder
    assert rec is not None
    try:
        if conf.train.signals:
            rec.log_signals(m.signals, conf.train.lr)
        if conf.tracking.log_model and net is not None:
            with tempfile.TemporaryDirectory() as tmp:
                save_network(net, Path(tmp))
                rec.log_dir(Path(tmp), "model")
    finally:
        status = m.status if m.status != "RUNNING" else "KILLED"
        rec.finish(status, m.reason)
        if status != "FINISHED":
            log.warning("run %s %s: %s", rec.run_id, status, m.reason)
