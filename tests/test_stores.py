"""Every store cdqn cannot use is refused with one line and exit status 2, no traceback:
an unwritable folder, a folder that cannot be created, a file that is not SQLite, another
program's SQLite database, a folder where the database file should be, a server that is down
(a closed port).  The real ``python -m cdqn.train`` and ``analysis/make_table.py`` in
subprocesses."""

from __future__ import annotations

import contextlib
import os
import sqlite3
import subprocess
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.conftest import TINY
from tests.helpers import free_port, run_cli, run_script

pytestmark = pytest.mark.slow  # one CLI start (torch, MLflow imports) per case

ROOT = Path(__file__).resolve().parents[1]


def _unwritable(tmp: Path) -> tuple[str, str]:
    if os.geteuid() == 0:  # root writes anywhere permissions allow: use a read-only fs
        return "sqlite:////sys/mlflow.db", "cannot write to the folder /sys"
    folder = tmp / "readonly"
    folder.mkdir()
    folder.chmod(0o555)
    return f"sqlite:///{folder}/mlflow.db", f"cannot write to the folder {folder}"


def _uncreatable(tmp: Path) -> tuple[str, str]:
    (tmp / "afile").write_text("")
    return f"sqlite:///{tmp}/afile/sub/mlflow.db", f"cannot create the folder {tmp}/afile/sub"


def _not_sqlite(tmp: Path) -> tuple[str, str]:
    (tmp / "notes.db").write_text("these are notes, not a database\n")
    return f"sqlite:///{tmp}/notes.db", f"{tmp}/notes.db is not an SQLite database"


def _other_program(tmp: Path) -> tuple[str, str]:
    with contextlib.closing(sqlite3.connect(tmp / "optuna.db")) as db:
        db.execute("CREATE TABLE studies (study_id INTEGER PRIMARY KEY, study_name TEXT)")
        db.commit()
    return f"sqlite:///{tmp}/optuna.db", f"{tmp}/optuna.db is another program's SQLite database"


def _folder_as_file(tmp: Path) -> tuple[str, str]:
    (tmp / "store.db").mkdir()
    return f"sqlite:///{tmp}/store.db", f"{tmp}/store.db is not a file"


def _server_down(tmp: Path) -> tuple[str, str]:
    uri = f"http://127.0.0.1:{free_port()}"
    return uri, "no MLflow tracking server reachable"


CASES: dict[str, Callable[[Path], tuple[str, str]]] = {
    "unwritable folder": _unwritable,
    "folder cannot be created": _uncreatable,
    "not an SQLite file": _not_sqlite,
    "another program's database": _other_program,
    "a folder, not a file": _folder_as_file,
    "server down": _server_down,
}


def _one_line_exit_2(proc: subprocess.CompletedProcess[str], *expected: str) -> None:
    """Exit status 2 and one error line holding every ``expected`` text, nothing retried."""
    out = proc.stdout + proc.stderr
    assert proc.returncode == 2, out[-3000:]
    assert "Traceback" not in out and "retrying" not in out, out[-3000:]
    errors = [ln for ln in out.splitlines() if "error" in ln.lower()]
    assert len(errors) == 1, out[-3000:]
    assert all(text in errors[0] for text in expected), errors[0]


@pytest.mark.parametrize("case", list(CASES))
def test_train_refuses_an_unusable_store(case: str, tmp_path: Path) -> None:
    uri, expected = CASES[case](tmp_path)
    server = ["tracking=server"] if uri.startswith("http") else []
    proc = run_cli("cdqn.train", [*TINY, *server, f"tracking.uri={uri}"], tmp_path, timeout=120)
    _one_line_exit_2(proc, f"tracking.uri='{uri}'", expected)


@pytest.mark.parametrize(
    "case", ["not an SQLite file", "another program's database", "server down", "no such file"]
)
def test_analysis_refuses_an_unusable_store(case: str, tmp_path: Path) -> None:
    if case == "no such file":
        uri, expected = f"sqlite:///{tmp_path}/none.db", f"no such file {tmp_path}/none.db"
    else:
        uri, expected = CASES[case](tmp_path)
    proc = run_script(ROOT / "analysis/make_table.py", ["--tracking-uri", uri], tmp_path, 120)
    _one_line_exit_2(proc, f"--tracking-uri='{uri}'", expected)


def _schema(database: Path) -> dict[str, object]:
    """What a store holds besides its runs: the schema (each object's SQL as the set of its
    lines: MLflow's migrations order a table's CHECK constraints differently from one store
    to the next), the migration it is at, and its experiments without their times."""
    with contextlib.closing(sqlite3.connect(database)) as db:
        sql = db.execute("SELECT type, name, sql FROM sqlite_master WHERE sql IS NOT NULL")
        return {
            "schema": sorted(
                (k, n, sorted(ln.strip(" ,") for ln in s.splitlines())) for k, n, s in sql
            ),
            "migration": db.execute("SELECT version_num FROM alembic_version").fetchall(),
            "experiments": sorted(
                db.execute(
                    "SELECT experiment_id, name, artifact_location, lifecycle_stage "
                    "FROM experiments"
                )  # fmt: skip
            ),
        }


def test_a_fresh_store_copied_from_the_migrated_one_is_what_mlflow_makes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A new SQLite store is a copy of this MLflow version's migrated empty store, kept in
    cdqn's cache folder (made by MLflow the first time); it holds what MLflow's own
    migration makes, its ``Default`` experiment placed as MLflow places it."""
    import mlflow
    from mlflow.tracking import MlflowClient

    from cdqn.config import EXPERIMENT_TAGS
    from cdqn.training.store import ensure_store

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    template = tmp_path / "cache" / "cdqn" / "mlflow" / mlflow.__version__ / "store.db"
    ensure_store(f"sqlite:///{tmp_path / 'first.db'}", "cdqn")  # makes the template
    assert template.exists()
    made = template.stat().st_mtime_ns
    (tmp_path / "empty.db").touch()  # an empty file is no database yet, as for SQLite
    for name in ("copied.db", "empty.db"):
        ensure_store(f"sqlite:///{tmp_path / name}", "cdqn")
    assert template.stat().st_mtime_ns == made  # copied, not made again
    native = MlflowClient(f"sqlite:///{tmp_path / 'native.db'}")
    native.create_experiment("cdqn", tags=EXPERIMENT_TAGS)
    expected = _schema(tmp_path / "native.db")
    assert (0, "Default", f"{tmp_path}/mlruns/0") in {e[:3] for e in expected["experiments"]}
    for name in ("first.db", "copied.db", "empty.db"):
        assert _schema(tmp_path / name) == expected, name
    client = MlflowClient(f"sqlite:///{tmp_path / 'copied.db'}")
    run = client.create_run(client.get_experiment_by_name("cdqn").experiment_id)
    client.log_metric(run.info.run_id, "episode_return", 1.0)
    client.set_terminated(run.info.run_id)
    assert client.get_run(run.info.run_id).info.status == "FINISHED"


def test_a_store_is_made_where_the_cache_folder_cannot_be(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The migrated empty store is a shortcut: with no cache folder to keep it in (here a
    file stands where the folder would be), MLflow migrates the new store itself."""
    from mlflow.tracking import MlflowClient

    from cdqn.training.store import ensure_store

    (tmp_path / "cache").write_text("")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    ensure_store(f"sqlite:///{tmp_path / 'mlflow.db'}", "cdqn")
    names = {
        e.name for e in MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}").search_experiments()
    }
    assert names == {"Default", "cdqn"}
    assert (tmp_path / "cache").is_file()
