"""Sweeps: every sweep and launcher config composes, a restarted sweep skips what already
FINISHED, and parallel jobs share a fresh SQLite store safely."""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig, OmegaConf

from cdqn.config import EnvConfig, validate
from cdqn.envs.make import episode_cap
from cdqn.training.run import run, run_population
from cdqn.training.store import ensure_store
from cdqn.training.sweep import PrepareStore, config_hash
from cdqn.tuning.settings import TuneSettings, episode_budget
from tests.conftest import CONF_DIR, compose_config
from tests.helpers import episode_returns, run_cli, runs_of, signal_table

ROOT = CONF_DIR.parent
SWEEPS = ROOT / "sweeps"
LAUNCHERS = {
    "local": "hydra_plugins.cdqn_launcher.cdqn_launcher.CdqnLocalLauncher",
    "slurm": "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher",
    "ray_cluster": "hydra_plugins.hydra_ray_launcher.ray_launcher.RayLauncher",
}


def _compose_sweep(name: str, overrides: list[str], hydra: bool = True) -> DictConfig:
    """What ``python -m cdqn.train -m --config-dir sweeps --config-name <name>`` composes."""
    with initialize_config_dir(str(SWEEPS), version_base="1.3"):
        return compose(
            name,
            overrides=[f"hydra.searchpath=[file://{CONF_DIR}]", *overrides],
            return_hydra_config=hydra,
        )


@pytest.mark.parametrize("sweep", sorted(p.stem for p in SWEEPS.glob("*.yaml")))
@pytest.mark.parametrize("launcher", sorted(LAUNCHERS))
def test_sweep_and_launcher_configs_compose(sweep: str, launcher: str) -> None:
    cfg = _compose_sweep(sweep, [f"hydra/launcher={launcher}"])
    assert cfg.hydra.launcher._target_ == LAUNCHERS[launcher]
    params = cfg.hydra.sweeper.params
    # every environment and controller, the longest jobs (Mountain car, Double DQN) first
    assert params.env.split(",") == ["mountaincar", "acrobot", "cartpole"]
    agents = ["ddqn"] if sweep == "like_online" else ["ddqn", "h2", "hinf", "hinf_f"]
    assert params.controller.split(",") == agents
    assert cfg.tracking.skip_finished and cfg.train.population >= 2


@pytest.mark.parametrize("env", ["cartpole", "acrobot", "mountaincar"])
@pytest.mark.parametrize("controller", ["ddqn", "h2", "hinf", "hinf_f"])
def test_the_like_for_like_sweep_takes_each_agents_tuned_preset(env: str, controller: str) -> None:
    cfg = _compose_sweep("like", [f"env={env}", f"controller={controller}"], hydra=False)
    assert cfg.weights.name == f"tuned_{env}-{controller}"
    assert cfg.env.name == env and cfg.extra.tuned.agent == controller
    env_cfg = EnvConfig(id=cfg.env.id, max_episode_steps=cfg.env.max_episode_steps)
    cap = episode_cap(env_cfg)  # the default budget: 300 000 steps over the cap
    assert cfg.extra.tuned.budget.episodes == episode_budget(TuneSettings(), cap)
    assert cfg.extra.tuned.budget.trials == 20
    assert cfg.train.episodes == 2000 and cfg.network.width == 2500


@pytest.mark.parametrize("env", ["cartpole", "acrobot", "mountaincar"])
def test_the_online_sweep_gives_double_dqn_the_designs_data_and_budget(env: str) -> None:
    """sweeps/like_online.yaml: Double DQN learning from each transition once, in temporal
    order, with the settings of its own study of the like-for-like presets' budget."""
    cfg = _compose_sweep("like_online", [f"env={env}", "controller=ddqn"], hydra=False)
    validate(OmegaConf.to_object(cfg))
    assert cfg.weights.name == f"tuned_{env}-ddqn_online" and cfg.env.name == env
    c = cfg.controller
    assert (c.buffer_size, c.batch_size, c.train_freq, c.learning_starts) == (1, 1, 1, 1)
    like = _compose_sweep("like", [f"env={env}", "controller=ddqn"], hydra=False)
    assert cfg.extra.tuned.budget == like.extra.tuned.budget
    assert (cfg.seed, cfg.train.population, cfg.train.episodes, cfg.network.width) == (
        like.seed,
        like.train.population,
        like.train.episodes,
        like.network.width,
    )
    assert cfg.tracking.experiment != like.tracking.experiment  # a table of its own


def test_every_job_of_the_paper_sweep_is_a_valid_configuration() -> None:
    for env in ("cartpole", "acrobot", "mountaincar"):
        for controller in ("h2", "hinf", "hinf_f", "ddqn"):
            cfg = _compose_sweep("paper", [f"env={env}", f"controller={controller}"], False)
            validate(OmegaConf.to_object(cfg))
            assert (cfg.train.episodes, cfg.network.width, cfg.train.lr) == (2000, 2500, 5e-5)
            assert (cfg.weights.name, cfg.train.population, cfg.seed) == (env, 10, 0)


def test_the_command_line_composes_the_paper_sweep(tmp_path: Path) -> None:
    """``python -m cdqn.train --config-dir sweeps --config-name paper --cfg job``."""
    out = run_cli("cdqn.train", ["--config-dir", str(SWEEPS), "--config-name", "paper",
                                 "hydra/launcher=slurm", "--cfg", "job"], tmp_path)  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    job = OmegaConf.create(out.stdout)
    assert job.train.population == 10 and job.tracking.skip_finished is True


def test_config_hash_ignores_where_and_how_a_run_is_recorded() -> None:
    base = compose_config(["seed=1"])
    same = compose_config(
        [
            "seed=1",
            "tracking.uri=sqlite:////elsewhere/m.db",
            "tracking.skip_finished=true",
            "train.progress=false",
            "train.checkpoint_every=7",
            "train.population=4",
        ]
    )
    assert config_hash(base) == config_hash(same)
    assert config_hash(base) != config_hash(compose_config(["seed=2"]))
    assert config_hash(base) != config_hash(compose_config(["seed=1", "train.lr=1e-4"]))
    assert config_hash(base) != config_hash(compose_config(["seed=1", "env=acrobot"]))


def test_config_hash_of_runs_recorded_before_own_targets_existed_is_kept() -> None:
    """A configuration with no controller's own learning target hashes as it did without the
    setting (runs of earlier versions still count); one with an own range does not."""
    base = compose_config(["env=acrobot", "controller=hinf_f"])
    before = OmegaConf.to_container(base, resolve=True)
    del before["weights"]["controller_target"]
    assert config_hash(base) == config_hash(before)
    own = compose_config(
        [
            "env=acrobot",
            "controller=hinf_f",
            "weights.controller_target.hinf_f.gamma_eff=[0.9,0.95]",
        ]
    )
    assert config_hash(own) != config_hash(base)


TINY = [
    "network.width=16",
    "train.episodes=2",
    "train.progress=false",
    "train.checkpoint_every=0",
    "controller=hinf_f",
    "tracking.skip_finished=true",
]


def test_a_restarted_run_skips_a_finished_one_and_retrains_a_failed_one(
    tracking_uri: str, caplog: pytest.LogCaptureFixture
) -> None:
    cfg = compose_config([*TINY, f"tracking.uri={tracking_uri}", "seed=0"])
    first = run(cfg, progress=False)
    with caplog.at_level(logging.INFO, logger="cdqn"):
        again = run(cfg, progress=False)
    assert (again.run_id, again.status) == (first.run_id, "FINISHED")
    assert again.final_score == pytest.approx(first.final_score)
    assert "skipping cartpole/hinf_f seed 0" in caplog.text
    assert len(runs_of(tracking_uri)) == 1
    MlflowClient(tracking_uri).set_terminated(first.run_id, "FAILED")
    retrained = run(cfg, progress=False)
    assert retrained.run_id != first.run_id and len(runs_of(tracking_uri)) == 2
    other = run(compose_config([*TINY, f"tracking.uri={tracking_uri}", "seed=1"]), False)
    assert other.run_id not in (first.run_id, retrained.run_id)


def test_a_restarted_population_trains_only_the_missing_seeds(
    tracking_uri: str, caplog: pytest.LogCaptureFixture
) -> None:
    run(compose_config([*TINY, f"tracking.uri={tracking_uri}", "seed=1"]), progress=False)
    cfg = compose_config([*TINY, f"tracking.uri={tracking_uri}", "seed=0", "train.population=3"])
    with caplog.at_level(logging.INFO, logger="cdqn"):
        result = run_population(cfg)
    assert "skipping cartpole/hinf_f seed 1" in caplog.text
    runs = runs_of(tracking_uri)
    assert sorted(r.data.tags["seed"] for r in runs) == ["0", "1", "2"]
    assert [r.status for r in result.members] == ["FINISHED"] * 3
    assert len(runs_of(tracking_uri)) == 3
    assert run_population(cfg).summary().run_id == result.summary().run_id  # all skipped
    assert len(runs_of(tracking_uri)) == 3


@pytest.mark.slow
def test_parallel_jobs_can_open_a_fresh_sqlite_store(tmp_path: Path) -> None:
    """Three processes create the same fresh store and experiment at once (unguarded, the
    first migration of a fresh SQLite store fails in all but one and corrupts it)."""
    uri = f"sqlite:///{tmp_path / 'fresh.db'}"
    with multiprocessing.get_context("spawn").Pool(3) as pool:
        pool.starmap(ensure_store, [(uri, "cdqn")] * 3)
    client = MlflowClient(uri)
    assert [e.name for e in client.search_experiments()].count("cdqn") == 1
    client.create_run(client.get_experiment_by_name("cdqn").experiment_id)


def test_the_store_is_prepared_before_a_multirun_starts(tmp_path: Path) -> None:
    cfg = compose_config([f"tracking.uri=sqlite:///{tmp_path / 'sweep.db'}"])
    PrepareStore().on_multirun_start(cfg)
    assert (tmp_path / "sweep.db").exists()
    assert MlflowClient(cfg.tracking.uri).get_experiment_by_name("cdqn") is not None


def _start_sweep(args: list[str], folder: Path) -> subprocess.Popen[bytes]:
    """``python -m cdqn.train <args>`` started in ``folder`` as its own process group (its
    workers with it), output discarded."""
    return subprocess.Popen(
        [sys.executable, "-m", "cdqn.train", *args],
        cwd=folder,
        env={**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )


def test_a_stopped_multirun_starts_no_queued_job_and_returns_each_jobs_exit(
    tmp_path: Path,
) -> None:
    """The local launcher's task function: a job's ``SystemExit`` comes back as its exit
    status, and once a signal has left its status in the stop file no queued job starts."""
    from hydra_plugins.cdqn_launcher.cdqn_launcher import ExitAsValue, JobExit

    started: list[int] = []

    def job(cfg: DictConfig) -> float:
        started.append(cfg.n)
        if cfg.n == 2:
            sys.exit(128 + signal.SIGTERM)  # as a run that SIGTERM stopped
        return 1.5

    stop = tmp_path / "stop"
    task = ExitAsValue(job, stop)
    assert task(OmegaConf.create({"n": 1})) == 1.5
    assert task(OmegaConf.create({"n": 2})) == JobExit(143)
    stop.write_text("143")  # what the launcher's SIGTERM handler leaves
    assert task(OmegaConf.create({"n": 3})) == JobExit(143)
    assert started == [1, 2]


@pytest.mark.slow
def test_a_local_sweep_stopped_by_sigterm_continues_then_skips_what_finished(
    tmp_path: Path,
) -> None:
    """The smoke sweep through the joblib launcher (two populations of two seeds, side by
    side) gets SIGTERM in its parent process alone (as from ``kill <pid>`` or ``timeout``)
    while both train: the workers stop too, each member is KILLED with its checkpoint,
    nothing of the command is left running and it exits with 143.  The same command again
    continues the same runs to FINISHED; a third time skips all four (a real multirun with a
    real store)."""
    args = ["-m", "--config-dir", str(SWEEPS), "--config-name", "smoke", "env=cartpole",
            "controller=hinf_f,hinf", "train.episodes=1000", "train.checkpoint_every=10",
            "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={tmp_path / 'multirun'}"]  # fmt: skip
    proc = _start_sweep(args, tmp_path)
    deadline = time.monotonic() + 300
    try:
        while proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.005)
            if len(list(tmp_path.glob(CHECKPOINTS))) == 4:  # both populations mid-way
                break
        assert proc.poll() is None, "the sweep ended before it could be stopped"
        proc.send_signal(signal.SIGTERM)  # the parent only, not its process group
        assert proc.wait(120) == 128 + signal.SIGTERM
        while time.monotonic() < deadline:  # the workers end with it
            try:
                os.killpg(proc.pid, 0)
            except ProcessLookupError:
                break
            time.sleep(0.05)
        else:
            pytest.fail("workers of the stopped sweep are still running")
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(30)
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    stopped = _by_member(uri)
    assert len(stopped) == 4 and {r.info.status for r in stopped.values()} == {"KILLED"}
    assert all("SIGTERM" in r.data.tags["failure_reason"] for r in stopped.values())

    again = run_cli("cdqn.train", args, tmp_path, timeout=600)
    assert again.returncode == 0, again.stderr[-2000:]
    continued = _by_member(uri)
    assert sorted(continued) == sorted(stopped)
    for key, r in continued.items():
        assert r.info.run_id == stopped[key].info.run_id and r.info.status == "FINISHED"
        assert len(episode_returns(MlflowClient(uri), r.info.run_id)) == 1000

    out = run_cli("cdqn.train", args, tmp_path, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert (out.stdout + out.stderr).count("skipping") == 4
    assert {r.info.run_id for r in runs_of(uri)} == {r.info.run_id for r in stopped.values()}


RESTART = [
    "env=cartpole",
    "controller=hinf_f,ddqn",
    "seed=range(2)",  # the cdqn sweeper makes each controller's two seeds one population
    "network=small",
    "controller.learning_starts=50",
    "train.episodes=400",  # both populations train long enough to be caught mid-way
    "controller.train_freq=1",  # Double DQN: a minibatch every step (slower, caught mid-way too)
    "train.checkpoint_every=10",
    "tracking.skip_finished=true",
    "hydra.launcher.n_jobs=2",
]


def _by_member(uri: str) -> dict[tuple[str, str], object]:
    return {(r.data.tags["controller"], r.data.tags["seed"]): r for r in runs_of(uri)}


CHECKPOINTS = "mlruns/*/*/artifacts/checkpoint/slot-a/state.pt"


@pytest.mark.slow
def test_a_killed_sweep_started_again_continues_itsruns_of(tmp_path: Path) -> None:
    """A real sweep (joblib launcher, two jobs in parallel: each controller's two seeds as one
    population, batched by the cdqn sweeper) gets SIGKILL in its whole process group while
    both jobs are mid-way (or, where the launcher runs them one after the other, while the
    second is); the same command again
    continues the runs it left RUNNING (no new runs) and the final store equals an
    uninterrupted sweep's: returns and signal rows of every seed."""
    folders = {name: tmp_path / name for name in ("reference", "killed")}

    def sweep(folder: Path) -> list[str]:
        """The arguments of ``python -m cdqn.train`` that sweep into ``folder``."""
        return ["-m", *RESTART, f"hydra.sweep.dir={folder / 'multirun'}"]

    for folder in folders.values():
        folder.mkdir()
    ref = run_cli("cdqn.train", sweep(folders["reference"]), folders["reference"], 600)
    assert ref.returncode == 0, ref.stderr[-3000:]
    assert "cdqn sweeper: 4 jobs as 2" in ref.stdout + ref.stderr
    uri = f"sqlite:///{folders['killed'] / 'mlflow.db'}"
    proc = _start_sweep(sweep(folders["killed"]), folders["killed"])
    deadline = time.monotonic() + 300
    try:
        # watch the artifact folders, not the store (a query takes longer than a small
        # population's whole run).  A population writes every member's checkpoint at once and
        # a FINISHED run's are deleted.  The launcher may run the two jobs side by side (kill
        # once all four runs have a checkpoint: both mid-way) or one after the other (kill
        # once a job has finished and the other one's runs have checkpoints)
        seen: set[Path] = set()
        while proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.005)
            now = {p.parents[3] for p in folders["killed"].glob(CHECKPOINTS)}
            seen |= now
            if len(now) == 4 or (len(now) >= 2 and seen - now):
                break
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(30)
    before = _by_member(uri)
    left = sorted(k for k, r in before.items() if r.info.status != "FINISHED")
    assert left, "the sweep ended before it could be killed"

    again = run_cli("cdqn.train", sweep(folders["killed"]), folders["killed"], 600)
    assert again.returncode == 0, again.stderr[-3000:]
    after = _by_member(uri)
    reference = _by_member(f"sqlite:///{folders['reference'] / 'mlflow.db'}")
    assert sorted(after) == sorted(reference) and len(after) == 4
    for key, r in after.items():
        if key in before:  # continued in the same run, not trained again in a new one
            assert r.info.run_id == before[key].info.run_id
        assert r.info.status == "FINISHED" and r.data.tags["population"] == "0-1"
        client = MlflowClient(uri)
        other = MlflowClient(f"sqlite:///{folders['reference'] / 'mlflow.db'}")
        ours = episode_returns(client, r.info.run_id)
        assert len(ours) == 400 and ours == episode_returns(other, reference[key].info.run_id)
        assert signal_table(client, r.info.run_id).equals(
            signal_table(other, reference[key].info.run_id)
        )
    resumed = [k for k in left if after[k].data.tags.get("resume_count")]
    assert resumed == [k for k in left if k in before], (left, resumed)
    print("continued after SIGKILL:", left)


def test_a_sweep_config_finds_the_users_presets(tmp_path: Path) -> None:
    """``--config-dir sweeps --config-name like`` takes each job's weights from
    ``tuned_<env>-<controller>``: the pre-check finds them in a ``hydra.searchpath`` folder
    (beside conf/), and names a missing one in one line."""
    from cdqn.cli import check_overrides

    env = "cartpole_pole"  # an environment preset whose agents conf/weights has no tuned presets of
    assert not list((CONF_DIR / "weights").glob(f"tuned_{env}-*.yaml"))
    src = (CONF_DIR / "weights" / f"{env}.yaml").read_text()
    (tmp_path / "weights").mkdir()
    (tmp_path / "weights" / f"tuned_{env}-h2.yaml").write_text(src)
    common = [f"env={env}", f"hydra.searchpath=[file://{tmp_path}]", "train.episodes=2"]
    assert check_overrides([*common, "controller=h2"], True, "like", config_dir=SWEEPS) == []
    (msg,) = check_overrides([*common, "controller=h2,hinf"], True, "like", config_dir=SWEEPS)
    assert f"tuned_{env}-hinf" in msg
