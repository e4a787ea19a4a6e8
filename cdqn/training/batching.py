"""Which seeds train as one batch: the configurations a population can train
(:func:`batchable`), and a multirun's jobs regrouped into populations (:func:`batch_jobs`).

A multirun over seeds, ``python -m cdqn.train -m controller=h2,ddqn seed='range(10)'``,
expands (as Hydra's basic sweeper does) into one job per seed.  The cdqn sweeper
(``hydra_plugins/cdqn_sweeper``, selected in ``conf/config.yaml``) hands the launcher
:func:`batch_jobs` of that list instead: jobs that differ only in ``seed`` become one job
``seed=<first> train.population=<K>`` per run of consecutive seeds, at most
``hydra.sweeper.max_population`` seeds each.  A population trains every member exactly as
the single run of its seed (:mod:`cdqn.training.population`), so only the wall time
changes.  Jobs stay as they are where the configuration cannot batch (:func:`batchable`),
where it already sets ``train.population`` or ``resume``, and where a seed is not an
integer or appears twice.  For a launcher of ``W`` parallel workers (joblib's), populations
are halved while that lets the workers end sooner (:func:`balance`), by a cost model of
members and jobs (:data:`MEMBER_COST`, :data:`JOB_COST`), and the longest jobs are launched
first (:func:`launch_order`).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

from omegaconf import DictConfig, open_dict

from cdqn.config import BOXED_CONTROLLERS, Config

SEED_KEY = "seed"
POPULATION_KEY = "train.population"


class JobShape(NamedTuple):
    """What the sweeper needs to know of one job's configuration."""

    batchable: bool
    """Its seeds may train as one population."""
    controller: str
    """``controller.name`` (``?`` when the configuration does not compose)."""


def batchable(conf: Config) -> bool:
    """Whether the members train as one batch: :class:`ControlledPopulation` (its
    controllers are the runtime controllers
    :class:`cdqn.agents.controlled_population.ControllerArrays` knows) or :class:`DDQNPopulation`,
    both on the fast path, with one design for all members (a measured NTK box builds each
    seed's design on its own network, :mod:`cdqn.ntk_bounds`)."""
    ctrl = conf.controller
    measured = (
        ctrl.synthesis.ntk_bounds == "measured"
        and ctrl.design == "synthesize"
        and ctrl.name in BOXED_CONTROLLERS
    )
    return conf.train.fast_path and not measured


def job_shape(cfg: DictConfig) -> JobShape:
    """:class:`JobShape` of a composed job configuration (its ``hydra`` node is ignored):
    batchable when it trains one seed (``train.population=1``, no ``resume``) and, once its
    environment is adopted (:func:`cdqn.envs.adopt`), :func:`batchable`."""
    from cdqn.envs import adopt

    job = copy.deepcopy(cfg)
    with open_dict(job):
        job.pop("hydra", None)
    try:
        controller = str(job.controller.name)
        if job.get("resume") or job.train.population != 1:
            return JobShape(False, controller)
        return JobShape(batchable(adopt(job).conf), controller)
    except Exception:  # the job does not compose: Hydra reports it when it validates the batch
        return JobShape(False, "?")


def _seed_of(job: Sequence[str]) -> tuple[tuple[str, ...], int | None]:
    """The job's overrides without ``seed=…``, and its seed (None: absent or not an int)."""
    rest, seed = [], None
    for override in job:
        key, _, value = override.partition("=")
        if key == SEED_KEY:
            seed = int(value) if value.lstrip("-").isdigit() else None
        else:
            rest.append(override)
    return tuple(rest), seed


def seed_runs(seeds: Sequence[int], max_population: int) -> list[tuple[int, int]]:
    """``(first seed, count)`` of each population for ``seeds``: runs of consecutive seeds,
    each split into ``ceil(n / max_population)`` parts of nearly equal size."""
    out: list[tuple[int, int]] = []
    ordered = sorted(seeds)
    start = 0
    for i in range(1, len(ordered) + 1):
        if i < len(ordered) and ordered[i] == ordered[i - 1] + 1:
            continue
        n = i - start
        parts = math.ceil(n / max_population)
        first = ordered[start]
        for p in range(parts):
            size = n // parts + (1 if p < n % parts else 0)
            out.append((first, size))
            first += size
        start = i
    return out


def _with_seed(job: Sequence[str], seed: int, population: int) -> list[str]:
    """``job`` with ``seed=<seed>`` and, for more than one seed, ``train.population=<K>``."""
    out = [f"{SEED_KEY}={seed}" if o.partition("=")[0] == SEED_KEY else o for o in job]
    return [*out, f"{POPULATION_KEY}={population}"] if population > 1 else out


MEMBER_COST = {"ddqn": 2.5}
"""A member's training time in units of a controlled member's (absent: 1).  Double DQN's
minibatch step makes its member-step about 2.5 times a controlled one on CartPole
(docs/speed.md)."""
JOB_COST = 1.0
"""What starting a job costs beyond its members (the worker's start, the design's synthesis,
a population's Python per step), in the same units: a population of 3 runs about 15 %
slower per member than one of 10."""


class Planned(NamedTuple):
    """One job of the batched sweep: ``overrides`` as the sweep wrote them (with the first
    seed's ``seed=…``), or a population of ``size`` seeds from ``seed``."""

    overrides: list[str]
    seed: int | None
    size: int
    controller: str

    @property
    def cost(self) -> float:
        return self.size * MEMBER_COST.get(self.controller, 1.0) + JOB_COST

    def job(self) -> list[str]:
        """The job's overrides: ``seed=<seed>`` and ``train.population=<size>``."""
        if self.seed is None:
            return self.overrides
        return _with_seed(self.overrides, self.seed, self.size)

    def halves(self) -> tuple[Planned, Planned]:
        """The population split in two of consecutive seeds, the first no smaller."""
        assert self.seed is not None
        first = (self.size + 1) // 2
        return (
            self._replace(size=first),
            self._replace(seed=self.seed + first, size=self.size - first),
        )


def batch_jobs(
    jobs: Sequence[Sequence[str]],
    max_population: int,
    shape: Callable[[list[str]], JobShape],
    workers: int | None = None,
) -> list[list[str]]:
    """The jobs of a multirun (override lists) with those that differ only in ``seed``
    grouped into populations (module docstring), split further by :func:`balance` for
    ``workers`` parallel workers (None: a launcher that runs every job at once), longest
    first.  ``shape`` tells whether a job's configuration can batch; it is asked once per
    group."""
    groups: dict[tuple[str, ...], list[tuple[Sequence[str], int | None]]] = {}
    for job in jobs:
        rest, seed = _seed_of(job)
        groups.setdefault(rest, []).append((job, seed))
    planned: list[Planned] = []
    for rest, members in groups.items():
        seeds = [s for _, s in members]
        first = list(members[0][0])
        explicit = any(o.partition("=")[0] in (POPULATION_KEY, "resume") for o in rest)
        kind = shape(first)
        can = (
            max_population > 1
            and len(members) > 1
            and None not in seeds
            and len(set(seeds)) == len(seeds)
            and not explicit
            and kind.batchable
        )
        if not can:
            planned += [Planned(list(job), None, 1, kind.controller) for job, _ in members]
            continue
        for seed, count in seed_runs([s for s in seeds if s is not None], max_population):
            planned.append(Planned(first, seed, count, kind.controller))
    if workers is not None:
        planned = balance(planned, workers)
    return [p.job() for p in launch_order(planned)]


def makespan(planned: Sequence[Planned], workers: int) -> float:
    """When the last of ``planned`` ends on ``workers`` workers that each take the next job
    of :func:`launch_order` as they become free (joblib's order), in job costs."""
    ends = [0.0] * max(1, workers)
    for p in launch_order(list(planned)):
        ends[ends.index(min(ends))] += p.cost
    return max(ends)


def balance(planned: list[Planned], workers: int) -> list[Planned]:
    """``planned`` with populations halved while that shortens the :func:`makespan` on
    ``workers`` workers: each round takes the one halving that shortens it most.  Four jobs
    of ten seeds on two workers, one of them Double DQN's, become six: Double DQN's two
    halves, one controller's two halves and the two others whole."""
    best = makespan(planned, workers)
    while True:
        trials = []
        for i, p in enumerate(planned):
            if p.seed is not None and p.size > 1:
                trial = [*planned[:i], *p.halves(), *planned[i + 1 :]]
                trials.append((makespan(trial, workers), i, trial))
        if not trials:
            return planned
        span, _, trial = min(trials, key=lambda t: (t[0], t[1]))
        if span >= best - 1e-9:
            return planned
        planned, best = trial, span


def launch_order(planned: list[Planned]) -> list[Planned]:
    """The longest jobs first (:attr:`Planned.cost`), otherwise in sweep order: started
    first, they leave the shorter jobs to fill the other workers."""
    return sorted(planned, key=lambda p: -p.cost)
