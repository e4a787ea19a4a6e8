"""Tune an agent for an environment: an Optuna study, each trial a population (docs/tuning.md)::

    python -m cdqn.tune env.id=<id> controller=hinf_f      # a certified design
    python -m cdqn.tune env.id=<id> controller=ddqn        # Double DQN, the same budget

A trial samples a specification from ``tune.space`` (``conf/space/<controller>.yaml``: the
observation maps and exploration every agent is offered, and the agent's own settings),
synthesises and certifies a design first (a :class:`~cdqn.control.errors.DesignError` prunes
the trial with its reason, nothing is trained), then trains a population of ``tune.seeds``
seeds from ``tune.seed`` for the environment's episode budget.  The best specification
becomes a preset that carries the environment settings it was tuned with, is trained again
on fresh seeds, and is compared with the other agents tuned on the same environment.
Implementation: :mod:`cdqn.tuning`.
"""

from __future__ import annotations

import logging
import sys

import hydra
from omegaconf import DictConfig

from cdqn.config import CONF_DIR, ConfigError, of_kind
from cdqn.control.errors import DesignError
from cdqn.tuning.report import summary_text
from cdqn.tuning.settings import TuneConfig, validate_tune
from cdqn.tuning.study import Study

log = logging.getLogger("cdqn.tune")

EXIT_NO_RESULT = 1
"""Exit status of a study in which no trial completed (no preset, no evaluation)."""


def check_tune(cfg: DictConfig) -> None:
    """What ``python -m cdqn.tune`` refuses (for :func:`cdqn.cli.preflight`): the study's
    settings and the environment as its configuration builds it (constructor arguments, an
    entry point that cannot be imported)."""
    from cdqn.envs import adopt, make_env

    conf = of_kind(adopt(cfg).conf, TuneConfig)
    validate_tune(conf)
    make_env(conf.env).close()


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="tune")
def main(cfg: DictConfig) -> None:
    try:
        summary = Study(cfg).run()
    except (ConfigError, DesignError) as err:
        log.error("%s", err)
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        log.error("interrupted: run the same command again to continue the study")
        sys.exit(130)
    print(summary_text(summary))
    if "no_result" in summary:  # worker 0: the study ended without a specification
        sys.exit(EXIT_NO_RESULT)


if __name__ == "__main__":
    import os

    from cdqn.cli import start_hydra
    from cdqn.tuning.clock import COMMAND_START_ENV, process_start

    # the study's time limit counts from here; the launcher's workers inherit the start
    os.environ[COMMAND_START_ENV] = repr(process_start())

    # the module's own main, not __main__'s: the joblib launcher's workers (tune.worker=0,1)
    # then import the task function and the config schema instead of unpickling copies
    from cdqn.tune import main as tune_main

    start_hydra(tune_main, "tune", check_tune)
