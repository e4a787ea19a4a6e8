"""Populations: ``K`` seeds of one configuration trained in one process as one batch.

``python -m cdqn.train train.population=10 seed=0`` trains seeds 0, 1, …, 9 together.  The
members' networks are stacked and stepped by the compiled loops a single run uses
(:class:`cdqn.network.StackedTwoLayer`), their environments step as one
(:mod:`cdqn.vector_env`) and their controllers run on arrays (:class:`ControllerBank`), so
the per-step Python of the trainer, the environment and the bookkeeping is paid once for
``K`` members.

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

from cdqn.agents.base import EpsilonGreedy, StepRecord
from cdqn.config import Config, TrainConfig, resolve_tracking_uri, validate
from cdqn.control.factory import ControllerSetup, make_controller
from cdqn.control.runtime import NoControl, RuntimeController, StateSpace, StaticGain
from cdqn.envs import env_sizes, make_env
from cdqn.interrupt import GracefulStop
from cdqn.network import NetworkSpec, QNetwork, StackedForward, StackedTwoLayer, save_network
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


class ControllerBank:
    """``K`` copies of one runtime controller, stepped on arrays.

    :class:`NoControl`, :class:`StaticGain` and :class:`StateSpace` run vectorised (the
    state-space products as stacks of the single run's vector products, so each row is
    bit-identical); any other controller (e.g. the gain-scheduled H2, whose per-step LQR
    solve is a few microseconds of scalar arithmetic) runs as ``K`` copies in a loop.
    """

    def __init__(self, controller: RuntimeController, k: int) -> None:
        self.kind = type(controller)
        self.loss_weight = np.full(k, float(controller.loss_weight))
        if self.kind is StaticGain:
            assert isinstance(controller, StaticGain)
            self.k1, self.k2, self.k3 = controller.k1, controller.k2, controller.k3
        elif self.kind is StateSpace:
            assert isinstance(controller, StateSpace)
            self.C, self.D = controller.C[:, None], controller.D[:, None]
            self.Ad, self.Bd = controller.Ad[None], controller.Bd[None]
            self.reset_state = controller.reset_state
            self.x = np.zeros((k, len(controller.C)))
        elif self.kind is not NoControl:
            self.copies = [copy.deepcopy(controller) for _ in range(k)]

    def reset(self, i: int) -> None:
        """Episode start of member ``i``."""
        if self.kind is StateSpace:
            if self.reset_state:
                self.x[i] = 0.0
        elif self.kind not in (NoControl, StaticGain):
            self.copies[i].reset()

    def state(self, i: int) -> np.ndarray | None:
        """Member ``i``'s controller state ``x_c`` (None for static controllers)."""
        if self.kind is StateSpace:
            return self.x[i]
        if self.kind in (NoControl, StaticGain):
            return None
        return getattr(self.copies[i], "x", None)

    def step(
        self,
        x_e: np.ndarray,
        q1: np.ndarray,
        q2: np.ndarray,
        theta1: np.ndarray,
        theta2: np.ndarray,
    ) -> np.ndarray:
        """``u`` per member, as each member's own controller would return it."""
        if self.kind is NoControl:
            return np.zeros_like(q1)
        if self.kind is StaticGain:
            return -self.k1 * q1 - self.k2 * q2 + self.k3 * x_e
        if self.kind is StateSpace:
            v = np.stack([x_e, q1, q2], axis=1)
            u = (self.x[:, None, :] @ self.C)[:, 0, 0] + (v[:, None, :] @ self.D)[:, 0, 0]
            self.x = (self.Ad @ self.x[:, :, None])[:, :, 0] + (self.Bd @ v[:, :, None])[:, :, 0]
            return u
        u = np.array(
            [
                c.step(*args)
                for c, *args in zip(
                    self.copies,
                    x_e.tolist(),
                    q1.tolist(),
                    q2.tolist(),
                    theta1.tolist(),
                    theta2.tolist(),
                    strict=True,
                )
            ]
        )
        self.loss_weight = np.array([c.loss_weight for c in self.copies])
        return u

    def select(self, keep: np.ndarray) -> None:
        self.loss_weight = self.loss_weight[keep]
        if self.kind is StateSpace:
            self.x = self.x[keep]
        elif self.kind not in (NoControl, StaticGain):
            self.copies = [self.copies[i] for i in keep]


class PopulationStep(StepRecord):
    """A :class:`StepRecord` whose fields are ``(K,)`` arrays (one entry per member)."""


class ControlledPopulation:
    """:class:`cdqn.agents.ControlledAgent` (fast path) for ``K`` members at once.

    Per step and member, exactly the single agent's algorithm (paper Sec. 4, Δt = α):
    ``Q1``, ``Q2``, Θ1, Θ2; ``e = r + γ Q2 − Q1``; ``x_e ← x_e + α e``;
    ``u = K(x_e, Q1, Q2)``; ``θ ← θ + α (e + u) ∂Q(s,a)/∂θ``.
    """

    def __init__(
        self,
        nets: list[QNetwork],
        controller: RuntimeController,
        cfg: TrainConfig,
        reset_integrator: bool,
        rngs: list[np.random.Generator],
    ) -> None:
        self.net = StackedTwoLayer.from_networks(nets)
        self.spec = nets[0].spec
        self.controller = ControllerBank(controller, len(nets))
        self.alpha = cfg.lr
        self.discount = cfg.discount
        self.bootstrap_terminal = cfg.bootstrap_terminal
        self.reset_integrator = reset_integrator
        self.explorers = [EpsilonGreedy(cfg, self.spec.n_actions, rng) for rng in rngs]
        self.x_e = np.zeros(len(nets))
        self._f1: StackedForward | None = None
        self._next: StackedForward | None = None
        """Forward pass at the last s' with the current parameters (reused at s = s')."""

    def __len__(self) -> int:
        return len(self.x_e)

    def start_episode(self, i: int) -> None:
        if self.reset_integrator:
            self.x_e[i] = 0.0
        self.controller.reset(i)

    def act(self, obs: np.ndarray) -> np.ndarray:
        """ε-greedy actions ``(K,)``; the forward pass at ``obs`` is kept for :meth:`update`."""
        self._f1 = f1 = self.net.forward(obs, reuse=self._next)
        actions = np.argmax(f1.q, axis=1)
        for i, explorer in enumerate(self.explorers):
            random_action = explorer.explore()
            if random_action is not None:
                actions[i] = random_action
        return actions

    def update(
        self,
        actions: np.ndarray,
        reward: np.ndarray,
        next_obs: np.ndarray,
        terminated: np.ndarray,
    ) -> PopulationStep:
        f1 = self._f1
        assert f1 is not None, "act() before update()"
        f2 = self.net.forward(next_obs)
        a2 = np.argmax(f2.q, axis=1)
        rows = self.net.rows
        q1, q2 = f1.q[rows, actions], f2.q[rows, a2]
        td = self.net.td_terms(f1, actions, f2, a2)
        q_next = q2 if self.bootstrap_terminal else np.where(terminated, 0.0, q2)

        error = reward + self.discount * q_next - q1
        self.x_e += self.alpha * error
        u = self.controller.step(self.x_e, q1, q_next, td.theta1, td.theta2)
        delta = error + u
        loss = 0.5 * self.controller.loss_weight * delta * delta
        self._next = self.net.sgd_step(f1, actions, self.alpha * delta, td.grad_b1, f2)
        return PopulationStep(loss, q1, q2, u, self.x_e.copy(), td.theta1, td.theta2)

    def select(self, keep: np.ndarray) -> None:
        """Keep only the members ``keep`` (indices, in that order)."""
        self.net.select(keep)
        self.controller.select(keep)
        self.explorers = [self.explorers[i] for i in keep]
        self.x_e = self.x_e[keep]
        if self._next is not None:
            self._next = StackedForward(*(field[keep] for field in self._next))

    def network(self, i: int) -> QNetwork:
        """Member ``i``'s network as a :class:`QNetwork`."""
        net = QNetwork(self.spec)
        self.net.copy_to(i, net)
        return net


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

    def write(self, block: np.ndarray, members: list[Member]) -> None:
        if self.n == len(self.data):
            self.flush_all(members)
        self.data[self.n] = block
        self.n += 1

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
) -> None:
    """The training loop of :func:`cdqn.trainer.train` for all members at once.

    Each member's environment is seeded with its seed at its first episode.  A member that
    finishes its ``episodes`` or diverges leaves the batch (``on_member_end`` is called with
    the member, the agent and its row, before the row is dropped).  ``max_steps`` (for the
    benchmark) ends the loop after that many population steps.
    """
    members = list(members)
    obs = np.stack([venv.reset(j, m.seed) for j, m in enumerate(members)])
    for j in range(len(members)):
        agent.start_episode(j)
    t = np.zeros(len(members), dtype=np.int64)
    ret = np.zeros(len(members))
    ep = np.array([m.episode for m in members], dtype=float)
    staging = _Staging(len(members))
    loss_seen = np.zeros(len(members), dtype=bool)
    bar = tqdm(total=episodes * len(members), disable=not progress, unit="ep", leave=True)
    steps = 0
    try:
        while members:
            actions = agent.act(obs)
            out = venv.step(actions)
            rec = agent.update(actions, out.reward, out.obs, out.terminated)
            block = np.stack(
                [ep, t, out.reward, rec.q1, rec.q2, rec.u, rec.x_e, rec.theta1, rec.theta2,
                 rec.loss],
                axis=1,
            )  # fmt: skip
            staging.write(block, members)
            # The trainer's divergence test, first as one cheap array test that every healthy
            # step passes, then exactly (cdqn.trainer) for the rows that did not.
            ok = np.isfinite(rec.u + rec.x_e + rec.loss) & (
                np.maximum(np.abs(rec.q1), np.abs(rec.q2)) <= q_limit
            )
            ret += out.reward
            t += 1
            obs = out.obs
            leaving: list[int] = []
            if not ok.all():
                for j in np.flatnonzero(~ok):
                    r = StepRecord(*(float(f[j]) for f in rec))
                    if (
                        abs(r.q1) <= q_limit
                        and abs(r.q2) <= q_limit
                        and math.isfinite(r.u + r.x_e)
                        and (math.isfinite(r.loss) or (not loss_seen[j] and math.isnan(r.loss)))
                    ):
                        ok[j] = True
                        loss_seen[j] = loss_seen[j] or not math.isnan(r.loss)
                        continue
                    try:
                        _diagnose(r, q_limit, members[j].episode, int(t[j] - 1))
                    except DivergenceError as err:
                        members[j].status, members[j].reason = "FAILED", f"diverged: {err}"
                    leaving.append(j)
            loss_seen |= ok
            done = out.terminated | out.truncated
            for j in np.flatnonzero(done & ok):
                m = members[j]
                staging.flush(j, m)
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
                stats = episode_stats(m.episode, m.signals.rows(start), m.returns, discount)
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
                staging.select(keep, members)
                obs, t, ret, ep = obs[keep], t[keep], ret[keep], ep[keep]
                loss_seen = loss_seen[keep]
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
    """Whether :class:`ControlledPopulation` can train this configuration."""
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


def run_population(cfg: DictConfig, progress: bool = True) -> PopulationResult:
    """Train seeds ``seed … seed+population−1`` of ``cfg``, each as its own MLflow run
    (module docstring)."""
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
                should_stop=stop.requested,
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
