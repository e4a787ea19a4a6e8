"""The paper's results table from the stored runs.

    python analysis/make_table.py                          # Markdown on stdout, files in tables/
    python analysis/make_table.py --tracking-uri http://127.0.0.1:5000 --experiment cdqn
    python analysis/make_table.py --compare-paper --out tables/ --threshold acrobot=-100
    python analysis/make_table.py --where train.episodes=2000 --where network.width=2500
    python analysis/make_table.py --research     # the research preset beside the present table
    python analysis/make_table.py --ablation     # each departure undone, beside the present table

Runs that differ in a setting that changes results (:data:`analysis.runs.SETTINGS`) are
never averaged together: each group of settings gets its own table, headed by the settings
that tell it apart; ``--where KEY=VALUE`` keeps one.  A column compares agents on equal
terms only if they share the settings of :data:`analysis.shared.SHARED_SETTINGS`; the caption
names every shared setting that differs between the agents of a column
(:func:`analysis.columns.caption`).  Writes ``result_summary.{md,csv,tex}``, the per-run
``run_scores.csv`` (the CSVs with a ``settings`` column) and ``settings.md`` (each shared
setting's value per environment and agent) into ``--out``.  ``--claims`` adds the paper's
claims, each with its statistic and whether it holds (:mod:`analysis.claims`), on stdout
and in ``claims.md``.  ``--research`` and ``--ablation`` set the runs of
``sweeps/research.yaml`` or ``sweeps/ablation/*.yaml`` beside the present table
(:mod:`analysis.compare`) and write ``research.{md,csv}`` or ``ablation.{md,csv}``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

if __package__ in (None, ""):  # run as a script: make the repository root importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pandas as pd

from analysis import table as tbl
from analysis.cli import add_store_arguments, note, open_store, select_runs
from analysis.columns import caption, settings_table
from analysis.runs import RunStore, WhereError, comparable_runs, environment, where

if TYPE_CHECKING:  # --claims, --research and --ablation load them (analysis.claims, .compare)
    from analysis import compare as cmp


def parse_thresholds(items: list[str]) -> dict[str, float]:
    """``["acrobot=-100", ...]`` -> ``{"acrobot": -100.0}``."""
    out = {}
    for item in items:
        env, sep, value = item.partition("=")
        if not sep:
            raise argparse.ArgumentTypeError(f"--threshold {item!r}: expected ENV=VALUE")
        out[env.strip()] = float(value)
    return out


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="make_table.py",
        description="Final scores per controller and environment (paper: tab:result_summary).",
    )
    add_store_arguments(parser)
    parser.add_argument("--out", type=Path, default=Path("tables"), help="output folder")
    parser.add_argument(
        "--compare-paper", action="store_true", help="add the paper's numbers beside each cell"
    )
    parser.add_argument(
        "--threshold",
        action="append",
        default=[],
        metavar="ENV=VALUE",
        help="solve threshold for an environment (default: the runs' env.solve_threshold)",
    )
    parser.add_argument(
        "--claims",
        action="store_true",
        help="the paper's claims, each with its statistic and whether it holds",
    )
    kind = parser.add_mutually_exclusive_group()
    kind.add_argument(
        "--research",
        action="store_true",
        help="the research preset's runs (sweeps/research.yaml) beside the present table "
        "(--experiment) and the paper's numbers",
    )
    kind.add_argument(
        "--ablation",
        action="store_true",
        help="one row per departure undone (sweeps/ablation/*.yaml), its cells beside the "
        "present table (--experiment)",
    )
    parser.add_argument(
        "--research-experiment", default="cdqn-research", help="experiment of --research"
    )
    parser.add_argument(
        "--ablation-experiment", default="cdqn-ablation", help="experiment of --ablation"
    )
    return parser


def _selected(store: RunStore, statuses: list[str], conditions: list[str]) -> pd.DataFrame:
    """The store's runs of ``statuses`` that match ``--where`` (none if no run matches)."""
    runs = store.runs(statuses)
    runs = runs.assign(env=environment(runs))
    try:
        return where(runs, conditions)
    except WhereError:
        return runs.iloc[:0]


def compared_groups(
    store: RunStore, args: argparse.Namespace, thresholds: dict[str, float]
) -> list[cmp.Compared]:
    """The research preset's groups of settings, or the ablations, as tables."""
    from analysis import compare as cmp

    finished = select_runs(store, args.where) if args.research else store.require_runs()
    failed = _selected(store, ["FAILED"], args.where)
    if args.research:
        groups = [(s or "research", g, failed) for s, g in finished.groupby("settings")]
    else:
        groups = cmp.ablation_groups(_selected(store, list(store.statuses), args.where), failed)
    return [cmp.build_group(store, label, fin, fail, thresholds) for label, fin, fail in groups]


def present_table(
    args: argparse.Namespace, compared: list[cmp.Compared], thresholds: dict[str, float]
) -> tbl.Table | None:
    """The present table beside ``compared``: the runs of ``--experiment`` of the same cells
    and budget (:func:`analysis.compare.present_runs`); ``None`` when it has none."""
    from analysis import compare as cmp

    store = RunStore(args.tracking_uri, args.experiment, statuses=args.status or ("FINISHED",))
    runs, _ = comparable_runs(_selected(store, list(store.statuses), args.where))
    runs = cmp.present_runs(runs, pd.concat([g.runs for g in compared]))
    if runs.empty:
        note(f"note: no present runs of these cells in {store.describe()}: no changes shown")
        return None
    episodes = store.episodes(tbl.TABLE_METRICS, runs)
    return tbl.build(episodes, runs, thresholds) if not episodes.empty else None


def claims_text(
    store: RunStore, runs: pd.DataFrame, scores: pd.DataFrame, conditions: list[str]
) -> str:
    """The claims on one group of runs: ``runs`` (the table's), their per-run ``scores``,
    and for divergence every run of the same cells and ``--where`` conditions, any status."""
    from analysis import claims as cl

    every = store.runs(["FINISHED", "FAILED", "KILLED", "RUNNING"])
    every = where(every.assign(env=environment(every)), conditions)
    cells = set(zip(runs["env"], runs["controller"], strict=True))
    pairs = zip(every["env"], every["controller"], strict=True)
    every = every[[pair in cells for pair in pairs]]
    lines = [f"- {claim.line()}" for claim in cl.evaluate(scores, runs, every, store)]
    return "Claims (analysis/claims.py):\n\n" + "\n".join(lines)


def comparison(args: argparse.Namespace, thresholds: dict[str, float]) -> int:
    """``--research`` or ``--ablation``: the tables of :mod:`analysis.compare`, on stdout and
    in ``--out``."""
    from analysis import compare as cmp

    start = time.perf_counter()
    name = "research" if args.research else "ablation"
    experiment = args.research_experiment if args.research else args.ablation_experiment
    store = open_store(argparse.Namespace(**{**vars(args), "experiment": experiment}))
    groups = compared_groups(store, args, thresholds)
    present = present_table(args, groups, thresholds)
    if args.research:
        blocks = [f"{g.label}\n\n{cmp.research_markdown(g, present)}" for g in groups]
        text = "\n\n".join(blocks) if len(groups) > 1 else cmp.research_markdown(groups[0], present)
    else:
        text = cmp.ablation_markdown(groups, present)
    markdown = text + "\n\n" + cmp.note_text(args.experiment)
    print(markdown)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{name}.md").write_text(markdown + "\n")
    cmp.long_table(groups, present).to_csv(args.out / f"{name}.csv", index=False)
    note(
        f"{sum(len(g.runs) for g in groups)} runs from {store.describe()} in "
        f"{time.perf_counter() - start:.1f} s; wrote {args.out}/{name}.{{md,csv}}"
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    thresholds = parse_thresholds(args.threshold)
    if args.research or args.ablation:
        return comparison(args, thresholds)
    start = time.perf_counter()
    store = open_store(args)
    runs = select_runs(store, args.where)
    episodes = store.episodes(tbl.TABLE_METRICS, runs)
    if episodes.empty:
        note(f"error: the runs in {store.describe()} have no episode metrics")
        return 1
    groups = list(runs.groupby("settings", sort=True))
    texts, latex, summaries, scores, claims = [], [], [], [], []
    for k, (settings, group) in enumerate(groups, start=1):
        table = tbl.build(episodes[episodes["run_id"].isin(group["run_id"])], group, thresholds)
        if len(groups) == 1:
            for line in tbl.missing_lines(table, "/".join(store.statuses)):
                note(line)
        shared = caption(group)
        text = tbl.to_markdown(table, args.compare_paper) + "\n\n" + tbl.notes(table, shared)
        if len(groups) > 1:
            text = f"Group {k} of {len(groups)}: {settings}\n\n{text}"
        if args.claims:
            claims.append(claims_text(store, group, table.scores, args.where))
            text += "\n\n" + claims[-1]
        texts.append(text)
        latex.append(tbl.to_latex(table, args.compare_paper, shared))
        summaries.append(table.summary.assign(settings=settings))
        scores.append(table.scores.assign(settings=settings))
    if len(groups) > 1:
        texts.insert(
            0,
            f"These runs form {len(groups)} groups of settings that change results; each has "
            "its own table (pick one with --where KEY=VALUE).",
        )
    markdown = "\n\n".join(texts)
    print(markdown)

    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "result_summary.md").write_text(markdown + "\n")
    pd.concat(summaries, ignore_index=True).to_csv(args.out / "result_summary.csv", index=False)
    pd.concat(scores, ignore_index=True).to_csv(args.out / "run_scores.csv", index=False)
    (args.out / "result_summary.tex").write_text("\n".join(latex))
    (args.out / "settings.md").write_text(settings_table(runs) + "\n")
    if claims:
        (args.out / "claims.md").write_text("\n\n".join(claims) + "\n")
    note(
        f"{len(runs)} runs from {store.describe()} in {time.perf_counter() - start:.1f} s; "
        f"wrote {args.out}/result_summary.{{md,csv,tex}}, run_scores.csv and settings.md"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
