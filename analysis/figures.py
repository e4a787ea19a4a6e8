"""The paper's figures from a :class:`~analysis.runs.RunStore`, one function per figure.

Every figure function takes a :class:`FigureContext` and returns a matplotlib figure, or
raises :class:`Skip` with a one-line reason when the store lacks the data.  File names are
the paper's figure labels without ``fig:`` (``Cartpole_learning``, ``NTK_range``, ...); the
single-run figures take the prefix of the selected environment (``Cartpole_Q500``).

Time axes: ``episode`` counts from 1; within an episode, ``k`` is the training step.  Learning
time is ``t = kα`` (one SGD step advances the learning dynamics by Δt = α), and frequencies
are in rad per unit of learning time, the axis of the controller design (paper Sec. 4).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from functools import cached_property, partial
from pathlib import Path
from typing import Any, NamedTuple

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
import seaborn as sns
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from analysis.runs import RunStore, param_value
from analysis.style import (
    CONTROLLER_ORDER,
    ENV_ORDER,
    controller_colors,
    controller_label,
    env_file_prefix,
    env_text,
    ordered,
)
from cdqn.records import Artifact, Metric
from cdqn.records import Signal as S
from cdqn.training.signals import ROUND_OFF, log_binned_max

FIGURE_METRICS = (Metric.RETURN_MA100, Metric.LOSS_MEAN)
"""The episode metrics the figures read (the rest come from per-step artifacts)."""
PAPER_THETA1 = (200.0, 500.0)
"""Paper Fig. NTK_range: 200 < Θ1 < 500."""
PAPER_RATIO = (0.8, 1.2)
"""Paper Fig. NTK_range: 0.8 Θ1 < Θ2 < 1.2 Θ1."""
MAX_LINE_POINTS = 100_000
"""Longer per-step series are drawn as a per-bin min-max envelope."""
MAX_SCATTER_POINTS = 30_000
"""The NTK scatter draws a fixed random subset of at most this many steps."""
FFT_BINS = 800
"""Log-spaced frequency bins of the FFT figure (the largest amplitude of each is drawn)."""
BOUND_STYLE: dict[str, Any] = {"color": "tab:red", "lw": 1.4, "ls": "--"}


class Skip(Exception):
    """The store lacks what a figure needs; the message says what."""


def apply_theme() -> None:
    """seaborn's white grid at paper scale with Computer Modern mathtext."""
    sns.set_theme(context="paper", style="whitegrid", font_scale=1.15)
    plt.rcParams.update(
        {"mathtext.fontset": "cm", "savefig.dpi": 200, "figure.constrained_layout.use": True}
    )


@dataclass
class Selection:
    """Which run the single-run figures show."""

    env: str = "cartpole"
    controller: str = "hinf"
    seed: int | None = None
    """``None``: the lowest seed present."""
    episode: int | None = None
    """Episode (from 1) of the one-episode figures; ``None``: the run's last episode."""
    window: int = 500
    """Episodes shown by the "500 episodes" figures (from the first)."""
    ntk_controller: str = "none"
    """Controller whose run feeds the NTK scatter (paper: uncontrolled learning)."""


@dataclass
class FigureContext:
    """The store, the runs to show and their episode metrics, loaded once per invocation."""

    store: RunStore
    runs: pd.DataFrame
    """The runs to show (see :func:`analysis.runs.comparable_runs`)."""
    selection: Selection = field(default_factory=Selection)
    notes: list[str] = field(default_factory=list)
    """One-line remarks about data a figure left out (printed by the CLI)."""

    @cached_property
    def episodes(self) -> pd.DataFrame:
        return self.store.episodes(FIGURE_METRICS, self.runs)

    @cached_property
    def colors(self) -> dict[str, str]:
        return controller_colors(list(self.runs["controller"].dropna().unique()))

    @property
    def envs(self) -> list[str]:
        return ordered(self.runs["env"].dropna(), ENV_ORDER)

    def find_run(self, env: str, controller: str, seed: int | None = None) -> pd.Series:
        """The run of (env, controller, seed), the lowest seed if ``seed`` is None."""
        runs = self.runs
        hit = runs[(runs["env"] == env) & (runs["controller"] == controller)]
        if hit.empty:
            raise Skip(f"no {env}/{controller} run in the store")
        hit = hit[hit["settings"] == self.group(env, hit)] if "settings" in hit else hit
        if seed is not None:
            hit = hit[hit["seed"] == seed]
            if hit.empty:
                raise Skip(f"no {env}/{controller} run with seed {seed}")
        return hit.sort_values(["seed", "start_time"]).iloc[0]

    def group(self, env: str, hit: pd.DataFrame) -> str:
        """The settings group of ``env`` the single-run figures show: of those ``hit`` has,
        the one with the most runs of ``env`` (the table's largest group; ``--where``
        narrows the runs to one), the latest on a tie; a note names the others."""
        runs = self.runs[self.runs["env"] == env]
        counts = runs.groupby("settings")["start_time"].agg(["size", "max"])
        counts = counts[counts.index.isin(set(hit["settings"]))]
        chosen = str(counts.sort_values(["size", "max"]).index[-1])
        others = [str(g) for g in counts.index if g != chosen]
        note = (
            f"single-run figures of {env} show the group [{chosen}] ({counts.loc[chosen, 'size']} "
            f"runs); not [{'], ['.join(others)}] (choose with --where)"
        )
        if others and note not in self.notes:
            self.notes.append(note)
        return chosen

    @cached_property
    def selected(self) -> pd.Series:
        sel = self.selection
        return self.find_run(sel.env, sel.controller, sel.seed)

    @cached_property
    def selected_steps(self) -> pd.DataFrame:
        return self.steps_of(self.selected)

    def steps_of(self, run: pd.Series) -> pd.DataFrame:
        steps = self.store.steps(run["run_id"])
        if steps is None or steps.empty:
            raise Skip(f"run {run['run_name']} has no {Artifact.STEPS}")
        return steps

    def run_title(self, run: pd.Series, what: str = "") -> str:
        """``<Env>, <controller>, seed <s>[: what]`` and, below, the run's name and id."""
        head = f"{env_text(run['env'])}, {controller_label(run['controller'])}, seed {run['seed']}"
        return f"{head}{': ' + what if what else ''}\nrun {run['run_name']} ({run['run_id'][:8]})"

    def window_text(self, steps: pd.DataFrame) -> str:
        """``episodes 1-500 of 2000`` for the steps a window figure shows."""
        total = _param(self.selected, "train.episodes")
        shown = steps[S.EPISODE].nunique()
        return f"episodes 1-{shown}" + (f" of {total}" if total is not None else "")


# ---------------------------------------------------------------------------- helpers
def _param(run: pd.Series, name: str, default: Any = None) -> Any:
    return param_value(run.get(f"params.{name}"), default)


def _mean_std(df: pd.DataFrame, column: str) -> pd.DataFrame:
    """Mean and std over runs per episode (population std, as the table)."""
    grouped = df.groupby(S.EPISODE)[column]
    return pd.DataFrame({"mean": grouped.mean(), "std": grouped.std(ddof=0).fillna(0.0)})


def _episode_axis(steps: pd.DataFrame) -> np.ndarray:
    """Continuous episode coordinate (from 1): episode + fraction of the episode done."""
    length = steps.groupby(S.EPISODE)[S.STEP].transform("max").to_numpy() + 1
    return steps[S.EPISODE].to_numpy() + 1 + steps[S.STEP].to_numpy() / length


def _legend(ax: Axes) -> None:
    """The legend right of the axes, off the data (constrained layout makes room)."""
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0, fontsize="small")


def _label(ax: Axes, xlabel: str, ylabel: str, title: str, legend: bool = True) -> None:
    """Axis labels and title of ``ax``, and its legend unless ``legend`` is false."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    if legend:
        _legend(ax)


def _trace(ax: Axes, x: np.ndarray, y: np.ndarray, **kw: Any) -> None:
    """Line plot; beyond :data:`MAX_LINE_POINTS`, a min-max envelope per bin (keeps peaks)."""
    if len(x) <= MAX_LINE_POINTS:
        ax.plot(x, y, rasterized=len(x) > 5000, **kw)
        return
    bins = np.linspace(x[0], x[-1], MAX_LINE_POINTS // 10 + 1)
    idx = np.clip(np.searchsorted(bins, x, side="right") - 1, 0, len(bins) - 2)
    frame = pd.DataFrame({"b": idx, "y": y}).groupby("b")["y"].agg(["min", "max"])
    centers = 0.5 * (bins[frame.index] + bins[frame.index + 1])
    ax.fill_between(
        centers,
        frame["min"],
        frame["max"],
        color=kw.get("color"),
        lw=0.3,
        label=kw.get("label"),
        rasterized=True,
    )


def _one_episode(ctx: FigureContext) -> tuple[pd.DataFrame, int]:
    steps = ctx.selected_steps
    episodes = steps[S.EPISODE].unique()
    want = ctx.selection.episode
    episode = int(episodes.max()) if want is None else want - 1
    if episode not in set(episodes.tolist()):
        raise Skip(f"run {ctx.selected['run_name']} has no episode {want}")
    return steps[steps[S.EPISODE] == episode], episode + 1


def _window(ctx: FigureContext) -> pd.DataFrame:
    steps = ctx.selected_steps
    return steps[steps[S.EPISODE] < ctx.selection.window]


class ThetaBounds(NamedTuple):
    theta1: tuple[float, float]
    ratio: tuple[float, float]
    source: str


def theta_bounds(ctx: FigureContext, run: pd.Series) -> ThetaBounds:
    """The NTK bounds of a run: its design record, else its params, else the paper's."""
    design = ctx.store.design(run["run_id"]) or {}
    tb = design.get("theta_bounds") or {}
    if tb.get("theta1") and tb.get("ratio"):
        return ThetaBounds(tuple(tb["theta1"]), tuple(tb["ratio"]), "design")
    t1 = _param(run, "weights.theta_bounds.theta1")
    ratio = _param(run, "weights.theta_bounds.ratio")
    if t1 and ratio:
        return ThetaBounds(tuple(t1), tuple(ratio), "config")
    return ThetaBounds(PAPER_THETA1, PAPER_RATIO, "paper")


# ----------------------------------------------------------------------------- figures
def learning(ctx: FigureContext, env: str) -> Figure:
    """``<Env>_learning``: return_ma100, mean ± std over seeds, one line per controller."""
    eps = ctx.episodes[ctx.episodes["env"] == env]
    if eps.empty:
        raise Skip(f"no {env} runs in the store")
    present = set(eps["controller"])
    ctx.notes += [
        f"{env_file_prefix(env)}_learning: no {ctrl} runs"
        for ctrl in CONTROLLER_ORDER[:4]
        if ctrl not in present
    ]
    fig, ax = plt.subplots(figsize=(8.4, 4.0))
    settings = sorted(eps["settings"].unique()) if "settings" in eps else [""]
    styles = dict(zip(settings, ["-", "--", ":", "-."] * len(settings), strict=False))
    longest = int(eps["episode"].max()) + 1
    for ctrl, setting in (
        (c, st) for c in ordered(eps["controller"], CONTROLLER_ORDER) for st in settings
    ):
        df = eps[(eps["controller"] == ctrl) & (eps.get("settings", "") == setting)]
        if df.empty:
            continue
        stats = _mean_std(df, Metric.RETURN_MA100)
        x = stats.index.to_numpy() + 1
        n = df["run_id"].nunique()
        color = ctx.colors[ctrl]
        label = f"{controller_label(ctrl)} ({n})" + (f" [{setting}]" if setting else "")
        short = len(x) <= max(20, longest // 50)  # a short run stays visible: markers
        ax.plot(
            x,
            stats["mean"],
            color=color,
            lw=1.5,
            ls=styles[setting],
            marker="o" if short else None,
            ms=4,
            label=label,
        )
        ax.fill_between(
            x,
            stats["mean"] - stats["std"],
            stats["mean"] + stats["std"],
            color=color,
            alpha=0.2,
            lw=0,
        )
    threshold = ctx.runs.loc[ctx.runs["env"] == env, "solve_threshold"].dropna()
    if not threshold.empty:
        ax.axhline(
            threshold.iloc[0], color="k", ls=":", lw=1.2, label=f"solved ({threshold.iloc[0]:g})"
        )
    title = f"{env_text(env)}: mean $\\pm$ std over seeds (number of seeds)"
    _label(ax, "episode", "return, 100-episode moving average", title)
    return fig


def loss(ctx: FigureContext) -> Figure:
    """``<Env>_loss``: episode-mean loss of the selected controller, mean ± std over seeds."""
    sel = ctx.selection
    eps = ctx.episodes
    df = eps[(eps["env"] == sel.env) & (eps["controller"] == sel.controller)]
    if df.empty:
        raise Skip(f"no {sel.env}/{sel.controller} run in the store")
    stats = _mean_std(df, Metric.LOSS_MEAN)
    x = stats.index.to_numpy() + 1
    color = ctx.colors[sel.controller]
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    ax.plot(x, stats["mean"], color=color, lw=1.2, label=controller_label(sel.controller))
    low = np.clip(stats["mean"] - stats["std"], stats["mean"][stats["mean"] > 0].min() / 10, None)
    ax.fill_between(x, low, stats["mean"] + stats["std"], color=color, alpha=0.2, lw=0)
    if (stats["mean"] > 0).all():
        ax.set_yscale("log")
    ax.set_xlabel("episode")
    ax.set_ylabel(r"loss $\mathcal{L}$ (episode mean)")
    n = df["run_id"].nunique()
    ax.set_title(
        f"{env_text(sel.env)}, {controller_label(sel.controller)}: "
        f"mean $\\pm$ std over {n} seed{'s' * (n != 1)}"
    )
    return fig


def q_window(ctx: FigureContext) -> Figure:
    """``<Env>_Q500``: Q1 and Q2 over the first ``window`` episodes of the selected run."""
    steps = _window(ctx)
    x = _episode_axis(steps)
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    _trace(ax, x, steps[S.Q1].to_numpy(), color="tab:blue", lw=0.6, label=r"$Q_1 = Q(s,a)$")
    _trace(
        ax,
        x,
        steps[S.Q2].to_numpy(),
        color="tab:orange",
        lw=0.6,
        alpha=0.8,
        label=r"$Q_2 = \max_{a'} Q(s',a')$",
    )
    _label(ax, "episode", r"$Q$ value", ctx.run_title(ctx.selected, ctx.window_text(steps)))
    return fig


def q_episode(ctx: FigureContext) -> Figure:
    """``<Env>_Q1``: Q1 and Q2 over one episode of the selected run."""
    steps, episode = _one_episode(ctx)
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    ax.plot(steps[S.STEP], steps[S.Q1], color="tab:blue", lw=1.2, label=r"$Q_1$")
    ax.plot(steps[S.STEP], steps[S.Q2], color="tab:orange", lw=1.2, ls="--", label=r"$Q_2$")
    ax.set_xlabel(r"step $k$ in the episode")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel(r"$Q$ value")
    ax.set_title(ctx.run_title(ctx.selected, f"episode {episode}"))
    _legend(ax)
    return fig


def u_window(ctx: FigureContext) -> Figure:
    """``<Env>_controlinput``: u(t) over the first ``window`` episodes of the selected run."""
    steps = _window(ctx)
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    _trace(
        ax,
        _episode_axis(steps),
        steps[S.U].to_numpy(),
        color=ctx.colors[ctx.selected["controller"]],
        lw=0.6,
    )
    _label(
        ax,
        "episode",
        r"control input $u$",
        ctx.run_title(ctx.selected, ctx.window_text(steps)),
        legend=False,
    )
    return fig


def u_episode(ctx: FigureContext) -> Figure:
    """``<Env>_controlinput1``: u(t) over one episode of the selected run."""
    steps, episode = _one_episode(ctx)
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    ax.plot(steps[S.STEP], steps[S.U], color=ctx.colors[ctx.selected["controller"]], lw=1.2)
    ax.set_xlabel(r"step $k$ in the episode")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel(r"control input $u$")
    ax.set_title(ctx.run_title(ctx.selected, f"episode {episode}"))
    return fig


def theta_training(ctx: FigureContext) -> Figure:
    """``<Env>_theta``: Θ1 at every step of the selected run with the design bounds."""
    run = ctx.selected
    steps = ctx.selected_steps
    bounds = theta_bounds(ctx, run)
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    _trace(
        ax,
        _episode_axis(steps),
        steps[S.THETA1].to_numpy(),
        color=ctx.colors[run["controller"]],
        lw=0.6,
        label=r"$\Theta_1$",
    )
    for i, value in enumerate(bounds.theta1):
        ax.axhline(
            value, **BOUND_STYLE, label=f"design bounds ({bounds.source})" if i == 0 else None
        )
    inside = np.mean((steps[S.THETA1] > bounds.theta1[0]) & (steps[S.THETA1] < bounds.theta1[1]))
    _label(
        ax,
        "episode",
        r"$\Theta_1 = \Theta((s,a),(s,a))$",
        ctx.run_title(run, f"{100 * inside:.0f}% of steps inside"),
    )
    return fig


def ntk_range(ctx: FigureContext) -> Figure:
    """``NTK_range``: Θ2 against Θ1 at every step, with the design's bound region."""
    sel = ctx.selection
    try:
        run = ctx.find_run(sel.env, sel.ntk_controller)
    except Skip:
        run = ctx.selected
    steps = ctx.steps_of(run)
    pts = steps[[S.THETA1, S.THETA2]].dropna()
    if pts.empty:
        raise Skip(f"run {run['run_name']} recorded no NTK values")
    if len(pts) > MAX_SCATTER_POINTS:
        pts = pts.sample(MAX_SCATTER_POINTS, random_state=0)
    bounds = theta_bounds(ctx, run)
    (lo, hi), (r_lo, r_hi) = bounds.theta1, bounds.ratio
    fig, ax = plt.subplots(figsize=(5.6, 4.6))
    ax.scatter(
        pts[S.THETA1],
        pts[S.THETA2],
        s=3,
        alpha=0.35,
        lw=0,
        color=ctx.colors[run["controller"]],
        rasterized=True,
        label="training steps",
    )
    region = np.array(
        [[lo, r_lo * lo], [hi, r_lo * hi], [hi, r_hi * hi], [lo, r_hi * lo], [lo, r_lo * lo]]
    )
    ax.plot(
        region[:, 0],
        region[:, 1],
        **{**BOUND_STYLE, "ls": "-"},
        label=rf"${lo:g} < \Theta_1 < {hi:g}$, ${r_lo:g}\Theta_1 < \Theta_2 < {r_hi:g}\Theta_1$",
    )
    _label(
        ax,
        r"$\Theta_1 = \Theta((s,a),(s,a))$",
        r"$\Theta_2 = \Theta((s,a),(s',a'))$",
        f"NTK evaluations: {ctx.run_title(run)}",
    )
    return fig


def fft(ctx: FigureContext) -> Figure:
    """``FFT``: amplitude spectra of r, Q1 and Q2 of the selected run.

    Logarithmic frequency axis without the constant (DC) term, whose value is written in
    each panel; linear amplitude, so that numerically zero content stays at zero.
    """
    run = ctx.selected
    spectra = ctx.store.fft(run["run_id"])
    if spectra is None or len(spectra) < 3:
        raise Skip(f"run {run['run_name']} has no {Artifact.FFT}")
    fig, axes = plt.subplots(1, 3, figsize=(11.0, 3.6), sharex=True)
    omega = 2 * np.pi * spectra[S.FREQ].to_numpy()
    for ax, col, sym in zip(axes, ("reward", "q1", "q2"), ("r", "Q_1", "Q_2"), strict=True):
        amp = spectra[col].to_numpy()
        w, peaks = log_binned_max(omega, amp, FFT_BINS)
        ax.semilogx(w, peaks, color=ctx.colors[run["controller"]], lw=0.8)
        dc = amp[omega == 0]
        # Round-off content (a constant reward) stays at zero instead of filling the axis.
        top = max(float(np.max(peaks, initial=0.0)), 1e-6 * float(np.abs(dc).max(initial=1.0)))
        ax.set_ylim(0, 1.05 * top)
        if float(np.max(peaks, initial=0.0)) <= ROUND_OFF * float(np.abs(dc).max(initial=1.0)):
            ax.set_ylim(0, 1)
            ax.text(
                0.5, 0.5, f"${sym}(t)$ is constant:\nno content at $\\omega > 0$",
                transform=ax.transAxes, ha="center", va="center",
            )  # fmt: skip
        ax.set_title(f"FFT of ${sym}(t)$")
        ax.set_xlabel(r"$\omega$ [rad/s], $t = k\alpha$")
        if dc.size:
            ax.text(
                0.97,
                0.95,
                f"DC: {dc[0]:.3g}",
                transform=ax.transAxes,
                ha="right",
                va="top",
                fontsize="small",
            )
    axes[0].set_ylabel("amplitude")
    fig.suptitle(ctx.run_title(run))
    return fig


def _weights(run: pd.Series) -> tuple[str, dict[str, tuple[list[float], list[float]]]]:
    controller = run["controller"] if run["controller"] in ("hinf", "hinf_f") else "hinf"
    out = {}
    for name in ("w_p", "w_u"):
        num = _param(run, f"weights.{controller}.{name}.num")
        den = _param(run, f"weights.{controller}.{name}.den")
        if num is not None and den is not None:
            out[name] = (list(num), list(den))
    return controller, out


def weight_bode(ctx: FigureContext) -> Figure:
    """``weight_bode``: Bode magnitude of the H∞ weights W_p and W_u (run params)."""
    run = ctx.selected
    controller, weights = _weights(run)
    if not weights:
        raise Skip(f"run {run['run_name']} has no weights.{controller}.w_p / w_u params")
    omega = np.logspace(-2, 6, 800)
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    symbols = {"w_p": ("W_p", "tab:blue"), "w_u": ("W_u", "tab:green")}
    for name, (num, den) in weights.items():
        mag = np.abs(np.polyval(num, 1j * omega) / np.polyval(den, 1j * omega))
        sym, color = symbols[name]
        ax.semilogx(
            omega,
            20 * np.log10(np.maximum(mag, 1e-300)),
            color=color,
            lw=1.5,
            label=f"${sym}(i\\omega)$",
        )
    title = f"{controller_label(controller)} design weights ({env_text(run['env'])})"
    _label(ax, r"$\omega$ [rad/s]", "magnitude [dB]", title)
    return fig


def closed_loop_sv(ctx: FigureContext) -> Figure:
    """``closed_loop_sv``: singular values of the designed closed loop, when stored."""
    sel = ctx.selection
    runs = ctx.runs
    candidates = pd.concat(
        [
            ctx.selected.to_frame().T,
            runs[(runs["env"] == sel.env) & (runs["controller"] == sel.controller)],
        ]
    ).drop_duplicates("run_id")
    for _, run in candidates.iterrows():
        sv = ctx.store.closed_loop_sv(run["run_id"])
        if sv is not None and not sv.empty:
            break
    else:
        raise Skip(f"no {sel.env}/{sel.controller} run has design/closed_loop_sv.csv")
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    color = ctx.colors[run["controller"]]
    for col, ls, sym in (
        ("sigma_max", "-", r"\bar\sigma"),
        ("sigma_min", "--", r"\underline{\sigma}"),
    ):
        if col in sv:
            mag = 20 * np.log10(np.maximum(sv[col].to_numpy(dtype=float), 1e-300))
            ax.semilogx(sv["omega"], mag, color=color, ls=ls, lw=1.5, label=f"${sym}$")
    _label(ax, r"$\omega$ [rad/s]", "singular value [dB]", f"Closed loop: {ctx.run_title(run)}")
    return fig


# ---------------------------------------------------------------------------- registry
class FigureSpec(NamedTuple):
    name: str
    """File name (the paper's label without ``fig:``)."""
    make: Callable[[FigureContext], Figure]


def figure_specs(ctx: FigureContext) -> Iterator[FigureSpec]:
    """Every figure for this store, in the paper's order."""
    for env in ordered([*ctx.envs, *ENV_ORDER], ENV_ORDER):
        yield FigureSpec(f"{env_file_prefix(env)}_learning", partial(learning, env=env))
    prefix = env_file_prefix(ctx.selection.env)
    yield FigureSpec(f"{prefix}_loss", loss)
    yield FigureSpec(f"{prefix}_Q500", q_window)
    yield FigureSpec(f"{prefix}_Q1", q_episode)
    yield FigureSpec(f"{prefix}_controlinput", u_window)
    yield FigureSpec(f"{prefix}_controlinput1", u_episode)
    yield FigureSpec(f"{prefix}_theta", theta_training)
    yield FigureSpec("NTK_range", ntk_range)
    yield FigureSpec("FFT", fft)
    yield FigureSpec("weight_bode", weight_bode)
    yield FigureSpec("closed_loop_sv", closed_loop_sv)


def save(fig: Figure, out: Path, name: str) -> list[Path]:
    """Write ``out/name.png`` and ``out/name.pdf`` and close the figure."""
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / f"{name}.png", out / f"{name}.pdf"]
    for path in paths:
        fig.savefig(path)
    plt.close(fig)
    return paths
