"""Which run the single-run figures show on a store of mixed settings: one of the largest
comparable group (the group the table leads with), named in the title, with a note about
the groups left out; a constant reward's spectrum panel says so."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from analysis.figures import FigureContext, Selection, fft


def _runs() -> pd.DataFrame:
    """Two 50-episode width-64 runs of a quick look, three runs of the paper's settings."""
    rows = []
    for i, (settings, seed) in enumerate(
        [("network.width=64, train.episodes=50", 0), ("network.width=64, train.episodes=50", 1),
         ("network.width=2500, train.episodes=2000", 0),
         ("network.width=2500, train.episodes=2000", 1),
         ("network.width=2500, train.episodes=2000", 2)]
    ):  # fmt: skip
        rows.append(
            {
                "run_id": f"{i:032x}",
                "run_name": f"cartpole-hinf-{'w64-e50-' if '64' in settings else ''}s{seed}",
                "env": "cartpole",
                "controller": "hinf",
                "seed": seed,
                "settings": settings,
                "start_time": 10 - i,  # the quick look is the newest
                "params.train.episodes": "50" if "64" in settings else "2000",
            }
        )
    return pd.DataFrame(rows)


def test_single_run_figures_show_the_largest_group() -> None:
    ctx = FigureContext(store=None, runs=_runs(), selection=Selection())
    run = ctx.selected
    assert run["settings"] == "network.width=2500, train.episodes=2000" and run["seed"] == 0
    assert any("[network.width=64, train.episodes=50]" in n for n in ctx.notes)
    title = ctx.run_title(run, "episodes 1-500 of 2000")
    assert title.endswith(f"\nrun cartpole-hinf-s0 ({run['run_id'][:8]})")


def test_where_keeps_the_other_group() -> None:
    runs = _runs()
    quick = runs[runs["settings"].str.contains("64")]
    ctx = FigureContext(store=None, runs=quick, selection=Selection())
    assert ctx.selected["run_name"] == "cartpole-hinf-w64-e50-s0" and ctx.notes == []


class _Spectra:
    """Stands in for the run store: the spectra of one run with CartPole's constant reward."""

    def fft(self, run_id: str) -> pd.DataFrame:
        freq = np.arange(50) / 10.0
        amp = np.r_[1.0, np.full(49, 3e-17)]  # DC and round-off
        return pd.DataFrame({"freq": freq, "reward": amp, "q1": np.r_[1, np.linspace(1, 0, 49)],
                             "q2": np.r_[1, np.linspace(1, 0, 49)]})  # fmt: skip


def test_a_constant_reward_panel_says_so() -> None:
    ctx = FigureContext(store=_Spectra(), runs=_runs(), selection=Selection())
    fig = fft(ctx)
    texts = [t.get_text() for t in fig.axes[0].texts]
    assert any("is constant" in t for t in texts), texts
    assert not any("is constant" in t.get_text() for t in fig.axes[1].texts)
    plt.close(fig)
