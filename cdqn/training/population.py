"""Populations: ``K`` seeds of one configuration trained in one process as one batch.

``python -m cdqn.train train.population=10 seed=0`` trains seeds 0, 1, …, 9 together.  The
members' networks are stacked and each step of all of them (forward passes, NTK,
controllers, SGD steps, signal rows) is two compiled calls built from the row functions a
single run uses (:mod:`cdqn.training.population_step`); their environments step as one
(:mod:`cdqn.vector_env`).  So the per-step Python of the trainer, the environment and the
bookkeeping is paid once for ``K`` members.

Each member is still its own MLflow run with the content of a single run of its seed
(params with ``seed`` set to the member's seed and ``train.population=1``, the same tags
plus ``population``, per-episode metrics, ``signals/steps.parquet``, ``signals/fft.parquet``,
``config.yaml`` and the model), and learns what that single run learns: every array
operation acts on each member's row alone, through the kernels a single run uses, so the
numbers are bit-identical (``tests/test_population.py``).

:class:`ControlledPopulation` is the batched :class:`cdqn.agents.ControlledAgent` (fast path)
for ``none``, ``h2``, ``hinf`` and ``hinf_f``, :class:`cdqn.training.ddqn_population.DDQNPopulation`
the batched :class:`cdqn.agents.DDQNAgent`.  ``train.fast_path=false`` falls back to
training the members one after another in the same process.

A population checkpoints as a whole (:mod:`cdqn.training.population_checkpoint`): each time its
slowest member has completed another ``train.checkpoint_every`` episodes, and when
SIGINT/SIGTERM stops it (at the end of the current population step), every member's state
goes into its own run's checkpoint slots and the members still training are closed KILLED
with ``resume=<run_id>`` in their ``failure_reason``.  ``python -m cdqn.train
resume=<run_id>`` on any member continues every unfinished member of its population
(:func:`resume_population`), bit for bit as if uninterrupted; a restarted sweep with
``tracking.skip_finished=true`` does the same for its KILLED members.
"""

from __future__ import annotations

import copy
import logging
import math
import tempfile
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf, read_write
from tqdm.auto import tqdm

from cdqn.agents.base import StepRecord
from cdqn.agents.episodic_replay import PopulationTail, Transitions, qualifies
from cdqn.config import Config, ReplayConfig, resolve_tracking_uri, validate
from cdqn.control.factory import ControllerSetup, make_controller
from cdqn.envs import env_sizes, make_env
from cdqn.network import NetworkSpec, QNetwork, save_network
from cdqn.training.checkpoint import ROOT as CHECKPOINT_ROOT
from cdqn.training.checkpoint import CheckpointStore
from cdqn.training.ddqn_population import DDQNPopulation
from cdqn.training.interrupt import GracefulStop
from cdqn.training.loop import DivergenceError, _diagnose, episode_stats
from cdqn.training.population_checkpoint import (
    MemberCheckpoint,
    capture_member,
    common_sequence,
    restore_member,
    stored_config,
)
from cdqn.training.population_step import CHECK, DONE, ControlledPopulation
from cdqn.training.signals import COLUMNS, SignalBuffer
from cdqn.training.sweep import (
    config_hash,
    ensure_store,
    final_score,
    find_finished,
    find_resumable,
    process_tags,
)
from cdqn.training.tracking import (
    Recorder,
    TrackingOutage,
    check_tracking,
    fail_fast_http,
    flatten,
    git_commit,
)
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
    carry: dict | None = None
    replay_tail: Transitions | None = None
    """Episodic replay: the transitions of the episode in progress, set for checkpoints."""
    """Where a restored member stands between two steps (observation ``obs``, step ``t`` of
    the episode, return so far ``ret``); None: it starts with a reset."""
    checkpointed: int | None = None
    """Episode of the member's last checkpoint, if any."""
    logged: set[int] = field(default_factory=set)
    """Episodes whose metrics are already stored (a resumed member skips them)."""

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
    on_checkpoint: Callable[[list[tuple[int, Member]], np.ndarray, np.ndarray, np.ndarray], None]
    | None = None,
    checkpoint_every: int = 0,
    replay: ReplayConfig | None = None,
) -> None:
    """The training loop of :func:`cdqn.training.loop.train` for all members at once.

    Each member's environment is seeded with its seed at its first episode.  A member that
    finishes its ``episodes`` or diverges leaves the batch (``on_member_end`` is called with
    the member, the agent and its row, before the row is dropped).  ``max_steps`` (for the
    benchmark) ends the loop after that many population steps.  ``replay``: episodic replay
    after each member's qualifying episode, as :func:`cdqn.training.loop.train` does it.

    ``on_checkpoint(items, obs, t, ret)`` (items: ``(row, member)`` pairs) is called between
    two steps, with every member's signal rows flushed: each time the slowest member has
    completed another ``checkpoint_every`` episodes, and when ``should_stop`` stops the
    loop.  A member with a ``carry`` continues from it instead of starting with a reset.
    """
    members = list(members)
    first = [venv.reset(j, m.seed) if m.carry is None else m.carry["obs"]
             for j, m in enumerate(members)]  # fmt: skip
    obs = np.stack(first)
    for j, m in enumerate(members):
        if m.carry is None:
            agent.start_episode(j)
    t = np.array([m.carry["t"] if m.carry else 0 for m in members], dtype=np.int64)
    ret = np.array([m.carry["ret"] if m.carry else 0.0 for m in members])
    every = checkpoint_every if on_checkpoint is not None else 0
    due = (min(m.episode for m in members) // every + 1) * every if every else 0
    ep = np.array([m.episode for m in members], dtype=float)
    staging = _Staging(len(members))
    tail = None
    if replay is not None and replay.repeats > 0:
        cap = replay.last or getattr(venv.envs[0].spec, "max_episode_steps", None) or 10_000
        tail = PopulationTail(len(members), obs.shape[1], cap)
        for j, m in enumerate(members):
            if m.carry is not None and m.carry.get("replay_tail") is not None:
                tail.restore(j, Transitions(**m.carry["replay_tail"]))

    def with_tails(items: list[tuple[int, Member]]) -> list[tuple[int, Member]]:
        """``items`` with each member's transitions of the episode in progress attached."""
        for j, m in items:
            if tail is not None:
                m.replay_tail = tail.transitions(j, min(int(t[j]), replay.last or int(t[j])))  # type: ignore[union-attr]
        return items

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
                gone = set(leaving)
                survivors = [(j, m) for j, m in enumerate(members) if j not in gone]
                if stop and on_checkpoint is not None and survivors:
                    staging.flush_all(members)
                    on_checkpoint(with_tails(survivors), obs, t, ret)
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
            if every and (slowest := min(m.episode for m in members)) >= due:
                staging.flush_all(members)
                assert on_checkpoint is not None
                on_checkpoint(with_tails(list(enumerate(members))), obs, t, ret)
                due = (slowest // every + 1) * every
    finally:
        bar.close()


def build_population(
    conf: Config, setup: ControllerSetup, seeds: list[int]
) -> tuple[ControlledPopulation | DDQNPopulation, VectorEnv]:
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
    if conf.controller.name == "ddqn":
        return DDQNPopulation(nets, conf.controller, conf.train, rngs), make_vector_env(envs)
    agent = ControlledPopulation(
        nets, setup.controller, conf.train, conf.controller.reset_integrator, rngs
    )
    return agent, make_vector_env(envs)


def batchable(conf: Config) -> bool:
    """Whether the members train as one batch: :class:`ControlledPopulation` (its
    controllers are the runtime controllers :class:`cdqn.training.population_step.ControllerArrays`
    knows) or :class:`cdqn.training.ddqn_population.DDQNPopulation`, both on the fast path, with one
    design for all members (a measured NTK box builds each seed's design on its own network,
    :mod:`cdqn.ntk_bounds`)."""
    ctrl = conf.controller
    measured = (
        ctrl.synthesis.ntk_bounds == "measured"
        and ctrl.design == "synthesize"
        and ctrl.name in ("hinf", "hinf_f", "h2")
    )
    return conf.train.fast_path and not measured


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
            members=list(self.members),
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
    if conf.tracking.skip_finished:  # continue this job's KILLED members (cdqn.training.sweep)
        signum = _resume_killed(cfg, uri, members, results, progress)
        members = [m for m in members if m.seed not in results]
        if signum is not None or not members:
            return PopulationResult([results[s] for s in sorted(results)], signum)
    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)

    agent, venv = build_population(conf, setup, [m.seed for m in members])
    seeds = member_seeds(conf.seed, conf.train.population)
    population_id = uuid.uuid4().hex
    try:
        for m in members:
            m.recorder = start_member_run(
                m, conf, setup, uri, f"{seeds[0]}-{seeds[-1]}", population_id
            )
    except BaseException:
        for env in venv.envs:
            env.close()
        raise
    signum = train_members(
        conf, agent, venv, members, results, progress, observe=observe, should_stop=should_stop
    )
    return PopulationResult([results[s] for s in sorted(results)], signum)


def train_members(
    conf: Config,
    agent: ControlledPopulation,
    venv: VectorEnv,
    members: list[Member],
    results: dict,
    progress: bool,
    sequence: int = 0,
    stores: dict[int, CheckpointStore] | None = None,
    observe: Callable[[Member], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> int | None:
    """Train ``members`` (their runs open) to the end, with checkpoints (every
    ``train.checkpoint_every`` episodes of the slowest member and on SIGINT/SIGTERM, see
    :mod:`cdqn.training.population_checkpoint`); put each member's ``RunResult`` into ``results``
    and close its run.  ``sequence``: number of the last checkpoint (a resumed population
    continues the count).  Returns the signal that stopped training, if any."""
    from cdqn.train import RunResult  # noqa: PLC0415

    envs = list(venv.envs)
    episodes = conf.train.episodes
    stores = stores or {
        m.seed: CheckpointStore(
            m.recorder.client, m.recorder.run_id, conf.train.signals, kind=MemberCheckpoint
        )
        for m in members
        if m.recorder is not None
    }
    counter = [sequence]
    for m in members:  # writes retried while the store does not answer (tracking.retry_s)
        if m.recorder is not None:
            m.recorder.retry_s = stores[m.seed].retry_s = conf.tracking.retry_s
            if m.recorder.uri.startswith(("http://", "https://")):
                fail_fast_http(conf.tracking.timeout)

    def on_checkpoint(
        items: list[tuple[int, Member]], obs: np.ndarray, t: np.ndarray, ret: np.ndarray
    ) -> None:
        counter[0] += 1
        ids = [m.recorder.run_id for _, m in items if m.recorder is not None]
        for j, m in items:
            assert m.recorder is not None
            m.recorder.flush()
            ckpt = capture_member(counter[0], ids, m, agent, venv, j, obs, t, ret,
                                  m.signals.n if conf.train.signals else 0)  # fmt: skip
            stores[m.seed].save(ckpt, m.signals)
            m.checkpointed = m.episode

    if not venv.checkpointable:
        log.warning(
            "population on %s: no checkpoints (only CartPole, Acrobot and MountainCar members "
            "can be captured mid-episode); an interrupted member is trained again",
            conf.env.id,
        )

    def on_episode(m: Member, stats: object) -> None:
        assert m.recorder is not None
        if stats.episode not in m.logged:  # type: ignore[attr-defined]
            m.recorder.log_episode(stats)  # type: ignore[arg-type]
        if observe is not None:
            observe(m)

    stop = GracefulStop()
    t0 = time.perf_counter()

    def killed_reason(m: Member, during: str) -> str:
        assert m.recorder is not None
        if m.checkpointed is None:
            return f"{during}; no checkpoint yet, resume={m.recorder.run_id} trains it again"
        where = (
            "checkpoint written"
            if stop.requested() and m.checkpointed == m.episode
            else f"the last checkpoint is at episode {m.checkpointed}"
        )
        return f"{during}; {where}, continue the population with resume={m.recorder.run_id}"

    def on_member_end(m: Member, pop: ControlledPopulation, j: int) -> None:
        if m.status == "KILLED":
            m.reason = killed_reason(
                m, f"{stop.name or 'stopped'} during episode {m.episode} of {episodes}"
            )
        finish_member(m, pop.network(j), conf)
        assert m.recorder is not None
        seconds = time.perf_counter() - t0
        results[m.seed] = RunResult(
            m.recorder.run_id, m.status, m.score, m.reason, returns=list(m.returns),
            steps=m.signals.n, seconds=seconds, rate=m.signals.n / seconds,
            epsilon=float(pop.epsilon[j]), solve_threshold=conf.env.solve_threshold,
        )  # fmt: skip

    with stop:
        try:
            train_population(
                agent,
                venv,
                members,
                episodes=episodes,
                discount=conf.train.discount,
                q_limit=conf.train.q_limit,
                on_episode=on_episode,
                on_member_end=on_member_end,
                progress=progress and conf.train.progress,
                should_stop=stop.requested
                if should_stop is None
                else lambda: stop.requested() or should_stop(),
                on_checkpoint=on_checkpoint if venv.checkpointable else None,
                checkpoint_every=conf.train.checkpoint_every,
                replay=conf.weights.replay if conf.controller.name != "ddqn" else None,
            )
        except TrackingOutage as err:  # runs cannot be closed; the store has the checkpoints
            open_ids = [m.recorder.run_id for m in members
                        if m.seed not in results and m.recorder is not None]  # fmt: skip
            log.error(
                "%s. The members %s stay RUNNING in the store; when the server answers again, "
                "resume=<any of them> (or the restarted sweep) continues them from their last "
                "checkpoint", err, ", ".join(open_ids),
            )  # fmt: skip
            raise
        except BaseException as err:  # close the members' runs that are still open
            stop.closing()
            for m in members:
                if m.seed not in results and m.recorder is not None:
                    m.status = "KILLED" if isinstance(err, KeyboardInterrupt) else "FAILED"
                    m.reason = f"{type(err).__name__}: {err}"
                    if m.status == "KILLED":
                        m.reason = killed_reason(m, f"stopped during episode {m.episode}")
                    finish_member(m, None, conf)
            raise
        finally:
            for env in envs:
                env.close()
    return stop.signum


def _resume_killed(
    cfg: DictConfig, uri: str, members: list[Member], results: dict, progress: bool
) -> int | None:
    """Resume the runs of ``members`` that a restarted sweep finds KILLED (or left RUNNING by
    a process that is gone), population by population; their results go into ``results``.
    Returns the signal that stopped one of them, if any."""
    from mlflow.tracking import MlflowClient  # noqa: PLC0415

    client = MlflowClient(uri)
    groups: dict[str, list] = {}
    for m in members:
        found = find_resumable(client, str(cfg.tracking.experiment), config_hash(m.cfg))
        if found is not None and "population_id" in found.data.tags:
            groups.setdefault(found.data.tags["population_id"], []).append(found)
    for runs in groups.values():
        ids = ", ".join(r.info.run_id for r in runs)
        log.info("continuing KILLED population members from their checkpoints: %s", ids)
        out = resume_population(uri, cfg.tracking, runs, progress)
        for r in out.members:
            seed = int(client.get_run(r.run_id).data.tags["seed"])
            results[seed] = r
        if out.signum is not None:
            return out.signum
    return None


def resume_population(uri: str, tracking: object, runs: list, progress: bool) -> PopulationResult:
    """Continue the members ``runs`` (MLflow runs of one population) from their newest
    common checkpoint, each in its own run, to the planned episode count.

    Without a common checkpoint the members train again from episode 0 in their runs
    (episodes whose metrics are stored are not logged twice); as every member's numbers
    depend on its seed alone, the result is the same either way.
    """
    from mlflow.tracking import MlflowClient  # noqa: PLC0415

    client = MlflowClient(uri)
    cfgs = [stored_config(client, r.info.run_id, tracking) for r in runs]
    confs: list[Config] = [OmegaConf.to_object(c) for c in cfgs]  # type: ignore[misc]
    conf = confs[0]
    validate(conf)
    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)
    members = [Member(c.seed, cfg) for c, cfg in zip(confs, cfgs, strict=True)]
    agent, venv = build_population(conf, setup, [m.seed for m in members])
    try:
        stores = {
            m.seed: CheckpointStore(client, r.info.run_id, conf.train.signals, MemberCheckpoint)
            for m, r in zip(members, runs, strict=True)
        }
        found = {m.seed: stores[m.seed].candidates() for m in members}
        sequence = max((c.sequence for items in found.values() for c, _ in items), default=0)
        common = common_sequence(found) if venv.checkpointable else None
        chosen = {}
        if common is not None:
            for m in members:
                ckpt, slot = next(c for c in found[m.seed] if c[0].sequence == common)
                if not stores[m.seed].complete(ckpt, slot):
                    chosen = {}
                    break
                chosen[m.seed] = ckpt
        if not chosen:
            log.warning("population has no common usable checkpoint: training it from episode 0")
            stores = {
                m.seed: CheckpointStore(client, r.info.run_id, conf.train.signals, MemberCheckpoint)
                for m, r in zip(members, runs, strict=True)
            }
        for j, (m, r) in enumerate(zip(members, runs, strict=True)):
            if chosen:
                restore_member(chosen[m.seed], m, agent, venv, j)
            reason = r.data.tags.get("failure_reason", "")
            if r.info.status == "RUNNING":
                log.warning("run %s is marked RUNNING (its process ended without closing it); "
                            "continuing it", r.info.run_id)  # fmt: skip
            m.recorder = Recorder.attach(uri, r.info.run_id)
            tags = {
                "resumed_from_episode": str(m.episode),
                "resume_count": str(int(r.data.tags.get("resume_count", "0")) + 1),
                **process_tags(),
            }
            if reason:
                tags["previous_failure_reason"] = reason
                client.delete_tag(r.info.run_id, "failure_reason")
            m.recorder.set_tags(tags)
            m.logged = m.recorder.logged_episodes()
            log.info(
                "resuming MLflow run %s (seed %d) at episode %d of %d",
                r.info.run_id, m.seed, m.episode, conf.train.episodes,
            )  # fmt: skip
    except BaseException:
        for env in venv.envs:
            env.close()
        raise
    results: dict = {}
    signum = train_members(conf, agent, venv, members, results, progress, sequence, stores)
    return PopulationResult([results[s] for s in sorted(results)], signum)


def start_member_run(
    m: Member,
    conf: Config,
    setup: ControllerSetup,
    uri: str,
    population: str,
    population_id: str | None = None,
) -> Recorder:
    """Open member ``m``'s MLflow run with the params, tags and artifacts of a single run;
    tag ``population_id`` names the population (what ``resume=`` finds its members by)."""
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
        "population_id": population_id or uuid.uuid4().hex,
        **process_tags(),
        **setup.tags(),
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
        if m.status == "FINISHED" and not conf.train.keep_checkpoints:
            rec.delete_artifacts(CHECKPOINT_ROOT)  # nothing left to resume
    finally:
        status = m.status if m.status != "RUNNING" else "KILLED"
        rec.finish(status, m.reason, m.score)
        if status != "FINISHED":
            log.warning("run %s %s: %s", rec.run_id, status, m.reason)
