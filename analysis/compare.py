"""Tables that set other runs beside the present table: the research preset and the ablations.

    python analysis/make_table.py --research      # sweeps/research.yaml's runs (cdqn-research)
    python analysis/make_table.py --ablation      # sweeps/ablation/*.yaml's runs (cdqn-ablation)

The *present* runs are those of ``--experiment`` (the paper sweep's, ``cdqn``); the compared
runs those of ``--research-experiment`` or ``--ablation-experiment`` in the same store.  Every
number is a cell of :mod:`analysis.table` (:func:`analysis.table.build`): final score mean ±
std over seeds, ``k/n`` seeds whose 100-episode average reached the threshold.

For each compared cell (environment × controller) the present cell is built from the present
runs of that cell with the same budget (:data:`BUDGET`); where those form several groups of
settings (runs of earlier defaults kept in the store) the group started last counts.  The
*change* of a cell is its mean minus the present cell's mean.

An ablation's runs carry the param ``extra.ablation`` (its name, the rows of the table) and
``extra.departure`` (the number of the departure it undoes in docs/departures.md); the
columns are the cells any ablation touched.  Runs of one ablation that differ in a setting
that changes results (:data:`analysis.runs.SETTINGS`) get one row per group of settings.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import NamedTuple

import numpy as np
import pandas as pd

from analysis import table as tbl
from analysis.runs import RunStore, comparable_runs, setting_values
from analysis.style import CONTROLLER_ORDER, ENV_ORDER, controller_text, env_text, ordered

BUDGET = ("train.episodes", "network.width")
"""Settings a present cell must share with the compared cell it stands beside."""
ABLATION = "extra.ablation"
"""Run param naming the ablation a run belongs to (``sweeps/ablation/<name>.yaml``)."""
DEPARTURE = "extra.departure"
"""Run param with the number of the departure the ablation undoes (docs/departures.md)."""

Cell = tuple[str, str]
"""(environment, controller)."""


class Compared(NamedTuple):
    """One group of compared runs and its table."""

    label: str
    """Row label: the ablation (``8 bootstrap``) or ``research``."""
    runs: pd.DataFrame
    """The FINISHED runs (rows of :func:`analysis.runs.comparable_runs`)."""
    table: tbl.Table
    """Their table (empty when every run failed)."""
    failed: dict[Cell, int]
    """Cell -> runs of the group that ended FAILED (diverged, or a design refused)."""


def build_group(
    store: RunStore,
    label: str,
    finished: pd.DataFrame,
    failed: pd.DataFrame,
    thresholds: Mapping[str, float],
) -> Compared:
    """The table of ``finished`` (rows of :func:`analysis.runs.comparable_runs`) and the
    count per cell of ``failed``, those of the same budget when any run finished."""
    episodes = store.episodes(tbl.TABLE_METRICS, finished)
    table = tbl.build(episodes, finished, thresholds) if not episodes.empty else tbl.empty()
    for key in BUDGET if not finished.empty else ():
        failed = failed[setting_values(failed, key).isin(set(setting_values(finished, key)))]
    counts = failed.groupby(["env", "controller"]).size()
    failures = {(str(e), str(c)): int(n) for (e, c), n in counts.items()}
    return Compared(label, finished, table, failures)


def present_runs(present: pd.DataFrame, compared: pd.DataFrame) -> pd.DataFrame:
    """The present runs each compared cell stands beside: the cell's present runs with the
    same :data:`BUDGET`, of the settings group started last (module docstring)."""
    if present.empty or compared.empty:
        return present.iloc[:0]
    budget = {key: setting_values(present, key) for key in BUDGET}
    wanted = {key: setting_values(compared, key) for key in BUDGET}
    keep = []
    for (env, ctrl), cell in compared.groupby(["env", "controller"]):
        mask = (present["env"] == env) & (present["controller"] == ctrl)
        for key in BUDGET:
            mask &= budget[key].isin(set(wanted[key][cell.index]))
        hit = present[mask]
        if hit.empty:
            continue
        last = hit.groupby("settings")["start_time"].max().idxmax()
        keep.append(hit[hit["settings"] == last])
    return pd.concat(keep) if keep else present.iloc[:0]


def ablation_groups(
    finished: pd.DataFrame, failed: pd.DataFrame
) -> list[tuple[str, pd.DataFrame, pd.DataFrame]]:
    """``(label, finished, failed)`` per ablation (and group of settings of its finished
    runs), in departure order; runs without ``extra.ablation`` are left out."""
    names, failed_names = setting_values(finished, ABLATION), setting_values(failed, ABLATION)
    out = []
    for name in sorted(set(names.dropna()) | set(failed_names.dropna())):
        mine_failed = failed[failed_names == name]
        both = pd.concat([finished[names == name], mine_failed])
        number = setting_values(both, DEPARTURE).dropna()
        label = f"{number.iloc[0]} {name}" if not number.empty else str(name)
        grouped, _ = comparable_runs(finished[names == name])
        if grouped.empty:
            out.append((label, grouped, mine_failed))
        for settings, group in grouped.groupby("settings", sort=True):
            out.append((f"{label} [{settings}]" if settings else label, group, mine_failed))
    return sorted(out, key=lambda item: _departure_key(item[0]))


def _departure_key(label: str) -> tuple[float, str]:
    head = label.split(" ", 1)[0]
    try:
        return (float(head), label)
    except ValueError:
        return (float("inf"), label)


def score_text(row: pd.Series | None, failed: int = 0) -> str:
    """``-96.86 ± 6.26, 10/10`` (final score, seeds that reached the threshold of those that
    finished), ``; 2 failed`` when runs failed; ``—`` for no run."""
    if row is None:
        return f"{failed} failed" if failed else "—"
    text = f"{row['mean']:.2f} ± {row['std']:.2f}, {row['n_solved']}/{row['n_seeds']}"
    return text + (f"; {failed} failed" if failed else "")


def change_text(row: pd.Series | None, present: pd.Series | None) -> str:
    """``Δ +3.40`` (mean minus the present mean), ``Δ n/a`` without either."""
    if row is None or present is None:
        return "Δ n/a"
    return f"Δ {row['mean'] - present['mean']:+.2f}"


def research_markdown(research: Compared, present: tbl.Table | None) -> str:
    """Controllers as rows, environments as columns; each cell the research preset's score
    and its change, then the present table's and the paper's."""
    t = research.table
    lines = [
        "| controller | " + " | ".join(env_text(e) for e in t.envs) + " |",
        "|---" * (len(t.envs) + 1) + "|",
    ]
    for ctrl in t.controllers:
        cells = []
        for env in t.envs:
            row = tbl.cell(t, ctrl, env)
            now, failed = _present(present, (env, ctrl)), research.failed.get((env, ctrl), 0)
            paper = tbl.PAPER_SCORES.get((ctrl, env))
            text = f"{score_text(row, failed)} ({change_text(row, now)})"
            text += f"; present {score_text(now)}"
            text += f"; paper {paper.mean:.2f} ± {paper.std:.2f}" if paper else "; paper —"
            cells.append(text)
        lines.append(f"| {controller_text(ctrl)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def touched_cells(groups: list[Compared]) -> list[Cell]:
    """Every cell any group has runs in, in the paper table's order (environment, then
    controller)."""
    cells = {cell for g in groups for cell in _cells(g.table.summary)}
    cells |= {cell for g in groups for cell in g.failed}
    envs = ordered({e for e, _ in cells}, ENV_ORDER)
    ctrls = ordered({c for _, c in cells}, CONTROLLER_ORDER)
    return [(e, c) for e in envs for c in ctrls if (e, c) in cells]


def ablation_markdown(groups: list[Compared], present: tbl.Table | None) -> str:
    """Ablations as rows, the cells they touch as columns; each cell the score with the
    departure undone and its change from the present table."""
    cells = touched_cells(groups)
    head = [f"{env_text(e)} {controller_text(c)}" for e, c in cells]
    lines = ["| departure undone | " + " | ".join(head) + " |", "|---" * (len(cells) + 1) + "|"]
    for g in groups:
        texts = []
        for env, ctrl in cells:
            row = tbl.cell(g.table, ctrl, env)
            failed = g.failed.get((env, ctrl), 0)
            if row is None and not failed:
                texts.append("")
                continue
            change = "" if row is None else f" ({change_text(row, _present(present, (env, ctrl)))})"
            texts.append(score_text(row, failed) + change)
        lines.append(f"| {g.label} | " + " | ".join(texts) + " |")
    present_row = [score_text(_present(present, cell)) for cell in cells]
    lines.append("| present table | " + " | ".join(present_row) + " |")
    return "\n".join(lines)


def long_table(groups: list[Compared], present: tbl.Table | None) -> pd.DataFrame:
    """One row per (group, cell): the group's summary row (:func:`analysis.table.summarize`)
    with ``label``, ``failed``, the present cell's ``present_mean``, ``present_std``,
    ``present_n_solved``, ``present_n_seeds`` and ``change``."""
    frames = []
    for g in groups:
        if g.table.summary.empty:
            continue
        s = g.table.summary.copy()
        s.insert(0, "label", g.label)
        s["failed"] = [g.failed.get(cell, 0) for cell in _cells(s)]
        now = [_present(present, cell) for cell in _cells(s)]
        for key in ("mean", "std", "n_solved", "n_seeds"):
            s[f"present_{key}"] = [np.nan if r is None else r[key] for r in now]
        s["change"] = s["mean"] - s["present_mean"]
        frames.append(s)
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def _cells(summary: pd.DataFrame) -> list[Cell]:
    """The (environment, controller) of every row of a summary."""
    if summary.empty:
        return []
    return [(str(e), str(c)) for e, c in zip(summary["env"], summary["controller"], strict=True)]


def _present(present: tbl.Table | None, cell: Cell) -> pd.Series | None:
    """The present table's row of ``cell`` (``None`` without one)."""
    return None if present is None else tbl.cell(present, cell[1], cell[0])


NOTE = (
    "Final score: mean return of each run's last {last} episodes, mean ± std over the seeds "
    "that finished (ddof={ddof}); k/n = seeds whose 100-episode average reached the solve "
    "threshold of those that finished; Δ = mean minus the present table's mean (runs of "
    "experiment {present!r} with the same episodes and width)."
)


def note_text(present_experiment: str) -> str:
    """The line under both tables."""
    return NOTE.format(last=tbl.LAST_EPISODES, ddof=tbl.STD_DDOF, present=present_experiment)
