"""The end of a multirun: which jobs finished, which failed, and why.

Every job writes its outcome to ``cdqn_job.json`` in its Hydra output folder
(:func:`record_job`), a population job one entry per member (seed) besides;
:class:`MultirunSummary`, registered under ``hydra.callbacks`` in ``conf/config.yaml``,
reads them all once the sweep is over, prints a table with one line per run (per seed)
and writes ``summary.json`` into the sweep folder.  The files work with every launcher (in-process,
joblib workers, Slurm jobs on a shared file system).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from cdqn.config import of_kind
from cdqn.training.result import RunResult, solve_text

log = logging.getLogger("cdqn")

JOB_FILE = "cdqn_job.json"
SUMMARY_FILE = "summary.json"


def record_job(
    status: str,
    run_id: str | None = None,
    reason: str | None = None,
    final_score: float | None = None,
    solved: str | None = None,
    members: Sequence[RunResult] = (),
    seed: int | None = None,
) -> None:
    """Write this Hydra job's outcome (status FINISHED, FAILED, KILLED or REFUSED), its
    final score and whether it reached the solve threshold (``solved``, e.g. ``not
    solved``); for a population, each member's too (``members`` in seed order, the first
    being seed ``seed``: :func:`member_entries`)."""
    try:
        hc = HydraConfig.get()
    except ValueError:  # not under Hydra (tests, notebooks)
        return
    overrides = list(hc.overrides.task)
    data: dict[str, Any] = {
        "job": of_kind(hc.job, DictConfig).get("num"),
        "overrides": overrides,
        "status": status,
        "run_id": run_id,
        "reason": reason,
        "final_score": _finite(final_score),
        "solved": solved,
    }
    if members:
        data["members"] = member_entries(members, seed, overrides)
    out = Path(hc.runtime.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / JOB_FILE).write_text(json.dumps(data, indent=1))


def _finite(score: float | None) -> float | None:
    return None if score is None or not math.isfinite(score) else score


def member_entries(
    members: Sequence[RunResult], seed: int | None, overrides: list[str]
) -> list[dict[str, Any]]:
    """One entry per member of a population job: its seed (``seed + i``; None when unknown),
    the overrides of the single run it stands for (the job's, with that seed and without
    ``train.population``), status, run, reason, final score and solve."""
    out = []
    for i, result in enumerate(members):
        own = None if seed is None else seed + i
        keys = [o.partition("=")[0] for o in overrides]
        lines = [o for o, k in zip(overrides, keys, strict=True) if k != "train.population"]
        if own is not None:
            lines = [f"seed={own}" if o.partition("=")[0] == "seed" else o for o in lines]
            lines += [] if "seed" in keys else [f"seed={own}"]
        out.append(
            {
                "seed": own,
                "overrides": lines,
                "status": result.status,
                "run_id": result.run_id,
                "reason": result.reason,
                "final_score": _finite(result.final_score),
                "solved": solve_text(result),
            }
        )
    return out


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
    """The table: a header counting statuses, one line per run (each member of a population
    job on its own line, with its seed), a failed one followed by its reason."""
    rows = [(job, entry) for job in jobs for entry in job.get("members") or [job]]
    counts: dict[str, int] = {}
    for _, entry in rows:
        counts[entry["status"]] = counts.get(entry["status"], 0) + 1
    head = ", ".join(f"{n} {status}" for status, n in sorted(counts.items()))
    runs = f" ({len(rows)} runs)" if len(rows) != len(jobs) else ""
    noun = "job" if len(jobs) == 1 else "jobs"
    lines = [f"cdqn multirun {sweep_dir}: {len(jobs)} {noun}{runs}: {head}"]
    for job, entry in rows:
        name = Path(job["dir"]).relative_to(sweep_dir) if job["dir"] else "?"
        run = f"run {entry['run_id']}" if entry.get("run_id") else "no run"
        score = entry.get("final_score")
        result = "" if score is None else f"score {score:8.2f}"
        if entry.get("solved"):
            result += f" ({entry['solved']})"
        overrides = " ".join(entry["overrides"])
        line = f"  {str(name):>4}  {entry['status']:<8}  {run}  {result}  {overrides}"
        if entry["status"] != "FINISHED" and entry.get("reason"):
            line += f"\n          -> {entry['reason']}"
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
