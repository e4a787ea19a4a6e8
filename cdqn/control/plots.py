"""Design plots: weights, cover against sampled relative errors, closed-loop singular
values, the Θ1–Θ2 samples with their box (matplotlib, Agg backend)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from cdqn.control.box import NTKBox
from cdqn.control.weights import SisoWeight


def _finish(
    fig: Figure,
    ax: Axes,
    path: Path,
    xlabel: str,
    ylabel: str,
    title: str,
    log: bool = False,
) -> None:
    """Label, grid and legend the axes, then write the figure to ``path`` and close it."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, which="both" if log else "major", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_weights(weights: list[SisoWeight], omega: np.ndarray, path: Path) -> None:
    """Bode magnitude of each design weight."""
    fig, ax = plt.subplots(figsize=(6, 4))
    for w in weights:
        ax.loglog(omega, np.maximum(w.mag(omega), 1e-300), label=w.name)
    _finish(fig, ax, path, "ω [rad/s of learning time]", "|W(jω)|", "Design weights", log=True)


def plot_cover(
    omega: np.ndarray, errors: np.ndarray, cover: SisoWeight, band: tuple[float, float], path: Path
) -> None:
    """Sampled relative errors ``σ̄(E_i(jω))`` and the fitted cover ``|w(jω)|``."""
    fig, ax = plt.subplots(figsize=(6, 4))
    for row in errors[:: max(1, len(errors) // 100)]:
        ax.loglog(omega, row, color="0.6", lw=0.5)
    ax.loglog(omega, errors.max(axis=0), color="k", lw=1.2, label="max over samples")
    ax.loglog(omega, cover.mag(omega), color="C3", lw=2, label="cover |w|")
    ax.axvspan(band[0], band[1], color="C0", alpha=0.05, label="fitted band")
    _finish(
        fig,
        ax,
        path,
        "ω [rad/s of learning time]",
        "σ̄((P_i − P_0) P_0⁻¹)",
        "Output-multiplicative cover of the sampled plants",
        log=True,
    )


def plot_sigma(omega: np.ndarray, sv: np.ndarray, gamma: float, title: str, path: Path) -> None:
    """Largest and smallest closed-loop singular value with the achieved γ."""
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.loglog(omega, sv[:, 0], label="σ_max")
    ax.loglog(omega, np.maximum(sv[:, -1], 1e-300), label="σ_min")
    if np.isfinite(gamma):
        ax.axhline(gamma, color="k", ls="--", lw=1, label=f"γ = {gamma:.4g}")
    _finish(fig, ax, path, "ω [rad/s of learning time]", "σ(T(jω))", title, log=True)


def plot_box(
    box: NTKBox,
    samples: np.ndarray,
    path: Path,
    measured: np.ndarray | None = None,
    unstable: np.ndarray | None = None,
) -> None:
    """Θ1–Θ2 scatter of the plant samples (and measured NTK values) with the box."""
    fig, ax = plt.subplots(figsize=(5, 5))
    if measured is not None and len(measured):
        ax.scatter(
            measured[:, 0], measured[:, 1], s=3, color="0.6", alpha=0.5, label="measured NTK"
        )
    ax.scatter(samples[:, 0], samples[:, 1], s=6, color="C0", label="plant samples")
    c = box.corners()[[0, 2, 3, 1, 0]]
    t1 = np.linspace(box.theta1[0], box.theta1[1], 50)
    ax.plot(t1, box.ratio[0] * t1, color="C3")
    ax.plot(t1, box.ratio[1] * t1, color="C3")
    ax.plot(c[[0, 3], 0], c[[0, 3], 1], color="C3")
    ax.plot(c[[1, 2], 0], c[[1, 2], 1], color="C3", label="box")
    ax.scatter([box.nominal[0]], [box.nominal[1]], marker="*", s=120, color="C2", label="nominal")
    if unstable is not None and len(unstable):
        ax.scatter(unstable[:, 0], unstable[:, 1], marker="x", color="k", label="unstable")
    _finish(fig, ax, path, "Θ1", "Θ2", "NTK box")
