"""The divergence check of every run: a single run, a population member, a tuning trial's
member and an evaluation's member fail by the same test and say why in the same words.

A step diverges when its loss, Q-values ``Q1``/``Q2``, control ``u`` or integrator state
``x_e`` are non-finite, or ``|Q|`` exceeds ``train.q_limit``; an episode when the
controller's state ``x_c`` is non-finite at its end.  A NaN loss before the first finite
one means "no update yet" (Double DQN before ``learning_starts``).  A run that diverged is
closed FAILED with ``failure_reason`` ``"diverged: …"`` (:func:`failure_reason`), and such a
run is never continued: with the same seed it would diverge again (:func:`is_divergence`).
"""

from __future__ import annotations

import math

import numpy as np

from cdqn.agents.base import StepRecord

PREFIX = "diverged"
"""How the ``failure_reason`` of a run that diverged begins."""


class DivergenceError(RuntimeError):
    """Learning diverged: a non-finite or too large value in the loss, Q or controller."""

    def __init__(self, reason: str, episode: int, step: int) -> None:
        super().__init__(f"{reason} (episode {episode}, step {step})")
        self.reason, self.episode, self.step = reason, episode, step


def failure_reason(err: DivergenceError) -> str:
    """The ``failure_reason`` of a run closed FAILED by ``err``."""
    return f"{PREFIX}: {err}"


def is_divergence(status: str, reason: str | None) -> bool:
    """Whether a run with ``status`` and ``failure_reason`` ``reason`` diverged."""
    return status == "FAILED" and (reason or "").startswith(PREFIX)


def check_step(rec: StepRecord, q_limit: float, loss_seen: bool, episode: int, t: int) -> bool:
    """Raise the :class:`DivergenceError` of step ``t`` of ``episode`` if ``rec`` fails the
    test (module docstring; ``loss_seen``: a finite loss came before); else whether a finite
    loss has been seen now."""
    if not (
        abs(rec.q1) <= q_limit
        and abs(rec.q2) <= q_limit
        and math.isfinite(rec.u + rec.x_e)
        and (math.isfinite(rec.loss) or (not loss_seen and math.isnan(rec.loss)))
    ):
        diagnose(rec, q_limit, episode, t)
    return loss_seen or not math.isnan(rec.loss)


def check_replayed(rec: StepRecord, q_limit: float, episode: int, t: int) -> None:
    """The test of a replayed update (every one has a finite loss)."""
    if not (
        abs(rec.q1) <= q_limit
        and abs(rec.q2) <= q_limit
        and math.isfinite(rec.u + rec.x_e + rec.loss)
    ):
        diagnose(rec, q_limit, episode, t)


def replay_failed(update: int, episode: int, t: int, kind: str = "episodic") -> DivergenceError:
    """The error of update ``update`` of an episodic (or ``kind``) replay that failed the
    test (in a compiled kernel that reports only which update failed)."""
    return DivergenceError(
        f"update {update} of {kind} replay failed the divergence test", episode, t
    )


def check_controller(x_c: np.ndarray | None, episode: int, t: int) -> None:
    """Raise the :class:`DivergenceError` of a non-finite controller state at the end of
    ``episode`` (``None``: a static controller, nothing to test)."""
    if x_c is not None and not np.all(np.isfinite(x_c)):
        raise DivergenceError(f"non-finite controller state x_c = {x_c}", episode, t)


def diagnose(rec: StepRecord, q_limit: float, episode: int, t: int) -> None:
    """Raise the :class:`DivergenceError` that names what went wrong in ``rec``."""
    for name, value in (("Q1", rec.q1), ("Q2", rec.q2), ("u", rec.u), ("x_e", rec.x_e)):
        if not math.isfinite(value):
            raise DivergenceError(f"non-finite {name} = {value}", episode, t)
    if not math.isfinite(rec.loss):
        raise DivergenceError(f"non-finite loss = {rec.loss}", episode, t)
    q = max(abs(rec.q1), abs(rec.q2))
    raise DivergenceError(f"|Q| = {q:.3g} above train.q_limit={q_limit:g}", episode, t)
