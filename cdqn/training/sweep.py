"""Sweeps that can be restarted: configuration hashes, skipping finished runs, and a
tracking store made ready once before parallel jobs start.

Every run is tagged ``config_hash``: a hash of its resolved configuration without the keys
that do not change what is learned (:data:`IGNORED_KEYS`: where it is recorded, progress
display, checkpoint interval, population size), seed included; a controller's own learning
target enters it only where one of its ranges is set, ``env.kwargs`` only when given.  With
``tracking.skip_finished=true`` a job first asks the store for a FINISHED run with its hash
and, if there is one, logs ``skipping …`` and trains nothing; a population skips the
members that finished and trains the others.  An interrupted sweep started again therefore
trains only what is missing.

:class:`PrepareStore` (a Hydra callback registered in ``conf/config.yaml``) creates the
tracking store and the experiment in the launching process before any job starts
(:func:`cdqn.training.store.ensure_store`; every job opens the store through it too).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import socket
from typing import Any

from hydra.experimental.callback import Callback
from mlflow.entities import Run
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig, OmegaConf

from cdqn.config import Config, NetworkConfig, TrainConfig, resolve_tracking_uri, sqlite_file
from cdqn.training.store import ensure_store

log = logging.getLogger("cdqn")

IGNORED_KEYS = (
    "tracking",
    "resume",
    "train.progress",
    "train.checkpoint_every",
    "train.population",
)
"""Configuration keys left out of :func:`config_hash`."""


def config_hash(cfg: DictConfig | dict[str, Any]) -> str:
    """16 hex digits of SHA-256 over the resolved configuration minus :data:`IGNORED_KEYS`."""
    tree = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else cfg
    tree = json.loads(json.dumps(tree, default=str))  # a deep copy of plain values
    tree.pop("hydra", None)
    for key in IGNORED_KEYS:
        *parents, leaf = key.split(".")
        node = tree
        for part in parents:
            node = node.get(part, {}) if isinstance(node, dict) else {}
        if isinstance(node, dict):
            node.pop(leaf, None)
    _drop_unset_own_targets(tree)
    _drop_empty_env_kwargs(tree)
    text = json.dumps(tree, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _drop_unset_own_targets(tree: dict[str, Any]) -> None:
    """Leave the controllers' own learning targets out where none of their ranges is set
    (``weights.controller_target``): the configuration is then the one of runs recorded
    before the setting existed, and a restarted sweep still finds them."""
    weights = tree.get("weights")
    if not isinstance(weights, dict):
        return
    own = weights.get("controller_target")
    if not isinstance(own, dict):
        return
    for name in list(own):
        ranges = own[name]
        if isinstance(ranges, dict) and all(v is None for v in ranges.values()):
            del own[name]
    if not own:
        weights.pop("controller_target")


def _drop_empty_env_kwargs(tree: dict[str, Any]) -> None:
    """Leave ``env.kwargs`` out when empty (the registration's constructor arguments): the
    configuration is then the one of runs recorded before the setting existed."""
    env = tree.get("env")
    if isinstance(env, dict) and not env.get("kwargs", True):
        env.pop("kwargs")


def _newest_run(client: MlflowClient, experiment: str, where: str) -> Run | None:
    """The most recently started run of ``experiment`` that matches the filter ``where``."""
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        return None
    runs = client.search_runs(
        [exp.experiment_id],
        filter_string=where,
        max_results=1,
        order_by=["attributes.start_time DESC"],
    )
    return runs[0] if runs else None


def find_finished(client: MlflowClient, experiment: str, chash: str) -> Run | None:
    """The most recent FINISHED run tagged ``config_hash = chash``, if any."""
    where = f"tags.config_hash = '{chash}' and attributes.status = 'FINISHED'"
    return _newest_run(client, experiment, where)


RESUMABLE = ("KILLED", "RUNNING")
"""Statuses of runs a restarted sweep continues from their last checkpoint."""


def process_tags() -> dict[str, str]:
    """Tags naming the process that trains a run (``host``, ``pid``): a run left RUNNING is
    resumed only when that process is gone (:func:`process_gone`)."""
    return {"host": socket.gethostname(), "pid": str(os.getpid())}


def process_gone(tags: dict[str, str]) -> bool:
    """Whether the process named by a run's ``host``/``pid`` tags no longer runs.  On
    another host this cannot be seen; the run counts as abandoned (two sweeps writing one
    store at the same time with the same configurations is not supported)."""
    if tags.get("host") != socket.gethostname() or not tags.get("pid", "").isdigit():
        return True
    pid = int(tags["pid"])
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    return False


def find_resumable(client: MlflowClient, experiment: str, chash: str) -> Run | None:
    """The most recent run tagged ``config_hash = chash`` that was KILLED, or left RUNNING by
    a process that is gone; a restarted sweep continues it instead of training anew."""
    run = _newest_run(client, experiment, f"tags.config_hash = '{chash}'")
    if run is None:  # the newest run with this hash decides (FAILED: start anew)
        return None
    status = run.info.status
    if status == "KILLED" or (status == "RUNNING" and process_gone(run.data.tags)):
        return run
    return None


def final_score(client: MlflowClient, run: Run) -> float:
    """Last logged ``return_ma100`` of ``run`` (NaN when it has none)."""
    history = client.get_metric_history(run.info.run_id, "return_ma100")
    return max(history, key=lambda m: m.step).value if history else float("nan")


class PrepareStore(Callback):
    """Hydra callback: make the tracking store and experiment ready before a multirun's jobs
    start (module docstring)."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:

        try:
            uri = resolve_tracking_uri(str(config.tracking.uri))
            experiment = str(config.tracking.experiment)
        except Exception as err:  # an unresolvable interpolation: each job will report it
            log.warning("could not prepare the tracking store: %s", err)
            return
        if sqlite_file(uri) is not None:
            ensure_store(uri, experiment)


def finished_elsewhere(cfg: DictConfig, uri: str) -> tuple[str, float] | None:
    """``(run_id, final score)`` of a FINISHED run with ``cfg``'s hash in the store at
    ``uri``, logging ``skipping …``; None when this configuration and seed must be trained."""
    client = MlflowClient(uri)
    run = find_finished(client, str(cfg.tracking.experiment), config_hash(cfg))
    if run is None:
        return None
    log.info(
        "skipping %s/%s seed %s: run %s already FINISHED with this configuration (config_hash %s)",
        cfg.env.name,
        cfg.controller.name,
        cfg.seed,
        run.info.run_id,
        run.data.tags.get("config_hash"),
    )
    return run.info.run_id, final_score(client, run)


def resumable_elsewhere(cfg: DictConfig, uri: str) -> str | None:
    """The run id a restarted sweep continues for ``cfg`` (:func:`find_resumable`), or None."""
    run = find_resumable(MlflowClient(uri), str(cfg.tracking.experiment), config_hash(cfg))
    return run.info.run_id if run is not None else None


NAME_PARTS = (
    ("network.width", "w"),
    ("train.episodes", "e"),
    ("train.lr", "lr"),
    ("train.discount", "g"),
)
"""Settings a run name shows, each with its letter, when they differ from the defaults of
:class:`cdqn.config.Config` (the paper's: width 2500, 2000 episodes, α = 5e-5, γ = 1)."""


def run_name(conf: Config, seed: int | None = None) -> str:
    """``<env.name>-<controller>[-w<width>][-e<episodes>][-lr<α>][-g<γ>]-s<seed>``: what
    tells a run apart from others in the MLflow runs table, e.g. ``cartpole-hinf-s0`` with
    the paper's settings, ``cartpole-hinf-w64-e50-s0`` for a quick look.  Every other
    setting is in the run's params and tags (``config_hash`` identifies the whole
    configuration)."""
    parts = [conf.env.name, conf.controller.name]
    defaults = {"network": NetworkConfig(), "train": TrainConfig()}
    for key, letter in NAME_PARTS:
        group, field = key.split(".")
        value = getattr(getattr(conf, group), field)
        if value != getattr(defaults[group], field):
            parts.append(f"{letter}{value:g}")
    parts.append(f"s{conf.seed if seed is None else seed}")
    return "-".join(parts)
