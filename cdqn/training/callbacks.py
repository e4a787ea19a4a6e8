"""The end of a multirun: which jobs finished, which failed, and why.

Every job writes its outcome to ``cdqn_job.json`` in its Hydra output folder
(:func:`record_job`); :class:`MultirunSummary`, registered under ``hydra.callbacks`` in
``conf/config.yaml``, reads them all once the sweep is over, prints a table and writes
``summary.json`` into the sweep folder.  The files work with every launcher (in-process,
joblib workers, Slurm jobs on a shared file system).
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger("cdqn")

JOB_FILE = "cdqn_job.json"
SUMMARY_FILE = "summary.json"


def record_job(
    status: str,
    run_id: str | None = None,
    reason: str | None = None,
    final_score: float | None = None,
    solved: str | None = None,
) -> None:
    """Write this Hydra job's outcome (status FINISHED, FAILED, KILLED or REFUSED), its
    final score and whether it reached the solve threshold (``solved``, e.g. ``not
    solved``)."""
    try:
        hc = HydraConfig.get()
    except ValueError:  # not under Hydra (tests, notebooks)
        return
    score = None if final_score is None or not math.isfinite(final_score) else final_score
    data = {
        "job": hc.job.get("num"),
        "overrides": list(hc.overrides.task),
        "status": status,
        "run_id": run_id,
        "reason": reason,
        "final_score": score,
        "solved": solved,
    }
    out = Path(hc.runtime.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / JOB_FILE).write_text(json.dumps(data, indent=1))


def summarize(sweep_dir: Path) -> list[dict[str, Any]]:
    """One entry per job folder of a sweep (folders holding ``.hydra/``), in job order."""
    jobs = []
    for hydra_dir in sweep_dir.rglob(".hydra"):
        job_dir = hydra_dir.parent
        result = job_dir / JOB_FILE
        if result.exists():
            entry = json.loads(result.read_text())
        else:
            overrides_file = hydra_dir / "overrides.yaml"
            overrides = list(OmegaConf.load(overrides_file)) if overrides_file.exists() else []
            entry = {
                "job": None,
                "overrides": overrides,
                "status": "UNKNOWN",
                "run_id": None,
                "reason": "no result: the job crashed or was killed before it finished",
            }
        entry["dir"] = str(job_dir)
        jobs.append(entry)
    return sorted(jobs, key=lambda e: (_job_key(e["dir"], sweep_dir), e["dir"]))


def format_summary(jobs: list[dict[str, Any]], sweep_dir: Path) -> str:
    counts: dict[str, int] = {}
    for job in jobs:
        counts[job["status"]] = counts.get(job["status"], 0) + 1
    head = ", ".join(f"{n} {status}" for status, n in sorted(counts.items()))
    lines = [f"cdqn multirun {sweep_dir}: {len(jobs)} jobs: {head}"]
    for job in jobs:
        name = Path(job["dir"]).relative_to(sweep_dir) if job["dir"] else "?"
        run = f"run {job['run_id']}" if job.get("run_id") else "no run"
        score = job.get("final_score")
        result = "" if score is None else f"score {score:8.2f}"
        if job.get("solved"):
            result += f" ({job['solved']})"
        line = (
            f"  {str(name):>4}  {job['status']:<8}  {run}  {result}  {' '.join(job['overrides'])}"
        )
        if job["status"] != "FINISHED" and job.get("reason"):
            line += f"\n          -> {job['reason']}"
        lines.append(line)
    return "\n".join(lines)


class MultirunSummary(Callback):
    """Prints which jobs of a multirun failed and why, and writes ``summary.json``."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        if not sweep_dir.is_dir():
            return
        jobs = summarize(sweep_dir)
        (sweep_dir / SUMMARY_FILE).write_text(json.dumps(jobs, indent=1))
        print(format_summary(jobs, sweep_dir), flush=True)


def _job_key(job_dir: str, sweep_dir: Path) -> tuple[int, ...]:
    parts = Path(job_dir).relative_to(sweep_dir).parts
    return tuple(int(p) if p.isdigit() else -1 for p in parts)
