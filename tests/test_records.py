"""The records contract (:mod:`cdqn.records`) agrees with the documented table of what a run
records, and a real run writes nothing outside it."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pandas as pd
import pytest
from mlflow.tracking import MlflowClient

import cdqn.records as records
from cdqn.records import (
    EPISODE_METRICS,
    FFT_COLUMNS,
    SERIES_METRICS,
    STEP_COLUMNS,
    Artifact,
    Metric,
    Signal,
    Tag,
    names,
)
from cdqn.training.loop import EpisodeStats
from cdqn.training.run import run
from tests.conftest import compose_config

DOC = Path(__file__).resolve().parents[1] / "docs" / "how_it_works.md"
SECTION = "## What a run records in MLflow"
METRICS = set(names(Metric)) | set(SERIES_METRICS)
TAGS = set(names(Tag))
ARTIFACTS = set(names(Artifact))


def _documented(doc: str) -> dict[str, set[str]]:
    """Keys of the table under :data:`SECTION` of ``doc``: ``metrics``, ``tags``,
    ``artifacts`` and ``columns`` (the comma-separated column lists of the parquet rows)."""
    text = doc.split(SECTION, 1)[1].split("\n## ", 1)[0]
    out: dict[str, set[str]] = {
        "metrics": set(),
        "tags": set(),
        "artifacts": set(),
        "columns": set(),
    }
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 2 or cells[1] in ("where", "---", "params"):
            continue
        what, where = re.sub(r"\([^()]*\)", "", cells[0]), cells[1]
        kind = where.split()[0].rstrip("s") + "s"
        out["columns"] |= {t for t in re.findall(r"`([^`]+)`", what) if "," in t}
        tokens = re.findall(r"`([^`,]+)`", where if kind == "artifacts" else what)
        keys: list[str] = []
        for tok in tokens:
            if tok.startswith("_") and keys:  # `signals/ratio_box_lower`/`_upper`
                keys.append(keys[-1].rsplit("_", 1)[0] + tok)
            else:
                keys.append(tok)
        out[kind] |= set(keys)
    return out


@pytest.fixture(scope="module")
def documented() -> dict[str, set[str]]:
    return _documented(DOC.read_text())


def test_every_documented_key_is_in_the_contract(documented: dict[str, set[str]]) -> None:
    assert documented["metrics"] and documented["tags"] and documented["artifacts"]
    assert documented["metrics"] - METRICS == set()
    assert documented["tags"] - TAGS == set()
    assert documented["artifacts"] - ARTIFACTS == set()
    assert documented["columns"] == {", ".join(STEP_COLUMNS), ", ".join(FFT_COLUMNS)}


def test_every_key_of_the_contract_is_documented(documented: dict[str, set[str]]) -> None:
    assert METRICS - documented["metrics"] == set()
    assert TAGS - documented["tags"] == set()
    folders = {p for p in ARTIFACTS if p.endswith("/")}
    parents = {a.rsplit("/", 1)[0] + "/" for a in documented["artifacts"] if "/" in a}
    assert ARTIFACTS - documented["artifacts"] - (folders & parents) == set()


def test_the_check_sees_a_key_left_out_of_the_table_or_one_too_many() -> None:
    text = DOC.read_text()
    for key, kind in ((Metric.UNSTABLE_FRACTION, "metrics"), (Tag.POPULATION_ID, "tags")):
        assert f"`{key}`" in text
        found = _documented(text.replace(f"`{key}`", "it"))
        assert key not in found[kind]
    pair = "`signals/ratio_box_lower`/`_upper`"
    assert pair in text
    found = _documented(text.replace(pair, "`signals/ratio_box_lower`"))
    assert "signals/ratio_box_upper" not in found["metrics"]
    found = _documented(text.replace("`final_score`, the mean", "`final_score`, `score`, the mean"))
    assert found["metrics"] - METRICS == {"score"}


def test_the_contract_is_a_lower_layer_with_unique_names() -> None:
    tree = ast.parse(Path(records.__file__).read_text())
    imported = {
        n.module if isinstance(n, ast.ImportFrom) else a.name
        for n in ast.walk(tree)
        if isinstance(n, ast.Import | ast.ImportFrom)
        for a in n.names
    }
    assert {m for m in imported if m and m.startswith("cdqn")} <= {"cdqn.config"}
    for space in (Metric, Tag, Artifact, Signal):
        values = names(space)
        assert len(values) == len(set(values)), space
    assert set(STEP_COLUMNS) | set(FFT_COLUMNS) == set(names(Signal))


def test_the_episode_metrics_are_what_the_training_loop_logs() -> None:
    stats = EpisodeStats(0, 1.0, 1.0, 1, 0.1, 0.0, 2.0, 0.0, 0, 0.1, 0.2, 0.3)
    assert tuple(stats.metrics()) == EPISODE_METRICS


def _artifact_files(client: MlflowClient, run_id: str, path: str | None = None) -> list[str]:
    out: list[str] = []
    for item in client.list_artifacts(run_id, path):
        out += _artifact_files(client, run_id, item.path) if item.is_dir else [item.path]
    return out


def test_a_real_run_writes_only_the_contract(tmp_path: Path) -> None:
    """A tiny controlled run (``network=small train.episodes=3``) in a real SQLite store:
    its metrics, tags, artifacts and signal columns are the contract's."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    cfg = compose_config(
        ["network=small", "train.episodes=3", f"tracking.uri={uri}", "controller=hinf"]
    )
    result = run(cfg, progress=False)
    client = MlflowClient(uri)
    data = client.get_run(result.run_id).data
    assert set(data.metrics) <= METRICS
    assert {Metric.EPISODE_RETURN, Metric.FINAL_SCORE, Metric.THETA1_OUTSIDE_BOX} <= set(
        data.metrics
    )
    assert set(data.metrics) >= set(SERIES_METRICS)  # a run with an NTK box writes them all
    own = {t for t in data.tags if not t.startswith("mlflow.")}
    assert own <= TAGS
    assert {Tag.ENV, Tag.ENV_ID, Tag.CONTROLLER, Tag.SEED, Tag.CONFIG_HASH} <= own
    files = _artifact_files(client, result.run_id)
    folders = tuple(p for p in ARTIFACTS if p.endswith("/"))
    assert [f for f in files if f not in ARTIFACTS and not f.startswith(folders)] == []
    assert {Artifact.CONFIG, Artifact.STEPS, Artifact.FFT, Artifact.DESIGN_RECORD} <= set(files)
    assert any(f.startswith(Artifact.MODEL) for f in files)
    steps = pd.read_parquet(client.download_artifacts(result.run_id, Artifact.STEPS, str(tmp_path)))
    fft = pd.read_parquet(client.download_artifacts(result.run_id, Artifact.FFT, str(tmp_path)))
    assert tuple(steps.columns) == STEP_COLUMNS and tuple(fft.columns) == FFT_COLUMNS
