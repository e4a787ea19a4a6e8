"""The paper's claims, each with the statistic that decides it on the stored runs.

``python analysis/make_table.py --claims`` prints one line per claim: what is claimed, the
measured statistic and ``holds`` / ``does not hold`` (``not measurable`` when the runs
needed are not in the store).  Over the seeds of two cells:

* *better final score*: a one-sided Mann–Whitney U test (``scipy.stats.mannwhitneyu``) of the
  final scores, holding at p < :data:`ALPHA`, reported with the difference of the means and
  its 95 % percentile bootstrap interval (:data:`BOOTSTRAP` resamples of each cell's seeds);
* *faster and steadier*: the median solve episode (a seed that never solved counts as never)
  and the std of the final scores, ordered as claimed;
* *fewer environment interactions*: the median environment steps to the solve threshold
  lower than Double DQN's and the area under the learning curve (AUC, mean of
  ``return_ma100``) higher by the one-sided test;
* *no divergence*: no run of a controlled agent among the table's runs diverged (the
  other agents' divergences are counted beside it);
* *Q-values below / above the true return* (paper Sec. 6, CartPole: H∞ settles below 200,
  Double DQN near 295): over each run's last :data:`Q_EPISODES` episodes, the mean of
  Q(s0, a0) at the first step over the mean return from that step discounted with the
  agent's own γ of its TD target (``controller.discount`` for Double DQN, else
  ``train.discount``), read from ``signals/steps.parquet``; below 1 settles below the true
  return, above 1 overestimates it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import pandas as pd
from scipy.stats import mannwhitneyu

from analysis.runs import RunStore, param_value
from analysis.style import controller_text, env_text
from cdqn.records import Artifact, Metric, Tag
from cdqn.records import Signal as S

ALPHA = 0.05
"""Significance level of the one-sided tests."""
BOOTSTRAP = 10_000
"""Bootstrap resamples of the difference of two cells' means."""
Q_EPISODES = 100
"""Last episodes whose Q(s0) and return are compared."""
CONTROLLED = ("h2", "hinf_f", "hinf")


class Claim(NamedTuple):
    """One claim of the paper and what the stored runs say about it."""

    text: str
    statistic: str
    holds: bool | None
    """None: the runs needed are not in the store."""

    def line(self) -> str:
        verdict = {True: "holds", False: "does not hold", None: "not measurable"}[self.holds]
        return f"{self.text}: {self.statistic} -> {verdict}"


def _cell(scores: pd.DataFrame, ctrl: str, env: str, column: str) -> np.ndarray:
    hit = scores[(scores["controller"] == ctrl) & (scores["env"] == env)]
    return hit[column].to_numpy(dtype=float)


def bootstrap_interval(a: np.ndarray, b: np.ndarray, seed: int = 0) -> tuple[float, float]:
    """95 % percentile bootstrap interval of mean(a) − mean(b), seeds resampled per cell."""
    rng = np.random.default_rng(seed)
    da = rng.choice(a, (BOOTSTRAP, a.size)).mean(axis=1)
    db = rng.choice(b, (BOOTSTRAP, b.size)).mean(axis=1)
    lo, hi = np.percentile(da - db, [2.5, 97.5])
    return float(lo), float(hi)


def _seeds(pairs: dict[str, np.ndarray]) -> str:
    """``seeds: H∞ dynamic 0, DDQN 10`` for a claim that lacks runs."""
    return "seeds: " + ", ".join(f"{controller_text(c)} {v.size}" for c, v in pairs.items())


def greater(a: np.ndarray, b: np.ndarray) -> tuple[float, str]:
    """One-sided Mann–Whitney U p-value of ``a > b`` and its text with the mean difference."""
    p = float(mannwhitneyu(a, b, alternative="greater").pvalue)
    lo, hi = bootstrap_interval(a, b)
    diff = a.mean() - b.mean()
    return p, f"Δmean {diff:+.2f} [95% CI {lo:+.2f}, {hi:+.2f}], Mann–Whitney p = {p:.3g}"


def score_claim(scores: pd.DataFrame, env: str, winner: str, loser: str) -> Claim:
    """``winner``'s final scores above ``loser``'s on ``env`` (one-sided test)."""
    text = f"{controller_text(winner)} beats {controller_text(loser)} on {env_text(env)}"
    a, b = (_cell(scores, c, env, Metric.FINAL_SCORE) for c in (winner, loser))
    if a.size < 2 or b.size < 2:
        return Claim(text, _seeds({winner: a, loser: b}), None)
    p, stat = greater(a, b)
    means = f"{a.mean():.2f} vs {b.mean():.2f}"
    return Claim(text, f"final {means}, {stat}", p < ALPHA)


def _solve_median(scores: pd.DataFrame, ctrl: str, env: str, column: str) -> float:
    values = _cell(scores, ctrl, env, column)
    return float(np.median(np.where(np.isnan(values), np.inf, values))) if values.size else np.nan


def ordering_claim(scores: pd.DataFrame, env: str, order: tuple[str, ...]) -> Claim:
    """``order`` solves ``env`` fastest first (median solve episode) with the least spread
    first (std of the final scores)."""
    names = ", then ".join(controller_text(c) for c in order)
    text = f"{env_text(env)}: fastest with least spread {names}"
    finals = [_cell(scores, c, env, Metric.FINAL_SCORE) for c in order]
    if any(f.size < 2 for f in finals):
        return Claim(text, _seeds(dict(zip(order, finals, strict=True))), None)
    medians = [_solve_median(scores, c, env, "solve_episode") for c in order]
    spreads = [float(np.std(f)) for f in finals]
    stat = "median solve episode " + " / ".join(f"{m:g}" for m in medians)
    stat += "; std of final scores " + " / ".join(f"{s:.2f}" for s in spreads)
    ordered = _increasing(medians) and _increasing(spreads)
    return Claim(text, stat, bool(ordered))


def _increasing(values: list[float]) -> bool:
    return all(a < b for a, b in zip(values, values[1:], strict=False))


def interaction_claim(scores: pd.DataFrame, env: str, ctrl: str) -> Claim:
    """``ctrl`` needs fewer environment steps to the threshold than Double DQN on ``env``
    and has the larger area under the learning curve."""
    text = f"{controller_text(ctrl)} needs fewer interactions than DDQN on {env_text(env)}"
    a, b = _cell(scores, ctrl, env, "auc"), _cell(scores, "ddqn", env, "auc")
    if a.size < 2 or b.size < 2:
        return Claim(text, _seeds({ctrl: a, "ddqn": b}), None)
    steps = [_solve_median(scores, c, env, "solve_steps") for c in (ctrl, "ddqn")]
    p, stat = greater(a, b)
    fewer = steps[0] < steps[1]
    return Claim(
        text,
        f"median steps to threshold {steps[0]:g} vs {steps[1]:g}; AUC {a.mean():.1f} vs "
        f"{b.mean():.1f}, {stat}",
        bool(fewer and p < ALPHA),
    )


def divergence_claim(runs: pd.DataFrame) -> Claim:
    """The controlled agents never diverge (paper Sec. 6: no target network, no random replay):
    none of ``runs`` (every status) of :data:`CONTROLLED` failed with ``diverged: ...``; the
    other agents' count is reported beside it."""
    reasons = runs.get(Tag.FAILURE_REASON, pd.Series(None, index=runs.index)).fillna("")
    diverged = (runs["status"] == "FAILED") & reasons.str.startswith("diverged")
    controlled = runs["controller"].isin(CONTROLLED)
    n, k = int(controlled.sum()), int((diverged & controlled).sum())
    others = f"; other agents {int((diverged & ~controlled).sum())} of {int((~controlled).sum())}"
    return Claim(
        "No divergence of the controlled agents over all runs",
        f"{k} of {n} controlled runs diverged{others}",
        k == 0 and n > 0,
    )


class QGap(NamedTuple):
    """Q(s0, a0) against the return from s0 over a run's last episodes."""

    q0: float
    """Mean Q(s, a) at each episode's first step."""
    ret: float
    """Mean return from that step, discounted with the agent's γ."""


def q_gap(steps: pd.DataFrame, gamma: float, last: int = Q_EPISODES) -> QGap:
    """:class:`QGap` of one run's ``signals/steps.parquet`` rows."""
    episodes = np.sort(steps[S.EPISODE].unique())[-last:]
    q0, ret = [], []
    for _, df in steps[steps[S.EPISODE].isin(episodes)].groupby(S.EPISODE):
        df = df.sort_values(S.STEP)
        rewards = df[S.REWARD].to_numpy(dtype=float)
        q0.append(float(df[S.Q1].iloc[0]))
        ret.append(float(np.sum(rewards * gamma ** np.arange(rewards.size))))
    return QGap(float(np.mean(q0)), float(np.mean(ret)))


def agent_gamma(run: pd.Series) -> float:
    """γ of the agent's TD target: Double DQN's ``controller.discount`` (null: the
    ``train.discount``), every other agent's ``train.discount``."""
    own = param_value(run.get("params.controller.discount"))
    if run["controller"] == "ddqn" and own is not None:
        return float(own)
    return float(param_value(run.get("params.train.discount"), 1.0))


def q_value_claim(
    runs: pd.DataFrame, steps: Callable[[str], pd.DataFrame | None], env: str, ctrl: str
) -> Claim:
    """Controlled agents' Q(s0) settles below the return, Double DQN's above it."""
    above = ctrl == "ddqn"
    side = "above (overestimates)" if above else "below"
    text = f"{controller_text(ctrl)} Q-values settle {side} the true return on {env_text(env)}"
    gaps = []
    for _, run in runs[(runs["env"] == env) & (runs["controller"] == ctrl)].iterrows():
        table = steps(str(run["run_id"]))
        if table is not None and not table.empty:
            gaps.append(q_gap(table, agent_gamma(run)))
    if not gaps:
        return Claim(text, f"no {Artifact.STEPS}", None)
    q0 = np.array([g.q0 for g in gaps])
    ret = np.array([g.ret for g in gaps])
    right = (q0 > ret) if above else (q0 < ret)
    stat = (
        f"Q(s0) {q0.mean():.1f} vs return {ret.mean():.1f} (last {Q_EPISODES} episodes, "
        f"{int(right.sum())}/{right.size} seeds {side.split()[0]})"
    )
    return Claim(text, stat, bool(right.all()))


def evaluate(
    scores: pd.DataFrame, runs: pd.DataFrame, all_runs: pd.DataFrame, store: RunStore
) -> list[Claim]:
    """Every claim on the table's per-run ``scores`` (:func:`analysis.table.run_scores`),
    its ``runs`` and ``all_runs`` (the same cells, every status)."""
    claims = [
        score_claim(scores, "cartpole", "hinf", "ddqn"),
        score_claim(scores, "mountaincar", "hinf", "ddqn"),
        score_claim(scores, "acrobot", "ddqn", "hinf"),
        ordering_claim(scores, "cartpole", ("hinf", "hinf_f", "ddqn")),
    ]
    claims += [
        interaction_claim(scores, env, ctrl)
        for env in ("cartpole", "acrobot", "mountaincar")
        for ctrl in CONTROLLED
    ]
    claims.append(divergence_claim(all_runs))
    claims += [q_value_claim(runs, store.steps, "cartpole", c) for c in (*CONTROLLED, "ddqn")]
    return claims
