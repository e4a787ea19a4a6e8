"""What a study shows: the design record of a trial, the study's plots, the printed summary."""

from __future__ import annotations

import json
import logging
import tempfile
from pathlib import Path
from typing import Any

from cdqn.records import Artifact, Tag, folder
from cdqn.tuning.objective import score_text

log = logging.getLogger("cdqn.tune")


def log_design(tracker: Any, run_id: str, setup: Any) -> None:
    """The design's record, report and certificate on run ``run_id`` (tags ``certificate``,
    ``design_source``; metrics worst pole, gains, learning-target ranges)."""
    rec = setup.design or {}
    tracker.client.log_dict(run_id, rec, Artifact.DESIGN_RECORD)
    report = Path(setup.artifacts or "") / "report.txt"
    if setup.artifacts is not None and report.is_file():
        tracker.client.log_artifact(run_id, str(report), folder(Artifact.DESIGN))
    cert = rec.get("certificate") or {}
    lt = rec.get("learning_target") or {}
    tags = {"certificate": "PASSED" if cert.get("passed", True) else "FAILED",
            Tag.DESIGN_SOURCE: setup.source}  # fmt: skip
    for k, v in tags.items():
        tracker.client.set_tag(run_id, k, str(v))
    values = {"worst_pole": cert.get("worst_pole"), "max_step_gain": lt.get("max_step_gain")}
    for i, k in enumerate(("k1", "k2", "k3")):
        if rec.get("gains"):
            values[k] = rec["gains"][i]
    for key in ("gamma_eff", "step_scale"):
        if isinstance(lt.get(key), list) and len(lt[key]) == 2:
            values[f"{key}_lo"], values[f"{key}_hi"] = lt[key]
    tracker.metrics(run_id, {k: v for k, v in values.items() if v is not None})


def plot_study(tracker: Any, parent: str, study: Any) -> None:
    """Optimisation history and parameter importances (optuna.visualization.matplotlib) and
    the trials as JSON, on the parent run."""
    import warnings

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from optuna.visualization import matplotlib as ovm

    from cdqn.config import of_kind

    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # optuna marks these plots experimental
        for name, plot in (("optimization_history", ovm.plot_optimization_history),
                           ("param_importances", ovm.plot_param_importances)):  # fmt: skip
            try:
                ax = plot(study)
            except (ValueError, RuntimeError) as err:  # too few complete trials
                log.info("no %s plot: %s", name, err)
                continue
            first = ax if isinstance(ax, Axes) else ax.flat[0]  # one Axes or an array of them
            fig = of_kind(first.figure, Figure)
            fig.set_size_inches(8, 5)
            fig.tight_layout()
            fig.savefig(Path(tmp) / f"{name}.png", dpi=120)
            plt.close(fig)
        rows = [{"number": tr.number, "state": tr.state.name, "value": tr.value,
                 "status": tr.user_attrs.get("status"), "reason": tr.user_attrs.get("reason"),
                 **tr.params} for tr in study.get_trials(deepcopy=False)]  # fmt: skip
        (Path(tmp) / "trials.json").write_text(json.dumps(rows, indent=1, default=str))
        tracker.client.log_artifacts(parent, tmp, "study")


def summary_text(s: dict[str, Any]) -> str:
    """The printed summary of a study."""
    if "counts" not in s:  # a worker other than 0
        return (f"study {s['study']}, worker {s['worker']}: ran trials {s['trials_run']} in "
                f"{s['wall_seconds']:.0f} s; MLflow parent run {s['parent_run']}; worker 0 "
                "writes the preset and the evaluation")  # fmt: skip
    c = s["counts"]
    lines = [
        f"study {s['study']}: {sum(c.values())} trials ({c['complete']} complete, "
        f"{c['pruned']} pruned, {c['infeasible']} infeasible, {c['failed']} failed) of "
        f"{s.get('episodes', '?')} episodes per member in {s['wall_seconds']:.0f} s; MLflow "
        f"parent run {s['parent_run']}"
    ]
    if "stopped" in s:
        lines.append(f"study {s['stopped']}")
    if "no_result" in s:
        lines.append(f"{s['no_result']}; no preset written")
    for row in s.get("recheck", []):
        finals = ", ".join(score_text(row[k]) for k in ("final", "recheck_final", "final_all"))
        lines.append(f"recheck of trial {row['trial']}: J = {row['objective']:.4g} on the trial's "
                     f"seeds, {row['recheck']:.4g} on the recheck's, {row['all']:.4g} over "
                     f"both; final MA100 {finals}")  # fmt: skip
    if "best_trial" in s:
        final = score_text(s["best_final_score"])
        lines.append(f"best trial {s['best_trial']}: J = {s['best_value']:.2f} (final MA100 "
                     f"{final}), {json.dumps(s['best_params'])}")  # fmt: skip
        lines.append(f"preset: {s['preset']}")
    for key in ("evaluation", "baseline"):
        if key in s:
            e = s[key]
            lines.append(f"{key} on fresh seeds {e['seeds'][0]}..{e['seeds'][-1]}: J = "
                         f"{e['objective']:.2f}, final MA100 "
                         f"{score_text(e['final_score'], e.get('final_std', float('nan')))}, "
                         f"{e['diverged']} diverged "
                         f"({e['seconds']:.0f} s)")  # fmt: skip
    if s.get("comparison"):
        lines += [f"tuned agents on {s['comparison']['env']}, fresh seeds:",
                  s["comparison"]["table"]]  # fmt: skip
    if "design_report" in s:
        lines += ["design of the best specification:", s["design_report"].rstrip()]
    return "\n".join(lines)
