"""The one exception of controller synthesis."""

from __future__ import annotations


class DesignError(RuntimeError):
    """A controller could not be designed or did not pass its certificate.

    The message states the reason (infeasible box, failing synthesis, the part of the box
    left unstable); cdqn never falls back to a zero gain.
    """
