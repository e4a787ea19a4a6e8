"""Hydra entry point: compose the config, train (:func:`cdqn.training.run.run`), report.

    python -m cdqn.train                                   # env=cartpole controller=hinf
    python -m cdqn.train env=acrobot controller=hinf_f seed=3 train.episodes=500
    python -m cdqn.train -m controller=h2,hinf,hinf_f,ddqn seed='range(10)'  # 4 populations
    python -m cdqn.train resume=<run_id>                   # continue an interrupted run

Exit status: 0 finished (or a multirun that ran; its summary lists failed jobs), 1 the run
FAILED (diverged or crashed), 2 refused configuration or tracking store, 75 the tracking
store went away for longer than ``tracking.retry_s`` (checkpointed locally, resumable),
128 + signal number when SIGINT/SIGTERM stopped the run (KILLED, resumable).

From Python: ``cdqn.training.run.run(cfg)`` (also importable from here) with a composed
config returns the :class:`cdqn.training.result.RunResult`.
"""

from __future__ import annotations

import logging
import math
import sys
from typing import TYPE_CHECKING, Any

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from cdqn.cli import resume_conflicts, start_hydra
from cdqn.config import CONF_DIR, ConfigError, register_configs, resolve_tracking_uri
from cdqn.control.errors import DesignError

if TYPE_CHECKING:
    from cdqn.training.result import RunResult
    from cdqn.training.run import run

__all__ = ["main", "run", "RunResult"]

log = logging.getLogger("cdqn")
register_configs()


def __getattr__(name: str) -> Any:
    """``run`` and ``RunResult``, imported on first use: torch and MLflow are imported only
    once the command line has passed its checks, so that a refused one answers at once."""
    if name == "run":
        from cdqn.training.run import run

        return run
    if name == "RunResult":
        from cdqn.training.result import RunResult

        return RunResult
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _is_multirun() -> bool:
    try:
        return HydraConfig.get().mode == RunMode.MULTIRUN
    except ValueError:
        return False


def _design_hint(cfg: DictConfig) -> str:
    """Where a design this environment's box certifies comes from, for a refused design."""
    env = cfg.env.get("id")
    return (f"; a design tuned to this environment: python -m cdqn.tune env.id={env} "
            f"controller=hinf_f (docs/your_environment.md), or controller=ddqn")  # fmt: skip


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def main(cfg: DictConfig) -> float:
    from cdqn.training.callbacks import record_job
    from cdqn.training.result import EXIT_OUTAGE, OUTAGE, solve_text, summary_text
    from cdqn.training.run import run
    from cdqn.training.tracking import TrackingOutage

    multirun = _is_multirun()
    try:
        if cfg.get("resume"):
            conflicts = resume_conflicts(list(HydraConfig.get().overrides.task))
            if conflicts:
                raise ConfigError("invalid configuration:\n  - " + "\n  - ".join(conflicts))
        result = run(cfg, progress=not multirun and sys.stderr.isatty())
    except (ConfigError, DesignError) as err:  # user errors, TrackingError included
        log.error("%s%s", err, _design_hint(cfg) if isinstance(err, DesignError) else "")
        record_job("REFUSED", reason=str(err))
        if not multirun:
            sys.exit(2)
        return float("nan")
    except TrackingOutage as err:  # the store went away where no local checkpoint is possible
        record_job(OUTAGE, reason=str(err))
        if not multirun:
            sys.exit(EXIT_OUTAGE)
        return float("nan")
    except KeyboardInterrupt:
        log.error("interrupted")
        sys.exit(130)
    except Exception as err:  # a crash; the MLflow run (if any) is already FAILED
        record_job("FAILED", reason=f"{type(err).__name__}: {err}")
        if not multirun:
            raise
        log.exception("job failed")
        return float("nan")
    seed = None if cfg.get("resume") else int(cfg.seed)  # a population's first member
    record_job(
        result.status, result.run_id, result.reason, result.final_score, solve_text(result),
        members=result.members, seed=seed,
    )  # fmt: skip
    if result.status == OUTAGE:
        sys.exit(EXIT_OUTAGE)
    if not multirun:
        print(summary_text(result, resolve_tracking_uri(cfg.tracking.uri), cfg.tracking.experiment))
    if result.status == "KILLED":
        sys.exit(128 + (result.signum or 2))
    if result.status == "FAILED" and not multirun:
        sys.exit(1)
    return result.final_score if math.isfinite(result.final_score) else float("nan")


if __name__ == "__main__":
    start_hydra(main)
