"""A multirun's seeds train as populations: which jobs the cdqn sweeper groups, that Hydra
finds and uses it, and that a batched sweep through the real command line stores, seed by
seed, exactly what the same sweep run one job per seed stores."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.plugins import Plugins
from hydra.plugins.sweeper import Sweeper
from mlflow.tracking import MlflowClient

from cdqn.training.batching import JobShape, Planned, batch_jobs, job_shape, makespan, seed_runs
from cdqn.training.callbacks import format_summary, member_entries
from cdqn.training.result import RunResult
from hydra_plugins.cdqn_sweeper.cdqn_sweeper import CdqnSweeper
from tests.conftest import CONF_DIR, compose_config
from tests.helpers import assert_same_run, run_cli, runs_of

ROOT = CONF_DIR.parent


def _product(controllers: list[str], seeds: list[int], extra: list[str] = ()) -> list[list[str]]:
    """The jobs Hydra's basic sweeper expands ``controller=… seed=…`` into, in its order."""
    return [[*extra, f"controller={c}", f"seed={s}"] for c in controllers for s in seeds]


def _by_controller(job: list[str]) -> JobShape:
    """Every configuration batches; the controller read off the overrides."""
    name = next(o.split("=", 1)[1] for o in job if o.startswith("controller="))
    return JobShape(True, name)


def test_contiguous_seeds_of_one_configuration_become_one_population() -> None:
    jobs = _product(["h2", "hinf", "ddqn"], list(range(10)))
    assert batch_jobs(jobs, 10, _by_controller) == [  # Double DQN, the longest, first
        ["controller=ddqn", "seed=0", "train.population=10"],
        ["controller=h2", "seed=0", "train.population=10"],
        ["controller=hinf", "seed=0", "train.population=10"],
    ]


def test_populations_are_capped_and_split_evenly() -> None:
    assert seed_runs(list(range(25)), 10) == [(0, 9), (9, 8), (17, 8)]
    assert seed_runs([7, 3, 4, 5, 9, 10], 10) == [(3, 3), (7, 1), (9, 2)]
    jobs = _product(["h2"], list(range(12)))
    assert batch_jobs(jobs, 5, _by_controller) == [
        ["controller=h2", "seed=0", "train.population=4"],
        ["controller=h2", "seed=4", "train.population=4"],
        ["controller=h2", "seed=8", "train.population=4"],
    ]


def _planned(job: list[str]) -> Planned:
    """The :class:`Planned` job of a batched job's overrides."""
    opts = dict(o.split("=", 1) for o in job)
    count = int(opts.get("train.population", 1))
    return Planned(job, int(opts["seed"]), count, opts["controller"])


def test_populations_are_split_so_that_two_workers_end_together() -> None:
    controllers = ["h2", "hinf", "hinf_f", "ddqn"]
    jobs = _product(controllers, list(range(10)))
    balanced = batch_jobs(jobs, 10, _by_controller, workers=2)
    assert balanced == [  # costs 13.5, 13.5, 11, 11, 6, 6: 30.5 on each worker
        ["controller=ddqn", "seed=0", "train.population=5"],
        ["controller=ddqn", "seed=5", "train.population=5"],
        ["controller=hinf", "seed=0", "train.population=10"],
        ["controller=hinf_f", "seed=0", "train.population=10"],
        ["controller=h2", "seed=0", "train.population=5"],
        ["controller=h2", "seed=5", "train.population=5"],
    ]
    runs = sorted(
        (p.controller, p.seed + i) for p in map(_planned, balanced) for i in range(p.size)
    )
    assert runs == sorted((c, s) for c in controllers for s in range(10))
    unbalanced = batch_jobs(jobs, 10, _by_controller)
    spans = [makespan([_planned(j) for j in js], 2) for js in (balanced, unbalanced)]
    assert spans == [30.5, 33.0]
    assert batch_jobs(jobs, 10, _by_controller, workers=1) == unbalanced  # no split helps


def test_seeds_that_are_not_consecutive_run_as_they_are() -> None:
    jobs = _product(["h2"], [0, 1, 2, 5, 8, 9])
    assert batch_jobs(jobs, 10, _by_controller) == [
        ["controller=h2", "seed=0", "train.population=3"],
        ["controller=h2", "seed=8", "train.population=2"],
        ["controller=h2", "seed=5"],
    ]


def test_jobs_that_differ_in_another_key_are_not_grouped() -> None:
    jobs = [
        [f"train.lr={lr}", f"seed={s}", "network=small"] for lr in ("1e-4", "5e-5") for s in (0, 1)
    ]
    shape = lambda job: JobShape(True, "hinf")  # noqa: E731
    assert batch_jobs(jobs, 10, shape) == [
        ["train.lr=1e-4", "seed=0", "network=small", "train.population=2"],
        ["train.lr=5e-5", "seed=0", "network=small", "train.population=2"],
    ]


@pytest.mark.parametrize(
    ("jobs", "max_population", "shape"),
    [
        (_product(["h2"], [0, 1, 2]), 10, lambda job: JobShape(False, "h2")),  # cannot batch
        (_product(["h2"], [0, 1, 2]), 1, _by_controller),  # one job per seed asked for
        (_product(["h2"], [0, 1], ["train.population=1"]), 10, _by_controller),  # explicit size
        (_product(["h2"], [1, 1, 2]), 10, _by_controller),  # a seed twice
        ([["controller=h2", "seed=${oc.env:S}"], ["controller=h2", "seed=1"]], 10, _by_controller),
        (_product(["h2"], [4]), 10, _by_controller),  # one seed
    ],
    ids=["not-batchable", "max-population-1", "explicit-population", "repeated", "not-int", "one"],
)
def test_jobs_that_cannot_batch_stay_one_per_seed(jobs, max_population, shape) -> None:
    assert batch_jobs(jobs, max_population, shape) == jobs


def test_job_shape_of_real_configurations() -> None:
    assert job_shape(compose_config(["controller=ddqn"])) == JobShape(True, "ddqn")
    assert job_shape(compose_config(["controller=hinf_f"])) == JobShape(True, "hinf_f")
    assert job_shape(compose_config(["train.fast_path=false"])) == JobShape(False, "hinf")
    assert job_shape(compose_config(["train.population=3"])) == JobShape(False, "hinf")
    # Acrobot's id under env=cartpole (weights=generic): each seed's design on its own measured box
    acrobot = compose_config(["env.id=Acrobot-v1", "controller=hinf_f"])
    assert job_shape(acrobot) == JobShape(False, "hinf_f")
    # the gain-scheduled H2 design is certified on no box: its seeds batch
    h2 = compose_config(["env.id=Acrobot-v1", "controller=h2"])
    assert job_shape(h2) == JobShape(True, "h2")
    assert job_shape(compose_config(["env=acrobot", "controller=h2"])) == JobShape(True, "h2")


def test_hydra_finds_and_selects_the_cdqn_sweeper() -> None:
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", return_hydra_config=True)
    assert cfg.hydra.sweeper._target_ == "hydra_plugins.cdqn_sweeper.cdqn_sweeper.CdqnSweeper"
    assert cfg.hydra.sweeper.max_population == 10
    assert cfg.hydra.launcher.n_jobs == -1  # joblib on every core
    names = {p.__name__ for p in Plugins.instance().discover(Sweeper)}
    assert "CdqnSweeper" in names


def test_summary_has_one_line_per_member() -> None:
    members = [
        RunResult("r3", "FINISHED", 20.0, returns=[20.0], solve_threshold=195.0),
        RunResult("r4", "FAILED", float("nan"), "diverged: |Q| = 2e+06", solve_threshold=195.0),
    ]
    overrides = ["controller=h2", "seed=3", "train.population=2"]
    job = {"job": 0, "overrides": overrides, "status": "FAILED", "run_id": "r3,r4", "dir": "/s/0"}
    job["members"] = member_entries(members, 3, overrides)
    single = {"job": 1, "overrides": ["seed=9"], "status": "FINISHED", "run_id": "r9"}
    text = format_summary([job, {**single, "dir": "/s/1"}], Path("/s"))
    assert text.splitlines() == [
        "cdqn multirun /s: 2 jobs (3 runs): 1 FAILED, 2 FINISHED",
        "     0  FINISHED  run r3  score    20.00 (not solved)  controller=h2 seed=3",
        "     0  FAILED    run r4    controller=h2 seed=4",
        "          -> diverged: |Q| = 2e+06",
        "     1  FINISHED  run r9    seed=9",
    ]


def test_a_bad_population_cap_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stop:
        CdqnSweeper(max_population=0)
    assert stop.value.code == 2
    assert "hydra.sweeper.max_population=0: must be at least 1" in capsys.readouterr().err


@pytest.mark.slow
def test_a_bad_population_cap_is_refused_in_one_line(tmp_path: Path) -> None:
    proc = run_cli("cdqn.train", ["-m", "hydra.sweeper.max_population=0"], tmp_path)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines()[-1] == (
        "cdqn: hydra.sweeper.max_population=0: must be at least 1 (1 launches one job per seed)"
    )
    assert "Traceback" not in proc.stderr


SWEEP = [
    "-m",
    "network=small",
    "train.episodes=6",
    "controller.learning_starts=40",  # Double DQN learns within the six episodes
    "seed=range(3)",
    "controller=hinf_f,ddqn",
]


@pytest.mark.slow
def test_a_batched_sweep_stores_what_one_job_per_seed_stores(tmp_path: Path) -> None:
    """The sweep through the real CLI (joblib launcher, two workers), batched and balanced
    (Double DQN's three seeds as a population of two and a single run, :func:`balance`), and
    again one job per seed (``hydra.sweeper.max_population=1``; Hydra's basic launcher runs
    the six jobs one after the other in the command's own process) into another store: every
    seed is its own FINISHED run with its own summary line, with the returns and signal rows
    of the unbatched run of that seed; started again with ``tracking.skip_finished=true``,
    the batched sweep skips every member."""
    stores = {name: tmp_path / name for name in ("batched", "single")}
    out = {}
    for name, folder in stores.items():
        folder.mkdir()
        single = ["hydra.sweeper.max_population=1", "hydra/launcher=basic"]
        extra = single if name == "single" else ["hydra.launcher.n_jobs=2"]
        proc = run_cli("cdqn.train", [*SWEEP, *extra, "hydra.sweep.dir=multirun"], folder, 900)
        assert proc.returncode == 0, proc.stderr[-3000:]
        out[name] = proc.stdout + proc.stderr
    assert "cdqn sweeper: 6 jobs as 3" in out["batched"]
    assert "balanced over 2 workers" in out["batched"]
    assert "cdqn multirun multirun: 3 jobs (6 runs): 6 FINISHED" in out["batched"]
    assert "cdqn multirun multirun: 6 jobs: 6 FINISHED" in out["single"]
    lines = [set(ln.split()) for ln in out["batched"].splitlines() if "FINISHED  run " in ln]
    assert sorted(
        (w, v)
        for words in lines
        for w in words
        for v in words
        if w.startswith("controller=") and v.startswith("seed=")
    ) == sorted((f"controller={c}", f"seed={s}") for c in ("ddqn", "hinf_f") for s in range(3))
    summary = json.loads((stores["batched"] / "multirun" / "summary.json").read_text())
    assert [len(job.get("members", [job])) for job in summary] == [2, 3, 1]

    batched, single = (MlflowClient(f"sqlite:///{f / 'mlflow.db'}") for f in stores.values())
    key = lambda r: (r.data.tags["controller"], r.data.tags["seed"])  # noqa: E731
    ours = {key(r): r for r in runs_of(f"sqlite:///{stores['batched'] / 'mlflow.db'}")}
    theirs = {key(r): r for r in runs_of(f"sqlite:///{stores['single'] / 'mlflow.db'}")}
    assert sorted(ours) == sorted(theirs) and len(ours) == 6
    populations = {("ddqn", "0"): "0-1", ("ddqn", "1"): "0-1", ("ddqn", "2"): None}
    for k, run in ours.items():
        assert run.data.tags.get("population") == populations.get(k, "0-2")
        assert "population" not in theirs[k].data.tags
        assert_same_run(batched, run.info.run_id, theirs[k].info.run_id, single)

    again = run_cli(
        "cdqn.train",
        [*SWEEP, "tracking.skip_finished=true", "hydra.sweep.dir=multirun-again"],
        stores["batched"],
        900,
    )
    assert again.returncode == 0, again.stderr[-3000:]
    assert (again.stdout + again.stderr).count("already FINISHED") == 6
    assert len(runs_of(f"sqlite:///{stores['batched'] / 'mlflow.db'}")) == 6
