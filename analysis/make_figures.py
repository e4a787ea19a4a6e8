"""Every figure of the paper from the stored runs, as PNG and PDF.

    python analysis/make_figures.py --out figures/
    python analysis/make_figures.py --env acrobot --controller hinf_f --seed 3 --episode 200
    python analysis/make_figures.py --only NTK_range --only FFT

Learning curves cover every environment in the store; the single-run figures (loss, Q, u,
Θ1, NTK scatter, FFT, weights, closed loop) show ``--env``/``--controller``/``--seed``.
A figure whose data is missing is skipped with one line on stderr.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make the repository root importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pandas as pd

from analysis.cli import add_store_arguments, note, open_store, select_runs


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="make_figures.py", description="The paper's figures from stored cdqn runs."
    )
    add_store_arguments(parser)
    parser.add_argument("--out", type=Path, default=Path("figures"), help="output folder")
    parser.add_argument(
        "--env", default=None, help="environment of single-run figures (default: cartpole)"
    )
    parser.add_argument(
        "--controller", default=None, help="controller of single-run figures (default: hinf)"
    )
    parser.add_argument("--seed", type=int, default=None, help="seed (default: the lowest)")
    parser.add_argument(
        "--episode", type=int, default=None, help="episode (from 1) of the one-episode figures"
    )
    parser.add_argument(
        "--window", type=int, default=500, help="episodes in the Q500 / controlinput figures"
    )
    parser.add_argument(
        "--ntk-controller",
        default="none",
        help="controller whose run feeds NTK_range (paper: uncontrolled; falls back to "
        "--controller)",
    )
    parser.add_argument(
        "--only", action="append", metavar="NAME", help="make only this figure (repeatable)"
    )
    return parser


def pick(runs: pd.DataFrame, column: str, given: str | None, default: str, where: str) -> str:
    """The ``--env`` / ``--controller`` of the single-run figures: the one given, or
    ``default`` if the runs have it, else the first they have.  A name cdqn does not know
    (not a controller, not an environment preset or gymnasium id) and the runs do not have
    is refused with exit status 2; a known one the runs lack leaves its figures skipped."""
    present = sorted(str(v) for v in runs[column].dropna().unique())
    if given is None:
        return default if default in present or not present else present[0]
    if given not in present and given not in known_names(column):
        allowed = "controllers" if column == "controller" else "environments"
        note(
            f"error: --{column} {given}: unknown; {allowed} in {where}: "
            f"{', '.join(present) or 'none'}"
        )
        raise SystemExit(2)
    return given


def known_names(column: str) -> set[str]:
    """Every controller name, or every environment preset name and gymnasium id."""
    from cdqn.config import CONTROLLERS

    if column == "controller":
        return set(CONTROLLERS)
    import gymnasium as gym

    from cdqn.envs import env_presets

    return set(env_presets()) | set(gym.registry)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    start = time.perf_counter()
    store = open_store(args)

    runs = select_runs(store, args.where)
    env = pick(runs, "env", args.env, "cartpole", store.describe())
    controller = pick(runs, "controller", args.controller, "hinf", store.describe())

    from analysis import figures as figs  # plotting imports only when there is something to plot

    figs.apply_theme()
    ctx = figs.FigureContext(
        store,
        runs,
        figs.Selection(
            env=env,
            controller=controller,
            seed=args.seed,
            episode=args.episode,
            window=args.window,
            ntk_controller=args.ntk_controller,
        ),
    )
    written, skipped = 0, 0
    specs = list(figs.figure_specs(ctx))
    unknown = set(args.only or []) - {s.name for s in specs}
    if unknown:
        note(f"error: unknown figure(s) {sorted(unknown)}; known: {[s.name for s in specs]}")
        return 2
    for spec in specs:
        if args.only and spec.name not in args.only:
            continue
        try:
            fig = spec.make(ctx)
        except figs.Skip as why:
            note(f"skipped {spec.name}: {why}")
            skipped += 1
            continue
        paths = figs.save(fig, args.out, spec.name)
        note(f"wrote {paths[0].with_suffix('')}.{{png,pdf}}")
        written += 1
    for line in ctx.notes:
        note(f"note: {line}")
    note(
        f"{written} figure(s) written to {args.out}, {skipped} skipped, from {store.describe()} "
        f"in {time.perf_counter() - start:.1f} s"
    )
    return 0 if written else 1


if __name__ == "__main__":
    sys.exit(main())
