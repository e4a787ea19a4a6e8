"""What a comparison holds equal: the settings every agent of one environment shares.

A column of the results table (one environment) compares agents.  The comparison is on
equal terms only when every agent of the column was trained with the same values of
:data:`SHARED_SETTINGS`: the same seeds and episode budget, the same observation map (what
the network sees) and the same exploration schedule and network.  What makes an agent the
agent it is, :data:`AGENT_SETTINGS`, differs by nature and is not compared: Double DQN's
replay, minibatch, target network, step size and discount; a controller's design, weights
and learning target.

:mod:`analysis.columns` reads both from the stored runs; ``make_table.py`` lists in the
table's caption every shared setting that differs between the agents of a column.
"""

from __future__ import annotations

from typing import NamedTuple


class Shared(NamedTuple):
    """One setting every agent of an environment shares."""

    key: str
    """Run tag or param name (``seed``, ``env.normalize``)."""
    what: str
    """What it sets, in a few words (for the settings table)."""


SEEDS = "seed"
"""The one shared setting compared as a set over an agent's runs, not run by run."""

SHARED_SETTINGS: tuple[Shared, ...] = (
    Shared(SEEDS, "seeds"),
    Shared("train.episodes", "episodes per run"),
    Shared("env.id", "environment"),
    Shared("env.kwargs", "environment arguments"),
    Shared("env.max_episode_steps", "episode cap (steps)"),
    Shared("env.obs_indices", "observed features"),
    Shared("env.normalize", "features mapped to [-1, 1]"),
    Shared("env.normalize_scale", "per-feature half-width after normalize"),
    Shared("env.rbf_centres", "radial basis centres per feature"),
    Shared("env.rbf_width", "radial basis width (grid spacings)"),
    Shared("train.eps_start", "ε at the start"),
    Shared("train.eps_end", "ε floor"),
    Shared("train.eps_dec", "ε decrease"),
    Shared("train.eps_schedule", "what lowers ε"),
    Shared("network.width", "hidden units"),
    Shared("network.dtype", "parameter type"),
)
"""Settings every agent of one environment must share for a like-for-like comparison."""

SHARED_KEYS: tuple[str, ...] = tuple(s.key for s in SHARED_SETTINGS)

AGENT_SETTINGS: dict[str, tuple[str, ...]] = {
    "ddqn": (
        "controller.buffer_size",
        "controller.batch_size",
        "controller.learning_starts",
        "controller.train_freq",
        "controller.target_update",
        "controller.lr",
        "controller.discount",
    ),
    "controlled": (
        "controller.design",
        "design_source",
        "controller.synthesis.ntk_bounds",
        "train.lr",
        "train.discount",
        "weights.target.",
        "weights.controller_target.",
        "weights.reset_integrator.",
        "weights.replay.",
        "weights.h2.",
        "weights.hinf.",
        "weights.hinf_f.",
        "weights.theta_bounds.",
    ),
}
"""Settings that belong to one kind of agent and are not compared between agents: Double
DQN's replay buffer, minibatch, target network, α and γ (``controller.*``, docs/ddqn.md);
a controlled agent's design, its weights (``weights.<controller>.*``) and its learning
target (α, γ and the synthesised target, docs/synthesis.md).  A key ending in ``.`` stands
for every param under it (:func:`analysis.runs.setting_keys`)."""


def agent_kind(controller: str) -> str:
    """``ddqn`` for Double DQN, ``controlled`` for every other agent."""
    return "ddqn" if controller == "ddqn" else "controlled"
