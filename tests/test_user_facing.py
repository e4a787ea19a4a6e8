"""What a user meets on the command line: an ``env.id=<id>`` run labelled and judged as that
environment, the summary at the end of a run and of a multirun, the MLflow experiment and
``final_score`` metric, resume checkpoints dropped once a run finished, and the analysis
scripts on such a store.  Real ``python -m cdqn.train`` subprocesses, a real SQLite store.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from mlflow.tracking import MlflowClient

from analysis.figures import FigureContext, learning
from analysis.runs import RunStore, comparable_runs
from cdqn.envs import adopt
from tests.conftest import compose_config
from tests.helpers import run_cli, run_script

pytestmark = pytest.mark.slow  # two training commands of a few episodes each

ROOT = Path(__file__).resolve().parents[1]
ENV_ID = "Acrobot-v1"
COMMON = [f"env.id={ENV_ID}", "controller=none", "network=small", "train.checkpoint_every=1"]


class Store:
    """The store both commands wrote into, with their outputs."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.uri = f"sqlite:///{folder / 'mlflow.db'}"
        self.client = MlflowClient(self.uri)

    def runs(self) -> list:
        exp = self.client.get_experiment_by_name("cdqn")
        return self.client.search_runs([exp.experiment_id], order_by=["attributes.start_time"])


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> tuple[Store, str, str]:
    """A single run (4 episodes, seed 0), then a multirun of a single run and a population of
    two (3 episodes, seeds 1 and 1-2), all ``env=cartpole env.id=Acrobot-v1``."""
    folder = tmp_path_factory.mktemp("user")
    single = run_cli("cdqn.train", [*COMMON, "train.episodes=4", "seed=0"], folder)
    assert single.returncode == 0, single.stderr
    multi = run_cli(
        "cdqn.train",
        [
            "-m",
            *COMMON,
            "train.episodes=3",
            "seed=1",
            "train.keep_checkpoints=true",
            "train.population=1,2",
        ],
        folder,
    )
    assert multi.returncode == 0, multi.stderr
    return Store(folder), single.stdout, multi.stdout


def test_env_id_run_is_named_tagged_and_capped_as_that_environment(store) -> None:
    st, _, _ = store
    runs = st.runs()
    names = sorted(r.info.run_name for r in runs)  # the multirun's two jobs run side by side
    expected = [f"{ENV_ID}-none-w64-e{e}-s{s}" for e, s in ((4, 0), (3, 1), (3, 1), (3, 2))]
    assert names == sorted(expected)  # the width and episodes differ
    first = runs[0]
    assert first.data.tags["env"] == ENV_ID and first.data.tags["env_id"] == ENV_ID
    params = first.data.params
    assert params["env.name"] == ENV_ID
    assert params["env.max_episode_steps"] == "500"  # Acrobot-v1's registration, not 200
    assert params["env.solve_threshold"] == "-100.0"  # not CartPole's 195
    assert params["controller.synthesis.ntk_bounds"] == "measured"
    lengths = st.client.get_metric_history(first.info.run_id, "episode_length")
    assert max(m.value for m in lengths) > 200  # the cap is Acrobot's 500 steps


def test_population_members_are_labelled_as_single_runs(store) -> None:
    st, _, _ = store
    seed1 = [r for r in st.runs() if r.data.tags["seed"] == "1"]
    single, member = sorted(seed1, key=lambda r: "population" in r.data.tags)
    assert member.data.tags["population"] == "1-2"
    drop = {"population", "pid", "mlflow.runName", "mlflow.user", "mlflow.source.name"}
    tags = {k: v for k, v in single.data.tags.items() if k not in drop and "mlflow" not in k}
    assert {k: v for k, v in member.data.tags.items() if k in tags} == tags
    assert set(member.data.tags) - set(single.data.tags) == {"population", "population_id"}
    same = {k for k in single.data.params if k != "train.keep_checkpoints"}
    assert {k: member.data.params[k] for k in same} == {k: single.data.params[k] for k in same}


def test_experiment_opens_as_model_training_and_runs_log_final_score(store) -> None:
    st, _, _ = store
    exp = st.client.get_experiment_by_name("cdqn")
    assert exp.tags["mlflow.experimentKind"] == "custom_model_development"
    for run in st.runs():
        returns = [m.value for m in st.client.get_metric_history(run.info.run_id, "episode_return")]
        assert run.data.metrics["final_score"] == pytest.approx(np.mean(returns[-100:]))


def test_finished_runs_drop_checkpoints_unless_kept(store) -> None:
    st, _, _ = store
    single, kept = st.runs()[0], st.runs()[1]
    assert st.client.list_artifacts(single.info.run_id, "checkpoint") == []
    assert [a.path for a in st.client.list_artifacts(kept.info.run_id, "checkpoint")]
    assert "model" in [a.path for a in st.client.list_artifacts(single.info.run_id)]


def test_summary_at_the_end_of_a_run(store) -> None:
    st, out, _ = store
    run_id = st.runs()[0].info.run_id
    score = st.runs()[0].data.metrics["final_score"]
    assert f"run {run_id} FINISHED: final score {score:.2f} (mean return of the last 4 of 4" in out
    assert "solve threshold -100 not reached" in out
    assert re.search(r"\d+ environment steps, [\d.]+ s of training \(\d+ steps/s\)", out)
    assert "warning: ε = " in out and "mostly random play" in out
    assert f"mlflow ui --backend-store-uri {st.uri}" in out
    exp_id = st.client.get_experiment_by_name("cdqn").experiment_id
    page = f"http://127.0.0.1:5000/#/experiments/{exp_id}?workflowType=machine_learning"
    assert f"and open {page} (the runs table)" in out


def test_multirun_summary_lists_scores(store) -> None:
    st, _, out = store
    lines = [ln for ln in out.splitlines() if "FINISHED  run " in ln]
    assert len(lines) == 3, out  # the single run, then each member of the population
    for line in lines:
        assert re.search(r"score +-?\d+\.\d\d \(not solved\)", line), line
    seeds = [next(w for w in ln.split() if w.startswith("seed=")) for ln in lines]
    assert seeds == ["seed=1", "seed=1", "seed=2"]


def test_table_counts_the_id_as_its_own_environment(store, tmp_path: Path) -> None:
    st, _, _ = store
    args = ["--tracking-uri", st.uri, "--out", str(tmp_path)]
    proc = run_cli_script("make_table.py", args, st.folder)
    assert proc.returncode == 0, proc.stderr
    assert "These runs form 2 groups" in proc.stdout  # 4 episodes vs 3 episodes
    assert f"| controller | {ENV_ID} |" in proc.stdout
    assert "Group 1 of 2: train.episodes=3" in proc.stdout
    assert "Cartpole" not in proc.stdout
    one = run_cli_script("make_table.py", [*args, "--where", "train.episodes=3"], st.folder)
    assert one.returncode == 0, one.stderr
    assert "groups" not in one.stdout
    cell = re.search(r"\| no control \| (.+) \|", one.stdout)
    assert cell is not None and "(n=2;" in cell[1], one.stdout  # seed 1 counted once
    assert "seed 1: 2 runs, only the latest one counts" in one.stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--where", "nosuch=1"], "--where nosuch=1: no run has a tag or param 'nosuch'"),
        (["--where", "train.episodes=99"], "no run has train.episodes=99; present: 3, 4"),
    ],
)
def test_where_refuses_what_matches_nothing(store, args: list[str], message: str) -> None:
    st, _, _ = store
    proc = run_cli_script("make_table.py", ["--tracking-uri", st.uri, *args], st.folder)
    assert proc.returncode == 2 and message in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.parametrize("flag", ["--env", "--controller"])
def test_figures_refuse_unknown_names(store, flag: str, tmp_path: Path) -> None:
    st, _, _ = store
    args = ["--tracking-uri", st.uri, "--out", str(tmp_path), flag, "nosuch"]
    proc = run_cli_script("make_figures.py", args, st.folder)
    assert proc.returncode == 2, proc.stderr
    assert f"error: {flag} nosuch: unknown" in proc.stderr and "Traceback" not in proc.stderr
    assert not list(tmp_path.iterdir())


def test_short_runs_stay_visible_in_learning_curves(store) -> None:
    st, _, _ = store
    runs, _ = comparable_runs(RunStore(st.uri).runs())
    fig = learning(FigureContext(RunStore(st.uri), runs), ENV_ID)
    lines = [ln for ln in fig.axes[0].lines if ln.get_label().startswith("no control")]
    assert len(lines) == 2  # one per group of settings, never averaged together
    assert all(ln.get_marker() == "o" for ln in lines)


def test_adopt_keeps_explicit_values_and_matching_weights() -> None:
    cfg = compose_config(["env.id=Acrobot-v1", "env.max_episode_steps=50", "weights=acrobot"])
    adopted = adopt(cfg)
    assert adopted.change is not None and cfg.env.name == "cartpole"  # the input unchanged
    assert adopted.cfg.env.max_episode_steps == 50  # set explicitly: kept
    assert adopted.cfg.env.solve_threshold == -100.0
    assert adopted.box_source == "config"  # the weights are Acrobot's
    assert adopt(adopted.cfg).change is None  # once adopted, nothing changes
    cfg = compose_config(["env=acrobot"])
    assert adopt(cfg).change is None and adopt(cfg).cfg.env.name == "acrobot"


def run_cli_script(script: str, args: list[str], cwd: Path):
    """``python analysis/<script> <args>`` as a user runs it."""
    return run_script(ROOT / "analysis" / script, args, cwd)
