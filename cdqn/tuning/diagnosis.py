"""Where a tuned design falls short of the tuned Double DQN: what each fresh seed did.

An evaluation (:func:`cdqn.tuning.evaluation.evaluate`) keeps, for each of its seeds, what
the comparison needs to say why one agent ends below another (``evaluation/seeds.json``):

* ``final``: the final score, the mean return of the seed's last 100 episodes;
* ``steps``: the environment steps the seed played, and ``learned_per_step``, the
  transitions each of them put into an update: Double DQN's ``batch_size / train_freq``
  (a minibatch every ``train_freq`` steps), a controlled agent's one TD step plus its
  sampled replay's ``weights.replay.sample`` and its episodic replay's updates per step
  (paper Sec. 4 takes one);
* ``epsilon``: the exploration rate ε at the end;
* for a design, ``theta1_outside_box``, ``ratio_above_box``, ``ratio_below_box``: the share of
  the steps of the last 100 episodes whose Θ1 left the NTK box the design was certified on,
  or whose ratio Θ2/Θ1 left it above (where the loop's pole leaves the unit circle once
  γ_eff·Θ2/Θ1 > 1) or below; with the box and the design's γ_eff (``design``).

When a controlled agent's final score ends below Double DQN's final score minus one standard
deviation on the same seeds, :func:`shortfall_text` sets the two side by side: the seeds
below that bar (a few seeds stuck, or all of them lower), the environment steps and the
transitions learned from per step, ε at the end, and the box with the share of steps
outside it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from cdqn.config import BOXED_CONTROLLERS
from cdqn.records import BOX_SERIES, SERIES_PREFIX, Metric, Tag
from cdqn.tuning.objective import WINDOW

LISTED = 5
"""Seeds below the bar named one by one; more are given as the lowest … the highest."""

BOX_SHARES = (Metric.THETA1_OUTSIDE_BOX, Metric.RATIO_ABOVE_BOX, Metric.RATIO_BELOW_BOX)
BOX_BOUNDS = tuple(SERIES_PREFIX + name for name in BOX_SERIES)
"""Metric keys of the NTK box a run logged: Θ1 lower, upper, Θ2/Θ1 lower, upper."""


def seed_record(
    tracker: Any, member: Any, final: float, controller: Any, sample: int = 0
) -> dict[str, Any]:
    """What one evaluation member (a :class:`cdqn.training.result.RunResult`) did; ``final``
    its final score as the comparison counts it (a diverged member's missing episodes at its
    lowest return, :func:`cdqn.tuning.objective.padded`).  Transitions per step: Double
    DQN's ``batch_size / train_freq``; a design's one TD step, its ``sample`` sampled
    replay's and its episodic replay's updates (module docstring)."""
    run, steps = member.run_id, int(member.steps)
    record: dict[str, Any] = {"final": float(final), "steps": steps,
                              "epsilon": float(member.epsilon)}  # fmt: skip
    if controller.name == "ddqn":
        record["learned_per_step"] = controller.batch_size / controller.train_freq
        return record
    replayed = sum(tracker.history(run, Metric.REPLAY_UPDATES))
    record["learned_per_step"] = 1.0 + sample + replayed / steps if steps else math.nan
    for key in BOX_SHARES:
        tail = tracker.history(run, key)[-WINDOW:]  # the final score's episodes
        if tail:
            record[key] = float(np.mean(tail))
    return record


def design_record(tracker: Any, run_id: str, cfg: Any) -> dict[str, Any] | None:
    """The NTK box a member's design was certified on and the γ_eff it keeps (None for an
    agent without a box): the box the run logged (``signals/theta1_box_*``, with
    ``train.signals``), else the configured one a design of ``ntk_bounds=config`` uses
    (``weights.theta_bounds``, where a study writes the box it measured)."""
    run = tracker.client.get_run(run_id)
    values = [run.data.metrics.get(key) for key in BOX_BOUNDS]
    ctrl = cfg.controller
    if any(v is None for v in values):
        if ctrl.name not in BOXED_CONTROLLERS or ctrl.synthesis.ntk_bounds != "config":
            return None
        bounds = cfg.weights.theta_bounds
        values = [*map(float, bounds.theta1), *map(float, bounds.ratio)]
    gamma = run.data.tags.get(Tag.DESIGN_GAMMA_EFF)
    return {"theta1": values[:2], "ratio": values[2:],
            "gamma_eff": None if gamma is None else float(gamma)}  # fmt: skip


def evaluation_record(
    tracker: Any, finals: dict[int, float], members: list[Any], cfg: Any
) -> dict[str, Any]:
    """``evaluation/seeds.json`` of an evaluation: each seed's :func:`seed_record` (``finals``
    and ``members`` in seed order) and the first member's :func:`design_record` (the
    members share one design)."""
    seeds = zip(finals.items(), members, strict=True)
    return {
        "seeds": {
            str(s): seed_record(tracker, m, f, cfg.controller, cfg.weights.replay.sample)
            for (s, f), m in seeds
        },
        "design": design_record(tracker, members[0].run_id, cfg) if members else None,
    }


def _mean(records: dict[str, dict[str, Any]], key: str) -> float:
    values = [r[key] for r in records.values() if key in r and np.isfinite(r[key])]
    return float(np.mean(values)) if values else math.nan


def shortfall_text(agent: str, mine: dict, base: dict, bar: float, places: int) -> str:
    """Why ``agent`` (its evaluation record ``mine``) ends below Double DQN's (``base``)
    final score minus one std, ``bar``, on the same seeds (module docstring); returns in
    ``places`` decimals."""
    ours, theirs = mine["seeds"], base["seeds"]

    def score(value: float) -> str:
        return f"{value:.{places}f}"

    below = sorted((s for s, r in ours.items() if r["final"] < bar), key=lambda s: ours[s]["final"])
    seeds = f"- seeds below the bar: {len(below)} of {len(ours)}"
    if below:
        shown = below if len(below) <= LISTED else [below[0], "…", below[-1]]
        seeds += " (" + ", ".join(s if s == "…" else f"{s}: {score(ours[s]['final'])}"
                                  for s in shown) + ")"  # fmt: skip
        rest = [r["final"] for s, r in ours.items() if s not in below]
        if rest:
            seeds += f"; the other {len(rest)} average {score(float(np.mean(rest)))}"
    medians = [score(float(np.median([r["final"] for r in x.values()]))) for x in (ours, theirs)]
    seeds += f"; median final score {agent} {medians[0]}, Double DQN {medians[1]}"
    lines = [
        f"\nWhere {agent} falls short (the same fresh seeds; shares over each seed's last "
        f"{WINDOW} episodes):",
        seeds,
        f"- environment steps per seed: {agent} {_mean(ours, 'steps'):,.0f}, Double DQN "
        f"{_mean(theirs, 'steps'):,.0f}; transitions learned from per step: {agent} "
        f"{_mean(ours, 'learned_per_step'):.2f}, Double DQN "
        f"{_mean(theirs, 'learned_per_step'):.2f}",
        f"- ε at the end: {agent} {_mean(ours, 'epsilon'):.3g}, Double DQN "
        f"{_mean(theirs, 'epsilon'):.3g}",
    ]
    if mine.get("design"):
        lines.append(_box_line(mine["design"], ours))
    return "\n".join(lines)


def _box_line(design: dict[str, Any], seeds: dict[str, dict[str, Any]]) -> str:
    """The design's NTK box, the γ_eff it allows and keeps, and the steps outside it."""
    (t_lo, t_hi), (r_lo, r_hi) = design["theta1"], design["ratio"]
    gamma = design.get("gamma_eff")
    allows = f"γ_eff below 1/{r_hi:.4g} = {1.0 / r_hi:.4g}" if r_hi > 0 else "any γ_eff"
    keeps = "" if gamma is None else f"; the design keeps γ_eff {gamma:.4g}"
    shares = ", ".join(f"{label} {100 * _mean(seeds, key):.1f} %" for label, key in (
        ("Θ1 outside", Metric.THETA1_OUTSIDE_BOX), ("Θ2/Θ1 above", Metric.RATIO_ABOVE_BOX),
        ("Θ2/Θ1 below", Metric.RATIO_BELOW_BOX)))  # fmt: skip
    return (f"- NTK box of the design: Θ1 ∈ [{t_lo:.4g}, {t_hi:.4g}], Θ2/Θ1 ∈ [{r_lo:.4g}, "
            f"{r_hi:.4g}] (a loop stable over it needs {allows}{keeps}); steps outside it: "
            f"{shares} (mean over seeds)")  # fmt: skip
