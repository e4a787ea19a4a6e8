"""Scalar (SISO) design weights as transfer functions ``num(s)/den(s)``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import control
import numpy as np

from cdqn.control.errors import DesignError


@dataclass(frozen=True)
class SisoWeight:
    """``W(s) = num(s) / den(s)``, coefficients highest power of s first."""

    num: tuple[float, ...]
    den: tuple[float, ...]
    name: str = "W"

    @classmethod
    def from_config(cls, cfg: Any, name: str) -> SisoWeight:
        """From a :class:`cdqn.config.TransferFunctionConfig` (or any ``num``/``den``)."""
        return cls.make(cfg.num, cfg.den, name)

    @classmethod
    def make(cls, num: Any, den: Any, name: str) -> SisoWeight:
        n = np.trim_zeros(np.atleast_1d(np.asarray(num, dtype=float)), "f")
        d = np.trim_zeros(np.atleast_1d(np.asarray(den, dtype=float)), "f")
        if d.size == 0 or n.size > d.size:
            raise DesignError(
                f"weight {name}: num {list(n)} / den {list(d)} is not a proper transfer function"
            )
        if np.any(np.roots(d).real >= 0) if d.size > 1 else False:
            raise DesignError(f"weight {name}: den {list(d)} has poles with Re >= 0")
        return cls(tuple(float(c) for c in n) or (0.0,), tuple(float(c) for c in d), name)

    @classmethod
    def constant(cls, value: float, name: str) -> SisoWeight:
        return cls((float(value),), (1.0,), name)

    def tf(self) -> control.TransferFunction:
        return control.tf(list(self.num), list(self.den))

    def ss(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """A minimal state-space realisation ``(A, B, C, D)`` (shapes n×n, n×1, 1×n, 1×1)."""
        sys = control.ss(self.tf())
        return (
            np.asarray(sys.A, float).reshape(sys.nstates, sys.nstates),
            np.asarray(sys.B, float).reshape(sys.nstates, 1),
            np.asarray(sys.C, float).reshape(1, sys.nstates),
            np.asarray(sys.D, float).reshape(1, 1),
        )

    def __call__(self, s: np.ndarray) -> np.ndarray:
        """``W(s)`` at complex points ``s``."""
        return np.polyval(self.num, s) / np.polyval(self.den, s)

    def mag(self, omega: np.ndarray) -> np.ndarray:
        """``|W(jω)|``."""
        return np.abs(self(1j * np.asarray(omega, dtype=float)))

    def scaled(self, k: float) -> SisoWeight:
        return SisoWeight(tuple(k * c for c in self.num), self.den, self.name)

    def to_dict(self) -> dict[str, Any]:
        return {"num": list(self.num), "den": list(self.den)}
