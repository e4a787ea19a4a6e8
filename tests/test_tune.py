"""``python -m cdqn.tune``: an Optuna study of certified designs, each trial a population, in a
real MLflow store and a real Optuna SQLite storage."""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path

import numpy as np
import optuna
import pytest
from hydra import compose, initialize_config_dir
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig, OmegaConf

from cdqn.cli import check_overrides
from cdqn.control.target import stable_over_box
from cdqn.training.batching import batchable
from cdqn.training.store import place_migrated
from cdqn.tune import check_tune
from cdqn.tuning.objective import area, ma100, padded
from cdqn.tuning.pruner import EpisodeMedianPruner
from cdqn.tuning.report import summary_text
from cdqn.tuning.settings import ParamSpec, PrunerConfig, TuneSettings, episode_budget, warmup
from cdqn.tuning.space import (
    apply,
    discount_of,
    fit_to_box,
    fit_to_budget,
    fit_to_observation,
    highest_floor,
    log_horizon_of,
    lowest,
    sample,
)
from cdqn.tuning.study import Study, _sampler, _with_controller
from tests.conftest import CONF_DIR
from tests.helpers import run_cli

REPO = Path(__file__).resolve().parents[1]


def _store(uri: str, experiment: str, tmp: Path) -> None:
    """Create the experiment of the store at ``uri`` with its artifacts under ``tmp`` (a
    SQLite store's default artifact root is ./mlruns of the working folder)."""
    place_migrated(uri)
    client = MlflowClient(uri)
    if client.get_experiment_by_name(experiment) is None:
        client.create_experiment(experiment, (tmp / "mlartifacts").as_uri())


ONLY_TARGET = [
    f"~tune.space.{d}"
    for d in (
        "normalize",
        "rbf",
        "eps_schedule",
        "eps_dec_action",
        "eps_dec_episode",
        "lr",
        "reset_integrator",
        "eps_end",
    )
]
"""The shared dimensions and α left out: these studies search the learning target alone."""


def _overrides(tmp: Path, study: str, trials: int, extra: list[str] | None = None) -> list[str]:
    _store(f"sqlite:///{tmp / 'mlflow.db'}", "cdqn-tune", tmp)
    return [
        f"tracking.uri=sqlite:///{tmp / 'mlflow.db'}",
        f"tune.storage=sqlite:///{tmp / 'optuna.db'}",
        f"tune.preset_dir={tmp / 'presets'}",
        f"controller.synthesis.cache_dir={tmp / 'cache'}",
        "network.width=16",
        f"tune.study={study}",
        f"tune.trials={trials}",
        "tune.seeds=2",
        "tune.episodes=12",
        "tune.eval_seeds=2",
        "tune.pruner.interval=4",
        "tune.pruner.startup_trials=1",
        "tune.pruner.warmup_episodes=4",
        # two feasible centres of γ_eff, the step scale around the CartPole design's
        "tune.space.gamma_eff.choices=null",  # centres in [low, high], not the default's
        "tune.space.gamma_eff.horizon=false",  # the tests' centres are discounts,
        "tune.space.gamma_eff.width=0.1",  # ranges [c - 0.05, c + 0.05]
        "tune.space.gamma_eff.low=-0.95",
        "tune.space.gamma_eff.high=-0.6",
        "tune.space.step_scale.low=0.6",
        "tune.space.step_scale.high=0.8",
        "~tune.space.w_p",
        *ONLY_TARGET,
        "controller.synthesis.ntk_bounds=config",  # CartPole's box: 1/ρ_max = 1/1.2
        *(
            f"{k}={v}"
            for k, v in TEST_DEFAULTS.items()
            if not any(e.startswith(f"{k}=") for e in extra or [])
        ),  # the test's own value where it gives one
        *(extra or []),
    ]


TEST_DEFAULTS = {"tune.recheck_trials": 0, "tune.eval_processes": 1, "tune.warm_start": "[]"}
"""What a test study does unless the test asks otherwise: no rechecks, its evaluation in the
study's own process (the end-to-end test trains them, split over processes), and every trial
sampled (tests/test_tune_warm_start.py starts from presets)."""


def _study(overrides: list[str]) -> dict:
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("tune", overrides=overrides)
    return Study(cfg).run()


def _runs(tmp: Path, **tags: str) -> list:
    client = MlflowClient(f"sqlite:///{tmp / 'mlflow.db'}")
    exp = client.get_experiment_by_name("cdqn-tune")
    query = " and ".join(f"tags.{k} = '{v}'" for k, v in tags.items())
    return client.search_runs([exp.experiment_id], query, max_results=1000)


def test_objective_is_the_mean_area_under_ma100() -> None:
    r = [0.0, 10.0, 20.0]
    assert ma100(r).tolist() == [0.0, 5.0, 10.0]
    assert area([r, [30.0, 30.0, 30.0]]) == pytest.approx((5.0 + 30.0) / 2)
    assert padded([3.0, 1.0], 4, failed=True) == [3.0, 1.0, 1.0, 1.0]
    assert padded([3.0, 1.0], 4, failed=False) is None
    assert ma100(list(range(150)))[-1] == pytest.approx(np.mean(range(50, 150)))


def _frozen(number: int, values: dict[int, float], complete: bool) -> optuna.trial.FrozenTrial:
    state = optuna.trial.TrialState.COMPLETE if complete else optuna.trial.TrialState.RUNNING
    trial = optuna.trial.create_trial(
        state=state, value=max(values.values()) if complete else None,
        intermediate_values=values,
    )  # fmt: skip
    trial.number = number
    return trial


def test_pruner_compares_the_current_value_at_the_same_episode() -> None:
    """J_n of a trial whose first episodes gave its best value: Optuna's MedianPruner keeps it
    (its best value beats the median), the project's pruner stops it (its J_n does not)."""
    study = optuna.create_study(direction="maximize")
    for i, values in enumerate(({25: 20.0, 50: 30.0}, {25: 21.0, 50: 32.0})):
        study.add_trial(_frozen(i, values, complete=True))
    losing = _frozen(2, {25: 40.0, 50: 15.0}, complete=False)  # random play, then worse
    winning = _frozen(3, {25: 10.0, 50: 33.0}, complete=False)
    ours = EpisodeMedianPruner(startup_trials=2, warmup_episodes=50)
    assert ours.prune(study, losing) and not ours.prune(study, winning)
    assert not optuna.pruners.MedianPruner(2, 50).prune(study, losing)
    # before the warm-up, before startup_trials complete trials, at an episode no
    # complete trial reported: never pruned
    assert not EpisodeMedianPruner(2, 60).prune(study, losing)
    assert not EpisodeMedianPruner(3, 50).prune(study, losing)
    assert not ours.prune(study, _frozen(4, {25: 40.0, 40: 1.0}, complete=False))
    # negative rewards: J_n falls for every trial; the lower one at the same episode loses
    neg = optuna.create_study(direction="maximize")
    neg.add_trial(_frozen(0, {25: -100.0, 50: -150.0}, complete=True))
    one = EpisodeMedianPruner(startup_trials=1, warmup_episodes=50)
    falling = _frozen(1, {25: -90.0, 50: -160.0}, complete=False)
    assert one.prune(neg, falling) and not optuna.pruners.MedianPruner(1, 50).prune(neg, falling)
    assert not one.prune(neg, _frozen(1, {25: -110.0, 50: -140.0}, complete=False))


@pytest.mark.slow
def test_clearly_losing_trial_is_pruned_at_an_intermediate_episode(tmp_path: Path) -> None:
    """A real study of two specifications on the same CartPole seeds: γ_eff ≈ −0.9 learns
    (J_n rises to 39.3, final MA100 36) and completes first; γ_eff ≈ 0.6 peaks at J_30 ≈ 40
    during the early, mostly random episodes, then falls (J_80 ≈ 37.7 against 39.1; final
    MA100 26 when trained to the end).  It is pruned at episode 80; Optuna's MedianPruner,
    comparing its best value (the early peak), would have kept it."""
    over = _overrides(tmp_path, "prune", 2, [
        "~tune.space.step_scale",
        "~tune.space.replay",
        "tune.space.gamma_eff.choices=[-0.9,0.6]",
        "weights.target.step_scale=[0.6,0.8]",  # the specification the curves below come from
        "tune.episodes=100",
        "tune.eval_seeds=0",
        "tune.pruner.interval=10",
        "tune.pruner.warmup_episodes=80",
        "train.lr=1e-3",      # learning (or failing) shows within 100 episodes
        "train.eps_dec=1e-2",
    ])  # fmt: skip
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    queued = optuna.create_study(study_name="prune", storage=storage, direction="maximize")
    queued.enqueue_trial({"gamma_eff": -0.9})
    queued.enqueue_trial({"gamma_eff": 0.6})
    summary = _study(over)
    assert summary["counts"] == {"complete": 1, "pruned": 1, "infeasible": 0, "failed": 0}
    good, bad = optuna.load_study(study_name="prune", storage=storage).trials
    assert good.params == {"gamma_eff": -0.9} and good.state.name == "COMPLETE"
    assert sorted(good.intermediate_values) == list(range(10, 101, 10))
    assert "final_score" in good.user_attrs
    assert bad.params == {"gamma_eff": 0.6} and bad.state.name == "PRUNED"
    assert bad.user_attrs["pruned_at"] == 80 == bad.last_step
    assert bad.intermediate_values[80] < good.intermediate_values[80]
    assert max(bad.intermediate_values.values()) > good.intermediate_values[80]
    late = optuna.load_study(study_name="prune", storage=storage)
    assert not optuna.pruners.MedianPruner(1, 80).prune(late, bad)  # the best-value rule
    runs = {r.data.tags["trial"]: r for r in _runs(tmp_path, kind="trial")}
    assert runs["1"].data.tags["trial_status"] == "pruned"
    assert "pruned at episode 80" in runs["1"].data.tags["reason"]
    members = _runs(tmp_path, **{"mlflow.parentRunId": runs["1"].info.run_id})
    assert len(members) == 2 and "KILLED" in {m.info.status for m in members}
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    for m in members:  # a pruned trial is not trained again: its checkpoints are gone
        assert "pruned at episode 80" in m.data.tags["failure_reason"]
        assert not client.list_artifacts(m.info.run_id, "checkpoint")
    assert runs["0"].data.tags["trial_status"] == "complete"
    assert not (REPO / "mlruns").exists() or not any(
        (REPO / "mlruns").rglob(runs["0"].info.run_id)
    )  # the artifacts went to the test's folder
    assert (tmp_path / "mlartifacts").is_dir()


@pytest.mark.filterwarnings("ignore:Heartbeat of storage:UserWarning")
def test_a_stale_trial_is_retried_with_its_specification(monkeypatch, tmp_path: Path) -> None:
    """The storage of a study: a trial whose process stopped beating (a killed worker) is
    failed once its heartbeat is older than the grace period and queued again with its
    specification, once; the storage is built without Optuna's deprecation warnings."""
    import time
    import warnings

    import cdqn.tuning.storage as tune

    monkeypatch.setattr(tune, "HEARTBEAT", 1)
    with warnings.catch_warnings():
        warnings.simplefilter("error", FutureWarning)
        storage = tune.open_storage(f"sqlite:///{tmp_path / 'optuna.db'}")
    study = optuna.create_study(study_name="hb", storage=storage, direction="maximize")
    trial = study.ask()
    trial.suggest_float("gamma_eff", -0.9, 0.9)
    storage.record_heartbeat(trial._trial_id)  # then the process dies
    time.sleep(3 * tune.HEARTBEAT + 1.5)
    optuna.storages.fail_stale_trials(study)
    stale, retry = study.get_trials()
    assert stale.state.name == "FAIL"
    assert retry.state.name == "WAITING" and retry.params == stale.params
    retried = study.ask()  # the retry runs first, with the same specification
    assert retried.number == retry.number and retried.params == stale.params
    storage.record_heartbeat(retried._trial_id)
    time.sleep(3 * tune.HEARTBEAT + 1.5)
    optuna.storages.fail_stale_trials(study)
    assert [t.state.name for t in study.get_trials()] == ["FAIL", "FAIL"]  # once only


SPLIT = ["tune.recheck_trials=3", "tune.eval_processes=0"]
"""The end-to-end test's rechecks, and its evaluations split over one process per core."""


@pytest.mark.slow
def test_study_end_to_end_resume_and_preset(tmp_path: Path) -> None:
    first = _study(_overrides(tmp_path, "tiny", 2, SPLIT))
    assert sum(first["counts"].values()) == 2
    parent = first["parent_run"]
    # run again with more trials: the same study (storage) and parent run continue
    second = _study(_overrides(tmp_path, "tiny", 3, SPLIT))
    assert second["parent_run"] == parent
    study = optuna.load_study(study_name="tiny", storage=f"sqlite:///{tmp_path / 'optuna.db'}")
    assert len(study.trials) == 3
    assert study.trials[2].params != study.trials[0].params  # the sampler continued
    assert second["counts"]["complete"] >= 1

    trials = _runs(tmp_path, kind="trial")
    assert sorted(r.data.tags["trial"] for r in trials) == ["0", "1", "2"]
    for r in trials:
        assert r.data.tags["mlflow.parentRunId"] == parent
        assert r.data.tags["trial_status"] in ("complete", "pruned")
        assert r.data.tags["certificate"] == "PASSED"
        assert {"gamma_eff", "step_scale", "replay"} <= set(r.data.params)
        members = _runs(tmp_path, **{"mlflow.parentRunId": r.info.run_id})
        assert len(members) == 2
        if r.data.tags["trial_status"] == "complete":
            assert r.info.status == "FINISHED" and "objective" in r.data.metrics
            assert {m.info.status for m in members} == {"FINISHED"}
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    run = client.get_run(parent)
    assert run.info.status == "FINISHED"
    assert run.data.metrics["best_value"] == pytest.approx(second["best_value"])
    assert "eval_objective" in run.data.metrics
    arts = {a.path for a in client.list_artifacts(parent, "study")}
    assert {"study/optimization_history.png", "study/trials.json"} <= arts
    ev = second["evaluation"]
    assert ev["seeds"] == [1000, 1001] and np.isfinite(ev["objective"])
    assert "best trial" in summary_text(second)

    # the best complete trials by J are trained again on seeds of their own; the best final
    # score over all its seeds is chosen, and a second close reuses the first's rechecks
    rows = second["recheck"]
    complete = [tr for tr in study.trials if tr.state == optuna.trial.TrialState.COMPLETE]
    assert len(rows) == min(3, len(complete)) >= 2
    by_number = {tr.number: tr for tr in study.trials}
    for row in rows:
        assert row["all"] == pytest.approx((2 * row["objective"] + 4 * row["recheck"]) / 6)
        assert row["final"] == by_number[row["trial"]].user_attrs["final_score"]
        both = (2 * row["final"] + 4 * row["recheck_final"]) / 6
        assert row["final_all"] == pytest.approx(both)
    assert second["best_trial"] == max(rows, key=lambda r: (r["final_all"], r["all"]))["trial"]
    assert second["best_value"] == pytest.approx(study.trials[second["best_trial"]].value)
    rechecks = _runs(tmp_path, kind="recheck")
    names = sorted(r.info.run_name for r in rechecks)
    assert len(names) == len(set(names)) >= len(rows)  # each trial rechecked once
    assert {r.data.tags["seeds"] for r in rechecks} == {"200-203"}
    assert "recheck of trial" in summary_text(second)

    # the preset trains with python -m cdqn.train weights=<name>
    preset = Path(second["preset"])
    assert preset == tmp_path / "presets" / "weights" / "tuned_tiny.yaml"
    proc = _train_with_preset(tmp_path)
    assert proc.returncode == 0, proc.stderr
    tc = MlflowClient(f"sqlite:///{tmp_path / 'train.db'}")
    (trained,) = tc.search_runs([tc.get_experiment_by_name("cdqn").experiment_id])
    assert trained.data.params["weights.name"] == "tuned_tiny"
    best_centre = second["best_params"]["gamma_eff"]
    assert json.loads(trained.data.params["weights.target.gamma_eff"]) == pytest.approx(
        [best_centre - 0.05, best_centre + 0.05]
    )


def _train_with_preset(tmp: Path):
    _store(f"sqlite:///{tmp / 'train.db'}", "cdqn", tmp)
    return run_cli(
        "cdqn.train",
        [
            "weights=tuned_tiny",
            f"hydra.searchpath=[file://{tmp / 'presets'}]",
            "controller=hinf_f",
            "controller.design=synthesize",
            f"controller.synthesis.cache_dir={tmp / 'cache'}",
            "network.width=16",
            "train.episodes=3",
            "train.progress=false",
            f"tracking.uri=sqlite:///{tmp / 'train.db'}",
            f"hydra.run.dir={tmp / 'train-out'}",
        ],
        REPO,
    )


def test_infeasible_specification_is_pruned_with_its_reason(tmp_path: Path) -> None:
    over = _overrides(tmp_path, "infeasible", 1, [
        "~tune.space.step_scale",
        "~tune.space.replay",
        "tune.space.gamma_eff.choices=[0.9]",  # γ_eff ∈ [0.85, 0.95] > 1/ρ_max = 1/1.2
    ])  # fmt: skip
    summary = _study(over)
    assert summary["counts"] == {"complete": 0, "pruned": 0, "infeasible": 1, "failed": 0}
    study = optuna.load_study(study_name="infeasible",
                              storage=f"sqlite:///{tmp_path / 'optuna.db'}")  # fmt: skip
    (trial,) = study.trials
    assert trial.state == optuna.trial.TrialState.PRUNED
    assert "conflicts with the NTK box" in trial.user_attrs["reason"]
    (run,) = _runs(tmp_path, kind="trial")
    assert run.data.tags["trial_status"] == "infeasible"
    assert "1/ρ_max" in run.data.tags["reason"]
    assert not _runs(tmp_path, **{"mlflow.parentRunId": run.info.run_id})  # never trained
    assert not (tmp_path / "presets").exists()
    assert summary["no_result"].startswith("no trial completed: 1 infeasible (each trial")
    (parent,) = _runs(tmp_path, kind="tune")
    assert parent.info.status == "FAILED" and parent.data.tags["best"].startswith("none: ")


def test_cli_study_without_a_complete_trial_exits_1_and_says_why(tmp_path: Path) -> None:
    """Every specification refused before training: the study prints why and what to change,
    writes no preset, and exits 1."""
    over = _overrides(tmp_path, "refused", 1, [
        "~tune.space.step_scale", "~tune.space.replay", "tune.space.gamma_eff.choices=[0.9]",
    ])  # fmt: skip
    proc = run_cli("cdqn.tune", over, tmp_path)
    assert proc.returncode == 1, proc.stderr[-3000:]
    last = proc.stdout.strip().splitlines()[-1]
    assert last.startswith("no trial completed: 1 infeasible") and "tune.trials" in last, last
    assert last.endswith("; no preset written") and "Traceback" not in proc.stderr
    assert not (tmp_path / "presets").exists()


@pytest.mark.parametrize(
    ("sampler_seed", "counts"),
    [(0, {"complete": 2, "pruned": 0, "infeasible": 1, "failed": 0}),  # one refused, two trained
     (2, {"complete": 0, "pruned": 0, "infeasible": 2, "failed": 0})],  # as many refused: stop
)  # fmt: skip
def test_an_infeasible_specification_does_not_use_up_the_budget(
    tmp_path: Path, sampler_seed: int, counts: dict[str, int]
) -> None:
    """``tune.trials`` counts the trials that train: a specification refused before training
    (γ_eff ∈ [0.85, 0.95] against 1/ρ_max = 1/1.2) is followed by another, until two train
    or two have been refused."""
    over = _overrides(tmp_path, "budget", 2, [
        "~tune.space.step_scale", "~tune.space.replay", "tune.pruner.kind=none",
        "tune.space.gamma_eff.choices=[0.9,-0.8]", f"tune.sampler_seed={sampler_seed}",
        "tune.eval_seeds=0",
    ])  # fmt: skip
    assert _study(over)["counts"] == counts


def test_cli_refuses_overlapping_seeds(tmp_path: Path) -> None:
    proc = run_cli("cdqn.tune", ["tune.seed=0", "tune.seeds=3", "tune.eval_seed=2"], tmp_path)
    assert proc.returncode == 2
    assert "tune.eval_seed=2" in proc.stderr and "overlap" in proc.stderr
    assert not (tmp_path / "optuna.db").exists()


def test_cli_refuses_recheck_seeds_that_overlap(tmp_path: Path) -> None:
    proc = run_cli("cdqn.tune", ["tune.recheck_seed=1005"], tmp_path)
    assert proc.returncode == 2
    assert "tune.recheck_seed=1005" in proc.stderr and "overlap" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "optuna.db").exists()


@pytest.mark.slow
def test_interrupted_study_continues_with_the_cut_trial(tmp_path: Path) -> None:
    import signal
    import subprocess
    import sys
    import time

    args = [
        *_overrides(tmp_path, "cut", 1, ["tune.episodes=20000", "tune.eval_seeds=0"]),
        "hydra.run.dir=" + str(tmp_path / "out"),
    ]
    log = (tmp_path / "first.log").open("w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "cdqn.tune", *args],
        cwd=REPO,
        stdout=log,
        stderr=subprocess.STDOUT,
        text=True,
    )
    deadline = time.time() + 240
    while "MLflow run" not in (tmp_path / "first.log").read_text():  # the population trains
        assert proc.poll() is None and time.time() < deadline, (tmp_path / "first.log").read_text()
        time.sleep(0.5)
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)  # a real signal: the population stops, the study exits
    assert proc.wait(timeout=240) == 130, (tmp_path / "first.log").read_text()
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    (cut,) = optuna.load_study(study_name="cut", storage=storage).trials
    assert cut.state == optuna.trial.TrialState.FAIL and cut.user_attrs["status"] == "interrupted"
    (run,) = _runs(tmp_path, kind="trial")
    assert run.info.status == "KILLED" and run.data.tags["trial_status"] == "failed"

    over = _overrides(tmp_path, "cut", 1, ["tune.episodes=20", "tune.eval_seeds=0"])
    summary = _study(over)  # the same command again: the cut specification is trained
    study = optuna.load_study(study_name="cut", storage=storage)
    assert [t.state.name for t in study.trials] == ["FAIL", "COMPLETE"]
    assert study.trials[1].params == cut.params and study.user_attrs["retried"] == [0]
    assert summary["counts"]["complete"] == 1 and summary["counts"]["failed"] == 0


def test_cli_refuses_a_negative_worker_index(tmp_path: Path) -> None:
    proc = run_cli("cdqn.tune", ["-m", "tune.worker=0,-1"], tmp_path)
    assert proc.returncode == 2
    assert "tune.worker=-1: must be an integer >= 0" in proc.stderr
    assert not (tmp_path / "optuna.db").exists()


def test_the_samplers_settings_reach_tpe_and_a_bad_one_is_refused(tmp_path: Path) -> None:
    """``tune.sampler_startup`` and ``tune.sampler_multivariate`` become the TPE sampler's
    random start and joint model; worker 1 continues another stream than worker 0."""
    joint = _sampler(TuneSettings(sampler_startup=4, sampler_multivariate=True), 7)
    apart = _sampler(TuneSettings(), 7)
    assert (joint._n_startup_trials, joint._multivariate, joint._group) == (4, True, True)
    assert (apart._n_startup_trials, apart._multivariate) == (10, False)
    draws = [
        _sampler(TuneSettings(worker=w), 7)._rng.rng.random() for w in (0, 0, 1)
    ]  # fmt: skip
    assert draws[0] == draws[1] != draws[2]
    proc = run_cli("cdqn.tune", ["tune.sampler_startup=0"], tmp_path)
    assert proc.returncode == 2
    assert "tune.sampler_startup=0: must be an integer >= 1" in proc.stderr


@pytest.mark.slow
def test_two_workers_through_the_joblib_launcher_share_one_study(tmp_path: Path) -> None:
    """A real multirun (hydra-joblib-launcher, two processes, ``tune.worker=0,1``) of a
    5-trial study: exactly 5 trials in all, both workers ran trials at the same time, one
    MLflow parent run that every trial and the one evaluation are children of."""

    args = [
        "-m",
        "hydra/launcher=local",
        "hydra.launcher.n_jobs=2",
        "tune.worker=0,1",
        f"hydra.sweep.dir={tmp_path / 'multirun'}",
        *_overrides(
            tmp_path,
            "par",
            5,
            ["tune.episodes=30", "tune.pruner.interval=10", "tune.pruner.warmup_episodes=10"],
        ),  # fmt: skip
    ]
    proc = run_cli("cdqn.tune", args, REPO, timeout=1200)
    assert proc.returncode == 0, proc.stderr[-3000:]

    study = optuna.load_study(study_name="par", storage=f"sqlite:///{tmp_path / 'optuna.db'}")
    # the time limit counts from the command's start, before the launcher started its
    # workers (the command wrote the sweep's multirun.yaml first), not from a worker's start
    launched = tmp_path / "multirun" / "multirun.yaml"
    assert study.user_attrs["clock_start"] < launched.stat().st_mtime
    trials = study.trials
    assert sorted(t.number for t in trials) == [0, 1, 2, 3, 4]  # exactly tune.trials
    assert {t.state.name for t in trials} <= {"COMPLETE", "PRUNED"}
    by_worker = {w: [t for t in trials if t.user_attrs["worker"] == w] for w in (0, 1)}
    assert by_worker[0] and by_worker[1]
    assert any(a.datetime_start < b.datetime_complete and b.datetime_start < a.datetime_complete
               for a in by_worker[0] for b in by_worker[1])  # fmt: skip  # in parallel

    (parent,) = _runs(tmp_path, kind="tune")
    assert parent.info.status == "FINISHED"
    assert study.user_attrs["mlflow_parent"] == parent.info.run_id
    assert parent.data.metrics["trials_complete"] + parent.data.metrics["trials_pruned"] == 5
    runs = _runs(tmp_path, kind="trial")
    assert sorted(int(r.data.tags["trial"]) for r in runs) == [0, 1, 2, 3, 4]
    assert {r.data.tags["mlflow.parentRunId"] for r in runs} == {parent.info.run_id}
    assert {r.data.tags["worker"] for r in runs} == {"0", "1"}
    (evaluation,) = _runs(tmp_path, kind="evaluation")  # written once, by worker 0
    assert evaluation.data.tags["mlflow.parentRunId"] == parent.info.run_id
    assert (tmp_path / "presets" / "weights" / "tuned_par.yaml").is_file()
    logs = sorted((tmp_path / "multirun").glob("*/tune.log"))
    assert len(logs) == 2
    for log in logs:  # each worker found the same parent run through the study
        assert f"(MLflow parent run {parent.info.run_id})" in log.read_text()


def test_the_double_dqn_baseline_is_configured_as_a_training_run_would_be() -> None:
    """``tune.baseline=ddqn`` trains Double DQN with the settings ``controller=ddqn`` gives a
    training run: its controller keys and the environment keys its file sets (raw
    observations, ``env.normalize=false``), on the study's environment."""
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        tune_cfg = compose("tune", overrides=["env=acrobot", "controller=hinf_f"])
        train_cfg = compose("config", overrides=["env=acrobot", "controller=ddqn"])
    assert tune_cfg.env.normalize is True
    out = _with_controller(tune_cfg, "ddqn")
    assert OmegaConf.to_container(out.controller) == OmegaConf.to_container(train_cfg.controller)
    assert out.env == train_cfg.env
    assert out.env.normalize is False and out.env.id == "Acrobot-v1"
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):  # a trial's own map
        tuned = compose(
            "tune", overrides=["env=acrobot", "controller=hinf_f", "env.normalize=true"]
        )
    assert _with_controller(tuned, "ddqn").env.normalize is False


def test_a_specification_moves_the_tuned_controllers_own_target(tmp_path: Path) -> None:
    """On an environment where ``hinf_f`` keeps its own effective-discount range, the
    ``weights.target.gamma_eff`` dimension moves that range (the one its design keeps)."""
    own = ["controller=hinf_f", "weights.controller_target.hinf_f.gamma_eff=[0.1,0.2]"]
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("tune", overrides=_overrides(tmp_path, "own", 1, own))
    study = Study(cfg)
    out = apply(study.base, study.space, {"gamma_eff": -0.7, "step_scale": 0.7})
    assert list(out.weights.controller_target.hinf_f.gamma_eff) == pytest.approx([-0.75, -0.65])
    assert list(out.weights.target.step_scale) == pytest.approx([0.65, 0.75])
    assert list(out.weights.target.gamma_eff) == list(study.base.weights.target.gamma_eff)


def _reads(node: object, at: str = "") -> dict[str, str]:
    """Every key of a composed (unresolved) configuration whose value is another key's,
    ``${other}``, as key → other."""
    if isinstance(node, dict):
        found: dict[str, str] = {}
        for k, v in node.items():
            found |= _reads(v, f"{at}.{k}" if at else str(k))
        return found
    hit = re.fullmatch(r"\$\{([\w.]+)\}", node) if isinstance(node, str) else None
    return {at: hit.group(1)} if hit else {}


def _unlike(value: object, p: ParamSpec) -> object:
    """A value of dimension ``p`` other than ``value``."""
    if p.choices is not None:
        return next(c for c in p.choices if c != value)
    assert p.low is not None and p.high is not None
    mid = (p.low + p.high) / 2 if not p.log else math.sqrt(p.low * p.high)
    return round(mid) if p.integer else mid


def test_the_rechecked_trial_with_the_best_final_score_over_its_seeds_is_chosen(
    tmp_path: Path,
) -> None:
    """Of the trials rechecked, the one that ends best over its trial and recheck seeds is
    chosen, not the one with the largest J: a trial that learns fast and falls back loses to
    one that holds what it learned (rechecks taken from the study, none trained)."""
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("tune", overrides=[*_overrides(tmp_path, "choice", 1)[:5],
                                         "controller=ddqn", "tune.recheck_trials=3"])  # fmt: skip
    chooser = Study(cfg)
    study = optuna.create_study(direction="maximize")
    # (J, final score) on the 3 trial seeds and on the 4 recheck seeds
    scores = {0: (340.0, 377.0, 335.0, 410.0), 1: (320.0, 499.0, 345.0, 482.0),
              2: (300.0, 500.0, 200.0, 300.0), 3: (100.0, 500.0, None, None)}  # fmt: skip
    for number, (j, final, j_re, final_re) in scores.items():
        study.add_trial(optuna.trial.create_trial(value=j, params={}, distributions={},
                                                  user_attrs={"final_score": final}))  # fmt: skip
        if j_re is not None:
            study.set_user_attr(f"recheck_{number}_seeds_200_4",
                                {"objective": j_re, "final_score": final_re})  # fmt: skip
    summary: dict = {}
    assert chooser.choose(study, summary).number == 1  # final over 7 seeds: 489.3
    rows = {row["trial"]: row for row in summary["recheck"]}
    assert sorted(rows) == [0, 1, 2]  # the three best by J; trial 3 is not rechecked
    assert rows[0]["all"] > rows[1]["all"]  # trial 0 has the best J over its seeds
    assert rows[1]["final_all"] == pytest.approx((3 * 499.0 + 4 * 482.0) / 7)


def test_a_continued_study_that_chooses_another_trial_records_it(tmp_path: Path) -> None:
    """Closed once, then continued after a better trial has joined: the second close
    records the new choice on the same parent run (its specification as tags ``best.<key>``,
    which a close may change) and writes its preset."""
    over = [*_overrides(tmp_path, "reclose", 1)[:5], "controller=ddqn", "tune.study=reclose",
            "tune.trials=1", "tune.seeds=1", "tune.episodes=4", "tune.eval_seeds=0",
            "tune.pruner.kind=none", "tune.recheck_trials=0", "tune.warm_start=[]"]  # fmt: skip
    first = _study(over)
    study = optuna.load_study(study_name="reclose", storage=f"sqlite:///{tmp_path / 'optuna.db'}")
    (trial,) = study.trials
    better = {**trial.params, "train_freq": 8 if trial.params["train_freq"] != 8 else 1}
    study.add_trial(optuna.trial.create_trial(
        value=trial.value + 1.0, params=better, distributions=trial.distributions,
        user_attrs={"final_score": 0.0}))  # fmt: skip
    second = _study(over)
    assert (first["best_trial"], second["best_trial"]) == (0, 1)
    parent = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}").get_run(second["parent_run"])
    assert second["parent_run"] == first["parent_run"]
    assert parent.data.tags["best_trial"] == "1"
    assert parent.data.tags["best.train_freq"] == str(better["train_freq"])
    assert OmegaConf.load(second["preset"]).controller.train_freq == better["train_freq"]


@pytest.mark.parametrize("agent", ["ddqn", "hinf_f"])
def test_every_key_that_reads_a_searched_one_follows_the_specification(
    agent: str, tmp_path: Path
) -> None:
    """A trial trains what its specification says: a key that reads a searched one
    (Double DQN's ``controller.lr: ${weights.ddqn.lr}`` and ``controller.target_update``, a
    design's ``controller.reset_integrator``) takes the sampled value, as a run of the
    preset (which writes the searched key) does."""
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("tune", overrides=[*_overrides(tmp_path, agent, 1)[:5],
                                         f"controller={agent}"])  # fmt: skip
    study = Study(cfg)
    raw = OmegaConf.to_container(cfg, resolve=False)
    assert isinstance(raw, dict)
    reads = _reads(raw)
    checked = 0
    for name, p in study.space.items():
        path = p.path.format(controller=agent)
        readers = [k for k, other in reads.items() if other == path]
        if not readers or p.width is not None or p.scale:
            continue
        params = {name: _unlike(OmegaConf.select(study.base, path), p)}
        out = study.specified(params, seed=100, population=1)
        for key in readers:
            assert OmegaConf.select(out, key) == params[name], (key, path)
        checked += 1
    assert checked >= (2 if agent == "ddqn" else 1)  # lr, target_update; reset_integrator


def test_the_discount_dimension_is_a_log_horizon(tmp_path: Path) -> None:
    """The shipped ``gamma_eff`` dimension reads its number h as a signed decimal
    log-horizon: the range written is [γ(h − 0.15), γ(h + 0.15)],
    γ(h) = sign(h)(1 − 10^−|h|)."""
    assert discount_of(2.0) == pytest.approx(0.99)
    assert discount_of(-1.0) == pytest.approx(-0.9)
    assert discount_of(0.0) == 0.0
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("tune", overrides=[*_overrides(tmp_path, "h", 1)[:5], "controller=hinf_f"])
    study = Study(cfg)
    assert study.space["gamma_eff"].horizon
    out = apply(study.base, study.space, {"gamma_eff": 2.0})
    lo, hi = out.weights.target.gamma_eff
    assert (lo, hi) == pytest.approx((1 - 10**-1.85, 1 - 10**-2.15))
    assert apply(study.base, study.space, {"gamma_eff": -2.0}).weights.target.gamma_eff[1] < -0.98


def test_horizons_no_box_allows_are_not_offered() -> None:
    """A static loop is stable over a box only for γ_eff < 1/ρ_max: with Θ2/Θ1 up to 1.195
    (CartPole's measured box) the positive centres give way to h = 0.9, the longest the box
    allows (its range starts at γ(0.75) = 0.822 < 0.837); at up to 1.05 the ones above 0.952
    go (h = 1 stays: its range starts at γ(0.85) = 0.859) for h = 1.45; at up to 1.0 none; a
    range's high end is lowered to the last centre whose range starts below the bound."""
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        space = OmegaConf.to_object(compose("tune", overrides=["controller=hinf_f"]).tune).space
    offered = space["gamma_eff"].choices
    assert offered == [-2.3, -2.0, -1.0, 1.0, 1.5, 2.0, 2.3]
    assert fit_to_box(space, 1.195)["gamma_eff"].choices == [-2.3, -2.0, -1.0, 0.9]
    assert fit_to_box(space, 1.05)["gamma_eff"].choices == [-2.3, -2.0, -1.0, 1.0, 1.45]
    for rho in (1.195, 1.05, 1.02, 1.5):
        fitted = fit_to_box(space, rho)["gamma_eff"]
        assert all(stable_over_box(lowest(fitted, c), rho) for c in fitted.choices)
        assert not stable_over_box(lowest(fitted, max(fitted.choices) + 0.05), rho)
    assert fit_to_box(space, 1.0) == space
    positive = {"gamma_eff": dataclasses.replace(space["gamma_eff"], choices=[1.0, 2.0])}
    assert fit_to_box(positive, 1.2)["gamma_eff"].choices == [0.9]
    plain = {"gamma_eff": dataclasses.replace(space["gamma_eff"], choices=[0.9, 0.95],
                                              horizon=False, width=None)}  # fmt: skip
    assert fit_to_box(plain, 1e6) == plain  # nothing would remain: kept, and said so
    ranged = {"gamma_eff": dataclasses.replace(space["gamma_eff"], choices=None, low=-2.5,
                                               high=2.5)}  # fmt: skip
    top = fit_to_box(ranged, 1.195)["gamma_eff"].high
    assert stable_over_box(discount_of(top - 0.15), 1.195)
    assert not stable_over_box(discount_of(top - 0.15 + 1e-6), 1.195)
    assert log_horizon_of(discount_of(-1.7)) == pytest.approx(-1.7)


def test_a_study_offers_the_horizons_its_measured_boxes_allow(tmp_path: Path) -> None:
    """A ``hinf_f`` study on a measured box measures each offered observation map's box once,
    before any trial, and offers only the γ_eff centres certifiable on one of them: every
    offered centre's range passes the same check the synthesis makes, the positive centres it
    rules out giving way to the longest positive one it allows."""
    over = [*_overrides(tmp_path, "boxfit", 1)[:5], "controller=hinf_f",
            "controller.synthesis.ntk_bounds=measured", "env=cartpole"]  # fmt: skip
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("tune", overrides=over)
    study = Study(cfg)
    maps = len(study.space["normalize"].choices)
    assert len(study.boxes) == maps  # raw and [−1, 1]
    rho_max = min(ratio[1] for _, ratio in study.boxes.values())
    assert rho_max > 1.0  # CartPole's box at width 16 reaches past Θ2 = Θ1
    kept = study.space["gamma_eff"].choices
    offered = OmegaConf.to_object(cfg.tune).space["gamma_eff"].choices
    assert kept and set(kept) - set(offered) == {max(kept)} and max(kept) not in offered
    for c in kept:
        assert stable_over_box(discount_of(c - 0.15), rho_max)
    assert not stable_over_box(discount_of(max(kept) + 0.05 - 0.15), rho_max)


def test_conditional_dimensions_are_sampled_only_when_their_condition_holds() -> None:
    """``eps_dec_episode`` is sampled with ``eps_schedule=episode`` only, ``eps_dec_action``
    with ``random_action`` only; both write ``train.eps_dec``."""
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("tune", overrides=["controller=ddqn"])
    space = OmegaConf.to_object(cfg.tune).space
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    seen = set()
    for _ in range(12):
        trial = study.ask()
        params = sample(trial, space)
        schedule = params["eps_schedule"]
        seen.add(schedule)
        own = "eps_dec_episode" if schedule == "episode" else "eps_dec_action"
        other = "eps_dec_action" if schedule == "episode" else "eps_dec_episode"
        assert own in params and other not in params
        out = apply(cfg, space, params)
        assert out.train.eps_schedule == schedule and out.train.eps_dec == params[own]
        study.tell(trial, 0.0)
    assert seen == {"episode", "random_action"}


def test_a_space_file_of_ones_own_adds_sampled_replay(tmp_path: Path) -> None:
    """docs/tuning.md: a space file in the user's folder adds a dimension to the design's
    space; the command line passes the check, and a trial's specification reaches
    ``weights.replay.sample``."""
    (tmp_path / "space").mkdir()
    (tmp_path / "space" / "hinf_f_sampled.yaml").write_text(
        "defaults: [hinf_f, _self_]\nsample: {path: weights.replay.sample, choices: [1, 2]}\n"
    )
    overrides = [f"hydra.searchpath=[file://{tmp_path}]", "space@tune.space=hinf_f_sampled",
                 "controller=hinf_f"]  # fmt: skip
    assert check_overrides(overrides, config_name="tune", check=check_tune) == []
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("tune", overrides=overrides)
    space = OmegaConf.to_object(cfg.tune).space
    assert {"sample", "w_p", "gamma_eff"} <= set(space)
    trial = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0)).ask()
    params = sample(trial, space)
    assert apply(cfg, space, params).weights.replay.sample == params["sample"] in (1, 2)


def test_radial_features_are_offered_only_where_the_observation_allows_them() -> None:
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        space = OmegaConf.to_object(compose("tune").tune).space
    assert space["rbf"].choices == [None, 4, 6]
    assert "rbf" not in fit_to_observation(space, bounded=False, n_features=2, max_features=4096)
    two = fit_to_observation(space, bounded=True, n_features=2, max_features=4096)
    assert two["rbf"].choices == [None, 4, 6]
    six = fit_to_observation(space, bounded=True, n_features=6, max_features=4096)
    assert six["rbf"].choices == [None, 4]  # 4^6 = 4096, 6^6 = 46656
    assert "rbf" not in fit_to_observation(space, bounded=True, n_features=7, max_features=4096)


def test_a_wide_one_hot_observation_is_not_offered_the_dense_map() -> None:
    """[−1, 1] turns a one-hot vector's zeros into −1: offered only up to max_features."""
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        space = OmegaConf.to_object(compose("tune").tune).space
    assert space["normalize"].choices == [False, True]
    wide = fit_to_observation(space, True, n_features=500, max_features=256, one_hot=True)
    assert wide["normalize"].choices == [False]
    narrow = fit_to_observation(space, True, n_features=16, max_features=256, one_hot=True)
    assert narrow["normalize"].choices == [False, True]
    box = fit_to_observation(space, True, n_features=500, max_features=256, one_hot=False)
    assert box["normalize"].choices == [False, True]


def test_a_per_episode_schedule_explores_for_a_share_of_the_budget() -> None:
    """ε from 1 to 0.01 (span 0.99) over at least a fifth of 2000 episodes: the per-episode
    decrease is kept to ≤ 0.99 / 400; a short study (100 episodes) keeps the range as it is;
    share 0 turns the bound off; the per-random-action range is never touched."""
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        space = OmegaConf.to_object(compose("tune").tune).space
    kept = fit_to_budget(space, 2000, 0.2, 0.99)
    assert kept["eps_dec_episode"].high == pytest.approx(0.99 / 400)
    assert kept["eps_dec_episode"].low == space["eps_dec_episode"].low
    assert kept["eps_dec_action"] == space["eps_dec_action"]
    assert fit_to_budget(space, 100, 0.2, 0.99) == space  # 0.99 / 20 is above the range
    assert fit_to_budget(space, 2000, 0.0, 0.99) == space
    # the span is measured to the highest floor offered: ε at 0.05 is reached first
    assert highest_floor(space, 0.01) == max(space["eps_end"].choices) == 0.05
    assert highest_floor({k: p for k, p in space.items() if k != "eps_end"}, 0.01) == 0.01
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    for _ in range(40):
        params = sample(trial := study.ask(), kept)
        assert params.get("eps_dec_episode", 0.0) <= 0.99 / 400
        study.tell(trial, 0.0)


@pytest.mark.parametrize(("env", "choices"), [("acrobot", None), ("mountaincar", [None, 4, 6])])
def test_a_study_offers_radial_features_within_its_feature_limit(
    tmp_path: Path, env: str, choices: list | None
) -> None:
    """tune.max_rbf_features (256) keeps Acrobot's 6 bounded features from 4^6 = 4096
    inputs; Mountain car's 2 features get 4 x 4 or 6 x 6."""
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        over = [*_overrides(tmp_path, "rbf", 1)[:5], f"env={env}", "controller=ddqn"]
        study = Study(compose("tune", overrides=over))
    assert (study.space["rbf"].choices if "rbf" in study.space else None) == choices


def test_the_episode_budget_follows_the_environments_cap() -> None:
    t = TuneSettings(steps=300_000, min_episodes=100, max_episodes=2000)
    assert episode_budget(t, 500) == 600
    assert episode_budget(t, 1000) == 300
    assert episode_budget(t, 100) == 2000  # at most max_episodes
    assert episode_budget(t, 10_000) == 100  # at least min_episodes
    assert episode_budget(TuneSettings(episodes=42), 500) == 42


@pytest.mark.parametrize(("env", "episodes"), [("acrobot", 600), ("cartpole", 1500)])
def test_a_study_reads_the_cap_its_environment_leaves_to_the_registration(
    tmp_path: Path, env: str, episodes: int
) -> None:
    """``env=acrobot`` leaves the cap to Acrobot-v1's registration (500 steps): the budget
    is 300 000 / 500 episodes, not ``max_episodes`` as for an environment without a cap."""
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        over = [*_overrides(tmp_path, "cap", 1)[:5], f"env={env}", "controller=hinf_f"]
        study = Study(compose("tune", overrides=over))
    assert study.conf.env.max_episode_steps == (None if env == "acrobot" else 200)
    assert study.episodes == episodes


def tuned_box(summary: dict) -> DictConfig:
    """``weights.theta_bounds`` of a study's preset."""
    return OmegaConf.load(summary["preset"]).weights.theta_bounds


@pytest.mark.slow
def test_both_agents_tuned_alike_compared_and_their_presets_reproduce_the_setting(
    tmp_path: Path,
) -> None:
    """A design study and a Double DQN study of one environment on the same budget: both
    search the shared dimensions (observation maps, exploration); the second study's
    evaluation compares the two on the same fresh seeds; each preset, trained with
    ``python -m cdqn.train``, has the tuned environment settings (cap, threshold,
    observation scaling, exploration) and α."""
    common = [
        f"tracking.uri=sqlite:///{tmp_path / 'mlflow.db'}",
        f"tune.storage=sqlite:///{tmp_path / 'optuna.db'}",
        f"tune.preset_dir={tmp_path / 'presets'}",
        f"controller.synthesis.cache_dir={tmp_path / 'cache'}",
        "env=cartpole", "env.max_episode_steps=60", "env.solve_threshold=50",
        "network.width=16", "tune.trials=2", "tune.seeds=2", "tune.episodes=8",
        "tune.eval_seeds=2", "tune.pruner.kind=none", "controller.learning_starts=50",
        *(f"{k}={v}" for k, v in TEST_DEFAULTS.items()),
    ]  # fmt: skip
    _store(f"sqlite:///{tmp_path / 'mlflow.db'}", "cdqn-tune", tmp_path)
    design = _study([*common, "controller=hinf_f", "tune.space.gamma_eff.choices=[-1.5,-0.5]"])
    ddqn = _study([*common, "controller=ddqn"])
    shared = {"normalize", "eps_schedule"}
    for summary in (design, ddqn):
        assert shared <= set(summary["best_params"])
        assert summary["evaluation"]["seeds"] == [1000, 1001]
    assert ddqn["comparison"]["rows"] == ["ddqn", "hinf_f"]
    assert "| hinf_f | CartPole-v1-cap60-hinf_f |" in ddqn["comparison"]["table"]
    chance = ddqn["comparison"]["random"]  # CartPole: about 22 steps of random balance
    assert 10 < chance["mean"] < 40 and chance["episodes"] == 100
    assert "A random policy scores" in ddqn["comparison"]["table"]
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    arts = {a.path for a in client.list_artifacts(ddqn["parent_run"], "comparison")}
    assert arts == {"comparison/comparison.md", "comparison/comparison.png"}

    # each evaluation keeps what its seeds did; the comparison says why a design falls short
    for summary, agent in ((design, "hinf_f"), (ddqn, "ddqn")):
        record = summary["evaluation"]["record"]
        (evaluation,) = _runs(tmp_path, kind="evaluation", agent=agent)
        members = _runs(tmp_path, **{"mlflow.parentRunId": evaluation.info.run_id})
        assert sorted(record["seeds"]) == sorted(m.data.tags["seed"] for m in members)
        for m in members:
            seed = record["seeds"][m.data.tags["seed"]]
            lengths = client.get_metric_history(m.info.run_id, "episode_length")
            assert seed["steps"] == sum(int(x.value) for x in lengths)
            assert seed["final"] == pytest.approx(m.data.metrics["final_score"])
            assert 0.0 <= seed["epsilon"] <= 1.0
            if agent == "ddqn":
                train_freq = summary["best_params"]["train_freq"]
                assert seed["learned_per_step"] == pytest.approx(32 / train_freq)
                assert "theta1_outside_box" not in seed and record["design"] is None
            else:
                # a TD step, the sampled replay's updates and any episodic replay's
                assert seed["learned_per_step"] >= 1.0 + summary["best_params"].get("sample", 0)
                assert 0.0 <= seed["theta1_outside_box"] <= 1.0
                # the box the study measured and the design was certified on
                assert record["design"]["theta1"] == list(tuned_box(summary).theta1)
                assert record["design"]["gamma_eff"] == float(m.data.tags["design_gamma_eff"])
        stored = client.list_artifacts(evaluation.info.run_id, "evaluation")
        assert "evaluation/seeds.json" in {a.path for a in stored}
    bar = ddqn["evaluation"]["final_score"] - ddqn["evaluation"]["final_std"]
    short = design["evaluation"]["final_score"] < bar
    assert ("Where hinf_f falls short" in ddqn["comparison"]["table"]) == short

    for summary, agent in ((design, "hinf_f"), (ddqn, "ddqn")):
        preset = Path(summary["preset"])
        tuned = OmegaConf.load(preset)
        assert tuned.env.max_episode_steps == 60 and tuned.env.solve_threshold == 50
        assert tuned.extra.tuned.budget.trials == 2 and "normalize" in tuned.extra.tuned.space
        with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
            cfg = compose("config", overrides=[f"controller={agent}", f"weights={preset.stem}",
                          f"hydra.searchpath=[file://{tmp_path / 'presets'}]"])  # fmt: skip
        best = summary["best_params"]
        assert cfg.env.max_episode_steps == 60 and cfg.env.solve_threshold == 50
        assert cfg.network.width == 16  # the network the study tuned on, not the default
        assert cfg.train.episodes == 8  # the study's episodes per member
        with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
            given = compose("config", overrides=[f"controller={agent}", f"weights={preset.stem}",
                            f"hydra.searchpath=[file://{tmp_path / 'presets'}]",
                            "train.episodes=5"])  # fmt: skip
        assert given.train.episodes == 5  # the command line still decides
        assert cfg.env.normalize == best["normalize"]
        assert cfg.train.eps_schedule == best["eps_schedule"]
        dec = best.get("eps_dec_episode", best.get("eps_dec_action"))
        assert cfg.train.eps_dec == pytest.approx(dec)
        if agent == "ddqn":
            assert cfg.controller.lr == pytest.approx(best["lr"])
            assert cfg.controller.train_freq == best["train_freq"]
        else:
            assert cfg.train.lr == pytest.approx(best["lr"])
            assert cfg.controller.synthesis.ntk_bounds == "config"
            measured = "CartPole-v1-cap60, seed 100"  # the study measured the box it designs on
            assert tuned.weights.theta_bounds.measured_on == measured
            assert f"NTK box (measured on {measured}):" in summary["design_report"]


def test_the_pruner_waits_half_the_episodes_by_default() -> None:
    assert warmup(PrunerConfig(), 600) == 300
    assert warmup(PrunerConfig(), 160) == 80
    assert warmup(PrunerConfig(), 100) == 50
    assert warmup(PrunerConfig(warmup_episodes=7), 600) == 7


def test_a_gain_scheduled_design_is_specified_without_a_box(tmp_path: Path) -> None:
    """The H2 design sees Θ1, Θ2 at every step and is certified on no box: a study of it
    with the tuner's measured box leaves theta_bounds as configured."""
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("tune", overrides=[*_overrides(tmp_path, "h2", 1)[:5], "controller=h2"])
    study = Study(cfg)
    out = study.specified({"gamma_eff": 2.0}, seed=100, population=1)
    assert out.controller.name == "h2" and not study.boxes
    assert list(out.weights.theta_bounds.ratio) == list(cfg.weights.theta_bounds.ratio)
    assert batchable(OmegaConf.to_object(out))  # one batch, which reports each episode
