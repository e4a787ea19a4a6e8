"""Per-step signals of a run, buffered in NumPy, and their spectra.

Columns (one row per environment step, :data:`cdqn.records.STEP_COLUMNS`): ``episode, step,
reward, q1, q2, u, x_e, theta1, theta2, loss`` with ``q1 = Q(s, a)`` and ``q2 = max Q(s', ·)``
before the update.
"""

from __future__ import annotations

from operator import attrgetter
from typing import NamedTuple

import numpy as np
import pandas as pd

from cdqn.agents.base import StepRecord
from cdqn.control.box import Box
from cdqn.records import (
    BOX_SERIES,
    SERIES,
    SERIES_PREFIX,
    SPECTRA,
    SPECTRUM_PREFIX,
    STEP_COLUMNS,
    column,
)
from cdqn.records import FFT_COLUMNS as FFT_COLUMNS
from cdqn.records import Signal as S

COLUMNS = STEP_COLUMNS
"""The step table's columns (:data:`cdqn.records.STEP_COLUMNS`)."""
_RECORD_COLUMNS = attrgetter(*COLUMNS[3:])
"""The signal columns after ``episode, step, reward`` from a :class:`StepRecord`, by name."""
ROUND_OFF = 1e-12
"""Relative amplitude below which a spectrum's content is floating-point round-off."""


class SignalBuffer:
    """Growable float64 table of per-step signals (one ``append`` per environment step)."""

    def __init__(self, capacity: int = 65536) -> None:
        self.data = np.empty((capacity, len(COLUMNS)))
        self.n = 0

    def append(self, episode: int, step: int, reward: float, rec: StepRecord) -> None:
        if self.n == len(self.data):
            self.data = np.concatenate([self.data, np.empty_like(self.data)])
        self.data[self.n] = (episode, step, reward, *_RECORD_COLUMNS(rec))
        self.n += 1

    def extend(self, rows: np.ndarray) -> None:
        """Append a block of rows (columns as :data:`COLUMNS`)."""
        need = self.n + len(rows)
        if need > len(self.data):
            grown = np.empty((max(need, 2 * len(self.data)), len(COLUMNS)))
            grown[: self.n] = self.data[: self.n]
            self.data = grown
        self.data[self.n : need] = rows
        self.n = need

    def rows(self, start: int, stop: int | None = None) -> np.ndarray:
        return self.data[start : self.n if stop is None else stop]

    def column(self, name: str, start: int = 0) -> np.ndarray:
        return self.data[start : self.n, COLUMNS.index(name)]

    def to_frame(self) -> pd.DataFrame:
        df = pd.DataFrame(self.data[: self.n], columns=list(COLUMNS))
        return df.astype({S.EPISODE: np.int64, S.STEP: np.int64})

    def state(self) -> np.ndarray:
        return self.data[: self.n].copy()

    def load(self, rows: np.ndarray) -> None:
        self.data = np.empty((max(len(rows) * 2, 65536), len(COLUMNS)))
        self.data[: len(rows)] = rows
        self.n = len(rows)


def amplitude_spectra(steps: pd.DataFrame, dt: float) -> pd.DataFrame:
    """One-sided amplitude spectra of reward, q1 and q2 over the whole run (paper Fig. FFT).

    ``A(f_k) = c_k |X_k| / N`` with ``c_0 = 1`` and ``c_k = 2`` otherwise, of the series
    sampled every training step; ``freq`` is in cycles per unit of learning time, where one
    step is ``Δt = α`` (so the spectra share the frequency axis of the controller design).
    Amplitudes below :data:`ROUND_OFF` times the series' largest magnitude are round-off
    and set to 0: a constant series (CartPole's reward) has its DC term alone.
    """
    n = len(steps)
    if n == 0:
        return pd.DataFrame({c: np.zeros(0) for c in FFT_COLUMNS})
    out = {S.FREQ: np.fft.rfftfreq(n, d=dt)}
    for col in SPECTRA:
        x = np.nan_to_num(steps[col].to_numpy(dtype=float))
        amp = np.abs(np.fft.rfft(x)) / n
        amp[1:] *= 2.0
        amp[amp < ROUND_OFF * np.abs(x).max(initial=0.0)] = 0.0
        out[col] = amp
    return pd.DataFrame(out)


SERIES_POINTS = 40
"""Points of each downsampled per-step series logged as an MLflow metric (one per 50
episodes of a 2000-episode run): with :data:`SPECTRUM_POINTS`, few enough points that
writing them stays under 50 ms per run (``python -m cdqn.bench``)."""
SPECTRUM_POINTS = 30
"""Log-spaced frequency bins of each amplitude spectrum logged as an MLflow metric."""
SPECTRUM_STEP_SCALE = 1000.0
"""A spectrum point's metric step is ``round(1000 ω)``: ω in rad per unit of learning time
(``t = kα``, as the FFT figure's axis) times 1000, so that MLflow's integer steps keep it."""


class SeriesPoint(NamedTuple):
    """One point of a metric series: ``key`` at integer ``step``."""

    key: str
    value: float
    step: int


def bucket_means(values: np.ndarray, points: int) -> tuple[np.ndarray, np.ndarray]:
    """Means of each column of ``values`` (rows × columns) over ``points`` equal spans of
    consecutive rows, NaN ignored (NaN where a span has no finite value), and the centre
    row of each span."""
    n = len(values)
    edges = np.unique(np.linspace(0, n, min(points, n) + 1).astype(np.int64))
    finite = np.isfinite(values)
    sums = np.add.reduceat(np.where(finite, values, 0.0), edges[:-1], axis=0)
    counts = np.add.reduceat(finite.astype(np.int64), edges[:-1], axis=0)
    means = np.full(sums.shape, np.nan)
    np.divide(sums, counts, out=means, where=counts > 0)
    return (edges[:-1] + edges[1:]) // 2, means


def log_binned_max(freq: np.ndarray, amp: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Max amplitude per log-spaced bin of the positive frequencies ``freq`` (ascending), at
    the bin's mean frequency (keeps the peaks of a long spectrum); unchanged when short."""
    keep = freq > 0
    freq, amp = freq[keep], amp[keep]
    if len(freq) <= bins:
        return freq, amp
    edges = np.geomspace(freq[0], freq[-1] * (1 + 1e-12), bins + 1)
    starts = np.unique(np.searchsorted(freq, edges[:-1]))
    starts = starts[starts < len(freq)]
    counts = np.diff(np.append(starts, len(freq)))
    return np.add.reduceat(freq, starts) / counts, np.maximum.reduceat(amp, starts)


def signal_series(
    data: np.ndarray, spectra: pd.DataFrame | None, box: Box | None
) -> list[SeriesPoint]:
    """The per-step signals of a run (rows as :data:`COLUMNS`) as metric series small
    enough for one ``log_batch`` (at most 1000 points; 298 here).

    ``signals/u``, ``q1``, ``q2`` and ``theta1``: means over :data:`SERIES_POINTS` equal
    spans of the run's steps, at the centre step of each span (step = environment step of
    the run, from 0); ``signals/theta2_over_theta1``: the span's mean Θ2 over its mean Θ1.
    With a design's NTK box, ``signals/theta1_box_lower`` / ``_upper`` and
    ``signals/ratio_box_lower`` / ``_upper`` at the first and last of those steps: the box
    the design was certified on (paper Sec. 3, Fig. NTK_range).  From ``spectra``
    (:func:`amplitude_spectra`): ``spectrum/reward``, ``spectrum/q1``, ``spectrum/q2``, the
    largest amplitude in each of :data:`SPECTRUM_POINTS` log-spaced bins of ω = 2πf, at
    step ``round(1000 ω)``.  Spans without a finite value (Θ of Double DQN) are left out.
    """
    if len(data) == 0:
        return []
    idx = [column(c) for c in (S.U, S.Q1, S.Q2, S.THETA1, S.THETA2)]
    steps, means = bucket_means(data[:, idx], SERIES_POINTS)
    means[:, 4] = np.where(
        means[:, 3] > 0, means[:, 4] / np.where(means[:, 3] > 0, means[:, 3], 1), np.nan
    )
    out: list[SeriesPoint] = []
    for j, name in enumerate(SERIES):
        key = SERIES_PREFIX + name
        out += [SeriesPoint(key, float(v), int(s))
                for s, v in zip(steps, means[:, j], strict=True) if np.isfinite(v)]  # fmt: skip
    ends = sorted({int(steps[0]), int(steps[-1])})
    if box is not None:
        bounds = (*box[0], *box[1])  # BOX_SERIES: Θ1 lower, upper, Θ2/Θ1 lower, upper
        out += [SeriesPoint(SERIES_PREFIX + name, float(v), step)
                for name, v in zip(BOX_SERIES, bounds, strict=True) for step in ends]  # fmt: skip
    if spectra is not None and len(spectra) > 1:
        omega = 2 * np.pi * spectra[S.FREQ].to_numpy()
        for name in SPECTRA:
            w, peaks = log_binned_max(omega, spectra[name].to_numpy(), SPECTRUM_POINTS)
            steps = np.round(SPECTRUM_STEP_SCALE * w).astype(np.int64)
            out += [SeriesPoint(SPECTRUM_PREFIX + name, float(a), int(s))
                    for s, a in zip(steps, peaks, strict=True) if np.isfinite(a)]  # fmt: skip
    return out
