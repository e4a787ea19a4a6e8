"""The paper's results table (``tab:result_summary``) from per-episode metrics.

Per run, the *final score* is the mean ``episode_return`` of its last 100 episodes (all of
them if it has fewer) and the *solve episode* is the first episode, counted from 1, whose
``return_ma100`` reaches the environment's solve threshold (param ``env.solve_threshold``).
Per (controller, environment) cell: mean ± std of the final scores over seeds (population
std, ``ddof = 0``), the number of seeds, how many of them solved and the median solve
episode, where a seed that never solved counts as never (so the median is "n/a" once half
the seeds or more never solved).  The *area under the learning curve* (AUC) of a run is the
mean of its ``return_ma100`` over all its episodes: how early and how well it learned in one
number (a run that learns sooner has the larger AUC at equal final score); a cell shows its
mean over seeds.  With ``episode_length`` in the episodes, a run's *solve steps* are the
environment steps up to and including its solve episode (environment interactions needed).
The best mean of each environment is bold.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import NamedTuple

import numpy as np
import pandas as pd

from analysis.style import (
    CONTROLLER_ORDER,
    ENV_ORDER,
    controller_latex,
    controller_text,
    env_text,
    ordered,
)
from cdqn.records import Metric

LAST_EPISODES = 100
"""Episodes averaged for a run's final score (paper: "final scores after 2000 episodes")."""
STD_DDOF = 0
"""Delta degrees of freedom of the std over seeds (NumPy's default)."""


class Score(NamedTuple):
    """A final score as the paper reports it (Varga, Kulcsár, Haghir Chehreghani 2022, table
    ``tab:result_summary``: after 2000 episodes, mean ± std over 10 seeds)."""

    mean: float
    std: float


PAPER_SCORES: dict[tuple[str, str], Score] = {
    ("h2", "cartpole"): Score(187.92, 2.47),
    ("h2", "acrobot"): Score(-146.44, 45.09),
    ("h2", "mountaincar"): Score(-140.57, 5.07),
    ("hinf_f", "cartpole"): Score(192.59, 7.13),
    ("hinf_f", "acrobot"): Score(-99.93, 3.79),
    ("hinf_f", "mountaincar"): Score(-141.41, 8.38),
    ("hinf", "cartpole"): Score(199.37, 1.21),
    ("hinf", "acrobot"): Score(-111.73, 13.17),
    ("hinf", "mountaincar"): Score(-134.45, 8.63),
    ("ddqn", "cartpole"): Score(197.56, 7.37),
    ("ddqn", "acrobot"): Score(-98.04, 8.58),
    ("ddqn", "mountaincar"): Score(-135.79, 9.41),
}
"""(controller, env) -> the paper's final score."""


TABLE_METRICS = (Metric.EPISODE_RETURN, Metric.RETURN_MA100, Metric.EPISODE_LENGTH)
"""The only metrics the table reads."""


class Table(NamedTuple):
    """Per-run scores and the per-cell summary behind the rendered tables."""

    scores: pd.DataFrame
    """One row per run: ``run_id, env, controller, seed, episodes, final_score, auc,
    solve_threshold, solve_episode, solve_steps``."""
    summary: pd.DataFrame
    """One row per present (controller, env) cell, see :func:`summarize`."""
    controllers: list[str]
    envs: list[str]


def run_scores(
    episodes: pd.DataFrame,
    runs: pd.DataFrame,
    thresholds: Mapping[str, float] | None = None,
    last: int = LAST_EPISODES,
) -> pd.DataFrame:
    """Final score and solve episode of every run in ``episodes``.

    ``runs`` supplies each run's ``solve_threshold``; ``thresholds`` (env -> value)
    overrides it per environment.
    """
    thresholds = dict(thresholds or {})
    info = runs.set_index("run_id")
    rows = []
    for run_id, df in episodes.groupby("run_id", sort=False):
        df = df.sort_values("episode")
        env = str(df["env"].iloc[0])
        threshold = float(thresholds.get(env, info.at[run_id, "solve_threshold"]))
        returns = df[Metric.EPISODE_RETURN].to_numpy(dtype=float)
        ma100 = df[Metric.RETURN_MA100].to_numpy(dtype=float)
        reached = (
            np.flatnonzero(ma100 >= threshold) if np.isfinite(threshold) else np.zeros(0, dtype=int)
        )
        rows.append(
            {
                "run_id": run_id,
                "env": env,
                "controller": df["controller"].iloc[0],
                "seed": df["seed"].iloc[0],
                "episodes": len(df),
                Metric.FINAL_SCORE: float(np.mean(returns[-last:])),
                "auc": float(np.mean(ma100)),
                "solve_threshold": threshold,
                "solve_episode": (
                    float(df["episode"].iloc[reached[0]] + 1) if reached.size else np.nan
                ),
                "solve_steps": _solve_steps(df, reached),
            }
        )
    cols = [
        "run_id",
        "env",
        "controller",
        "seed",
        "episodes",
        Metric.FINAL_SCORE,
        "auc",
        "solve_threshold",
        "solve_episode",
        "solve_steps",
    ]
    return pd.DataFrame(rows, columns=cols)


def _solve_steps(df: pd.DataFrame, reached: np.ndarray) -> float:
    """Environment steps of the episodes up to and including the first that reached the
    threshold (NaN if none did or the run has no ``episode_length``)."""
    if not reached.size or "episode_length" not in df.columns:
        return np.nan
    return float(df["episode_length"].to_numpy(dtype=float)[: reached[0] + 1].sum())


def summarize(scores: pd.DataFrame) -> pd.DataFrame:
    """One row per (controller, env) present in ``scores``.

    Columns ``controller, env, n_seeds, mean, std, auc_mean, auc_std, min_episodes,
    max_episodes, solve_threshold, n_solved, median_solve_episode, paper_mean, paper_std,
    best``
    (``best``: the highest mean of its environment; ties are all best).
    """
    rows = []
    for (ctrl, env), df in scores.groupby(["controller", "env"], sort=False):
        solve = df["solve_episode"].to_numpy(dtype=float)
        thresholds = df["solve_threshold"].dropna().unique()
        median = float(np.median(np.where(np.isnan(solve), np.inf, solve)))
        paper = PAPER_SCORES.get((str(ctrl), str(env)))
        rows.append(
            {
                "controller": ctrl,
                "env": env,
                "n_seeds": len(df),
                "mean": float(df[Metric.FINAL_SCORE].mean()),
                "std": float(np.std(df[Metric.FINAL_SCORE].to_numpy(dtype=float), ddof=STD_DDOF)),
                "auc_mean": float(df["auc"].mean()),
                "auc_std": float(np.std(df["auc"].to_numpy(dtype=float), ddof=STD_DDOF)),
                "min_episodes": int(df["episodes"].min()),
                "max_episodes": int(df["episodes"].max()),
                "solve_threshold": float(thresholds[0]) if len(thresholds) == 1 else np.nan,
                "n_solved": int(np.isfinite(solve).sum()),
                "median_solve_episode": median if np.isfinite(median) else np.nan,
                "paper_mean": paper.mean if paper else np.nan,
                "paper_std": paper.std if paper else np.nan,
            }
        )
    out = pd.DataFrame(rows)
    if out.empty:
        return out
    out["best"] = out["mean"] == out.groupby("env")["mean"].transform("max")
    return out


def build(
    episodes: pd.DataFrame,
    runs: pd.DataFrame,
    thresholds: Mapping[str, float] | None = None,
) -> Table:
    """Scores, summary and the row / column order of the table."""
    scores = run_scores(episodes, runs, thresholds)
    summary = summarize(scores)
    return Table(
        scores,
        summary,
        ordered(scores["controller"], CONTROLLER_ORDER),
        ordered(scores["env"], ENV_ORDER),
    )


def missing_lines(table: Table, counted: str = "FINISHED") -> list[str]:
    """One line per paper environment, controller or cell without ``counted`` runs."""
    what = f"no {counted} runs"
    lines = [f"skipped: {what} for environment {e!r}" for e in ENV_ORDER if e not in table.envs]
    lines += [
        f"skipped: {what} for controller {ctrl!r}"
        for ctrl in CONTROLLER_ORDER[:4]
        if ctrl not in table.controllers
    ]
    present = set(zip(table.summary["controller"], table.summary["env"], strict=True))
    lines += [
        f"skipped: {what} for controller {ctrl!r} on {env!r}"
        for ctrl in table.controllers
        for env in table.envs
        if (ctrl, env) not in present
    ]
    return lines


def empty() -> Table:
    """The table of no runs."""
    none = pd.DataFrame({"run_id": []})
    return Table(run_scores(none, none), pd.DataFrame(), [], [])


def cell(table: Table, ctrl: str, env: str) -> pd.Series | None:
    """The summary row of one (controller, environment) cell, ``None`` if it has no runs."""
    s = table.summary
    if s.empty:
        return None
    hit = s[(s["controller"] == ctrl) & (s["env"] == env)]
    return None if hit.empty else hit.iloc[0]


def _solve_text(row: pd.Series) -> str:
    if not np.isfinite(row["solve_threshold"]) and row["n_solved"] == 0:
        return "solve n/a"
    median = row["median_solve_episode"]
    ep = f"{median:.0f}" if np.isfinite(median) else "n/a"
    return f"solve ep. {ep}, {row['n_solved']}/{row['n_seeds']} reach"


def to_markdown(table: Table, compare_paper: bool = False) -> str:
    """GitHub Markdown: controllers as rows, environments as columns, best mean bold."""
    header = "| controller | " + " | ".join(env_text(e) for e in table.envs) + " |"
    lines = [header, "|---" * (len(table.envs) + 1) + "|"]
    for ctrl in table.controllers:
        cells = []
        for env in table.envs:
            row = cell(table, ctrl, env)
            if row is None:
                cells.append("—")
                continue
            score = f"{row['mean']:.2f} ± {row['std']:.2f}"
            if row["best"]:
                score = f"**{score}**"
            text = f"{score} (n={row['n_seeds']}; {_solve_text(row)}; AUC {row['auc_mean']:.1f})"
            if compare_paper:
                text += " " + _paper_text(row)
            cells.append(text)
        lines.append(f"| {controller_text(ctrl)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _paper_text(row: pd.Series) -> str:
    if not np.isfinite(row["paper_mean"]):
        return "[paper: —]"
    return f"[paper: {row['paper_mean']:.2f} ± {row['paper_std']:.2f}]"


def notes(table: Table, caption: str = "") -> str:
    """What the numbers mean, for under the Markdown table; ``caption`` (what the agents of
    each column share, :func:`analysis.columns.caption`) follows."""
    s = table.summary
    episodes = f"{s['min_episodes'].min()}–{s['max_episodes'].max()}"
    if s["min_episodes"].min() == s["max_episodes"].max():
        episodes = str(s["min_episodes"].min())
    thresholds = ", ".join(
        f"{env_text(env)} {th:g}"
        for env in table.envs
        for th in s.loc[s["env"] == env, "solve_threshold"].dropna().unique()[:1]
    )
    return (
        f"Final score: mean return of each run's last {LAST_EPISODES} episodes "
        f"({episodes} episodes per run); mean ± std over seeds (ddof={STD_DDOF}); best mean per "
        "environment in bold. n = seeds; solve ep. = median first episode (from 1) with "
        f"return_ma100 ≥ threshold ({thresholds or 'none'}), k/n reach = seeds that reached "
        "it; AUC = mean over seeds of each run's return_ma100 averaged over its episodes."
        + (f" {caption}" if caption else "")
    )


def to_latex(table: Table, compare_paper: bool = False, caption: str = "") -> str:
    """A ``table`` float with a booktabs ``tabular``, labelled ``tab:result_summary``;
    ``caption`` (what the agents of each column share) ends the caption."""
    cols = "l" + "c" * len(table.envs)
    lines = [
        r"% Generated by analysis/make_table.py; needs \usepackage{booktabs}.",
        r"\begin{table}[htb]",
        r"\centering",
        r"\caption{Final scores: mean $\pm$ std over seeds of the mean return of each run's "
        rf"last {LAST_EPISODES} episodes; below, seeds $n$, median episode at which the "
        r"100-episode moving average first reaches the solve threshold, seeds that reach it "
        r"and the area under the learning curve (AUC, mean moving average over the episodes). "
        + _latex_escape(caption)
        + "}",
        r"\label{tab:result_summary}",
        rf"\begin{{tabular}}{{{cols}}}",
        r"\toprule",
        "Controller & " + " & ".join(_latex_escape(env_text(e)) for e in table.envs) + r" \\",
        r"\midrule",
    ]
    for ctrl in table.controllers:
        scores, extras = [], []
        for env in table.envs:
            row = cell(table, ctrl, env)
            if row is None:
                scores.append("--")
                extras.append("")
                continue
            body = rf"{row['mean']:.2f} \pm {row['std']:.2f}"
            scores.append(rf"$\mathbf{{{body}}}$" if row["best"] else f"${body}$")
            median = row["median_solve_episode"]
            ep = f"{median:.0f}" if np.isfinite(median) else "n/a"
            extra = (
                rf"\scriptsize $n={row['n_seeds']}$, ep.~{ep}, "
                rf"{row['n_solved']}/{row['n_seeds']}, AUC ${row['auc_mean']:.1f}$"
            )
            if compare_paper and np.isfinite(row["paper_mean"]):
                extra += rf"; paper ${row['paper_mean']:.2f} \pm {row['paper_std']:.2f}$"
            extras.append(extra)
        lines.append(controller_latex(ctrl) + " & " + " & ".join(scores) + r" \\")
        lines.append(" & " + " & ".join(extras) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
    return "\n".join(lines) + "\n"


def _latex_escape(text: str) -> str:
    return text.replace("_", r"\_").replace("&", r"\&").replace("%", r"\%")
