"""Per-step signals of a run, buffered in NumPy, and their spectra.

Columns (one row per environment step): ``episode, step, reward, q1, q2, u, x_e, theta1,
theta2, loss`` with ``q1 = Q(s, a)`` and ``q2 = max Q(s', ·)`` before the update.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from cdqn.agents.base import StepRecord

COLUMNS = ("episode", "step", "reward", "q1", "q2", "u", "x_e", "theta1", "theta2", "loss")
FFT_COLUMNS = ("freq", "reward", "q1", "q2")


class SignalBuffer:
    """Growable float64 table of per-step signals (one ``append`` per environment step)."""

    def __init__(self, capacity: int = 65536) -> None:
        self.data = np.empty((capacity, len(COLUMNS)))
        self.n = 0

    def append(self, episode: int, step: int, reward: float, rec: StepRecord) -> None:
        if self.n == len(self.data):
            self.data = np.concatenate([self.data, np.empty_like(self.data)])
        self.data[self.n] = (episode, step, reward, *rec[1:8], rec[0])
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
        return df.astype({"episode": np.int64, "step": np.int64})

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
    """
    n = len(steps)
    if n == 0:
        return pd.DataFrame({c: np.zeros(0) for c in FFT_COLUMNS})
    out = {"freq": np.fft.rfftfreq(n, d=dt)}
    for col in FFT_COLUMNS[1:]:
        x = np.nan_to_num(steps[col].to_numpy(dtype=float))
        amp = np.abs(np.fft.rfft(x)) / n
        amp[1:] *= 2.0
        out[col] = amp
    return pd.DataFrame(out)
