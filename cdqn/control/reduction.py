"""Balanced truncation of a synthesised controller (MATLAB's ``balreal`` + ``modred``).

SLICOT AB09MD balances the stable part of ``K`` (square-root Balance & Truncate) and keeps
its unstable part; states of the stable part whose Hankel singular value ``σ_i`` is below
the threshold are removed.  The feedthrough ``D`` is kept (truncation, not matched DC
gain).  The caller checks that the reduced controller still stabilises the box and raises
the order until it does.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import slycot

from cdqn.control.certificate import ControllerMatrices


@dataclass
class Reduction:
    """Hankel singular values of the controller's stable part and its unstable order."""

    hsv: np.ndarray
    """Hankel singular values of the stable part, decreasing."""
    n_unstable: int
    """Controller states with Re λ ≥ 0 (always kept)."""

    def order_for(self, threshold: float) -> int:
        """Order kept by ``threshold``: unstable states plus ``σ_i ≥ threshold``."""
        return self.n_unstable + int(np.sum(self.hsv >= threshold))


def hankel(K: ControllerMatrices) -> Reduction:
    """Hankel singular values of ``K`` (stable part) and its number of unstable states."""
    n = K.nstates
    if n == 0:
        return Reduction(np.zeros(0), 0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", slycot.exceptions.SlycotResultWarning)
        out = slycot.ab09md(
            "C", "B", "S", n, K.B.shape[1], K.C.shape[0], K.A, K.B, K.C, alpha=0.0, nr=n
        )
    ns, hsv = out[4], out[5]
    return Reduction(np.asarray(hsv[:ns], float), n - ns)


def truncate(K: ControllerMatrices, order: int) -> ControllerMatrices:
    """Balanced truncation of ``K`` to ``order`` states (``order ≥`` its unstable states)."""
    n = K.nstates
    if order >= n:
        return K
    with warnings.catch_warnings():  # SLICOT lowers nr to the minimal order itself
        warnings.simplefilter("ignore", slycot.exceptions.SlycotResultWarning)
        nr, Ar, Br, Cr, _, _ = slycot.ab09md(
            "C", "B", "S", n, K.B.shape[1], K.C.shape[0], K.A, K.B, K.C, alpha=0.0, nr=order
        )
    return ControllerMatrices(Ar[:nr, :nr], Br[:nr], Cr[:, :nr], K.D.copy())
