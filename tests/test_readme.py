"""The README's command examples run as written, with tiny budgets appended, in a temporary
folder; the paths cdqn writes there are all in ``.gitignore``; ``--help`` is short.

Every ``python -m cdqn.<tool>`` and ``python analysis/<script>.py`` line of the README's
``bash`` blocks is found by parsing them; a command is left out only for a stated reason
(a placeholder no earlier command fills, more than four runs, an optional package)."""

from __future__ import annotations

import importlib.util
import re
import shlex
import subprocess
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

from tests.helpers import run_cli, run_script

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"

TINY: dict[str, list[str]] = {
    "cdqn.train": ["network.width=32", "train.episodes=3", "train.progress=false"],
    "cdqn.tune": ["network.width=32", "tune.trials=1", "tune.seeds=1", "tune.episodes=2"],
    "cdqn.evaluate": ["episodes=2"],
    "cdqn.synthesize": ["network.width=32"],
    "cdqn.bench": [
        "--controllers",
        "none",
        "--width",
        "32",
        "--steps",
        "60",
        "--warmup",
        "10",
        "--repeats",
        "1",
        "--population",
        "0",
        "--no-estimate",
    ],  # fmt: skip
    "analysis/make_table.py": [],
    "analysis/make_figures.py": ["--only", "FFT", "--only", "Cartpole_controlinput"],
}
"""What each tool gets appended (an appended key replaces the README's own value)."""
MAX_RUNS = 4


def readme_commands(text: str) -> list[list[str]]:
    """The cdqn and analysis commands of the README's ``bash`` blocks, as argument lists
    (comments dropped, continuation lines joined)."""
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S):
        for line in block.replace("\\\n", " ").splitlines():
            args = shlex.split(line, comments=True)
            if len(args) > 2 and args[:2] == ["python", "-m"] and args[2].startswith("cdqn."):
                commands.append(args[2:])
            elif args[:1] == ["python"] and len(args) > 1 and args[1].startswith("analysis/"):
                commands.append(args[1:])
    return commands


def skip_reason(args: list[str]) -> str | None:
    """Why a README command is not run here, or None."""
    text = " ".join(args)
    if "tuned_<" in text:
        return "needs the preset a tuning study writes"
    if args[0] == "cdqn.tune":
        return "a tuning study (its own tests: tests/test_tune.py)"
    if "resume=<" in text:
        return "needs an interrupted run (tests/test_resume.py)"
    if "range(" in text:
        return f"more than {MAX_RUNS} runs"
    if "LunarLander" in text and importlib.util.find_spec("Box2D") is None:
        return "needs gymnasium[box2d]"
    return None


def with_budget(args: list[str], run_id: str) -> list[str]:
    """``args`` with the tiny budget of its tool appended (replacing the same keys) and
    ``<run_id>`` filled in."""
    tool, rest = args[0], [a.replace("<run_id>", run_id) for a in args[1:]]
    tiny = TINY[tool]
    if tool.startswith("cdqn.") and tool != "cdqn.bench":
        keys = {t.split("=")[0] for t in tiny}
        rest = [a for a in rest if a.split("=")[0] not in keys]
    return [tool, *rest, *tiny]


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    """``python -m <tool> <args>`` (``python <script> <args>``) in ``cwd``, with this
    checkout's ``cdqn`` importable (:func:`tests.helpers.run_cli`)."""
    tool, rest = args[0], args[1:]
    if tool.startswith("analysis/"):
        return run_script(ROOT / tool, rest, cwd, timeout=600)
    return run_cli(tool, rest, cwd, timeout=600)


def test_readme_commands_are_found() -> None:
    commands = readme_commands(README.read_text())
    tools = {c[0] for c in commands}
    assert {"cdqn.train", "cdqn.evaluate", "cdqn.bench", "cdqn.synthesize", "cdqn.tune"} <= tools
    assert {"analysis/make_table.py", "analysis/make_figures.py"} <= tools
    assert all(c[0] in TINY for c in commands), [c[0] for c in commands]


@pytest.mark.slow
def test_readme_commands_run(tmp_path: Path) -> None:
    commands = readme_commands(README.read_text())
    ran, skipped = [], []
    run_id = ""
    for args in commands:
        if (why := skip_reason(args)) is not None:
            skipped.append(f"{' '.join(args)}: {why}")
            continue
        full = with_budget(args, run_id)
        proc = _run(full, tmp_path)
        assert proc.returncode == 0, f"{' '.join(full)}\n{proc.stdout[-2000:]}{proc.stderr[-3000:]}"
        assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
        ran.append(" ".join(full))
        if args[0] == "cdqn.train" and not run_id:
            client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
            run_id = client.search_runs(["1"])[0].info.run_id
    assert len(ran) >= 9, (ran, skipped)
    assert _ignored(tmp_path) == []


def _ignored(folder: Path) -> list[str]:
    """Top-level entries of ``folder`` (where the commands ran) that ``.gitignore`` misses."""
    missing = []
    for entry in sorted(folder.iterdir()):
        name = entry.name + ("/x" if entry.is_dir() else "")
        proc = subprocess.run(
            ["git", "-C", str(ROOT), "check-ignore", "-q", "--no-index", name],
            capture_output=True,
        )
        if proc.returncode != 0:
            missing.append(entry.name)
    return missing


@pytest.mark.parametrize("tool", ["cdqn.train", "cdqn.tune"])
def test_help_lists_the_groups_and_points_to_the_docs(tool: str, tmp_path: Path) -> None:
    proc = _run([tool, "--help"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert len(lines) < 40, proc.stdout
    for group in ("controller", "env", "network", "tracking", "train", "weights"):
        assert any(ln.startswith(f"{group}: ") for ln in lines), proc.stdout
    assert "cdqn/config.py" in proc.stdout and "docs/" in proc.stdout


def test_every_path_cdqn_writes_is_ignored() -> None:
    """The defaults of every place cdqn writes into the folder it runs in."""
    from cdqn.config import TrackingConfig
    from cdqn.tuning.settings import TuneSettings

    tune = TuneSettings()
    optuna = tune.storage.removeprefix("sqlite:///")
    paths = [
        "mlflow.db", "mlflow.db.lock", "mlruns/0/x", "outputs/x", "multirun/x",
        f"{TrackingConfig().local_checkpoints}/x", optuna, f"{optuna}.tune-lock",
        f"{tune.preset_dir}/weights/x.yaml", "synthesis/x", "tables/x", "figures/x",
    ]  # fmt: skip
    proc = subprocess.run(
        ["git", "-C", str(ROOT), "check-ignore", "--no-index", "-v", "-n", *paths],
        capture_output=True,
        text=True,
    )
    missing = [ln.split("\t")[-1] for ln in proc.stdout.splitlines() if ln.startswith("::")]
    assert missing == [], missing
