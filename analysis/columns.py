"""Which shared settings differ between the agents of one environment (one table column).

For every environment of the runs and every setting of :data:`analysis.shared.SHARED_SETTINGS`
each agent (controller) gets a value text: its runs' value (``true``, ``6``, ``null``), or
``a or b`` when its own runs disagree, and for ``seed`` the set of its seeds (``0–9``).  A
setting *differs* in a column when two agents' texts differ or one agent's runs disagree;
:func:`caption` names every such setting, agent by agent, for the table's caption.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, NamedTuple

import pandas as pd

from analysis.runs import setting_values
from analysis.shared import SEEDS, SHARED_SETTINGS
from analysis.style import CONTROLLER_ORDER, ENV_ORDER, env_text, ordered

YAML_WORDS = {"True": "true", "False": "false", "None": "null"}
"""Param texts shown as in the YAML configuration."""


class Difference(NamedTuple):
    """A shared setting whose value is not the same for every agent of an environment."""

    env: str
    key: str
    values: dict[str, str]
    """Agent -> its value text (``a or b`` when the agent's own runs disagree)."""

    def text(self) -> str:
        """``Acrobot: env.normalize differs: ddqn false; h2, hinf, hinf_f true``."""
        groups: dict[str, list[str]] = {}
        for agent in sorted(self.values):
            groups.setdefault(self.values[agent], []).append(agent)
        parts = [f"{', '.join(agents)} {value}" for value, agents in groups.items()]
        return f"{env_text(self.env)}: {self.key} differs: {'; '.join(parts)}"


def seed_text(seeds: Iterable[Any]) -> str:
    """``[0, 1, 2, 5]`` -> ``0–2, 5`` (missing values left out)."""
    values = sorted({int(s) for s in seeds if pd.notna(s)})
    runs: list[list[int]] = []
    for s in values:
        if runs and s == runs[-1][-1] + 1:
            runs[-1].append(s)
        else:
            runs.append([s])
    parts = [str(r[0]) if len(r) == 1 else f"{r[0]}–{r[-1]}" for r in runs]
    return ", ".join(parts) or "none"


def agent_values(runs: pd.DataFrame, key: str) -> dict[str, str]:
    """Agent -> value text of shared setting ``key`` over the agent's runs in ``runs``."""
    if key == SEEDS:
        return {str(c): seed_text(df["seed"]) for c, df in runs.groupby("controller")}
    texts = setting_values(runs, key).map(lambda v: "null" if v is None or v != v else v)
    texts = texts.map(lambda v: YAML_WORDS.get(str(v), str(v)))
    out = {}
    for ctrl, values in texts.groupby(runs["controller"]):
        distinct = sorted(set(values))
        out[str(ctrl)] = " or ".join(distinct)
    return out


def column_differences(runs: pd.DataFrame) -> list[Difference]:
    """Every (environment, shared setting) whose value is not one for all agents' runs."""
    out = []
    for env in ordered(runs["env"].dropna().unique(), ENV_ORDER):
        col = runs[runs["env"] == env]
        for setting in SHARED_SETTINGS:
            values = agent_values(col, setting.key)
            mixed = any(" or " in v for v in values.values())
            if mixed or len(set(values.values())) > 1:
                out.append(Difference(str(env), setting.key, values))
    return out


TUNED_BUDGET = ("trials", "seeds", "first_seed", "episodes")
"""The budget a tuned preset records (``extra.tuned.budget``, :mod:`cdqn.tuning.presets`)."""


def tuned_budget(runs: pd.DataFrame) -> str | None:
    """``20 trials × 3 seeds (from 100) × 500 episodes`` when every run of ``runs`` trains a
    preset tuned with that one budget, else None."""
    values = []
    for name in TUNED_BUDGET:
        texts = set(setting_values(runs, f"extra.tuned.budget.{name}"))
        if len(texts) != 1 or None in texts:
            return None
        values.append(texts.pop())
    trials, seeds, first, episodes = values
    return f"{trials} trials × {seeds} seeds (from {first}) × {episodes} episodes"


def searched(runs: pd.DataFrame, diff: Difference) -> bool:
    """Whether ``diff``'s setting was chosen for every agent of its column by a search of the
    same budget that offered it to each (the agents' tuned presets, :func:`tuned_budget`)."""
    col = runs[runs["env"] == diff.env]
    if tuned_budget(col) is None:
        return False
    paths = [c for c in col.columns if c.startswith("params.extra.tuned.space.")]
    for _, df in col.groupby("controller"):
        offered = {str(v) for c in paths if c.endswith(".path") for v in df[c].dropna()}
        if diff.key not in offered:
            return False
    return True


def caption(runs: pd.DataFrame) -> str:
    """The table's caption line on its comparison: what every column's agents share and,
    one by one, the shared settings that differ between the agents of a column: chosen for
    each agent by an equal search (:func:`searched`), or not on equal terms."""
    keys = ", ".join(s.key for s in SHARED_SETTINGS)
    diffs = column_differences(runs)
    chosen = [d for d in diffs if searched(runs, d)]
    unequal = [d for d in diffs if d not in chosen]
    text = f"the agents of each column share {keys}"
    if chosen:
        envs = sorted({d.env for d in chosen})
        budgets = "; ".join(f"{env_text(e)} {tuned_budget(runs[runs['env'] == e])}" for e in envs)
        listed = ". ".join(d.text() for d in chosen)
        text += (
            f", or were offered the same and chose by searches of one budget per column "
            f"({budgets}): {listed}"
        )
    if not unequal:
        return f"Like for like: {text}."
    listed = ". ".join(d.text() for d in unequal)
    return (
        f"Not like for like: {text}; except: {listed}. "
        "Cells of such a column are not a comparison on equal terms."
    )


def settings_table(runs: pd.DataFrame) -> str:
    """Markdown: per environment, each shared setting's value for each agent, the settings
    that differ in bold (a setting no run records is left out)."""
    blocks = []
    for env in ordered(runs["env"].dropna().unique(), ENV_ORDER):
        col = runs[runs["env"] == env]
        agents = ordered(col["controller"].astype(str).unique(), CONTROLLER_ORDER)
        lines = [
            f"**{env_text(str(env))}**",
            "",
            "| setting | " + " | ".join(agents) + " |",
            "|---" * (len(agents) + 1) + "|",
        ]
        for setting in SHARED_SETTINGS:
            if not _recorded(runs, setting.key):
                continue
            values = agent_values(col, setting.key)
            cells = [values.get(a, "—") for a in agents]
            differs = len(set(cells)) > 1 or any(" or " in c for c in cells)
            name = f"**{setting.key}**" if differs else setting.key
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks)


def _recorded(runs: pd.DataFrame, key: str) -> bool:
    return key in runs.columns or f"params.{key}" in runs.columns
