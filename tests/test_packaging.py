"""The wheel carries the configs: installed, cdqn runs from any folder, outside the clone."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from tests.helpers import ROOT


def _run(args: list[str], cwd: Path, site: Path) -> subprocess.CompletedProcess[str]:
    """``python <args>`` in ``cwd`` with the installed wheel (``site``) first on the path and
    nothing of the clone importable."""
    env = {**os.environ, "PYTHONPATH": str(site), "PYTHONUNBUFFERED": "1"}
    env.pop("HYDRA_FULL_ERROR", None)
    return subprocess.run(
        [sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=600
    )


@pytest.mark.slow
def test_wheel_runs_outside_the_clone(tmp_path: Path) -> None:
    """Build the wheel, install it (without its dependencies, which this interpreter has) into
    a folder of its own, and run training, the table of its run, tuning's help and synthesis
    from an empty folder."""
    wheels, site, work = tmp_path / "wheels", tmp_path / "site", tmp_path / "work"
    work.mkdir()
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check"]
    subprocess.run([*pip, "wheel", str(ROOT), "--no-deps", "-w", str(wheels)], check=True)
    (wheel,) = wheels.glob("cdqn-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    shipped = {f"cdqn/conf/{p.relative_to(ROOT / 'conf')}" for p in (ROOT / "conf").rglob("*.yaml")}
    assert shipped and shipped <= names, sorted(shipped - names)
    assert "hydra_plugins/cdqn_sweeper/cdqn_sweeper.py" in names
    assert "analysis/make_table.py" in names
    subprocess.run([*pip, "install", "--no-deps", "--target", str(site), str(wheel)], check=True)

    where = _run(
        ["-c", "import cdqn.config as c; print(c.__file__); print(c.CONF_DIR)"], work, site
    )
    assert where.stdout.split() == [str(site / "cdqn" / "config.py"), str(site / "cdqn" / "conf")]

    uri = f"sqlite:///{tmp_path / 'm.db'}"
    train = ["train.episodes=2", "network.width=16", "train.progress=false", f"tracking.uri={uri}"]
    proc = _run(["-m", "cdqn.train", *train], work, site)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "FINISHED" in proc.stdout
    table = _run(["-m", "analysis.make_table", "--tracking-uri", uri, "--out", "t"], work, site)
    assert table.returncode == 0 and "| cartpole |" in table.stdout.lower(), table.stderr[-3000:]
    proc = _run(["-m", "cdqn.train", "--info", "plugins"], work, site)
    assert "CdqnSweeper" in proc.stdout, proc.stdout[-3000:]
    proc = _run(["-m", "cdqn.tune", "--help"], work, site)
    assert proc.returncode == 0 and "python -m cdqn.tune" in proc.stdout, proc.stderr[-3000:]
    out = tmp_path / "design"
    syn = ["controller=hinf_f", f"out={out}", "controller.synthesis.cache=false"]
    proc = _run(["-m", "cdqn.synthesize", *syn], work, site)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "certificate: PASSED" in proc.stdout and (out / "controller.json").is_file()
    proc = _run(["-m", "cdqn.train", "controller=foo", f"tracking.uri={uri}"], work, site)
    assert proc.returncode == 2 and "controller=foo: unknown controller" in proc.stderr
