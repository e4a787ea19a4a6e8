"""The life of a run: open → record → checkpoint → close, and resume, written once.

Every run cdqn trains is a :class:`~cdqn.training.member.Member` of a population:
a population of ``K`` seeds has ``K`` of them, a single run is a population of one (the
same in the compiled kernels).  Tuning trials and evaluations train populations
(:func:`cdqn.training.run.run_population`), so their members' runs pass through here too.
:class:`RunLifecycle` takes one member's MLflow run through its life:

* :meth:`~RunLifecycle.open`: a new run with the params (the resolved configuration of
  the member's seed), tags and design artifacts of a single run;
* :meth:`~RunLifecycle.watch`: from here on, writes are retried while the store does not
  answer, for ``tracking.retry_s`` (then :class:`~cdqn.training.tracking.TrackingOutage`);
* :meth:`~RunLifecycle.record`: one episode's metrics (not twice after a resume);
* :meth:`~RunLifecycle.checkpoint`: a checkpoint into the run's slots
  (:mod:`cdqn.training.checkpoint`), or :meth:`~RunLifecycle.keep_locally` into
  ``tracking.local_checkpoints`` while the store is away;
* :meth:`~RunLifecycle.close`: signals, model and status (FINISHED, FAILED with
  ``failure_reason``, KILLED); a FINISHED run's checkpoints are deleted unless
  ``train.keep_checkpoints``; :meth:`~RunLifecycle.close_locally` keeps what closing
  writes when the store is away;
* :meth:`~RunLifecycle.resume`: the same run again (RUNNING), tagged
  ``resumed_from_episode`` and ``resume_count``, its last ``failure_reason`` moved to
  ``previous_failure_reason``, and the metrics a lost store did not take queued.

Whether a run diverged is decided by :mod:`cdqn.training.divergence`, for every run alike.
"""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Protocol

from mlflow.entities import Run
from mlflow.tracking import MlflowClient

from cdqn.config import Config, to_plain
from cdqn.control.box import Box
from cdqn.control.setup import ControllerSetup
from cdqn.network import QNetwork, save_network
from cdqn.records import Artifact, Tag, folder
from cdqn.training.checkpoint import ROOT as CHECKPOINT_ROOT
from cdqn.training.checkpoint import Checkpoint, CheckpointStore, save_local
from cdqn.training.loop import EpisodeStats
from cdqn.training.member import Member
from cdqn.training.sweep import config_hash, process_tags, run_name
from cdqn.training.tracking import (
    Recorder,
    TrackingOutage,
    closes_for_good,
    fail_fast_http,
    flatten,
    git_commit,
)

log = logging.getLogger("cdqn")


class EpisodeCheckpoint(Protocol):
    """A checkpoint (:class:`~cdqn.training.checkpoint.Checkpoint` or
    :class:`~cdqn.training.population_checkpoint.MemberCheckpoint`): the state after its
    ``episode`` episodes."""

    @property
    def episode(self) -> int: ...


class RunLifecycle:
    """The MLflow runs of the members of one configuration ``conf`` in the store at ``uri``
    (module docstring); ``kind``: the checkpoint dataclass they store
    (:class:`~cdqn.training.checkpoint.Checkpoint` for a single run,
    :class:`~cdqn.training.population_checkpoint.MemberCheckpoint` for a batch)."""

    def __init__(self, conf: Config, uri: str, kind: type = Checkpoint) -> None:
        self.conf, self.uri, self.kind = conf, uri, kind

    def open(
        self, m: Member, setup: ControllerSetup, tags: Mapping[str, str] | None = None
    ) -> None:
        """Open member ``m``'s run: params, tags (and ``tags``) and design artifacts of a
        single run of its seed, and its checkpoint store."""
        conf = self.conf
        container = to_plain(m.cfg)
        run_tags = {
            Tag.ENV: conf.env.name,
            Tag.ENV_ID: conf.env.id,
            Tag.CONTROLLER: conf.controller.name,
            Tag.SEED: str(m.seed),
            Tag.GIT_COMMIT: git_commit(),
            Tag.DESIGN_SOURCE: setup.source,
            Tag.CONFIG_HASH: config_hash(m.cfg),
            **(tags or {}),
            **process_tags(),
            **setup.tags(),
        }
        rec = Recorder.start(uri=self.uri, experiment=conf.tracking.experiment,
                             run_name=run_name(conf, m.seed), params=flatten(container),
                             tags=run_tags, config=container)  # fmt: skip
        if setup.artifacts is not None:
            rec.log_dir(setup.artifacts, folder(Artifact.DESIGN))
        if setup.design:  # after the folder: the record names this run's box source
            rec.log_dict(setup.design, Artifact.DESIGN_RECORD)
        m.recorder = rec
        m.store = CheckpointStore(rec.client, rec.run_id, conf.train.signals, self.kind)
        log.debug("MLflow run %s (%s, %s, seed %d)",
                  rec.run_id, conf.env.name, conf.controller.name, m.seed)  # fmt: skip

    def resume(
        self,
        m: Member,
        client: MlflowClient,
        run: Run,
        store: CheckpointStore | None,
        pending: list[tuple[str, float, int, int]],
        to_close: bool = False,
    ) -> None:
        """Reopen ``run`` as member ``m``'s (restored to episode ``m.episode``), with the
        checkpoint ``store`` it was restored from; ``pending``: metrics the store did not
        take before it went away, written with the next ones.  ``to_close``: a member that
        ended while the store was away, reopened only to be closed (a run left RUNNING is
        no surprise then)."""
        if run.info.status == "RUNNING" and not to_close:
            log.warning(
                "run %s is marked RUNNING (its process ended without closing it, e.g. SIGKILL); "
                "continuing it. Stop any process still training it first.",
                run.info.run_id,
            )
        run_id = run.info.run_id
        m.recorder = Recorder.attach(self.uri, run_id)
        m.store = store
        tags = {
            Tag.RESUMED_FROM_EPISODE: str(m.episode),
            Tag.RESUME_COUNT: str(int(run.data.tags.get(Tag.RESUME_COUNT, "0")) + 1),
            **process_tags(),
        }
        reason = run.data.tags.get(Tag.FAILURE_REASON, "")
        if reason:
            tags[Tag.PREVIOUS_FAILURE_REASON] = reason
            client.delete_tag(run_id, Tag.FAILURE_REASON)
        m.recorder.set_tags(tags)
        m.logged = m.recorder.logged_episodes()
        m.recorder.add_pending(pending)

    def watch(self, m: Member) -> None:
        """Retry member ``m``'s writes while the store does not answer
        (``tracking.retry_s``), with MLflow's own HTTP retries off."""
        tracking = self.conf.tracking
        assert m.recorder is not None
        m.recorder.retry_s = tracking.retry_s
        if m.store is not None:
            m.store.retry_s = tracking.retry_s
        if m.recorder.uri.startswith(("http://", "https://")):
            fail_fast_http(tracking.timeout)

    def record(self, m: Member, stats: EpisodeStats) -> None:
        """One episode's metrics, unless the store has them (a resumed run)."""
        assert m.recorder is not None
        if stats.episode not in m.logged:
            m.recorder.log_episode(stats)

    def checkpoint(self, m: Member, ckpt: EpisodeCheckpoint, announce: bool = True) -> None:
        """Member ``m``'s metrics so far and checkpoint ``ckpt`` into its run (``announce``:
        log it; a population logs one line for all its members)."""
        assert m.recorder is not None and m.store is not None
        m.recorder.flush()
        m.store.save(ckpt, m.signals, announce=announce)
        m.checkpointed = ckpt.episode

    def keep_locally(self, m: Member, ckpt: EpisodeCheckpoint) -> Path:
        """Checkpoint ``ckpt`` and the metrics of its episodes not yet written, into
        member ``m``'s local file (the store is away); where it is."""
        assert m.recorder is not None
        episode = ckpt.episode
        pending = [p for p in m.recorder.pending if p[3] < episode]
        path = save_local(self.conf.tracking.local_checkpoints, m.recorder.run_id, ckpt,
                          m.signals, pending)  # fmt: skip
        m.checkpointed = episode
        return path

    def close(
        self, m: Member, net: QNetwork | None, model: Path | None = None, box: Box | None = None
    ) -> None:
        """Signals, model (of ``net``, or the saved one in folder ``model``) and status of
        member ``m``'s run (``box``: the design's NTK box, drawn with the signal series).  A
        store that went away (:class:`~cdqn.training.tracking.TrackingOutage`) leaves the
        run open; any other error closes it, then is raised."""
        conf, rec = self.conf, m.recorder
        assert rec is not None
        try:
            if conf.train.signals:
                final = closes_for_good(m.status, m.reason)
                rec.log_signals(m.signals, conf.train.lr, box, final)
            if conf.tracking.log_model and net is not None:
                with tempfile.TemporaryDirectory() as tmp:
                    save_network(net, Path(tmp))
                    rec.log_dir(Path(tmp), folder(Artifact.MODEL))
            elif conf.tracking.log_model and model is not None:
                rec.log_dir(model, folder(Artifact.MODEL))
            if m.status == "FINISHED" and not conf.train.keep_checkpoints:
                rec.delete_artifacts(CHECKPOINT_ROOT)  # nothing left to resume
        except TrackingOutage:
            raise
        except BaseException:
            _finish(m)
            raise
        _finish(m)

    def close_locally(self, m: Member, net: QNetwork | None) -> Path:
        """Keep what closing member ``m``'s run writes (status, metrics not yet written,
        signal rows, model) in ``tracking.local_checkpoints``, for a member that ended
        while the store was away."""
        from cdqn.training.population_checkpoint import CLOSING_FILE, MemberClosing  # store away

        conf = self.conf
        assert m.recorder is not None
        rows = m.signals.n if conf.train.signals else 0
        closing = MemberClosing(m.status, m.reason, [float(r) for r in m.returns], rows)
        path = save_local(conf.tracking.local_checkpoints, m.recorder.run_id, closing,
                          m.signals, m.recorder.pending, CLOSING_FILE)  # fmt: skip
        if conf.tracking.log_model and net is not None:
            save_network(net, path.parent / "model")
        return path


def _finish(m: Member) -> None:
    """Close member ``m``'s run with its status (a member still RUNNING: KILLED), reason
    and final score."""
    rec = m.recorder
    assert rec is not None
    status = m.status if m.status != "RUNNING" else "KILLED"
    rec.finish(status, m.reason, m.score)
    if status != "FINISHED":
        log.warning("run %s %s: %s", rec.run_id, status, m.reason)
