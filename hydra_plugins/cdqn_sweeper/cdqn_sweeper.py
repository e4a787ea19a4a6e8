"""A Hydra sweeper that trains a multirun's seeds as populations.

It expands the sweep as Hydra's basic sweeper does (cartesian product of the swept values,
``hydra.sweeper.params`` included), then regroups the jobs that differ only in ``seed``
into population jobs ``seed=<first> train.population=<K>`` of at most
``hydra.sweeper.max_population`` consecutive seeds
(:func:`cdqn.training.batching.batch_jobs`), splits them further so that the launcher's
workers end together (:func:`cdqn.training.batching.balance`), and hands them to the
configured launcher (joblib on the local cores, submitit on Slurm, Ray).  Every member of
a population is its own MLflow run and learns exactly what the single run of its seed
learns.
``hydra.sweeper.max_population=1`` launches one job per seed.

Selected in ``conf/config.yaml`` (``override hydra/sweeper: cdqn``); the ``cdqn`` option of
the ``hydra/sweeper`` group is registered here, and Hydra finds this module in the
``hydra_plugins`` namespace package.
"""

import logging
import sys
from dataclasses import dataclass
from typing import Any

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.config_store import ConfigStore
from hydra.core.override_parser.types import Override

log = logging.getLogger(__name__)

EXIT_CONFIG = 2
"""Exit status of a refused setting (as ``python -m cdqn.train``)."""


@dataclass
class CdqnSweeperConf:
    _target_: str = "hydra_plugins.cdqn_sweeper.cdqn_sweeper.CdqnSweeper"
    max_population: int = 10
    """Seeds per population job at most (1: one job per seed)."""
    max_batch_size: int | None = None
    """Jobs handed to the launcher at once (None: all), as the basic sweeper's."""
    params: dict[str, str] | None = None
    """Swept values given in the config (``key: a,b,c``), as the basic sweeper's."""


ConfigStore.instance().store(
    group="hydra/sweeper", name="cdqn", node=CdqnSweeperConf, provider="cdqn"
)


class CdqnSweeper(BasicSweeper):
    """Hydra's basic sweeper with seeds batched into populations (module docstring)."""

    def __init__(
        self,
        max_population: int = 10,
        max_batch_size: int | None = None,
        params: dict[str, str] | None = None,
    ) -> None:
        if max_population < 1:
            print(
                f"cdqn: hydra.sweeper.max_population={max_population}: must be at least 1 "
                "(1 launches one job per seed)",
                file=sys.stderr,
            )
            sys.exit(EXIT_CONFIG)
        super().__init__(max_batch_size, params)
        self.max_population = max_population

    def split_arguments(  # type: ignore[override]  # the base's is static; batching composes (self)
        self, overrides: list[Override], max_batch_size: int | None
    ) -> list[list[list[str]]]:
        """The basic sweeper's jobs, seeds batched, in chunks of ``max_batch_size`` (an
        instance method where the basic sweeper's is static: the sweep calls it on the
        sweeper, and batching composes each job's configuration)."""
        from cdqn.training.batching import batch_jobs

        (jobs,) = BasicSweeper.split_arguments(overrides, None)
        workers = self._workers()
        batched = batch_jobs(jobs, self.max_population, self._shape, workers)
        if len(batched) < len(jobs):
            log.info(
                "cdqn sweeper: %d jobs as %d (seeds trained as populations of up to %d%s)",
                len(jobs), len(batched), self.max_population,
                "" if workers is None else f", balanced over {workers} workers",
            )  # fmt: skip
        return list(BasicSweeper.split_overrides_to_chunks(batched, max_batch_size))

    def _workers(self) -> int | None:
        """The launcher's parallel workers: joblib's ``hydra.launcher.n_jobs`` (−1: every
        core, −2: all but one, as joblib counts them), or None for a launcher without it
        (Slurm, Ray: every job at once)."""
        assert self.config is not None
        n_jobs = self.config.hydra.launcher.get("n_jobs")
        if n_jobs is None:
            return None
        if n_jobs < 0:
            from joblib import cpu_count

            return max(1, cpu_count() + 1 + int(n_jobs))
        return max(1, int(n_jobs))

    def _shape(self, overrides: list[str]) -> Any:
        """:class:`cdqn.training.batching.JobShape` of one job, composed as Hydra will."""
        from cdqn.training.batching import JobShape, job_shape

        assert self.hydra_context is not None and self.config is not None
        try:
            cfg = self.hydra_context.config_loader.load_sweep_config(self.config, overrides)
        except Exception:  # reported by Hydra when it validates the batch
            return JobShape(False, "?")
        return job_shape(cfg)
