"""The research preset and the ablation sweeps: every job composes, validates and changes what
it says; ``make_table.py --research`` and ``--ablation`` render from a store of real runs.

The store holds tiny real runs (width 16, 3 episodes) of the paper sweep (the present table),
the research preset and three ablations, one of whose runs diverges (FAILED).
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hydra import compose, initialize_config_dir
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig, OmegaConf

from analysis import make_table
from analysis.compare import ABLATION, present_runs
from analysis.runs import RunStore, comparable_runs
from cdqn.config import validate
from cdqn.training.tracking import flatten
from tests.conftest import CONF_DIR

SWEEPS = CONF_DIR.parent / "sweeps"
ABLATIONS = sorted(p.stem for p in (SWEEPS / "ablation").glob("*.yaml"))
ENVS, AGENTS = ("cartpole", "acrobot", "mountaincar"), ("h2", "hinf", "hinf_f", "ddqn")
CELLS = [(e, c) for e in ENVS for c in AGENTS]
NOT_SETTINGS = ("extra.", "tracking.")
"""Keys an ablation sets that do not change what a run learns."""
TINY = ["network.width=16", "train.episodes=3", "train.progress=false", "train.population=2"]


def compose_sweep(name: str, overrides: list[str], hydra: bool = True) -> DictConfig:
    """What ``python -m cdqn.train -m --config-dir sweeps --config-name <name> <overrides>``
    composes for one job (``hydra``: with the ``hydra`` node)."""
    with initialize_config_dir(str(SWEEPS), version_base="1.3"):
        return compose(
            name,
            overrides=[f"hydra.searchpath=[file://{CONF_DIR}]", *overrides],
            return_hydra_config=hydra,
        )


@cache
def _job(name: str, overrides: tuple[str, ...]) -> dict[str, object]:
    """One job's resolved settings, flattened, after checking that it is a valid run."""
    cfg = compose_sweep(name, list(overrides), hydra=False)
    validate(OmegaConf.to_object(cfg))
    return flatten(OmegaConf.to_container(cfg, resolve=True))


def _swept(cfg: DictConfig) -> list[tuple[str, str]]:
    params = cfg.hydra.sweeper.params
    return [(e, c) for e in params.env.split(",") for c in params.controller.split(",")]


@pytest.mark.parametrize("name", ABLATIONS)
def test_every_ablation_job_validates_and_changes_its_cells(name: str) -> None:
    """Each job of an ablation is a valid configuration that differs from the paper sweep's
    job of the same cell in a setting that changes learning; the sweep's own folder,
    experiment and run params name it."""
    cfg = compose_sweep("paper", [f"+ablation={name}"])
    assert cfg.hydra.sweep.dir == f"multirun/ablation/{name}"
    assert (cfg.tracking.experiment, cfg.extra.ablation) == ("cdqn-ablation", name)
    assert 1 <= int(cfg.extra.departure) <= 15
    for env, ctrl in _swept(cfg):
        cell = (f"env={env}", f"controller={ctrl}")
        mine, paper = _job("paper", (f"+ablation={name}", *cell)), _job("paper", cell)
        assert (mine["train.episodes"], mine["network.width"]) == (2000, 2500)
        changed = {k for k in mine.keys() | paper.keys() if mine.get(k) != paper.get(k)}
        assert {k for k in changed if not k.startswith(NOT_SETTINGS)}, (name, env, ctrl)


def test_ablations_are_named_apart() -> None:
    dirs = {compose_sweep("paper", [f"+ablation={a}"]).hydra.sweep.dir for a in ABLATIONS}
    assert len(dirs) == len(ABLATIONS) >= 14


def test_the_research_preset_takes_the_research_codes_settings() -> None:
    cfg = compose_sweep("research", [])
    assert cfg.tracking.experiment == "cdqn-research"
    assert cfg.hydra.sweep.dir == "multirun/research"
    assert sorted(_swept(cfg)) == sorted(CELLS)
    for env, ctrl in CELLS:
        job = compose_sweep("research", [f"env={env}", f"controller={ctrl}"], hydra=False)
        validate(OmegaConf.to_object(job))
        assert (job.train.episodes, job.network.width, job.train.lr) == (2000, 2500, 5e-5)
        assert (job.env.normalize, job.env.rbf_centres) == (False, None)
        assert (job.train.eps_dec, job.train.eps_schedule) == (1e-4, "random_action")
        assert job.env.obs_indices == ([2, 3] if env == "cartpole" else None)
        assert job.weights.replay.repeats == (500 if (env, ctrl) == ("acrobot", "hinf_f") else 0)
        if ctrl == "ddqn":
            assert not job.train.bootstrap_terminal
            assert (job.controller.discount, job.controller.lr) == (None, None)
            assert job.controller.target_update == 500
        else:
            assert job.train.bootstrap_terminal and job.controller.reset_integrator
            assert job.controller.design == "paper"
            assert job.controller.discretization == "euler"


STORE_RUNS = [
    # (sweep config, extra overrides, env, controller)
    ("paper", [], "cartpole", "h2"),
    ("paper", [], "cartpole", "hinf_f"),
    ("paper", ["train.episodes=4"], "cartpole", "h2"),  # another budget: never beside
    ("research", [], "cartpole", "h2"),
    ("research", [], "cartpole", "hinf_f"),
    ("paper", ["+ablation=h2-gain-map"], "cartpole", "h2"),
    ("paper", ["+ablation=bootstrap"], "cartpole", "h2"),
    ("paper", ["+ablation=bootstrap"], "cartpole", "hinf_f"),
    ("paper", ["+ablation=target", "train.q_limit=1e-9"], "cartpole", "h2"),  # diverges
]


@pytest.fixture(scope="module")
def store_uri(tmp_path_factory: pytest.TempPathFactory) -> str:
    from cdqn.training.run import run_population

    uri = f"sqlite:///{tmp_path_factory.mktemp('compare') / 'mlflow.db'}"
    for name, extra, env, ctrl in STORE_RUNS:
        cell = [f"env={env}", f"controller={ctrl}"]
        cfg = compose_sweep(name, [f"tracking.uri={uri}", *TINY, *cell, *extra], hydra=False)
        run_population(cfg, progress=False)
    return uri


def _scores(uri: str, experiment: str, **params: str) -> dict[tuple[str, str], np.ndarray]:
    """Final scores per cell straight from the client, for the runs with these params."""
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name(experiment)
    out: dict[tuple[str, str], list[float]] = {}
    for r in client.search_runs([exp.experiment_id]):
        p = r.data.params
        if r.info.status != "FINISHED" or any(p.get(k) != v for k, v in params.items()):
            continue
        hist = client.get_metric_history(r.info.run_id, "episode_return")
        cell = (r.data.tags["env"], r.data.tags["controller"])
        out.setdefault(cell, []).append(float(np.mean([m.value for m in hist][-100:])))
    return {k: np.array(v) for k, v in out.items()}


def _text(values: np.ndarray) -> str:
    return f"{values.mean():.2f} ± {np.std(values):.2f}, 0/{len(values)}"


def test_research_table_sets_the_preset_beside_the_present_and_the_paper(
    store_uri: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["--tracking-uri", store_uri, "--out", str(tmp_path), "--research"]
    assert make_table.main(args) == 0
    out = capsys.readouterr().out
    research = _scores(store_uri, "cdqn-research")[("cartpole", "h2")]
    present = _scores(store_uri, "cdqn", **{"train.episodes": "3"})[("cartpole", "h2")]
    change = research.mean() - present.mean()
    row = next(line for line in out.splitlines() if line.startswith("| H2 |"))
    assert row == (
        f"| H2 | {_text(research)} (Δ {change:+.2f}); present {_text(present)}; "
        "paper 187.92 ± 2.47 |"
    )
    csv = pd.read_csv(tmp_path / "research.csv")
    assert set(csv["controller"]) == {"h2", "hinf_f"}
    h2 = csv[csv["controller"] == "h2"].iloc[0]
    assert h2["change"] == pytest.approx(change) and h2["present_n_seeds"] == 2
    assert (tmp_path / "research.md").read_text().startswith("| controller | Cartpole |")


def test_ablation_table_has_a_row_per_departure_and_the_cells_it_touched(
    store_uri: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["--tracking-uri", store_uri, "--out", str(tmp_path), "--ablation"]
    assert make_table.main(args) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "| departure undone | Cartpole H2 | Cartpole H∞ fixed-structure |"
    body = [line for line in lines[2:] if line.startswith("| ")]
    rows = {line.split(" | ")[0][2:]: line[2:-2].split(" | ")[1:] for line in body}
    assert list(rows) == ["2 h2-gain-map", "8 bootstrap", "10 target", "present table"]
    present = _scores(store_uri, "cdqn", **{"train.episodes": "3"})
    boot = _scores(store_uri, "cdqn-ablation", **{ABLATION: "bootstrap"})
    for i, cell in enumerate([("cartpole", "h2"), ("cartpole", "hinf_f")]):
        change = boot[cell].mean() - present[cell].mean()
        assert rows["8 bootstrap"][i] == f"{_text(boot[cell])} (Δ {change:+.2f})"
        assert rows["present table"][i] == _text(present[cell])
    assert rows["2 h2-gain-map"][1] == ""  # a cell the ablation does not touch
    assert rows["10 target"][0] == "2 failed"
    csv = pd.read_csv(tmp_path / "ablation.csv")
    assert set(csv["label"]) == {"2 h2-gain-map", "8 bootstrap"}


def test_the_present_cell_shares_the_compared_cells_budget(store_uri: str) -> None:
    present, _ = comparable_runs(RunStore(store_uri, "cdqn").runs())
    compared, _ = comparable_runs(RunStore(store_uri, "cdqn-research").runs())
    beside = present_runs(present, compared)
    assert len(present) == 6 and len(beside) == 4
    assert set(beside["params.train.episodes"]) == {"3"}
