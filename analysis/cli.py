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
    WhereError,
    comparable_runs,
    environment,
    where,
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
    parser.add_argument(
        "--where",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="only runs whose tag or param KEY has this value (train.episodes=2000, "
        "network.width=64, env=cartpole, design_source=synthesized); repeatable",
    )


def open_store(args: argparse.Namespace) -> RunStore:
    """The store named on the command line; exits with status 2 if it is no store (no such
    file, not an SQLite database, no server answering), 1 if it has no runs."""
    from cdqn.training.tracking import TrackingError, check_readable

    try:
        check_readable(args.tracking_uri, timeout=10.0)
    except TrackingError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
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


def select_runs(store: RunStore, conditions: list[str] | None = None) -> pd.DataFrame:
    """The store's runs that match ``conditions`` (``--where``), grouped by the settings that
    change results, one per (env, settings, controller, seed), with a note for each oddity;
    exits with status 2 when a condition names no setting or matches no run."""
    runs = store.require_runs()
    runs = runs.assign(env=environment(runs))
    try:
        runs = where(runs, conditions or [])
    except WhereError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    runs, notes = comparable_runs(runs)
    for line in notes:
        note(f"note: {line}")
    return runs


def note(message: str) -> None:
    """One line on stderr (skips, notes), keeping stdout for the table."""
    print(message, file=sys.stderr)
