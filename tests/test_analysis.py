"""The analysis package on a small store of real training runs.

One module-scoped store: short real runs of a few controllers on CartPole and MountainCar
(distinct seeds per controller so that the cells differ), one run that diverges (FAILED), and
a closed-loop singular-value file added to one run as a synthesized design would store it.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from mlflow.tracking import MlflowClient

from analysis import make_figures, make_table
from analysis.columns import caption, column_differences
from analysis.runs import EPISODE_METRICS, RunStore, comparable_runs
from analysis.table import run_scores
from tests.conftest import TINY, compose_config

EXPERIMENT = "analysis-test"
RUNS = [
    # (env, controller, seed, episodes)
    ("cartpole", "hinf", 0, 6),
    ("cartpole", "hinf", 1, 6),
    ("cartpole", "hinf_f", 2, 6),
    ("cartpole", "hinf_f", 3, 6),
    ("cartpole", "ddqn", 4, 6),
    ("cartpole", "ddqn", 5, 6),
    ("cartpole", "none", 6, 6),
    ("mountaincar", "hinf", 0, 3),
    ("mountaincar", "hinf", 1, 3),
    ("mountaincar", "hinf_f", 2, 3),
]
N_FINISHED = len(RUNS)


@pytest.fixture(scope="module")
def store_uri(tmp_path_factory: pytest.TempPathFactory) -> str:
    from cdqn.training.run import run

    root = tmp_path_factory.mktemp("store")
    uri = f"sqlite:///{root / 'mlflow.db'}"
    common = [*TINY, f"tracking.uri={uri}", f"tracking.experiment={EXPERIMENT}"]
    ids = {}
    for env, ctrl, seed, episodes in RUNS:
        cfg = compose_config(
            [
                *common,
                f"env={env}",
                f"controller={ctrl}",
                f"seed={seed}",
                f"train.episodes={episodes}",
            ]
        )
        ids[(env, ctrl, seed)] = run(cfg, progress=False).run_id
    failed = run(
        compose_config([*common, "controller=none", "seed=7", "train.q_limit=1e-9"]),
        progress=False,
    )
    assert failed.status == "FAILED"
    omega = np.logspace(-2, 5, 50)
    sv = root / "closed_loop_sv.csv"
    pd.DataFrame(
        {"omega": omega, "sigma_max": 1 / (1 + omega), "sigma_min": 0.1 / (1 + omega)}
    ).to_csv(sv, index=False)
    MlflowClient(uri).log_artifact(ids[("cartpole", "hinf", 0)], str(sv), "design")
    return uri


def _history(client: MlflowClient, run_id: str, key: str) -> np.ndarray:
    hist = sorted(client.get_metric_history(run_id, key), key=lambda m: m.step)
    return np.array([m.value for m in hist])


def _direct_scores(uri: str, threshold: dict[str, float] | None = None) -> pd.DataFrame:
    """The table's numbers computed straight from the MLflow client, run by run."""
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name(EXPERIMENT)
    rows = []
    for r in client.search_runs([exp.experiment_id]):
        if r.info.status != "FINISHED":
            continue
        env = r.data.tags["env"]
        returns = _history(client, r.info.run_id, "episode_return")
        ma = _history(client, r.info.run_id, "return_ma100")
        thr = (threshold or {}).get(env, float(r.data.params["env.solve_threshold"]))
        hit = np.flatnonzero(ma >= thr)
        rows.append(
            {
                "controller": r.data.tags["controller"],
                "env": env,
                "final": returns[-100:].mean(),
                "solve": hit[0] + 1 if hit.size else np.inf,
            }
        )
    df = pd.DataFrame(rows)
    out = df.groupby(["controller", "env"]).agg(
        n=("final", "size"),
        mean=("final", "mean"),
        std=("final", lambda x: np.std(x.to_numpy())),
        solved=("solve", lambda x: int(np.isfinite(x).sum())),
        median=("solve", lambda x: np.median(x.to_numpy())),
    )
    return out


def _markdown_cells(text: str) -> dict[tuple[str, str], str]:
    lines = [ln for ln in text.splitlines() if ln.startswith("|")]
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    cells = {}
    for line in lines[2:]:
        parts = [c.strip() for c in line.strip("|").split("|")]
        for env, cell in zip(header[1:], parts[1:], strict=True):
            cells[(parts[0], env)] = cell
    return cells


def test_runs_load_finished_only_with_tags_and_metrics(store_uri: str) -> None:
    store = RunStore(store_uri, EXPERIMENT)
    runs = store.runs()
    assert len(runs) == N_FINISHED
    assert set(runs["status"]) == {"FINISHED"}
    assert len(store.runs(["FINISHED", "FAILED"])) == N_FINISHED + 1
    assert {"env", "controller", "seed", "git_commit", "design_source"} <= set(runs.columns)
    assert runs["solve_threshold"].notna().all()

    episodes = store.episodes()
    assert list(episodes.columns[-len(EPISODE_METRICS) :]) == list(EPISODE_METRICS)
    assert len(episodes) == sum(n for *_, n in RUNS)
    one = runs.iloc[0]
    mine = episodes[episodes["run_id"] == one["run_id"]].sort_values("episode")
    direct = _history(MlflowClient(store_uri), one["run_id"], "return_ma100")
    np.testing.assert_array_equal(mine["return_ma100"].to_numpy(), direct)

    steps = store.steps(one["run_id"])
    assert steps is not None and len(steps) == mine["episode_length"].sum()
    assert store.closed_loop_sv(one["run_id"]) is None or one["controller"] == "hinf"


def test_database_query_equals_client_api(store_uri: str) -> None:
    store = RunStore(store_uri, EXPERIMENT)
    ids = list(store.runs()["run_id"])
    keys = list(EPISODE_METRICS)
    fast = store._metrics_sql(ids, keys)
    assert fast is not None and len(fast) > 0
    pd.testing.assert_frame_equal(fast, store._metrics_client(ids, keys), check_dtype=False)


def test_comparable_runs_keep_latest_run_per_seed(store_uri: str) -> None:
    runs = RunStore(store_uri, EXPERIMENT).runs()
    again = runs.iloc[[0]].assign(run_id="rerun", start_time=runs["start_time"].max() + 1)
    kept, notes = comparable_runs(pd.concat([runs, again], ignore_index=True))
    assert len(kept) == len(runs)
    assert "rerun" in set(kept["run_id"]) and runs.iloc[0]["run_id"] not in set(kept["run_id"])
    assert set(kept["settings"]) == {""}
    env, ctrl, seed = runs.iloc[0][["env", "controller", "seed"]]
    assert f"{env}/{ctrl} seed {seed}: 2 runs, only the latest one counts" in notes


def test_comparable_runs_never_mix_settings(store_uri: str) -> None:
    runs = RunStore(store_uri, EXPERIMENT).runs()
    wide = runs.iloc[[0]].assign(run_id="wide", start_time=runs["start_time"].max() + 1)
    wide["params.network.width"] = "64"
    kept, notes = comparable_runs(pd.concat([runs, wide], ignore_index=True))
    assert len(kept) == len(runs) + 1  # same seed, other width: its own group, not a rerun
    width = runs.iloc[0]["params.network.width"]
    assert kept.loc[kept["run_id"] == "wide", "settings"].item() == "network.width=64"
    assert set(kept["settings"]) == {"network.width=64", f"network.width={width}"}
    assert any("differ in network.width: 2 groups" in n and "--where" in n for n in notes)


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("controller.lr", "0.001"),  # Double DQN's α
        ("controller.target_update", "1"),
        ("controller.batch_size", "1"),
        ("env.rbf_centres", "4"),
        ("train.eps_end", "0.05"),
        ("weights.reset_integrator.hinf", "False"),
        ("weights.hinf.w_p.num", "[0.5]"),
    ],
)
def test_comparable_runs_split_on_every_agent_and_shared_setting(
    store_uri: str, key: str, value: str
) -> None:
    """A run that differs from the others of its cell only in an agent's own setting or in a
    setting the agents of a column share is never averaged with them."""
    runs = RunStore(store_uri, EXPERIMENT).runs()
    assert f"params.{key}" in runs.columns
    other = runs.iloc[[0]].assign(run_id="other", start_time=runs["start_time"].max() + 1)
    other[f"params.{key}"] = value
    kept, notes = comparable_runs(pd.concat([runs, other], ignore_index=True))
    assert len(kept) == len(runs) + 1, key  # same seed, another setting: not a rerun
    assert kept.loc[kept["run_id"] == "other", "settings"].item().startswith(f"{key}={value}")
    assert any(key in n and "never averaged together" in n for n in notes)


def test_table_equals_direct_computation_and_bolds_best(
    store_uri: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "tables"
    code = make_table.main(
        [
            "--tracking-uri",
            store_uri,
            "--experiment",
            EXPERIMENT,
            "--out",
            str(out),
            "--compare-paper",
        ]
    )
    assert code == 0
    printed = capsys.readouterr()
    summary = pd.read_csv(out / "result_summary.csv").set_index(["controller", "env"])
    direct = _direct_scores(store_uri)
    assert sorted(summary.index) == sorted(direct.index)
    for key, row in direct.iterrows():
        got = summary.loc[key]
        assert got["n_seeds"] == row["n"]
        assert got["mean"] == pytest.approx(row["mean"], abs=1e-9)
        assert got["std"] == pytest.approx(row["std"], abs=1e-9)

    cells = _markdown_cells(printed.out)
    labels = {
        "hinf": "H∞ dynamic",
        "hinf_f": "H∞ fixed-structure",
        "ddqn": "DDQN",
        "none": "no control",
    }
    envs = {"cartpole": "Cartpole", "mountaincar": "Mountain car"}
    unique_best = 0
    for env, df in direct.groupby(level="env"):
        best = df["mean"].max()
        unique_best += int((df["mean"] == best).sum() == 1)
        for (ctrl, _), row in df.iterrows():
            cell = cells[(labels[ctrl], envs[env])]
            assert cell.startswith("**") == (row["mean"] == best), cell
            assert f"n={int(row['n'])}" in cell
    assert unique_best >= 1, "the store should have a column with a single best cell"
    assert cells[("DDQN", "Mountain car")] == "—"
    assert "[paper: 199.37 ± 1.21]" in cells[("H∞ dynamic", "Cartpole")]
    assert "skipped: no FINISHED runs for environment 'acrobot'" in printed.err
    assert "skipped: no FINISHED runs for controller 'h2'" in printed.err
    assert "1 FAILED" in printed.err

    tex = (out / "result_summary.tex").read_text()
    assert r"\toprule" in tex and r"\bottomrule" in tex and "tab:result_summary" in tex
    assert tex.count(r"\mathbf{") == int(summary["best"].sum())
    assert (out / "run_scores.csv").stat().st_size > 0


def test_solve_episode_is_first_crossing_of_threshold(
    store_uri: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    store = RunStore(store_uri, EXPERIMENT)
    cartpole = store.episodes(["return_ma100"])
    cartpole = cartpole[cartpole["env"] == "cartpole"]
    threshold = float(cartpole.groupby("run_id")["return_ma100"].max().median())
    args = [
        "--tracking-uri",
        store_uri,
        "--experiment",
        EXPERIMENT,
        "--out",
        str(tmp_path),
        "--threshold",
        f"cartpole={threshold}",
    ]
    assert make_table.main(args) == 0
    capsys.readouterr()
    summary = pd.read_csv(tmp_path / "result_summary.csv").set_index(["controller", "env"])
    direct = _direct_scores(store_uri, {"cartpole": threshold})
    assert direct["solved"].sum() > 0
    for key, row in direct.iterrows():
        got = summary.loc[key]
        assert got["n_solved"] == row["solved"]
        if np.isfinite(row["median"]):
            assert got["median_solve_episode"] == pytest.approx(row["median"])
        else:
            assert np.isnan(got["median_solve_episode"])


def test_final_score_is_mean_of_last_100_episodes() -> None:
    n = 150
    episodes = pd.DataFrame(
        {
            "run_id": "r",
            "env": "cartpole",
            "controller": "hinf",
            "seed": 0,
            "episode": np.arange(n),
            "episode_return": np.arange(n, dtype=float),
            "return_ma100": np.arange(n, dtype=float),
        }
    ).sample(frac=1.0, random_state=0)
    runs = pd.DataFrame({"run_id": ["r"], "solve_threshold": [120.0]})
    scores = run_scores(episodes, runs)
    assert scores.loc[0, "final_score"] == pytest.approx(np.arange(50, 150).mean())
    assert scores.loc[0, "solve_episode"] == 121


def test_every_figure_written_and_non_empty(
    store_uri: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = make_figures.main(
        ["--tracking-uri", store_uri, "--experiment", EXPERIMENT, "--out", str(tmp_path)]
    )
    err = capsys.readouterr().err
    assert code == 0
    expected = [
        "Cartpole_learning", "Mountaincar_learning", "Cartpole_loss", "Cartpole_Q500",
        "Cartpole_Q1", "Cartpole_controlinput", "Cartpole_controlinput1", "Cartpole_theta",
        "NTK_range", "FFT", "weight_bode", "closed_loop_sv",
    ]  # fmt: skip
    for name in expected:
        for ext in ("png", "pdf"):
            path = tmp_path / f"{name}.{ext}"
            assert path.exists() and path.stat().st_size > 1000, path
    assert re.search(r"skipped Acrobot_learning: .*acrobot", err)
    assert "Mountaincar_learning: no ddqn runs" in err


def test_missing_selection_is_skipped_with_a_message(
    store_uri: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = [
        "--tracking-uri",
        store_uri,
        "--experiment",
        EXPERIMENT,
        "--out",
        str(tmp_path),
        "--controller",
        "h2",
        "--only",
        "Cartpole_Q500",
        "--only",
        "weight_bode",
        "--only",
        "Cartpole_learning",
    ]
    assert make_figures.main(args) == 0
    err = capsys.readouterr().err
    assert "skipped Cartpole_Q500: no cartpole/h2 run in the store" in err
    assert "skipped weight_bode: no cartpole/h2 run in the store" in err
    assert (tmp_path / "Cartpole_learning.png").exists()
    assert not (tmp_path / "Cartpole_Q500.png").exists()


@pytest.mark.parametrize("script", [make_table, make_figures])
def test_empty_store_is_a_clear_error(
    script: object, store_uri: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = f"sqlite:///{tmp_path / 'nothing.db'}"
    with pytest.raises(SystemExit) as exc:  # no store at all: exit status 2
        script.main(["--tracking-uri", missing, "--out", str(tmp_path / "out")])
    assert exc.value.code == 2
    assert f"error: --tracking-uri={missing!r}: no such file" in capsys.readouterr().err
    for uri, experiment in ((store_uri, "no-such-experiment"),):
        with pytest.raises(SystemExit) as exc:
            script.main(
                [
                    "--tracking-uri",
                    uri,
                    "--experiment",
                    experiment,
                    "--out",
                    str(tmp_path / "out"),
                ]
            )
        assert exc.value.code == 1
        err = capsys.readouterr().err
        assert "error: no FINISHED cdqn runs" in err
        assert uri in err and repr(experiment) in err
    assert not (tmp_path / "nothing.db").exists()
    assert not (tmp_path / "out").exists()


COLUMN_RUNS = [
    # (env, controller, seed, extra overrides): Acrobot as shipped (Double DQN without
    # normalize), Cartpole with a seed only Double DQN has, Mountain car with one Double DQN
    # seed without the radial basis features.
    ("acrobot", "hinf_f", 0, []),
    ("acrobot", "ddqn", 0, []),
    ("cartpole", "hinf_f", 0, []),
    ("cartpole", "ddqn", 0, []),
    ("cartpole", "ddqn", 1, []),
    ("mountaincar", "hinf_f", 0, []),
    ("mountaincar", "hinf_f", 1, []),
    ("mountaincar", "ddqn", 0, []),
    ("mountaincar", "ddqn", 1, ["weights.ddqn.rbf_centres=null"]),
]


@pytest.fixture(scope="module")
def column_store(tmp_path_factory: pytest.TempPathFactory) -> str:
    """Real runs whose columns are not like for like, in three different ways."""
    from cdqn.training.run import run

    uri = f"sqlite:///{tmp_path_factory.mktemp('columns') / 'mlflow.db'}"
    for env, ctrl, seed, extra in COLUMN_RUNS:
        cfg = compose_config(
            [
                *TINY,
                "train.episodes=2",
                "train.signals=false",
                f"tracking.uri={uri}",
                f"tracking.experiment={EXPERIMENT}",
                f"env={env}",
                f"controller={ctrl}",
                f"seed={seed}",
                *extra,
            ]
        )
        assert run(cfg, progress=False).status == "FINISHED"
    return uri


def test_caption_names_every_shared_setting_that_differs(
    column_store: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["--tracking-uri", column_store, "--experiment", EXPERIMENT, "--out", str(tmp_path)]
    assert make_table.main(args) == 0
    out = capsys.readouterr().out
    assert "Not like for like" in out
    assert "Acrobot: env.normalize differs: ddqn false; hinf_f true" in out
    assert "Cartpole: seed differs: ddqn 0–1; hinf_f 0" in out
    # Double DQN's Mountain car runs with and without the features: two groups, never averaged
    assert "2 groups of settings" in out and "6 or null" not in out
    diffs = column_differences(RunStore(column_store, EXPERIMENT).runs())
    assert {(d.env, d.key) for d in diffs} == {
        ("acrobot", "env.normalize"),
        ("cartpole", "seed"),
        ("mountaincar", "env.rbf_centres"),
    }
    assert "Not like for like" in (tmp_path / "result_summary.tex").read_text()
    settings = (tmp_path / "settings.md").read_text()
    assert "| **env.normalize** | true | false |" in settings
    assert "| env.normalize | true | true |" in settings  # Mountain car: shared
    assert "| **env.rbf_centres** | 6 | 6 or null |" in settings


def test_like_for_like_columns_say_so(
    column_store: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["--tracking-uri", column_store, "--experiment", EXPERIMENT, "--out", str(tmp_path)]
    assert make_table.main([*args, "--where", "env=mountaincar", "--where", "seed=0"]) == 0
    out = capsys.readouterr().out
    assert "Like for like: the agents of each column share seed, train.episodes" in out
    assert "differs" not in out


def test_auc_is_mean_moving_average_and_steps_count_to_solve_episode() -> None:
    n = 6
    episodes = pd.DataFrame(
        {
            "run_id": "r",
            "env": "cartpole",
            "controller": "hinf",
            "seed": 0,
            "episode": np.arange(n),
            "episode_return": np.arange(n, dtype=float),
            "return_ma100": np.array([0.0, 1.0, 3.0, 2.0, 5.0, 7.0]),
            "episode_length": np.array([10.0, 20.0, 30.0, 40.0, 50.0, 60.0]),
        }
    )
    runs = pd.DataFrame({"run_id": ["r"], "solve_threshold": [2.5]})
    scores = run_scores(episodes, runs)
    assert scores.loc[0, "auc"] == pytest.approx(3.0)
    assert scores.loc[0, "solve_episode"] == 3
    assert scores.loc[0, "solve_steps"] == 60.0


def test_shipped_configs_differ_only_in_acrobot_normalize() -> None:
    """The paper's four agents, composed as ``python -m cdqn.train`` would run them: every
    column shares its observation map, exploration and network except Acrobot's normalize."""
    from omegaconf import OmegaConf

    from cdqn.training.tracking import flatten

    rows = []
    for env in ("cartpole", "acrobot", "mountaincar"):
        for ctrl in ("h2", "hinf_f", "hinf", "ddqn"):
            cfg = compose_config([f"env={env}", f"controller={ctrl}"])
            params = flatten(OmegaConf.to_container(cfg, resolve=True))
            row = {f"params.{k}": str(v) for k, v in params.items()}
            rows.append({**row, "env": env, "controller": ctrl, "seed": 0})
    diffs = column_differences(pd.DataFrame(rows))
    assert [d.text() for d in diffs] == [
        "Acrobot: env.normalize differs: ddqn false; h2, hinf, hinf_f true"
    ]


def _claim_lines(text: str) -> dict[str, str]:
    """Claim text -> the rest of its line (statistic and verdict)."""
    lines = [ln[2:] for ln in text.splitlines() if ln.startswith("- ")]
    return dict(ln.split(": ", 1) for ln in lines)


def test_claims_state_statistic_and_verdict(
    store_uri: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from scipy.stats import mannwhitneyu

    args = ["--tracking-uri", store_uri, "--experiment", EXPERIMENT, "--out", str(tmp_path)]
    assert make_table.main([*args, "--claims"]) == 0
    out = capsys.readouterr().out
    claims = _claim_lines((tmp_path / "claims.md").read_text())
    assert claims == _claim_lines(out)

    scores = pd.read_csv(tmp_path / "run_scores.csv")
    cart = scores[scores["env"] == "cartpole"]
    hinf = cart.loc[cart["controller"] == "hinf", "final_score"].to_numpy()
    ddqn = cart.loc[cart["controller"] == "ddqn", "final_score"].to_numpy()
    p = mannwhitneyu(hinf, ddqn, alternative="greater").pvalue
    beats = claims["H∞ dynamic beats DDQN on Cartpole"]
    assert f"final {hinf.mean():.2f} vs {ddqn.mean():.2f}" in beats
    assert f"Mann–Whitney p = {p:.3g}" in beats
    assert beats.endswith("-> does not hold")  # two seeds against two: p >= 1/6
    assert claims["H∞ dynamic beats DDQN on Mountain car"] == (
        "seeds: H∞ dynamic 2, DDQN 0 -> not measurable"
    )
    # the store's one diverged run (cartpole, no control) is counted beside the controlled ones
    every = RunStore(store_uri, EXPERIMENT, statuses=("FINISHED", "FAILED")).runs()
    n = int(every["controller"].isin(("h2", "hinf", "hinf_f")).sum())
    assert claims["No divergence of the controlled agents over all runs"] == (
        f"0 of {n} controlled runs diverged; other agents 1 of {N_FINISHED + 1 - n} -> holds"
    )

    store = RunStore(store_uri, EXPERIMENT)
    runs = store.runs()
    q0, ret = [], []
    for run_id in runs.loc[(runs["env"] == "cartpole") & (runs["controller"] == "hinf"), "run_id"]:
        steps = store.steps(run_id)
        firsts = steps.sort_values("step").groupby("episode").first()
        q0.append(firsts["q1"].mean())
        ret.append(steps.groupby("episode")["reward"].sum().mean())  # γ = 1
    q = claims["H∞ dynamic Q-values settle below the true return on Cartpole"]
    assert q.startswith(f"Q(s0) {np.mean(q0):.1f} vs return {np.mean(ret):.1f}")
    below = sum(a < b for a, b in zip(q0, ret, strict=True))
    assert f"{below}/2 seeds below" in q
    assert q.endswith("-> holds" if below == 2 else "-> does not hold")


def test_q_gap_discounts_with_the_agents_gamma() -> None:
    from analysis.claims import agent_gamma, q_gap

    steps = pd.DataFrame(
        {
            "episode": [0, 0, 0, 1, 1],
            "step": [2, 0, 1, 0, 1],
            "reward": [1.0, 1.0, 1.0, 2.0, 2.0],
            "q1": [9.0, 5.0, 9.0, 7.0, 9.0],
        }
    )
    gap = q_gap(steps, 0.5)
    assert gap.q0 == pytest.approx(6.0)  # first steps: 5 and 7
    assert gap.ret == pytest.approx(((1 + 0.5 + 0.25) + (2 + 1)) / 2)
    assert q_gap(steps, 0.5, last=1).q0 == pytest.approx(7.0)
    ddqn = pd.Series({"controller": "ddqn", "params.controller.discount": "0.99",
                      "params.train.discount": "1.0"})  # fmt: skip
    assert agent_gamma(ddqn) == 0.99
    assert agent_gamma(ddqn.replace({"ddqn": "hinf"})) == 1.0


def _tuned_runs(budgets: dict[str, str], offered: dict[str, list[str]]) -> pd.DataFrame:
    """Two runs per agent of one column: each agent's own ε decrease, its preset's budget
    (episodes) and the paths its search offered."""
    rows = []
    for i, ctrl in enumerate(budgets):
        for seed in (0, 1):
            row = {"env": "cartpole", "controller": ctrl, "seed": seed,
                   "params.train.eps_dec": str(1e-4 * (i + 1)),
                   "params.extra.tuned.budget.trials": "20",
                   "params.extra.tuned.budget.seeds": "3",
                   "params.extra.tuned.budget.first_seed": "100",
                   "params.extra.tuned.budget.episodes": budgets[ctrl]}  # fmt: skip
            for n, path in enumerate(offered[ctrl]):
                row[f"params.extra.tuned.space.d{n}.path"] = path
            rows.append(row)
    return pd.DataFrame(rows)


def test_a_setting_chosen_by_equal_searches_is_like_for_like() -> None:
    """An ε decrease that differs because each agent's search of the same budget chose it
    keeps the column like for like; another budget, or a search that did not offer it, does
    not."""
    both = {"ddqn": ["train.eps_dec"], "hinf_f": ["train.eps_dec", "train.lr"]}
    text = caption(_tuned_runs({"ddqn": "500", "hinf_f": "500"}, both))
    assert text.startswith("Like for like")
    assert "20 trials × 3 seeds (from 100) × 500 episodes" in text
    assert "train.eps_dec differs" in text
    other_budget = caption(_tuned_runs({"ddqn": "500", "hinf_f": "200"}, both))
    assert other_budget.startswith("Not like for like")
    not_offered = {"ddqn": ["train.lr"], "hinf_f": ["train.eps_dec"]}
    assert caption(_tuned_runs({"ddqn": "500", "hinf_f": "500"}, not_offered)).startswith(
        "Not like for like"
    )
