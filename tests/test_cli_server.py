"""The command lines the tests start from :mod:`tests.cli_server` behave as fresh
``python`` processes would: their own folder, environment, arguments, ``sys.path[0]``,
streams, exit code and end (``atexit``), a time limit that kills them, and no state carried
from one command to the next."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from tests.helpers import run_script

PROBE = """
import atexit, json, os, sys
atexit.register(lambda: print("atexit ran"))
print(json.dumps({"cwd": os.getcwd(), "argv": sys.argv, "path0": sys.path[0],
                  "probe": os.environ.get("CDQN_PROBE"), "pid": os.getpid(),
                  "seen": "cdqn_probe_mark" in globals()}))
globals()["cdqn_probe_mark"] = 1
print("to stderr", file=sys.stderr)
sys.exit(int(sys.argv[1]))
"""


def test_each_command_is_its_own_process(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    script = tmp_path / "scripts" / "probe.py"
    script.parent.mkdir()
    script.write_text(PROBE)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.setenv("CDQN_PROBE", "first")
    first = run_script(script, ["3", "x y"], work)
    monkeypatch.setenv("CDQN_PROBE", "second")
    second = run_script(script, ["0"], work)
    a, b = (json.loads(p.stdout.splitlines()[0]) for p in (first, second))
    assert (first.returncode, second.returncode) == (3, 0)
    assert a["cwd"] == str(work) and a["argv"] == [str(script), "3", "x y"]
    assert a["path0"] == str(script.parent)  # as `python <script>` puts it
    assert (a["probe"], b["probe"]) == ("first", "second")  # the environment at each call
    assert a["pid"] != b["pid"] and os.getpid() not in (a["pid"], b["pid"])
    assert not a["seen"] and not b["seen"]  # nothing carried over
    assert first.stdout.splitlines()[-1] == "atexit ran"
    assert first.stderr == "to stderr\n"


def test_a_command_past_its_time_limit_is_killed(tmp_path: Path):
    script = tmp_path / "slow.py"
    script.write_text("import sys, time\nprint('started', flush=True)\ntime.sleep(600)\n")
    with pytest.raises(subprocess.TimeoutExpired) as err:
        run_script(script, [], tmp_path, timeout=3)
    assert "started" in (err.value.output or "")
    (tmp_path / "next.py").write_text("print('next')\n")
    after = run_script(tmp_path / "next.py", [], tmp_path)  # the server goes on
    assert after.returncode == 0 and after.stdout == "next\n"
