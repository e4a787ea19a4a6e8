"""The best specification on fresh seeds, and the tuned agents of one environment side by side.

Every study of an environment evaluates its best trial on the same fresh seeds
(``tune.eval_seed`` …) for the same episodes; the evaluation run keeps each seed's returns
(``evaluation/returns.json``).  :func:`write_comparison` puts the latest evaluation of each
agent tuned on the environment (same seeds, same episodes) into one table and one figure:
final score (mean return of the last 100 episodes, mean ± std over seeds), first episode
whose 100-episode mean reaches the solve threshold (median over seeds), seeds that reach it,
and J, the area under the learning curve (:mod:`cdqn.tuning.objective`)."""

from __future__ import annotations

import copy
import itertools
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf, read_write

from cdqn.records import Artifact, Metric, folder
from cdqn.tuning.diagnosis import evaluation_record, shortfall_text
from cdqn.tuning.objective import area, decimals, final, ma100, padded, score_text

log = logging.getLogger("cdqn.tune")
RETURNS = Artifact.EVALUATION_RETURNS
"""Artifact of an evaluation run: ``{seed: [return per episode]}``."""
UNTUNED = " (untuned)"
"""Suffix of the comparison's row of a study's untuned ``tune.baseline``."""
SEEDS = Artifact.EVALUATION_SEEDS
"""Artifact of an evaluation run: what each seed did (:mod:`cdqn.tuning.diagnosis`)."""


def evaluate(study: Any, cfg: DictConfig, name: str, kind: str = "evaluation") -> dict[str, Any]:
    """Train ``cfg`` on its seeds (the fresh ones; a recheck's, ``kind=recheck``); its
    objective, final score and per-seed returns.  The seeds are split into
    ``tune.eval_processes`` populations trained side by side (one per core by default); each
    member's returns are read back from the store."""
    from cdqn.training.divergence import is_divergence

    conf, tracker = study.conf, study.tracker
    agent = str(cfg.controller.name)
    tags = {"study": conf.tune.study, "agent": agent, "env": conf.env.name,
            "episodes": str(study.episodes), "seeds": _seeds_tag(cfg)}  # fmt: skip
    run = tracker.child(study.parent, name, tags, kind=kind)
    t0 = time.perf_counter()
    members = _train_split(cfg, eval_processes(conf.tune.eval_processes, int(cfg.train.population)))
    ids = [r.run_id for r in members]
    tracker.nest(run, ids)
    seeds = [int(cfg.seed) + i for i in range(len(members))]
    failed = {s for s, r in zip(seeds, members, strict=True) if is_divergence(r.status, r.reason)}
    n = study.episodes
    curves = {s: padded(tracker.returns(rid), n, s in failed) or tracker.returns(rid)
              for s, rid in zip(seeds, ids, strict=True)}  # fmt: skip
    row = summarise(agent, curves, n, conf.env.solve_threshold)
    out = {**row, "seeds": seeds, "diverged": len(failed), "seconds": time.perf_counter() - t0}
    tracker.client.log_dict(run, {str(s): list(map(float, c)) for s, c in curves.items()}, RETURNS)
    if kind == "evaluation":  # what the comparison reads (a recheck only chooses the trial)
        finals = {s: final(c) for s, c in curves.items()}
        out["record"] = evaluation_record(tracker, finals, members, cfg)
        tracker.client.log_dict(run, out["record"], SEEDS)
    tracker.metrics(run, {Metric.OBJECTIVE: row["objective"],
                          Metric.FINAL_SCORE: row["final_score"]})  # fmt: skip
    tracker.end(run, "FINISHED", "complete")
    log.info("%s on seeds %s: J = %.2f, final MA100 = %s (%.0f s)", name, seeds, row["objective"],
             score_text(row["final_score"], row["final_std"]), out["seconds"])  # fmt: skip
    return out


def eval_processes(setting: int, seeds: int) -> int:
    """Processes of the evaluation: ``tune.eval_processes``, 0 for one per core."""
    return max(1, min(seeds, setting or os.cpu_count() or 1))


def _train_split(cfg: DictConfig, processes: int) -> list[Any]:
    """The population of ``cfg`` as ``processes`` populations of consecutive seeds, each
    trained by its own ``python -m cdqn.tuning.evaluation <config> <result>`` process side by
    side (new interpreters: a study may itself run in a launcher's worker process); the
    members' results in seed order."""
    from cdqn.training.result import RunResult
    from cdqn.training.run import run_population

    k = int(cfg.train.population)
    if processes == 1:
        return run_population(cfg, progress=False).members
    bounds = np.linspace(0, k, processes + 1).astype(int)
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
    with tempfile.TemporaryDirectory() as tmp:
        procs = []
        for i, (lo, hi) in enumerate(itertools.pairwise(bounds)):
            part = copy.deepcopy(cfg)
            with read_write(part):
                part.seed = int(cfg.seed) + int(lo)
                part.train.population = int(hi - lo)
            OmegaConf.save(part, Path(tmp) / f"part{i}.yaml", resolve=True)
            args = [sys.executable, "-m", "cdqn.tuning.evaluation",
                    str(Path(tmp) / f"part{i}.yaml"), str(Path(tmp) / f"part{i}.json")]  # fmt: skip
            procs.append(subprocess.Popen(args, env=env))
        codes = [p.wait() for p in procs]
        if any(codes):
            raise RuntimeError(f"an evaluation process failed (exit statuses {codes})")
        out = []
        for i in range(processes):
            rows = json.loads((Path(tmp) / f"part{i}.json").read_text())
            out += [RunResult(**row) for row in rows]
    return out


def _train_part(config: Path, result: Path) -> None:
    """One part of :func:`_train_split`: train the population of ``config``, write its
    members' results to ``result`` (JSON)."""
    import dataclasses

    from cdqn.config import Config, merged
    from cdqn.training.run import run_population

    cfg = merged(OmegaConf.structured(Config), OmegaConf.load(config))
    members = run_population(cfg, progress=False).members
    result.write_text(json.dumps([dataclasses.asdict(m) for m in members]))


def _seeds_tag(cfg: DictConfig) -> str:
    first = int(cfg.seed)
    return f"{first}-{first + int(cfg.train.population) - 1}"


def summarise(
    agent: str, curves: dict[int, list[float]], n: int, threshold: float | None
) -> dict[str, Any]:
    """One agent's row: J, final score (mean ± std over seeds), solve episodes, the mean
    MA100 curve."""
    full = [c for c in curves.values() if len(c) == n]
    finals = [final(c) for c in curves.values() if c]
    solved = []
    if threshold is not None:
        for c in curves.values():
            hit = np.flatnonzero(ma100(c) >= threshold) if c else np.array([])
            solved.append(int(hit[0]) + 1 if hit.size else None)
    reached = [e for e in solved if e is not None]
    return {
        "agent": agent,
        "objective": area(full) if full and len(full) == len(curves) else float("nan"),
        "final_score": float(np.mean(finals)),
        "final_std": float(np.std(finals)),
        "finals": finals,
        "solve_median": float(np.median(reached)) if reached else None,
        "solved": len(reached),
        "curve": np.mean([ma100(c) for c in full], axis=0).tolist() if full else [],
        "curve_std": np.std([ma100(c) for c in full], axis=0).tolist() if full else [],
    }


def write_comparison(study: Any, summary: dict[str, Any]) -> dict[str, Any]:
    """The latest evaluation of every agent tuned on this environment with the same fresh
    seeds and episodes (and this study's untuned ``tune.baseline``), as a Markdown table and
    a figure on the parent run (``comparison/``)."""
    rows = _other_agents(study, summary["evaluation"])
    mine = {**summary["evaluation"], "agent": study.agent, "study": study.conf.tune.study}
    rows = sorted([mine, *rows], key=lambda r: r["agent"])
    if "baseline" in summary:
        rows.append({**summary["baseline"], "agent": f"{summary['baseline']['agent']}{UNTUNED}",
                     "study": study.conf.tune.study})  # fmt: skip
    env = study.conf.env
    chance = random_policy(env, summary["evaluation"]["seeds"])
    table = comparison_table(rows, env.solve_threshold, study.episodes, chance) + _shortfalls(rows)
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "comparison.md").write_text(table + "\n")
        _figure(rows, env, Path(tmp) / "comparison.png", chance)
        study.tracker.client.log_artifacts(study.parent, tmp, "comparison")
    return {"env": env.name, "table": table, "rows": [r["agent"] for r in rows],
            "random": chance}  # fmt: skip


def random_policy(env_cfg: Any, seeds: list[int], episodes: int = 100) -> dict[str, float]:
    """Return per episode of uniformly random actions on the environment of ``env_cfg``
    (its observation maps left out: they do not change what happens), ``episodes`` episodes
    spread over ``seeds`` (each seed resets its environment and seeds its action space):
    the score of an agent that learns nothing, on the same seeds."""
    from cdqn.envs import make_env

    cfg = copy.deepcopy(env_cfg)
    cfg.normalize, cfg.rbf_centres, cfg.obs_indices = False, None, None
    env = make_env(cfg)
    returns: list[float] = []
    for i in range(episodes):
        seed = seeds[i % len(seeds)]
        first = i < len(seeds)
        env.reset(seed=seed if first else None)
        if first:
            env.action_space.seed(seed)
        total, done = 0.0, False
        while not done:
            _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
    env.close()
    return {"mean": float(np.mean(returns)), "std": float(np.std(returns)), "episodes": episodes}


def _other_agents(study: Any, mine: dict[str, Any]) -> list[dict[str, Any]]:
    """The latest FINISHED evaluation of each other agent's study of this environment on the
    same seeds and episodes, read back from the store."""
    client, conf = study.tracker.client, study.conf
    seeds = f"{mine['seeds'][0]}-{mine['seeds'][-1]}"
    found = client.search_runs(
        [study.tracker.experiment_id],
        filter_string=(
            f"tags.kind = 'evaluation' and tags.env = '{conf.env.name}' and "
            f"tags.seeds = '{seeds}' and tags.episodes = '{study.episodes}' and "
            "attributes.status = 'FINISHED'"
        ),  # fmt: skip
        order_by=["attributes.start_time DESC"],
    )
    rows: dict[str, dict[str, Any]] = {}
    for run in found:
        agent = run.data.tags.get("agent", "")
        if agent == study.agent or agent in rows or "baseline" in run.info.run_name:
            continue
        with tempfile.TemporaryDirectory() as tmp:
            path = client.download_artifacts(run.info.run_id, RETURNS, tmp)
            curves = {int(k): v for k, v in json.loads(Path(path).read_text()).items()}
            record = _record(client, run.info.run_id, tmp)
        row = summarise(agent, curves, study.episodes, conf.env.solve_threshold)
        rows[agent] = {**row, "study": run.data.tags.get("study", ""), "seeds": sorted(curves),
                       "record": record}  # fmt: skip
    return list(rows.values())


def _record(client: Any, run_id: str, tmp: str) -> dict[str, Any] | None:
    """An evaluation's ``evaluation/seeds.json`` (None for one written without it)."""
    if not any(a.path == SEEDS for a in client.list_artifacts(run_id, folder(Artifact.EVALUATION))):
        return None
    return json.loads(Path(client.download_artifacts(run_id, SEEDS, tmp)).read_text())


def _shortfalls(rows: list[dict[str, Any]]) -> str:
    """:func:`cdqn.tuning.diagnosis.shortfall_text` of each agent whose final score ends
    below Double DQN's minus one std, where both evaluations kept their seeds' records."""
    base = next((r for r in rows if r["agent"] == "ddqn"), None)
    if base is None or not base.get("record"):
        return ""
    bar, p = base["final_score"] - base["final_std"], _places(rows)
    return "".join(
        "\n" + shortfall_text(r["agent"], r["record"], base["record"], bar, p)
        for r in rows
        if r["agent"] != "ddqn"
        and not r["agent"].endswith(UNTUNED)
        and r.get("record")
        and r["final_score"] < bar
    )


def _places(rows: list[dict[str, Any]]) -> int:
    """Decimals of the comparison's returns: at least two; three where the returns are below
    0.1 (a goal rarely reached)."""
    return max(2, decimals(*(v for r in rows for v in (r["final_score"], r["final_std"]))))


def comparison_table(
    rows: list[dict[str, Any]],
    threshold: float | None,
    episodes: int,
    chance: dict[str, float] | None = None,
) -> str:
    """Markdown: one row per agent, and whether each design reaches Double DQN's final score
    minus one standard deviation on the same seeds; with ``chance`` (:func:`random_policy`),
    how far each agent ends above a random policy.  An environment without a solve
    threshold (``env.solve_threshold=null``: none registered, none given) has no solve
    episode and no count of seeds that reach it (``n/a``)."""
    reach = "no solve threshold" if threshold is None else f"seeds ≥ {threshold:g}"
    head = (
        f"| agent | study | final score (mean ± std, {len(rows[0]['finals'])} seeds) | "
        f"solve episode (median) | {reach} | J (area, {episodes} episodes) |"
    )
    lines = [head, "|---|---|---|---|---|---|"]
    p = _places(rows)
    pj = max(2, decimals(*(r["objective"] for r in rows)))
    for r in rows:
        solve = "n/a" if r["solve_median"] is None else f"{r['solve_median']:.0f}"
        solved = "n/a" if threshold is None else f"{r['solved']}/{len(r['finals'])}"
        lines.append(f"| {r['agent']} | {r['study']} | {r['final_score']:.{p}f} ± "
                     f"{r['final_std']:.{p}f} | {solve} | {solved} | "
                     f"{r['objective']:.{pj}f} |")  # fmt: skip
    base = next((r for r in rows if r["agent"] == "ddqn"), None)
    if base is not None:
        bar = base["final_score"] - base["final_std"]
        for r in rows:
            if r["agent"] != "ddqn":
                gap = r["final_score"] - bar
                verdict = "reaches" if gap >= 0 else "falls short of"
                lines.append(f"\n{r['agent']} {verdict} Double DQN's final score minus one std "
                             f"({bar:.{p}f}) by {abs(gap):.{p}f}.")  # fmt: skip
    if chance is not None:
        ends = ", ".join(f"{r['agent']} {r['final_score'] - chance['mean']:+.{p}f}" for r in rows)
        lines.append(f"\nA random policy scores {chance['mean']:.{p}f} ± {chance['std']:.{p}f} "
                     f"per episode ({chance['episodes']} episodes on the same seeds); final "
                     f"score against it: {ends}.")  # fmt: skip
    return "\n".join(lines)


def _figure(
    rows: list[dict[str, Any]], env: Any, out: Path, chance: dict[str, float] | None = None
) -> None:
    """Mean MA100 over the seeds with ± one std, one line per agent; the solve threshold
    dotted, a random policy's mean return dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for r in rows:
        if not r["curve"]:
            continue
        x = np.arange(1, len(r["curve"]) + 1)
        mean, std = np.asarray(r["curve"]), np.asarray(r["curve_std"])
        ax.plot(x, mean, label=f"{r['agent']} ({score_text(r['final_score'], r['final_std'])})")
        ax.fill_between(x, mean - std, mean + std, alpha=0.2)
    if env.solve_threshold is not None:
        ax.axhline(env.solve_threshold, color="grey", ls=":", lw=1)
    if chance is not None:
        ax.axhline(chance["mean"], color="black", ls="--", lw=1,
                   label=f"random policy ({score_text(chance['mean'])})")  # fmt: skip
    ax.set_xlabel("episode")
    ax.set_ylabel("MA100 return, mean ± std")
    ax.set_title(f"{env.name}: tuned agents on fresh seeds", loc="left", fontsize=10)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    logging.basicConfig(level=logging.WARNING)
    _train_part(Path(sys.argv[1]), Path(sys.argv[2]))
