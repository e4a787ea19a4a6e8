"""Environments unlike the presets through the tuner: ``Tuple``/``Discrete`` observations
(one-hot), no registered episode cap, no registered solve threshold; a real Optuna SQLite
storage and a real MLflow store."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from mlflow.tracking import MlflowClient
from omegaconf import OmegaConf

from cdqn.config import ConfigError, EnvConfig
from cdqn.envs import adopt
from cdqn.training.run import run
from cdqn.tuning.diagnosis import shortfall_text
from cdqn.tuning.evaluation import comparison_table, random_policy, summarise
from cdqn.tuning.objective import score_text
from cdqn.tuning.report import summary_text
from tests.conftest import CONF_DIR
from tests.test_tune import _runs, _store, _study


def test_the_comparison_of_an_environment_without_a_solve_threshold_says_so() -> None:
    row = {**summarise("ddqn", {1000: [-1.0] * 4, 1001: [-2.0] * 4}, 4, None), "study": "s"}
    table = comparison_table([row], None, 4)
    assert "None" not in table
    assert "| solve episode (median) | no solve threshold |" in table
    assert "| ddqn | s | -1.50 ± 0.50 | n/a | n/a | -1.50 |" in table
    row = {**summarise("ddqn", {1000: [-1.0] * 4, 1001: [-2.0] * 4}, 4, -1.5), "study": "s"}
    table = comparison_table([row], -1.5, 4)
    assert "| seeds ≥ -1.5 |" in table and "| ddqn | s | -1.50 ± 0.50 | 1 | 1/2 |" in table


def test_the_comparison_says_by_how_much_a_design_reaches_or_falls_short() -> None:
    """Double DQN 0.59 ± 0.07 (bar 0.52): a design at 0.43 falls short by 0.09, one at 0.60
    reaches it by 0.08."""
    base = {**summarise("ddqn", {1000: [0.52] * 4, 1001: [0.66] * 4}, 4, None), "study": "d"}
    low = {**summarise("hinf_f", {1000: [0.43] * 4, 1001: [0.43] * 4}, 4, None), "study": "h"}
    high = {**summarise("hinf", {1000: [0.6] * 4, 1001: [0.6] * 4}, 4, None), "study": "i"}
    table = comparison_table([base, low, high], None, 4)
    assert "hinf_f falls short of Double DQN's final score minus one std (0.52) by 0.09." in table
    assert "hinf reaches Double DQN's final score minus one std (0.52) by 0.08." in table


def _seed(final: float, steps: int, per_step: float, eps: float, **shares: float) -> dict:
    return {"final": final, "steps": steps, "learned_per_step": per_step, "epsilon": eps,
            **shares}  # fmt: skip


def test_a_shortfall_is_set_beside_what_each_agent_did_on_its_seeds() -> None:
    """Acrobot-like: Double DQN −120 ± 20 on four seeds (bar −140); the design ends at −196.25
    because one seed stays at the cap (−500) while the other three end at −95: the seeds
    below the bar, the average of the others, the medians, the steps, the transitions per
    step, ε and the box with the steps outside it (Θ2/Θ1 up to 1.25: γ_eff below 0.8)."""
    ddqn = {"seeds": {str(1000 + i): _seed(f, 40_000, 8.0, 0.01)
                      for i, f in enumerate([-100.0, -100.0, -140.0, -140.0])},
            "design": None}  # fmt: skip
    shares = {"theta1_outside_box": 0.5, "ratio_above_box": 0.02, "ratio_below_box": 0.1}
    design = {
        "seeds": {
            "1000": _seed(-95.0, 20_000, 1.0, 0.01, **shares),
            "1001": _seed(-500.0, 50_000, 1.0, 0.01, **{**shares, "theta1_outside_box": 0.9}),
            "1002": _seed(-95.0, 20_000, 1.5, 0.03, **shares),
            "1003": _seed(-95.0, 30_000, 1.5, 0.03, **shares),
        },
        "design": {"theta1": [100.0, 400.0], "ratio": [0.8, 1.25], "gamma_eff": 0.7},
    }
    text = shortfall_text("hinf_f", design, ddqn, -140.0, 2)
    assert text.splitlines()[1:] == [
        "Where hinf_f falls short (the same fresh seeds; shares over each seed's last 100 "
        "episodes):",
        "- seeds below the bar: 1 of 4 (1001: -500.00); the other 3 average -95.00; median "
        "final score hinf_f -95.00, Double DQN -120.00",
        "- environment steps per seed: hinf_f 30,000, Double DQN 40,000; transitions learned "
        "from per step: hinf_f 1.25, Double DQN 8.00",
        "- ε at the end: hinf_f 0.02, Double DQN 0.01",
        "- NTK box of the design: Θ1 ∈ [100, 400], Θ2/Θ1 ∈ [0.8, 1.25] (a loop stable over it "
        "needs γ_eff below 1/1.25 = 0.8; the design keeps γ_eff 0.7); steps outside it: Θ1 "
        "outside 60.0 %, Θ2/Θ1 above 2.0 %, Θ2/Θ1 below 10.0 % (mean over seeds)",
    ]
    low = {s: {**r, "final": -150.0} for s, r in design["seeds"].items()}
    all_low = {**design, "design": None, "seeds": low}
    text = shortfall_text("hinf_f", all_low, ddqn, -140.0, 2)
    assert "- seeds below the bar: 4 of 4 (1000: -150.00, 1001: -150.00, 1002: -150.00, " in text
    assert "the other" not in text and "NTK box" not in text
    many = {str(2000 + i): {**design["seeds"]["1000"], "final": -150.0 - i} for i in range(6)}
    text = shortfall_text("hinf_f", {"seeds": many, "design": None}, ddqn, -140.0, 2)
    assert "- seeds below the bar: 6 of 6 (2005: -155.00, …, 2000: -150.00); median" in text


def test_the_comparison_says_how_far_each_agent_ends_above_a_random_policy() -> None:
    """Taxi-v4 played with random actions on two seeds scores far below the −200 of a policy
    that only waits out the cap (illegal pick-ups cost 10); the table says how far each agent
    ends from it."""
    chance = random_policy(EnvConfig(id="Taxi-v4", max_episode_steps=200), [1000, 1001], 20)
    assert chance["episodes"] == 20 and chance["mean"] < -300 and chance["std"] > 0
    assert random_policy(EnvConfig(id="Taxi-v4", max_episode_steps=200), [1000, 1001], 20) == (
        chance
    )  # the same seeds, the same episodes
    base = {**summarise("ddqn", {1000: [-205.0] * 4, 1001: [-207.0] * 4}, 4, None), "study": "d"}
    table = comparison_table([base], None, 4, {"mean": -776.25, "std": 101.5, "episodes": 20})
    assert table.endswith("A random policy scores -776.25 ± 101.50 per episode (20 episodes on "
                          "the same seeds); final score against it: ddqn +570.25.")  # fmt: skip


def test_the_comparison_keeps_three_decimals_where_the_returns_are_below_a_tenth() -> None:
    """FrozenLake8x8: Double DQN 0.020 ± 0.024 and a design at 0.003 show as such, with the
    bar (−0.004) and the margin (0.007), not as 0.02 ± 0.02, (−0.00) and 0.01."""
    base = {**summarise("ddqn", {1000: [-0.004] * 4, 1001: [0.044] * 4}, 4, None), "study": "d"}
    low = {**summarise("hinf_f", {1000: [0.003] * 4, 1001: [0.003] * 4}, 4, None), "study": "h"}
    table = comparison_table([base, low], None, 4)
    assert "| ddqn | d | 0.020 ± 0.024 | n/a | n/a | 0.020 |" in table
    assert "hinf_f reaches Double DQN's final score minus one std (-0.004) by 0.007." in table


def test_the_printed_scores_keep_the_digits_of_the_environments_return_scale() -> None:
    """FrozenLake's returns lie in [0, 1]: its summary says 0.43 ± 0.27, not 0.4 ± 0.3
    (which would hide the gap to Double DQN's 0.59 ± 0.07); CartPole's keep one decimal."""
    assert score_text(0.432, 0.2694) == "0.43 ± 0.27"
    assert score_text(0.6133) == "0.61"
    assert score_text(0.012, 0.0109) == "0.012 ± 0.011"
    assert score_text(0.0, 0.0) == "0.00 ± 0.00"
    assert score_text(416.91, 106.67) == "416.9 ± 106.7" and score_text(-42.9) == "-42.9"
    assert score_text(float("nan"), float("nan")) == "nan ± nan"
    evaluation = {"seeds": list(range(1000, 1010)), "objective": 0.364, "final_score": 0.432,
                  "final_std": 0.2694, "diverged": 0, "seconds": 45.0}  # fmt: skip
    text = summary_text({
        "study": "FrozenLake-v1-hinf_f", "counts": {"complete": 9, "pruned": 11, "infeasible": 0,
        "failed": 0}, "episodes": 2000, "wall_seconds": 173.0, "parent_run": "p", "best_trial": 2,
        "best_value": 0.4358, "best_final_score": 0.6133, "best_params": {}, "preset": "x.yaml",
        "evaluation": evaluation,
    })  # fmt: skip
    assert "best trial 2: J = 0.44 (final MA100 0.61)" in text
    assert "J = 0.36, final MA100 0.43 ± 0.27, 0 diverged (45 s)" in text


@pytest.mark.slow
def test_a_tuple_observation_environment_without_cap_or_threshold_is_tuned_as_itself(
    tmp_path: Path,
) -> None:
    """Blackjack-v1 (``Tuple`` of ``Discrete``: one-hot, 45 inputs; no registered cap or
    reward threshold) tuned for Double DQN: the study, its runs and its preset are
    Blackjack's at the cap given (``Blackjack-v1-cap20``), with no solve threshold; the
    preset records the search space the observation allowed (no radial features over 45
    inputs) and trains again."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    _store(uri, "cdqn-tune", tmp_path)
    summary = _study([
        "env.id=Blackjack-v1", "env.max_episode_steps=20", "controller=ddqn",
        f"tracking.uri={uri}", f"tune.storage=sqlite:///{tmp_path / 'optuna.db'}",
        f"tune.preset_dir={tmp_path / 'presets'}", "network.width=16", "tune.trials=1",
        "tune.seeds=2", "tune.episodes=6", "tune.eval_seeds=2", "tune.pruner.kind=none",
        "tune.eval_processes=1",
    ])  # fmt: skip
    assert summary["study"] == "Blackjack-v1-cap20-ddqn" and summary["counts"]["complete"] == 1
    assert "no solve threshold" in summary["comparison"]["table"]
    (parent,) = _runs(tmp_path, kind="tune")
    tags = parent.data.tags
    assert (tags["env"], tags["env_id"]) == ("Blackjack-v1-cap20", "Blackjack-v1")
    assert parent.data.params["env.max_episode_steps"] == "20"
    assert parent.data.params["env.solve_threshold"] == "None"
    members = [r for r in _runs(tmp_path) if "population" in r.data.tags]
    assert len(members) == 4  # the trial's two and the evaluation's two
    assert {r.data.tags["env"] for r in members} == {"Blackjack-v1-cap20"}
    assert all(r.info.run_name.startswith("Blackjack-v1-cap20-ddqn-") for r in members)

    preset = Path(summary["preset"])
    assert preset.name == "tuned_Blackjack-v1-cap20-ddqn.yaml"
    tuned = OmegaConf.load(preset)
    assert (tuned.env.id, tuned.env.name) == ("Blackjack-v1", "Blackjack-v1-cap20")
    assert tuned.env.max_episode_steps == 20 and tuned.env.solve_threshold is None
    assert "rbf" not in tuned.extra.tuned.space and "normalize" in tuned.extra.tuned.space
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=[
            "controller=ddqn", f"weights={preset.stem}", "network.width=16",
            f"hydra.searchpath=[file://{tmp_path / 'presets'}]", "train.episodes=2",
            "train.progress=false", f"tracking.uri=sqlite:///{tmp_path / 'train.db'}",
        ])  # fmt: skip
    adopted = adopt(cfg)
    assert adopted.change is None  # the preset's environment is Blackjack's already
    result = run(adopted.cfg, progress=False)
    trained = MlflowClient(f"sqlite:///{tmp_path / 'train.db'}").get_run(result.run_id)
    assert result.status == "FINISHED" and trained.data.tags["env"] == "Blackjack-v1-cap20"
    assert trained.data.params["env.max_episode_steps"] == "20"


def test_a_study_refuses_another_environment_under_its_name(tmp_path: Path) -> None:
    """The default study name is the label, which says an adopted id's ``env.kwargs`` and a
    cap other than its registration's: the 8x8 map without slip is a study of its own
    (``FrozenLake-v1.is_slippery-false.map_name-8x8-ddqn``), whose preset is named by that
    label, and so is the lake at 50 steps (``FrozenLake-v1-cap50-ddqn``); the study
    ``FrozenLake-v1-ddqn`` named for a run at another cap is refused before it trains or opens a
    run, instead of mixing its trials (and preset) with those of the lake at its registered
    cap."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    _store(uri, "cdqn-tune", tmp_path)
    common = [
        "env.id=FrozenLake-v1", "controller=ddqn", f"tracking.uri={uri}",
        f"tune.storage=sqlite:///{tmp_path / 'optuna.db'}", f"tune.preset_dir={tmp_path}",
        "network.width=16", "tune.trials=1", "tune.seeds=1", "tune.episodes=2",
        "tune.eval_seeds=0", "tune.pruner.kind=none",
    ]  # fmt: skip
    assert _study(common)["study"] == "FrozenLake-v1-ddqn"
    kwargs = ["+env.kwargs.map_name=8x8", "+env.kwargs.is_slippery=false"]
    own = _study([*common, *kwargs])
    label = "FrozenLake-v1.is_slippery-false.map_name-8x8"
    assert own["study"] == f"{label}-ddqn" and own["counts"]["complete"] == 1
    assert Path(own["preset"]).name == f"tuned_{label}-ddqn.yaml"
    capped = _study([*common, "env.max_episode_steps=50"])  # another task: its own study
    assert capped["study"] == "FrozenLake-v1-cap50-ddqn"
    with pytest.raises(ConfigError) as err:
        _study(
            [*common, "env.max_episode_steps=50", "tune.trials=2", "tune.study=FrozenLake-v1-ddqn"]
        )
    (line,) = str(err.value).splitlines()
    assert line.startswith(
        f"tune.study=FrozenLake-v1-ddqn: the study in sqlite:///{tmp_path / 'optuna.db'} "
        "tunes env env.id=FrozenLake-v1 env.max_episode_steps=100, not this run's env "
        "env.id=FrozenLake-v1 env.max_episode_steps=50"
    )
    assert line.endswith("tune.study=<name> (or tune.storage=<url>)")
    kwargs_study = [*common, *kwargs, "env.max_episode_steps=50", "tune.study=FrozenLake-v1-ddqn"]
    assert "+env.kwargs.is_slippery=False +env.kwargs.map_name=8x8" in _message(kwargs_study)
    assert len(_runs(tmp_path, kind="trial")) == 3  # nothing of the refused runs
    again = _study([*common, "tune.trials=2"])  # the same environment continues the study
    assert again["counts"]["complete"] == 2


def test_a_presets_own_id_with_constructor_arguments_is_a_study_of_its_label(
    tmp_path: Path,
) -> None:
    """``env=cartpole +env.kwargs.sutton_barto_reward=true``: the study, its preset file,
    its parent and member runs carry the label with the argument, not ``cartpole``."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    _store(uri, "cdqn-tune", tmp_path)
    label = "cartpole.sutton_barto_reward-true"
    summary = _study(
        ["env=cartpole", "+env.kwargs.sutton_barto_reward=true", *_one_trial(tmp_path, uri)]
    )
    assert summary["study"] == f"{label}-ddqn"
    assert Path(summary["preset"]).name == f"tuned_{label}-ddqn.yaml"
    tuned = OmegaConf.load(summary["preset"])
    assert (tuned.env.name, tuned.env.kwargs) == (label, {"sutton_barto_reward": True})
    (parent,) = _runs(tmp_path, kind="tune")
    assert parent.info.run_name == f"tune-{label}-ddqn" and parent.data.tags["env"] == label
    members = [r for r in _runs(tmp_path) if "population" in r.data.tags]
    assert members and {r.data.tags["env"] for r in members} == {label}
    assert all(r.info.run_name.startswith(f"{label}-ddqn-") for r in members)


def test_another_id_than_the_presets_is_tuned_on_its_own_features(tmp_path: Path) -> None:
    """``env=acrobot env.id=CartPole-v1``: Acrobot's six ``env.normalize_scale`` widths are
    not CartPole's, so a trial that scales the observation scales it to [−1, 1] (it stopped
    with a traceback when it kept them)."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    _store(uri, "cdqn-tune", tmp_path)
    normalize = "tune.space.normalize.choices=[true]"
    summary = _study(["env=acrobot", "env.id=CartPole-v1", normalize, *_one_trial(tmp_path, uri)])
    assert summary["study"] == "CartPole-v1-ddqn" and summary["counts"]["complete"] == 1
    members = [r for r in _runs(tmp_path) if "population" in r.data.tags]
    assert members and all(r.data.tags["env"] == "CartPole-v1" for r in members)
    assert {r.data.params["env.normalize"] for r in members} == {"True"}
    assert {r.data.params["env.normalize_scale"] for r in members} == {"None"}


def _one_trial(tmp_path: Path, uri: str) -> list[str]:
    """A study of one Double DQN trial, one seed, three episodes, no evaluation, in
    ``tmp_path``."""
    return [
        "controller=ddqn", f"tracking.uri={uri}",
        f"tune.storage=sqlite:///{tmp_path / 'optuna.db'}",
        f"tune.preset_dir={tmp_path / 'presets'}", "network.width=16", "tune.trials=1",
        "tune.seeds=1", "tune.episodes=3", "tune.eval_seeds=0", "tune.pruner.kind=none",
    ]  # fmt: skip


def _message(overrides: list[str]) -> str:
    with pytest.raises(ConfigError) as err:
        _study(overrides)
    return str(err.value)


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        (["env.id=FrozenLake-v1", "+env.kwargs.foo=1"],
         "env.kwargs={'foo': 1}: FrozenLake-v1's constructor refused them (TypeError: "),
        (["env.id=HalfCheetah-v2", "env.max_episode_steps=10"],
         "env.id='HalfCheetah-v2' cannot be made here: its entry point "),
    ],
)  # fmt: skip
def test_the_tuner_refuses_an_environment_it_cannot_make_before_it_starts(
    overrides: list[str], expected: str
) -> None:
    """As ``cdqn.train``: one line before Hydra starts, not an error of the started study."""
    from cdqn.cli import check_overrides
    from cdqn.tune import check_tune

    errors = check_overrides(overrides, config_name="tune", check=check_tune)
    assert len(errors) == 1 and errors[0].startswith(expected), errors


def test_a_search_space_that_samples_a_refused_value_stops_the_study_in_one_line(
    tmp_path: Path,
) -> None:
    """A user's range outside what cdqn accepts (ε lowered by 2–3 per random action): the
    first trial's configuration is refused, the study stops with one line and exit status 2,
    no traceback, and its MLflow runs end FAILED with the reason (they stayed RUNNING)."""
    from tests.helpers import run_cli

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    _store(uri, "cdqn-tune", tmp_path)
    space = [
        "tune.space.eps_schedule.choices=[random_action]",
        "tune.space.eps_dec_action.low=2", "tune.space.eps_dec_action.high=3",
    ]  # fmt: skip
    proc = run_cli("cdqn.tune", [*_one_trial(tmp_path, uri), "tune.trials=2", *space], tmp_path)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    lines = proc.stderr.splitlines()
    (first,) = [i for i, ln in enumerate(lines) if ln.startswith("error:")]
    (line, detail) = lines[first:]
    assert line == "error: tune.space: trial 0's sample is invalid configuration:"
    assert detail.startswith("  - train.eps_dec=2.") and detail.endswith(": must lie in [0, 1]")
    (parent,) = _runs(tmp_path, kind="tune")
    assert parent.info.status == "FAILED"
    assert parent.data.tags["failure_reason"].startswith("tune.space: trial 0's sample is")
    (trial,) = _runs(tmp_path, kind="trial")
    assert trial.info.status == "FAILED"
