"""``tune.time_limit``: a study starts no trial that, with its evaluation, would end past the
limit (:mod:`cdqn.tuning.clock`); real Optuna storages and a real MLflow store."""

from __future__ import annotations

import time
from datetime import datetime, timedelta
from pathlib import Path

import optuna
import pytest
from mlflow.tracking import MlflowClient
from optuna.distributions import FloatDistribution
from optuna.trial import FrozenTrial, TrialState

from cdqn.cli import check_overrides
from cdqn.records import Tag
from cdqn.tuning.clock import (
    COMMAND_START_ENV,
    END_MARGIN,
    START,
    START_ALLOWANCE,
    EvaluationSize,
    Pace,
    StudyClock,
    command_start,
    estimate,
    process_start,
    recorded_stop,
)
from cdqn.tuning.evaluation import eval_processes
from cdqn.tuning.report import summary_text
from tests.helpers import run_cli
from tests.test_tune import _overrides, _runs, _study

T0 = datetime(2026, 1, 1)


def _trial(number: int, seconds: float, played: int | None, state: TrialState) -> FrozenTrial:
    attrs = {} if played is None else {"member_episodes": played}
    return FrozenTrial(
        number=number, state=state, value=1.0 if state == TrialState.COMPLETE else None,
        datetime_start=T0, datetime_complete=T0 + timedelta(seconds=seconds),
        params={"x": 0.5}, distributions={"x": FloatDistribution(0, 1)}, user_attrs=attrs,
        system_attrs={}, intermediate_values={}, trial_id=number,
    )  # fmt: skip


def test_the_estimate_is_one_median_trial_and_the_evaluation_at_the_slowest_complete_pace(
) -> None:  # fmt: skip
    trials = [
        _trial(0, 30.0, 600, TrialState.COMPLETE),  # τ 0.05 s
        _trial(1, 10.0, 150, TrialState.PRUNED),  # τ 0.067 s: pruned, never evaluated
        _trial(2, 60.0, 1000, TrialState.COMPLETE),  # τ 0.06 s: the slowest complete one
        _trial(3, 1.0, None, TrialState.PRUNED),  # infeasible: trained nothing
        _trial(4, 99.0, 600, TrialState.FAIL),
    ]
    size = EvaluationSize(seeds=10, processes=2, episodes=200, runs=1)
    est = estimate(trials, size)
    assert est is not None
    assert est.trial == 30.0  # median of 30, 10, 60
    tau = 0.06  # any complete trial may be the best one, the one evaluated
    assert est.per_member_episode == pytest.approx(tau)
    start = START_ALLOWANCE  # the evaluation's processes start
    assert est.evaluation == pytest.approx(tau * 5 * 200 + start)  # 5 seeds per process
    assert est.total == pytest.approx(30.0 + tau * 1000 + start)
    with_baseline = estimate(trials, EvaluationSize(10, 2, 200, runs=2))
    assert with_baseline is not None
    assert with_baseline.evaluation == pytest.approx(2 * (tau * 1000 + start))
    assert estimate(trials, EvaluationSize(0, 1, 200, 1)).evaluation == 0.0  # no evaluation
    # rechecks are not reserved: they run in the time the trials leave
    rechecked = EvaluationSize(10, 2, 200, 1, recheck_seeds=4)
    assert estimate(trials, rechecked).evaluation == pytest.approx(tau * 1000 + start)
    assert rechecked.recheck_seconds(tau) == pytest.approx(tau * 2 * 200 + start)  # 2 per core
    assert estimate(trials[3:], size) is None  # before any trial trained: no estimate


def test_a_recheck_starts_only_when_it_and_the_evaluation_fit_the_limit() -> None:
    study = optuna.create_study()
    size = EvaluationSize(10, 2, 200, 1, recheck_seeds=4)
    assert not size.time_for_recheck(study, 0.0, 1000.0)  # no pace to judge by yet
    study.add_trial(_trial(0, 30.0, 600, TrialState.COMPLETE))  # τ 0.05 s
    need = size.recheck_seconds(0.05) + size.seconds(0.05)  # 20 + 50 s and two starts
    assert need == pytest.approx(70.0 + 2 * START_ALLOWANCE)
    assert size.time_for_recheck(study, 1000.0 - need - 1.0, 1000.0)
    assert not size.time_for_recheck(study, 1000.0 - need + 1.0, 1000.0)
    assert size.time_for_recheck(study, 1e9, None)  # no limit


def test_a_recheck_is_timed_at_its_finalists_pace_not_the_slowest_trials() -> None:
    """The recheck and the evaluation train one of the finalists: a slower trial that is not
    one of them does not stop the rechecks."""
    study = optuna.create_study()
    size = EvaluationSize(10, 2, 200, 1, recheck_seeds=4)
    finalist = _trial(0, 30.0, 600, TrialState.COMPLETE)  # τ 0.05 s
    study.add_trial(finalist)
    study.add_trial(_trial(1, 300.0, 600, TrialState.COMPLETE))  # τ 0.5 s, not a finalist
    elapsed = 1000.0 - (size.recheck_seconds(0.05) + size.seconds(0.05)) - 1.0
    assert not size.time_for_recheck(study, elapsed, 1000.0)  # at the slowest complete pace
    assert size.time_for_recheck(study, elapsed, 1000.0, [finalist])
    assert not size.time_for_recheck(study, elapsed + 2.0, 1000.0, [finalist])


def test_before_a_trial_completes_the_evaluation_is_the_most_a_complete_one_can_cost() -> None:
    pruned = [_trial(0, 40.0, 100, TrialState.PRUNED), _trial(1, 10.0, 300, TrialState.PRUNED)]
    capped = EvaluationSize(seeds=10, processes=2, episodes=200, runs=1, members=3,
                            trial_cap=450.0)  # fmt: skip
    est = estimate(pruned, capped)
    assert est is not None
    # a complete trial played 3 × 200 member-episodes in at most 450 s
    assert est.per_member_episode == pytest.approx(450.0 / 600)
    assert est.evaluation == pytest.approx(450.0 * 5 / 3 + START_ALLOWANCE)
    assert est.trial == 450.0  # the next trial may be the first to complete, at the cap
    uncapped = estimate(pruned, EvaluationSize(10, 2, 200, 1, members=3))
    assert uncapped is not None and uncapped.per_member_episode == pytest.approx(50.0 / 400)
    assert uncapped.trial == 25.0


def test_a_complete_trial_that_diverged_early_does_not_set_the_pace() -> None:
    """A trial whose members all diverged within a few episodes is complete (J keeps their
    lowest return) but its seconds per member-episode are mostly its start: its pace counts
    only once a quarter of its member-episodes are played; until another trial shows one,
    the evaluation is bounded as before any trial completed."""
    diverged = _trial(0, 6.0, 16, TrialState.COMPLETE)  # 3 members x 1500 episodes asked
    capped = EvaluationSize(seeds=10, processes=2, episodes=1500, runs=1, members=3,
                            trial_cap=450.0)  # fmt: skip
    est = estimate([diverged], capped)
    assert est is not None
    assert est.per_member_episode == pytest.approx(450.0 / 4500)  # not 6 / 16
    assert est.evaluation < 1800
    full = _trial(1, 90.0, 4500, TrialState.COMPLETE)
    assert estimate([diverged, full], capped).per_member_episode == pytest.approx(0.02)
    quarter = _trial(2, 45.0, 1125, TrialState.COMPLETE)  # a quarter: its pace counts
    assert estimate([full, quarter], capped).per_member_episode == pytest.approx(0.04)


def test_a_trial_is_too_long_past_its_share_of_the_limit() -> None:
    study = optuna.create_study()
    clock = StudyClock(study, 1800.0, EvaluationSize(10, 2, 200, 1, 3, 450.0), joined=False)
    assert not clock.too_long(449.0) and clock.too_long(451.0)
    uncapped = StudyClock(study, 1800.0, EvaluationSize(10, 2, 200, 1, 3), joined=False)
    assert not uncapped.too_long(1e9)


def test_a_trial_projected_past_its_cap_stops_after_a_quarter_of_it() -> None:
    """T_cap 450 s: from 112.5 s of training a trial stops when its projected time to play
    all its episodes (Pace.total) exceeds two caps, 900 s; before, its projection does not
    stop it."""
    study = optuna.create_study()
    clock = StudyClock(study, 1800.0, EvaluationSize(10, 2, 200, 1, 3, 450.0), joined=False)
    assert clock.too_long(112.5, 901.0)
    assert not clock.too_long(112.0, 3000.0)  # too early to trust its pace
    assert not clock.too_long(300.0, 899.0) and not clock.too_long(300.0, None)
    # CliffWalking-like: 50 member-episodes in 112.5 s, 1.5 s each lately, 4 500 to play
    pace = Pace(4500)
    for p in range(1, 51):
        pace.mark(112.5 - 1.5 * (50 - p), p)
    assert pace.total() == pytest.approx(112.5 + 4450 * 1.5)
    assert clock.too_long(112.5, pace.total())
    uncapped = StudyClock(study, 1800.0, EvaluationSize(10, 2, 200, 1, 3), joined=False)
    assert not uncapped.too_long(1e9, 1e9)


def test_workers_share_the_clock_and_a_new_invocation_restarts_it(tmp_path: Path) -> None:
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    size = EvaluationSize(2, 1, 10, 1)
    first = optuna.create_study(study_name="clock", storage=storage)
    clock = StudyClock(first, 100.0, size, joined=False)
    other = optuna.load_study(study_name="clock", storage=storage)  # a second worker
    assert StudyClock(other, 100.0, size, joined=True).start == clock.start
    other.set_user_attr(START, time.time() - 500.0)  # a parent left open by a killed process
    assert StudyClock(other, 100.0, size, joined=True).start > time.time() - 5.0
    other.set_user_attr(START, time.time() - 50.0)
    assert StudyClock(other, None, size, joined=True).start < time.time() - 40.0
    assert StudyClock(other, None, size, joined=False).start > time.time() - 5.0  # restarted


def test_the_clock_starts_at_the_command_start_its_workers_inherit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``python -m cdqn.tune`` sets :data:`COMMAND_START_ENV` to its process's start; a worker
    that opens the study starts the clock there, and keeps a margin of the limit free."""
    before = time.time()
    assert before - 3600 * 24 * 365 < process_start() <= before  # this process: started before
    monkeypatch.delenv(COMMAND_START_ENV, raising=False)
    assert before <= command_start() <= time.time()  # no command: now
    monkeypatch.setenv(COMMAND_START_ENV, repr(before - 30.0))
    assert command_start() == before - 30.0
    study = optuna.create_study()
    clock = StudyClock(study, 1000.0, EvaluationSize(2, 1, 10, 1), joined=False)
    assert clock.start == before - 30.0 and 30.0 <= clock.elapsed() < 60.0
    assert clock.aim == pytest.approx(1000.0 * (1 - END_MARGIN))
    for bad in ("soon", repr(time.time() + 100.0)):  # unreadable, in the future: now
        monkeypatch.setenv(COMMAND_START_ENV, bad)
        assert before <= command_start() <= time.time()


def test_the_clock_stops_when_one_more_trial_and_the_evaluation_would_overrun() -> None:
    study = optuna.create_study()
    limit = 100.0 + START_ALLOWANCE
    clock = StudyClock(study, limit, EvaluationSize(2, 1, 100, 1), joined=False)
    assert clock.check() is None  # no trial yet: the first one always starts
    study.add_trial(_trial(0, 20.0, 200, TrialState.COMPLETE))  # τ = 0.1 s: 20 s + start
    assert clock.check() is None  # 0 + 20 + 20 + start ≤ limit
    clock.start -= 70.0
    stop = clock.check()
    assert stop is not None and not stop.too_small
    assert stop.needed == pytest.approx(40.0 + START_ALLOWANCE)
    assert recorded_stop(study) == stop
    assert stop.text(4).startswith(f"stopped at its time limit ({limit:g} s) after 4 trials")
    assert StudyClock(study, None, EvaluationSize(2, 1, 100, 1), joined=False).check() is None
    assert recorded_stop(study) is None  # a new invocation forgets the last one's stop


def test_a_running_trial_is_overdue_when_the_evaluation_would_end_past_the_limit() -> None:
    study = optuna.create_study()
    limit = 100.0
    clock = StudyClock(study, limit, EvaluationSize(2, 1, 100, 1), joined=False)
    clock.start -= 500.0
    assert not clock.overdue()  # past the limit, but nothing complete to evaluate
    study.add_trial(_trial(0, 5.0, 200, TrialState.PRUNED))
    clock._asked = -float("inf")
    assert not clock.overdue()
    study.add_trial(_trial(1, 5.0, 200, TrialState.COMPLETE))  # τ = 0.025 s: T_eval 5 s + start
    assert clock.aim == pytest.approx(limit * (1 - END_MARGIN))
    clock.start = time.time() - (clock.aim - 5.0 - START_ALLOWANCE - 2.0)
    clock._asked = -float("inf")
    assert not clock.overdue()  # the evaluation still ends 2 s before limit − margin
    clock.start -= 4.0
    assert clock.overdue()
    assert not StudyClock(study, None, EvaluationSize(2, 1, 100, 1), joined=False).overdue()


def test_a_running_trial_slower_than_the_complete_ones_is_overdue_at_its_own_pace() -> None:
    study = optuna.create_study()
    limit = 1000.0
    clock = StudyClock(study, limit, EvaluationSize(10, 2, 100, 1, 3, 250.0), joined=False)
    study.add_trial(_trial(0, 30.0, 300, TrialState.COMPLETE))  # τ 0.1 s: T_eval 50 s + start
    clock.start = time.time() - 700.0
    assert not clock.overdue()
    assert not clock.overdue(pace=0.4)  # its evaluation: 200 s + start, ending at 960 s
    assert clock.overdue(pace=0.6)  # 300 s + start: past the limit


def test_a_running_trial_is_paced_by_its_later_episodes() -> None:
    """Taxi-like: the first 400 member-episodes take 0.2 s each, the next 400 0.05 s; of 2 000
    the trial's evaluation is paced by what its remaining 1 200 will take at 0.05 s, not by
    the mean so far (0.125 s); CartPole-like lengthening episodes are paced slower than
    their mean."""
    pace = Pace(2000)
    for p in range(1, 401):
        pace.mark(0.2 * p, p)
    assert pace.projected() is None  # 400 of 2 000: under a quarter
    assert pace.total() == pytest.approx(80.0 + 1600 * 0.2)  # T_run is projected already
    for p in range(401, 801):
        pace.mark(80.0 + 0.05 * (p - 400), p)
    assert pace.projected() == pytest.approx((100.0 + 1200 * 0.05) / 2000)  # 0.08 s
    longer = Pace(1000)
    for p in range(1, 501):
        longer.mark(0.01 * p if p <= 250 else 2.5 + 0.03 * (p - 250), p)
    assert longer.projected() == pytest.approx((10.0 + 500 * 0.03) / 1000)  # above the mean 0.02


@pytest.mark.parametrize(
    ("value", "expected"),
    [("-5", "tune.time_limit=-5.0: must be a number of seconds >= 0, or null for no limit"),
     ("abc", "tune.time_limit=abc: Value 'abc' of type 'str' could not be converted to Float")],
)  # fmt: skip
def test_a_bad_limit_is_refused_with_one_line(value: str, expected: str) -> None:
    errors = check_overrides([f"tune.time_limit={value}"], config_name="tune",
                             check=_check_tune())  # fmt: skip
    assert len(errors) == 1 and errors[0].startswith(expected), errors


def _check_tune():
    from cdqn.tune import check_tune

    return check_tune


def test_cli_refuses_a_negative_limit_with_exit_2(tmp_path: Path) -> None:
    proc = run_cli("cdqn.tune", ["tune.time_limit=-1"], tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "tune.time_limit=-1.0: must be a number of seconds >= 0" in proc.stderr
    assert not (tmp_path / "optuna.db").exists()


def _parent(tmp: Path, run_id: str):
    return MlflowClient(f"sqlite:///{tmp / 'mlflow.db'}").get_run(run_id)


@pytest.mark.slow
def test_a_limit_too_small_for_one_trial_runs_one_and_says_so(tmp_path: Path) -> None:
    summary = _study(_overrides(tmp_path, "small", 10, ["tune.time_limit=0",
                                                        "tune.trial_share=null"]))  # fmt: skip
    assert sum(summary["counts"].values()) == 1
    assert summary["evaluation"]["seeds"] == [1000, 1001]
    reason = _parent(tmp_path, summary["parent_run"]).data.tags[Tag.STOPPED]
    assert reason.startswith("tune.time_limit=0 s is too small for even one trial")
    assert reason.endswith("ran 1 trial(s) anyway") and reason in summary_text(summary)


@pytest.mark.slow
def test_a_limit_of_a_few_trials_stops_a_ten_trial_study_before_its_evaluation(
    tmp_path: Path,
) -> None:
    """A study runs 3 trials without a limit; run again for 10 more with a limit that leaves
    about 2.5 of its trials besides the evaluation, it stops early, says why on its parent
    run and in its summary, and still evaluates its best trial on the fresh seeds."""
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    first = _study(_overrides(tmp_path, "limited", 3, ["tune.time_limit=null",
                                                       "tune.eval_seeds=0"]))  # fmt: skip
    assert "stopped" not in first
    trials = optuna.load_study(study_name="limited", storage=storage).trials
    est = estimate(trials, EvaluationSize(seeds=2, processes=eval_processes(1, 2), episodes=12,
                                          runs=1))  # fmt: skip
    assert est is not None
    limit = round(est.evaluation + 2.5 * est.trial)
    summary = _study(_overrides(tmp_path, "limited", 13, [f"tune.time_limit={limit}"]))
    total = sum(summary["counts"].values())
    assert 4 <= total < 13  # at least one more trial, and not all ten
    assert summary["evaluation"]["seeds"] == [1000, 1001]
    (evaluation,) = _runs(tmp_path, kind="evaluation")
    assert evaluation.info.status == "FINISHED"
    parent = _parent(tmp_path, summary["parent_run"])
    assert parent.info.run_id == first["parent_run"]
    assert parent.data.tags[Tag.STOPPED] == summary["stopped"]
    assert summary["stopped"].startswith(
        f"stopped at its time limit ({limit} s) after {total} trials"
    )
    assert f"study {summary['stopped']}" in summary_text(summary)


@pytest.mark.slow
def test_trials_longer_than_their_cap_stop_and_the_study_says_so(tmp_path: Path) -> None:
    """A cap of 0.01 s stops every trial before its first episode ends (opening its members'
    runs alone takes longer); no trial completes, and the summary says why."""
    summary = _study(_overrides(tmp_path, "capped", 2, ["tune.time_limit=1000",
                                                        "tune.trial_share=0.00001"]))  # fmt: skip
    assert summary["counts"]["complete"] == 0 and summary["counts"]["pruned"] == 2
    for tr in optuna.load_study(study_name="capped",
                                storage=f"sqlite:///{tmp_path / 'optuna.db'}").trials:  # fmt: skip
        assert tr.user_attrs["too_long"] is True
        assert "tune.trial_share × tune.time_limit = 0.01 s" in tr.user_attrs["reason"]
    assert summary["no_result"] == ("no trial completed: 2 trial(s) stopped at their cap "
                                    "(0.01 s) without ending an episode; give a larger "
                                    "tune.time_limit or tune.trial_share")  # fmt: skip
    parent = _parent(tmp_path, summary["parent_run"])
    assert parent.data.tags["best"] == f"none: {summary['no_result']}"
    assert parent.info.status == "FAILED"
    assert f"{summary['no_result']}; no preset written" in summary_text(summary)


def test_the_summary_names_the_episodes_a_trial_fits_at_the_stopped_trials_pace() -> None:
    from cdqn.tuning.study import _too_long_hint

    study = optuna.create_study()
    for number, (seconds, played) in enumerate([(450.0, 600), (450.0, 300)]):
        trial = _trial(number, seconds, played, TrialState.PRUNED)
        trial.set_user_attr("too_long", True)
        study.add_trial(trial)
    study.add_trial(_trial(2, 10.0, 600, TrialState.PRUNED))  # pruned on its score
    size = EvaluationSize(10, 2, 1500, 1, members=3, trial_cap=450.0)
    # 900 s for 900 member-episodes: a trial of 3 members fits 150 episodes in 450 s
    assert _too_long_hint(study, size) == (
        ": 2 trial(s) stopped at their cap (450 s) at 1 s per member-episode, where a trial "
        "of 3 members fits about 150 of its 1500 episodes; give tune.episodes=<at most 150> "
        "(or a lower tune.steps), or a larger tune.time_limit"
    )
    assert _too_long_hint(optuna.create_study(), size) == ""


def test_a_bad_trial_share_is_refused_with_one_line() -> None:
    errors = check_overrides(["tune.trial_share=0"], config_name="tune", check=_check_tune())
    assert errors == ["tune.trial_share=0.0: must be a share in (0, 1], or null for no cap"]
