"""The study's wall-time budget (``tune.time_limit``): whether a worker may start another
trial, and when a running one stops.

The whole study — its trials, then the evaluation on fresh seeds (and ``tune.baseline``) —
is to end within ``tune.time_limit`` seconds of its start.  Three rules keep it there.  The
rechecks of the best trials run in the time the trials leave: each starts only when it and
the evaluation still end within the limit (:meth:`EvaluationSize.time_for_recheck`).

* **A trial trains for at most T_cap = tune.trial_share · tune.time_limit** (a quarter by
  default); one still training then stops at its members' next episode ends and is pruned
  (:meth:`StudyClock.too_long`).  It stops sooner when it will clearly not finish in T_cap:
  once it has trained for :data:`PROJECT_AFTER` · T_cap, at any episode end where its
  projected time to play all its episodes (:meth:`Pace.total`) exceeds
  :data:`PROJECT_MARGIN` · T_cap.  A complete trial has
  therefore played its K members' episodes in at most T_cap, and its evaluation, which
  trains ⌈eval_seeds / processes⌉ members per process at the same pace, takes at most
  ⌈eval_seeds / processes⌉ / K · T_cap: the first trial of each worker and the
  evaluation of any complete trial fit the limit whatever the specification costs.
* **Before each trial** a worker estimates the time the study still needs,

      T_rest = T_trial + T_eval,

  and starts no trial when ``elapsed + T_rest > tune.time_limit``:

  - T_trial, one more trial: the median wall time (Optuna's start to completion) of the
    study's trials that trained, complete or pruned (infeasible trials train nothing and are
    left out), and T_cap while no trial has completed (the next one may be the first to, at
    the cap); none before the first such trial, so each worker's first trial starts
    whatever the limit (a limit below T_rest alone is *too small* for one trial, and the
    study says so);
  - T_eval, the evaluation: τ · ⌈eval_seeds / processes⌉ · episodes + T_start, twice that
    with a ``tune.baseline``, which trains the same seeds again; τ is the wall time per
    member-episode (each trial records the episodes its members played,
    ``member_episodes``) of the slowest complete trial that played a quarter of its
    member-episodes (:data:`PACE_SHARE`), since the best specification is the one evaluated
    and any complete one may become it; before such a trial completes, the most a
    complete trial can take, T_cap / (K · episodes) (without a cap, the pace of the trials
    that trained); T_start is :data:`START_ALLOWANCE`.
* **A trial still training when the evaluation would no longer end within the limit**
  (elapsed + T_eval > limit, with τ no faster than the trial's own projected pace,
  :class:`Pace`) stops at its members' next episode ends and is pruned
  (:meth:`StudyClock.overdue`), once the study has a complete trial to evaluate.

A population trains its members side by side in one process, so a trial of K members and
an evaluation process of K members cost alike per member-episode.

The limit is the user's: the clock starts when the command started (the start of the
``python -m cdqn.tune`` process, which its launcher's workers receive in
:data:`COMMAND_START_ENV`; importing, composing the configuration and starting the workers
took 18 s of a MountainCar-v0 study), and every rule aims at ``limit − margin``, with
margin = :data:`END_MARGIN` · limit kept for what the estimates cannot see: an evaluation
slower than the trials' pace (696 s against an estimated 688 s in that study), the members'
last episodes before a trial stops, and the summary.

The workers of a study share one clock: the worker that opens the study's MLflow parent run
(the first one, or the first after a restart) writes the start time into the study
(``clock_start``, seconds since the epoch); a worker that joins the open parent run reads
it.  The worker that stops records why in the study (``time_limit_stop``); worker 0 writes
it on the parent run (tag ``stopped``) and in the printed summary."""

from __future__ import annotations

import bisect
import logging
import math
import os
import statistics
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

log = logging.getLogger("cdqn.tune")
START = "clock_start"
"""Study user attribute: the study's start, seconds since the epoch."""
STOP = "time_limit_stop"
"""Study user attribute: why the study stopped starting trials (:class:`Stop` as a dict)."""
MEMBER_EPISODES = "member_episodes"
"""Trial user attribute: the episodes its members played in all."""
CAPPED = "too_long"
"""Trial user attribute: True when the trial was stopped at T_cap."""
PACE_SHARE = 0.25
"""A trial's seconds per member-episode tell its pace once it has played this share of its
members' episodes: before that, its start (box, synthesis, runs) and its first, longest
episodes weigh too much (a trial whose members all diverged within a few episodes "takes"
seconds per episode)."""


def shows_pace(played: int, full: int) -> bool:
    """Whether ``played`` of ``full`` member-episodes tell a trial's pace (:data:`PACE_SHARE`)."""
    return played >= PACE_SHARE * full


PROJECT_AFTER = 0.25
"""A trial's projected time (:meth:`Pace.total`) decides whether it stops before T_cap once
it has trained for this share of T_cap."""
PROJECT_MARGIN = 2.0
"""A trial stops before T_cap when its projected time exceeds this many T_caps.  Episodes
that shorten as an agent learns (Mountain car's, CliffWalking's) make early projections
high: of the complete trials of the stored studies, one reached 0.99 T_cap (it completed in
389 s of 450).  Replayed on 628 trials of both agents' studies of seven environments
(T_cap = 450 s), the rule with this margin stops 25, all of which were stopped later anyway
(at T_cap, by the pruner or by the limit), and saves 6 229 s of trial time
(docs/research/tuning.md)."""


class Pace:
    """A running trial's pace: the seconds it will have trained once its members have played
    all ``full`` of their episodes, and per member-episode, which is what its evaluation
    would take per member-episode, projected from what it has played so far.

    With t seconds trained and p member-episodes played, and r the seconds per
    member-episode of the later half of them (from p/2 to p),

        T_run = t + (full − p) · r,    τ_run = T_run / full,

    τ_run None until p shows the pace (:func:`shows_pace`).  Episodes change length as an
    agent learns (Taxi's and CliffWalking's shorten, CartPole's lengthen), so the later half
    tells the episodes still to come better than the mean so far."""

    def __init__(self, full: int) -> None:
        self.full = max(1, full)
        self._seconds: list[float] = []
        self._played: list[int] = []
        self._total: float | None = None

    def mark(self, seconds: float, played: int) -> None:
        """Record that ``played`` member-episodes had been played after ``seconds`` (at an
        episode's end: the projection changes only here, not at every step)."""
        self._seconds.append(seconds)
        self._played.append(played)
        if played <= 0:
            return
        i = bisect.bisect_left(self._played, played / 2)
        t0, p0 = self._seconds[i], self._played[i]
        recent = (seconds - t0) / (played - p0) if played > p0 else seconds / played
        self._total = seconds + max(0, self.full - played) * recent

    def total(self) -> float | None:
        """T_run (class docstring), or None before the first member-episode ends."""
        return self._total

    def projected(self) -> float | None:
        """τ_run (class docstring), or None before a quarter of the episodes show it."""
        if self._total is None or not shows_pace(self._played[-1], self.full):
            return None
        return self._total / self.full


END_MARGIN = 0.02
"""Share of ``tune.time_limit`` kept free at the end (module docstring)."""
COMMAND_START_ENV = "CDQN_COMMAND_START"
"""Environment variable: the command's start, seconds since the epoch (:func:`command_start`)."""


def process_start() -> float:
    """This process's start, seconds since the epoch (Linux ``/proc``; elsewhere, now)."""
    try:
        with open("/proc/self/stat") as f:
            ticks = int(f.read().rsplit(")", 1)[1].split()[19])  # field 22, starttime
        with open("/proc/stat") as f:
            boot = next(float(ln.split()[1]) for ln in f if ln.startswith("btime "))
        return boot + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return time.time()


def command_start() -> float:
    """When the user's command started: :data:`COMMAND_START_ENV`, which ``python -m
    cdqn.tune`` sets to its process's start and its launcher's workers inherit; now when it
    is unset (a study run from Python), unreadable or in the future."""
    now = time.time()
    try:
        start = float(os.environ[COMMAND_START_ENV])
    except (KeyError, ValueError):
        return now
    return start if start <= now else now


START_ALLOWANCE = 60.0
"""T_start, seconds: the evaluation's processes are new interpreters that import torch and
MLflow and compile the training kernels before the first episode (measured 20–60 s on two
cores shared with other work), then the summary's plots and comparison."""


@dataclass(frozen=True)
class Estimate:
    """The time the study still needs, seconds."""

    trial: float
    """One more trial: the median wall time of the trials that trained."""
    evaluation: float
    """The evaluation (and baseline) on fresh seeds."""
    per_member_episode: float
    """τ of the evaluation: wall time per member-episode (module docstring)."""

    @property
    def total(self) -> float:
        return self.trial + self.evaluation


@dataclass(frozen=True)
class Stop:
    """Why a worker started no further trial."""

    limit: float
    """``tune.time_limit``, seconds."""
    elapsed: float
    """Seconds since the study's start when the worker stopped."""
    needed: float
    """The estimate of one more trial and the evaluation, seconds."""
    too_small: bool
    """The limit is smaller than one trial and the evaluation: one trial ran anyway."""

    def text(self, trials: int) -> str:
        """One line for the summary and the parent run's ``stopped`` tag."""
        if self.too_small:
            return (f"tune.time_limit={self.limit:g} s is too small for even one trial and "
                    f"the evaluation (about {self.needed:.0f} s): ran {trials} trial(s) "
                    "anyway")  # fmt: skip
        return (f"stopped at its time limit ({self.limit:g} s) after {trials} trials: "
                f"{self.elapsed:.0f} s elapsed, one more trial and the evaluation need about "
                f"{self.needed:.0f} s")  # fmt: skip


@dataclass(frozen=True)
class EvaluationSize:
    """What the evaluation trains, for :func:`estimate`."""

    seeds: int
    """``tune.eval_seeds`` (0: no evaluation)."""
    processes: int
    """Processes the seeds are split over."""
    episodes: int
    """Episodes per member."""
    runs: int
    """Evaluations: 1, or 2 with a ``tune.baseline``."""
    members: int = 1
    """K, the members of a trial's population (``tune.seeds``)."""
    trial_cap: float | None = None
    """T_cap, the most seconds a trial trains (None: no cap)."""
    recheck_seeds: int = 0
    """Seeds of each recheck, split over ``processes`` as the evaluation's are."""

    def per_process(self, seeds: int | None = None) -> int:
        """Members each process trains for ``seeds`` seeds (default: the evaluation's)."""
        n = self.seeds if seeds is None else seeds
        return math.ceil(n / max(1, min(self.processes, n))) if n else 0

    def seconds(self, tau: float) -> float:
        """T_eval at τ seconds per member-episode."""
        if not self.seeds:
            return 0.0
        return (tau * self.per_process() * self.episodes + START_ALLOWANCE) * self.runs

    def recheck_seconds(self, tau: float) -> float:
        """One recheck at τ seconds per member-episode (0 without recheck seeds)."""
        if not self.recheck_seeds:
            return 0.0
        return tau * self.per_process(self.recheck_seeds) * self.episodes + START_ALLOWANCE

    def time_for_recheck(
        self, study: Any, elapsed: float, limit: float | None, finalists: Sequence[Any] = ()
    ) -> bool:
        """Whether one more recheck and then the evaluation end within ``limit`` (rechecks use
        time the trials left; they are never reserved).  Both train one of the ``finalists``,
        so they are timed at the slowest finalist's own pace; without one that shows a pace,
        at the pace of :func:`estimate`."""
        if limit is None:
            return True
        own = complete_paces(finalists, max(1, self.members) * self.episodes)
        if own:
            tau = max(own)
        elif (est := estimate(study.get_trials(deepcopy=False), self)) is not None:
            tau = est.per_member_episode
        else:
            return False
        return elapsed + self.recheck_seconds(tau) + self.seconds(tau) <= limit


def complete_paces(trials: Sequence[Any], full: int) -> list[float]:
    """Seconds per member-episode of the complete ``trials`` that show their pace
    (:func:`shows_pace` of ``full`` member-episodes)."""
    from optuna.trial import TrialState

    out = []
    for tr in trials:
        played = int(tr.user_attrs.get(MEMBER_EPISODES) or 0)
        start, end = tr.datetime_start, tr.datetime_complete
        if (
            tr.state == TrialState.COMPLETE
            and start
            and end
            and played
            and shows_pace(played, full)
        ):
            out.append((end - start).total_seconds() / played)
    return out


def estimate(trials: list[Any], size: EvaluationSize) -> Estimate | None:
    """The time still needed (module docstring) from the study's finished trials
    (``optuna.trial.FrozenTrial``); None before any trial trained."""
    from optuna.trial import TrialState

    seconds: list[float] = []
    paced: list[tuple[float, int]] = []  # trials that played an episode
    for tr in trials:
        played = tr.user_attrs.get(MEMBER_EPISODES)
        if tr.state not in (TrialState.COMPLETE, TrialState.PRUNED) or played is None:
            continue
        if tr.datetime_start is None or tr.datetime_complete is None:
            continue
        seconds.append((tr.datetime_complete - tr.datetime_start).total_seconds())
        if played:
            paced.append((seconds[-1], int(played)))
    if not seconds:
        return None
    full = max(1, size.members) * size.episodes
    complete = complete_paces(trials, full)
    trial = statistics.median(seconds)
    if complete:
        tau = max(complete)
    elif size.trial_cap is not None:
        tau = size.trial_cap / full
        trial = max(trial, size.trial_cap)
    else:
        tau = sum(s for s, _ in paced) / max(1, sum(e for _, e in paced))
    return Estimate(trial, size.seconds(tau), tau)


class StudyClock:
    """The clock of one study's invocation (module docstring); ``limit`` None: no limit."""

    def __init__(self, study: Any, limit: float | None, size: EvaluationSize, joined: bool):
        """``joined``: this worker found the parent run open (another worker of the same
        invocation opened it) and reads the clock; otherwise, or when the recorded start is
        older than the limit (a parent run left open by a killed process), it starts it."""
        self.study, self.limit, self.size = study, limit, size
        self.aim = None if limit is None else limit * (1.0 - END_MARGIN)
        """The time the rules aim at: limit − margin (module docstring)."""
        start = study.user_attrs.get(START)
        stale = start is None or (limit is not None and time.time() - float(start) > limit)
        if not joined or stale:
            study.set_user_attr(START, command_start())
            study.set_user_attr(STOP, None)
        self.start = float(study.user_attrs[START])
        self._asked: float = -math.inf
        self._tau: float | None = None

    def elapsed(self) -> float:
        return time.time() - self.start

    def too_long(self, trained: float, total: float | None = None) -> bool:
        """Whether a trial that has trained for ``trained`` seconds is to stop: past T_cap,
        or past :data:`PROJECT_AFTER` · T_cap with ``total``, its projected time to play all
        its episodes (:meth:`Pace.total`), past :data:`PROJECT_MARGIN` · T_cap (module
        docstring)."""
        cap = self.size.trial_cap
        if cap is None:
            return False
        late = trained >= PROJECT_AFTER * cap
        projected = total is not None and late and total > PROJECT_MARGIN * cap
        return trained > cap or projected

    def overdue(self, pace: float | None = None) -> bool:
        """Whether a running trial is to stop so that the evaluation still ends within the
        limit: the study holds a complete trial, and elapsed + T_eval > limit, T_eval at the
        slower of τ and ``pace``, the running trial's projected seconds per member-episode
        (:meth:`Pace.projected`: it may complete and be the one evaluated; None until a
        quarter of its member-episodes show it).  Asked at every step: the storage is
        read at most once a second."""
        if self.aim is None:
            return False
        now = time.monotonic()
        if now - self._asked >= 1.0:
            from optuna.trial import TrialState

            self._asked = now
            trials = self.study.get_trials(deepcopy=False)
            est = estimate(trials, self.size)
            complete = any(tr.state == TrialState.COMPLETE for tr in trials)
            self._tau = est.per_member_episode if complete and est is not None else None
        if self._tau is None:
            return False
        tau = max(self._tau, pace or 0.0)
        return self.elapsed() + self.size.seconds(tau) > self.aim

    def check(self) -> Stop | None:
        """A :class:`Stop` when one more trial and the evaluation would end past the limit
        (recorded in the study), else None."""
        if self.limit is None or self.aim is None:
            return None
        trials = self.study.get_trials(deepcopy=False)
        est = estimate(trials, self.size)
        elapsed = self.elapsed()
        if est is None or elapsed + est.total <= self.aim:
            return None
        stop = Stop(self.limit, elapsed, est.total, too_small=est.total > self.aim)
        self.study.set_user_attr(STOP, stop.__dict__)
        log.info("time limit %g s: %.0f s elapsed, one more trial (%.0f s) and the "
                 "evaluation (%.0f s, %.3g s per member-episode) would end past it; no further "
                 "trial", self.limit, elapsed, est.trial, est.evaluation,
                 est.per_member_episode)  # fmt: skip
        return stop


def recorded_stop(study: Any) -> Stop | None:
    """The :class:`Stop` a worker recorded in ``study`` in this invocation, if any."""
    found = study.user_attrs.get(STOP)
    return Stop(**found) if found else None
