"""SIGINT/SIGTERM during training: stop cleanly at the next episode boundary.

The first signal asks the training loop to stop once the current episode ends (an episode
lasts milliseconds to a second), so that the checkpoint written next is at an episode
boundary and a resumed run equals an uninterrupted one.  A second signal while training
stops at once (the last periodic checkpoint stays the one to resume from).  While the run
is being closed (signals, model, status written), two further signals are needed to abort.
"""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Callable
from types import FrameType, TracebackType
from typing import Any

log = logging.getLogger("cdqn")

SIGNALS = (signal.SIGINT, signal.SIGTERM)
Handler = Callable[[int, FrameType | None], Any] | int | signal.Handlers | None
"""What ``signal.signal`` installs and returns."""


class GracefulStop:
    """Context manager that turns SIGINT/SIGTERM into a stop request.

    Handlers are installed only in the main thread (elsewhere Python cannot receive
    signals); ``requested()`` is then always False.
    """

    def __init__(self) -> None:
        self.signum: int | None = None
        """The first signal received, if any."""
        self._count = 0
        self._abort_at = 2
        self._previous: dict[int, Handler] = {}

    def __enter__(self) -> GracefulStop:
        if threading.current_thread() is threading.main_thread():
            for sig in SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    def requested(self) -> bool:
        """True once a signal asked training to stop."""
        return self.signum is not None

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum is not None else ""

    def closing(self) -> None:
        """The run is being closed: from now on two more signals are needed to abort."""
        self._abort_at = self._count + 2

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self._count += 1
        if self.signum is None:
            self.signum = signum
            log.warning(
                "%s: stopping at the end of this episode (checkpoint, run marked KILLED); "
                "send it again to stop at once",
                signal.Signals(signum).name,
            )
        if self._count >= self._abort_at:
            raise KeyboardInterrupt
