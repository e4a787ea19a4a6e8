"""The study's MLflow runs: a parent per study, a child per trial and per evaluation."""

from __future__ import annotations

import json
import logging
import math
import time
from typing import Any

from omegaconf import DictConfig

from cdqn.config import to_plain
from cdqn.records import Artifact, Metric, Tag

log = logging.getLogger("cdqn.tune")


class Tracker:
    """The study's MLflow runs: a parent per study, a child per trial (module docstring)."""

    def __init__(self, uri: str, experiment: str) -> None:
        from mlflow.tracking import MlflowClient

        from cdqn.training.store import ensure_store
        from cdqn.training.tracking import check_tracking

        check_tracking(uri)  # an unusable store: one line, exit status 2
        ensure_store(uri, experiment)
        self.client = MlflowClient(uri)
        exp = self.client.get_experiment_by_name(experiment)
        self.experiment_id = (
            exp.experiment_id if exp is not None else self.client.create_experiment(experiment)
        )
        # MLflow 3's UI then opens the experiment as model training (runs table), not GenAI
        self.client.set_experiment_tag(
            self.experiment_id, "mlflow.experimentKind", "custom_model_development"
        )

    def parent(self, study: Any, conf: Any, cfg: DictConfig) -> str:
        """The study's parent run: created at the first start, reopened on a restart
        (``joined``: it was open, another worker of the study opened it)."""
        from cdqn.training.tracking import flatten, git_commit

        self.joined = False
        run_id = study.user_attrs.get("mlflow_parent")
        if run_id is not None:
            try:
                if self.client.get_run(run_id).info.status == "RUNNING":
                    self.joined = True
                    return run_id  # another worker of the study has it open
                self.client.update_run(run_id, status="RUNNING")
                self.client.set_tag(run_id, "resumed", time.strftime("%Y-%m-%dT%H:%M:%S"))
                return run_id
            except Exception:  # the store changed: start a new parent
                log.warning("parent run %s not found; a new parent run is started", run_id)
        tags = {Tag.STUDY: conf.tune.study, Tag.KIND: "tune", Tag.ENV: conf.env.name,
                Tag.ENV_ID: conf.env.id, Tag.CONTROLLER: conf.controller.name,
                Tag.GIT_COMMIT: git_commit()}  # fmt: skip
        run = self.client.create_run(self.experiment_id, run_name=f"tune-{conf.tune.study}",
                                     tags=tags)  # fmt: skip
        run_id = run.info.run_id
        container = to_plain(cfg)
        self.log_params(run_id, flatten(container))
        self.client.log_dict(run_id, container, Artifact.CONFIG)
        study.set_user_attr("mlflow_parent", run_id)
        return run_id

    def child(self, parent: str, name: str, tags: dict[str, str], kind: str = "trial") -> str:
        run = self.client.create_run(
            self.experiment_id,
            run_name=name,
            tags={"mlflow.parentRunId": parent, Tag.KIND: kind, **tags},
        )
        return run.info.run_id

    def log_params(self, run_id: str, params: dict[str, Any]) -> None:
        from mlflow.entities import Param

        items = [Param(k, json.dumps(v) if isinstance(v, list | dict) else str(v)[:6000])
                 for k, v in params.items()]  # fmt: skip
        for i in range(0, len(items), 100):
            self.client.log_batch(run_id, params=items[i : i + 100])

    def metrics(self, run_id: str, values: dict[str, float], step: int = 0) -> None:
        for k, v in values.items():
            if v is not None and math.isfinite(float(v)):
                self.client.log_metric(run_id, k, float(v), step=step)

    def end(self, run_id: str, status: str, trial_status: str, reason: str | None = None) -> None:
        self.client.set_tag(run_id, Tag.TRIAL_STATUS, trial_status)
        if reason:
            self.client.set_tag(run_id, "reason", reason[:5000])
        self.client.set_terminated(run_id, status)

    def nest(self, parent: str, run_ids: list[str], reason: str | None = None) -> None:
        for rid in run_ids:
            self.client.set_tag(rid, "mlflow.parentRunId", parent)
            if reason:
                self.client.set_tag(rid, Tag.FAILURE_REASON, reason)

    def drop_checkpoints(self, run_ids: list[str]) -> None:
        """Delete the resume checkpoints of a pruned trial's member runs: a pruned trial is
        not trained again (a trial cut short by a signal is, and keeps them)."""
        from cdqn.training.checkpoint import ROOT
        from cdqn.training.tracking import delete_artifacts

        for rid in run_ids:
            delete_artifacts(self.client, rid, ROOT)

    def history(self, run_id: str, key: str) -> list[float]:
        """Per-episode values of metric ``key`` of a run, in episode order."""
        hist = self.client.get_metric_history(run_id, key)
        return [m.value for m in sorted(hist, key=lambda m: m.step)]

    def returns(self, run_id: str) -> list[float]:
        return self.history(run_id, Metric.EPISODE_RETURN)
