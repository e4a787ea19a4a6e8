"""Command-line pieces shared by ``make_table.py`` and ``make_figures.py``."""

from __future__ import annotations

import argparse
import sys

import pandas as pd

from analysis.runs import (
    DEFAULT_EXPERIMENT,
    DEFAULT_URI,
    EmptyStoreError,
    RunStore,
    comparable_runs,
)


def add_store_arguments(parser: argparse.ArgumentParser) -> None:
    """``--tracking-uri``, ``--experiment``, ``--status``."""
    parser.add_argument(
        "--tracking-uri",
        default=DEFAULT_URI,
        help=f"MLflow tracking URI (default: the training default, {DEFAULT_URI})",
    )
    parser.add_argument(
        "--experiment",
        default=DEFAULT_EXPERIMENT,
        help=f"MLflow experiment name (default: {DEFAULT_EXPERIMENT})",
    )
    parser.add_argument(
        "--status",
        action="append",
        choices=["FINISHED", "FAILED", "KILLED", "RUNNING"],
        help="run status to include; repeatable (default: FINISHED only)",
    )


def open_store(args: argparse.Namespace) -> RunStore:
    """The store named on the command line; exits with status 1 if it has no runs."""
    store = RunStore(args.tracking_uri, args.experiment, statuses=args.status or ("FINISHED",))
    try:
        store.require_runs()
    except EmptyStoreError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(1) from None
    excluded = store.runs(["FINISHED", "FAILED", "KILLED", "RUNNING", "SCHEDULED"])
    excluded = excluded[~excluded["status"].isin(store.statuses)]
    if not excluded.empty:
        counts = ", ".join(f"{n} {s}" for s, n in excluded["status"].value_counts().items())
        print(f"note: left out {counts} run(s) (include them with --status)", file=sys.stderr)
    return store


def select_runs(store: RunStore) -> pd.DataFrame:
    """The store's runs, one per (env, controller, seed), with a note for each oddity."""
    runs, notes = comparable_runs(store.require_runs())
    for line in notes:
        note(f"note: {line}")
    return runs


def note(message: str) -> None:
    """One line on stderr (skips, notes), keeping stdout for the table."""
    print(message, file=sys.stderr)
