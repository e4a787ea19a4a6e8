"""What a run shows in MLflow and says at its end: the per-step signals and spectra as
metric series (checked against a direct computation, and in a real store for a single run
and a population's members), run names from the settings that differ from the defaults,
and the closing summary of a resumed run."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from mlflow.tracking import MlflowClient
from omegaconf import OmegaConf

from cdqn.training.result import RunResult, result_lines
from cdqn.training.run import run
from cdqn.training.signals import (
    COLUMNS,
    SERIES_POINTS,
    SPECTRUM_POINTS,
    amplitude_spectra,
    signal_series,
)
from cdqn.training.sweep import run_name
from tests.conftest import TINY, compose_config

BOX = ((200.0, 500.0), (0.8, 1.2))


def _table(rows: int, seed: int = 0) -> np.ndarray:
    table = np.random.default_rng(seed).normal(size=(rows, len(COLUMNS)))
    table[:, 0], table[:, 1] = np.arange(rows) // 50, np.arange(rows) % 50
    table[:, COLUMNS.index("reward")] = 1.0  # CartPole's constant reward
    table[:, COLUMNS.index("theta1")] = 300.0 + 10 * table[:, COLUMNS.index("theta1")]
    return table


def _series(points: list, key: str) -> tuple[np.ndarray, np.ndarray]:
    hits = [(p.step, p.value) for p in points if p.key == key]
    return np.array([s for s, _ in hits]), np.array([v for _, v in hits])


def test_signal_series_are_span_means_and_binned_spectra() -> None:
    rows = 10_007
    table = _table(rows)
    table[:100, COLUMNS.index("q2")] = np.nan  # a span's NaN rows are left out of its mean
    frame = pd.DataFrame(table, columns=list(COLUMNS))
    spectra = amplitude_spectra(frame, 5e-5)
    points = signal_series(table, spectra, BOX)
    assert len(points) <= 1000  # one log_batch
    edges = np.linspace(0, rows, SERIES_POINTS + 1).astype(int)
    for name in ("u", "q1", "q2", "theta1"):
        steps, values = _series(points, f"signals/{name}")
        col = table[:, COLUMNS.index(name)]
        want = [np.nanmean(col[a:b]) for a, b in zip(edges[:-1], edges[1:], strict=True)]
        assert np.allclose(values, want) and len(values) == SERIES_POINTS
        assert np.array_equal(steps, (edges[:-1] + edges[1:]) // 2)
    _, ratio = _series(points, "signals/theta2_over_theta1")
    t1, t2 = table[:, COLUMNS.index("theta1")], table[:, COLUMNS.index("theta2")]
    want = [t2[a:b].mean() / t1[a:b].mean() for a, b in zip(edges[:-1], edges[1:], strict=True)]
    assert np.allclose(ratio, want)
    steps, lower = _series(points, "signals/theta1_box_lower")
    assert list(lower) == [200.0, 200.0] and steps[-1] == (edges[-2] + edges[-1]) // 2
    # spectra: the largest amplitude per log-spaced bin of ω, at step round(1000 ω)
    omega = 2 * np.pi * spectra["freq"].to_numpy()
    steps, peaks = _series(points, "spectrum/q1")
    assert 0 < len(peaks) <= SPECTRUM_POINTS and np.all(np.diff(steps) > 0)
    assert peaks.max() == pytest.approx(spectra["q1"].to_numpy()[omega > 0].max())
    assert 1000 * omega[1] <= steps[0] and steps[-1] <= 1000 * omega[-1] + 1
    _, reward = _series(points, "spectrum/reward")
    assert np.all(reward == 0.0)  # a constant reward: nothing but its DC term, no round-off


def test_signal_series_leave_out_what_was_not_recorded() -> None:
    table = _table(500)
    table[:, COLUMNS.index("theta1")] = np.nan  # Double DQN records no NTK
    table[:, COLUMNS.index("theta2")] = np.nan
    keys = {p.key for p in signal_series(table, None, None)}
    assert keys == {"signals/u", "signals/q1", "signals/q2"}
    assert signal_series(table[:0], None, BOX) == []


@pytest.mark.parametrize(
    ("overrides", "name"),
    [
        ([], "cartpole-hinf-s0"),
        (["network=small", "train.episodes=50", "seed=3"], "cartpole-hinf-w64-e50-s3"),
        (["env=acrobot", "controller=ddqn", "train.lr=5e-4"], "acrobot-ddqn-lr0.0005-s0"),
        (["controller=h2", "train.discount=0.99"], "cartpole-h2-g0.99-s0"),
    ],
)
def test_run_names_show_the_settings_that_differ_from_the_defaults(
    overrides: list[str], name: str
) -> None:
    conf = OmegaConf.to_object(compose_config(overrides))
    assert run_name(conf) == name


def test_a_resumed_run_says_what_its_time_covers() -> None:
    fresh = RunResult("a", "FINISHED", 10.0, returns=[10.0], steps=1000, seconds=2.0, rate=500.0)
    assert "  1000 environment steps, 2.0 s of training (500 steps/s)" in result_lines(fresh)
    resumed = RunResult(
        "b", "FINISHED", 10.0, returns=[10.0], steps=1000, seconds=2.0, rate=300.0,
        steps_before=400,
    )  # fmt: skip
    line = "  1000 environment steps; resumed at step 400: 600 steps in 2.0 s of training"
    assert f"{line} (300 steps/s)" in result_lines(resumed)


@pytest.mark.slow
@pytest.mark.parametrize("population", [1, 2])
def test_runs_log_their_signals_as_metric_series(tmp_path: Path, population: int) -> None:
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    cfg = compose_config(
        [*TINY, "train.episodes=6", f"train.population={population}", f"tracking.uri={uri}"]
    )
    result = run(cfg, progress=False)
    client = MlflowClient(uri)
    for member in result.members or [result]:
        r = client.get_run(member.run_id)
        assert r.info.run_name == f"cartpole-hinf-w32-e6-s{r.data.tags['seed']}"
        u = client.get_metric_history(member.run_id, "signals/u")
        assert 0 < len(u) <= SERIES_POINTS and u[-1].step < member.steps
        steps = pd.read_parquet(client.download_artifacts(member.run_id, "signals/steps.parquet"))
        first = steps.iloc[: int(np.linspace(0, len(steps), len(u) + 1)[1])]
        assert math.isclose(min(u, key=lambda m: m.step).value, first["u"].mean())
        box = client.get_metric_history(member.run_id, "signals/theta1_box_upper")
        assert len(box) == 2 and box[0].value == box[1].value > 0
        assert client.get_metric_history(member.run_id, "spectrum/q2")
