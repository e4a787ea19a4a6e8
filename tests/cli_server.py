"""A process that starts command lines the way ``python -m <module> <args>`` does, minus the
imports: it imports what cdqn's command lines import, once, then forks one child per command
(:func:`tests.helpers.run_cli`).

Each child becomes the command: its working folder, environment, ``sys.argv``, ``sys.path[0]``
and standard streams are the command's; the module runs as ``__main__`` (``runpy``, as
``-m`` does); it ends as an interpreter ends (an uncaught exception prints its traceback and
exits 1, ``SystemExit`` gives its code, threads are joined and ``atexit`` runs).  Variables
that cdqn's imports set with ``os.environ.setdefault`` are set in the child's environment
the same way.  Nothing else runs in this process: no torch operation (its thread pools start
in the child), no MLflow client, no Hydra state.

Protocol (one command at a time): a JSON line ``{"module" or "script", "args", "cwd", "env",
"stdout", "stderr"}`` on stdin (``script``: ``python <script> <args>``); this process answers
``{"pid": …}`` when the child starts and ``{"returncode": …}`` when it ends (negative: the
signal that ended it, as ``subprocess``).
"""

from __future__ import annotations

import gc
import importlib
import io
import json
import os
import runpy
import sys
from typing import Any

SERVED = ("cdqn.train", "cdqn.tune", "cdqn.evaluate", "cdqn.synthesize")
"""The modules started here, besides the ``analysis/`` scripts; others (``cdqn.bench`` and
``cdqn.profile`` set thread counts before torch is imported) start as fresh interpreters."""


PREIMPORTED = (
    "cdqn.cli",
    "cdqn.training.run",
    "cdqn.tuning.study",
    "analysis.make_table",
    "analysis.make_figures",
    "mlflow.store.tracking.sqlalchemy_store",
    "optuna",
)
"""What this process imports before it serves (the commands' heavy imports)."""


def serve() -> tuple[dict[str, Any], dict[str, str]] | None:
    """Answer requests until stdin closes; in a child, return its request and the variables
    the imports set."""
    before = dict(os.environ)
    for name in PREIMPORTED:
        importlib.import_module(name)
    set_by_imports = {k: v for k, v in os.environ.items() if before.get(k) != v}
    gc.freeze()  # the imported objects stay out of the children's collections
    print(json.dumps({"ready": os.getpid()}), flush=True)
    for line in sys.stdin:
        request = json.loads(line)
        pid = os.fork()
        if pid == 0:
            return request, set_by_imports
        print(json.dumps({"pid": pid}), flush=True)
        _, status = os.waitpid(pid, 0)
        print(json.dumps({"returncode": os.waitstatus_to_exitcode(status)}), flush=True)
    return None


def become(request: dict[str, Any], set_by_imports: dict[str, str]) -> None:
    """Make this child the command's process (module docstring)."""
    env = dict(request["env"])
    for key, value in set_by_imports.items():
        env.setdefault(key, value)
    os.environ.clear()
    os.environ.update(env)
    os.chdir(request["cwd"])
    script = request.get("script")
    sys.path[0] = os.path.dirname(os.path.realpath(script)) if script else os.getcwd()
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.close(null)
    for fd, path in ((1, request["stdout"]), (2, request["stderr"])):
        out = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(out, fd)
        os.close(out)
    sys.stdin = sys.__stdin__ = open(0, encoding="utf-8", closefd=False)  # noqa: SIM115
    sys.stdout = sys.__stdout__ = _stream(1, "strict")
    sys.stderr = sys.__stderr__ = _stream(2, "backslashreplace")
    sys.argv = [script or request["module"], *request["args"]]


def _stream(fd: int, errors: str) -> io.TextIOWrapper:
    """A text stream on ``fd`` as Python makes it under ``PYTHONUNBUFFERED``."""
    raw = io.FileIO(fd, "w", closefd=False)
    return io.TextIOWrapper(raw, encoding="utf-8", errors=errors, write_through=True)


if __name__ == "__main__":
    child = serve()
    if child is not None:
        become(*child)
        if child[0].get("script"):
            runpy.run_path(child[0]["script"], run_name="__main__")
        else:
            runpy.run_module(child[0]["module"], run_name="__main__", alter_sys=True)
