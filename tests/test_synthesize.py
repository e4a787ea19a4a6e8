"""The synthesis CLI: ``python -m cdqn.synthesize env=<env> controller=<kind> out=<dir>``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from cdqn.control.errors import DesignError
from cdqn.synthesize import synthesize
from tests.conftest import CONF_DIR
from tests.helpers import run_cli

REPO = Path(__file__).resolve().parents[1]


def _cfg(overrides: list[str]):
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        return compose("synthesize", overrides=overrides)


def test_cli_writes_design_and_plots(tmp_path: Path) -> None:
    out = tmp_path / "design"
    proc = run_cli(
        "cdqn.synthesize",
        [
            "env=mountaincar",
            "controller=hinf",
            f"out={out}",
            f"controller.synthesis.cache_dir={tmp_path / 'cache'}",
        ],
        REPO,
    )
    assert proc.returncode == 0, proc.stderr
    assert "certificate: PASSED" in proc.stdout and "achieved γ" in proc.stdout
    assert "learning plant: gradient_flow" in proc.stdout
    record = json.loads((out / "controller.json").read_text())
    for key in ("kind", "A", "B", "C", "D", "theta_bounds", "discount", "gamma"):
        assert key in record
    assert set(record["theta_bounds"]) == {"theta1", "ratio"}
    for name in (
        "weights_bode.png",
        "cover.png",
        "closed_loop_sv.png",
        "ntk_box.png",
        "closed_loop_sv.csv",
        "report.txt",
    ):
        assert (out / name).stat().st_size > 0


def test_cli_error_exits_with_reason(tmp_path: Path) -> None:
    proc = run_cli(
        "cdqn.synthesize",
        [
            "env=cartpole",
            "controller=hinf_f",
            f"out={tmp_path}",
            "weights.theta_bounds.theta1=[200.0,50000.0]",
            "controller.synthesis.plant=paper",
        ],
        REPO,
    )
    assert proc.returncode == 2
    assert "infeasible NTK box" in proc.stderr


def test_h2_report(tmp_path: Path) -> None:
    text = synthesize(_cfg(["env=acrobot", "controller=h2", f"out={tmp_path}"]))
    assert "gain-scheduled LQR" in text
    record = json.loads((tmp_path / "controller.json").read_text())
    assert record["kind"] == "h2" and record["certificate"]["passed"]
    assert record["certificate"]["worst_pole"] < 0
    assert record["certificate"]["plant"] == "gradient_flow"
    assert "learning target kept over the box" in text
    lo, hi = record["learning_target"]["gamma_eff"]
    target = record["learning_target"]["target"]["gamma_eff"]
    assert target[0] - 1e-9 <= lo <= hi <= target[1] + 1e-9


def test_in_process_design_error(tmp_path: Path) -> None:
    cfg = _cfg(
        [
            "env=cartpole",
            "controller=hinf",
            f"out={tmp_path}",
            "controller.synthesis.cache=false",
            "controller.synthesis.plant=paper",
        ]
    )
    with pytest.raises(DesignError, match="failed its certificate"):
        synthesize(cfg)
