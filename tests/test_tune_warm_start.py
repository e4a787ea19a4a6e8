"""``tune.warm_start``: a new study's first trials are the specifications of presets, fitted
to its own space (:func:`cdqn.tuning.space.fitted_specification`); real Optuna and MLflow
stores."""

from __future__ import annotations

import json
from pathlib import Path

import optuna
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from cdqn.cli import check_overrides
from cdqn.records import Tag
from cdqn.tuning.presets import specification_of
from cdqn.tuning.settings import ParamSpec
from cdqn.tuning.space import fitted_specification, with_each_input_map
from cdqn.tuning.study import Study
from tests.conftest import CONF_DIR
from tests.test_tune import _overrides, _runs, _study

SPACE = {
    "rbf": ParamSpec(path="env.rbf_centres", choices=[None, 4]),
    "schedule": ParamSpec(path="train.eps_schedule", choices=["random_action", "episode"]),
    "per_episode": ParamSpec(
        path="train.eps_dec", low=5e-4, high=3e-3, log=True, when={"schedule": "episode"}
    ),  # fmt: skip
    "gamma_eff": ParamSpec(
        path="weights.target.gamma_eff", choices=[-1.0, 1.5, 2.0], width=0.3, horizon=True
    ),  # fmt: skip
    "period": ParamSpec(path="controller.target_update", low=100, high=1000, integer=True),
}
SEARCHED = {
    "rbf": {"path": "env.rbf_centres", "choices": [None, 4, 6]},
    "schedule": {"path": "train.eps_schedule"},
    "per_episode": {"path": "train.eps_dec", "low": 5e-4, "high": 2e-2, "log": True},
    "gamma_eff": {
        "path": "weights.target.gamma_eff",
        "low": -2.5,
        "high": 2.5,
        "width": 0.3,
        "horizon": True,
    },  # fmt: skip
    "period": {"path": "controller.target_update", "low": 10, "high": 5000, "integer": True},
}


def test_a_specification_is_fitted_to_the_values_this_space_offers() -> None:
    found = {"rbf": 6, "schedule": "episode", "per_episode": 0.0055, "gamma_eff": 1.85,
             "period": 4321.7, "gone": 3}  # fmt: skip
    assert fitted_specification(SPACE, found, SEARCHED) == {
        "rbf": 4,  # 6 centres per feature not offered here: the nearest number offered
        "schedule": "episode",
        "per_episode": 3e-3,  # clipped into [low, high]
        "gamma_eff": 2.0,  # a continuous centre: the nearest choice
        "period": 1000,  # a whole number
    }  # a dimension this space has not ("gone") is dropped
    by_action = fitted_specification(SPACE, found | {"schedule": "random_action"}, SEARCHED)
    assert "per_episode" not in by_action  # its `when` does not hold
    # γ_eff searched as a discount, not a log-horizon: another quantity, left to the sampler
    as_discount = SEARCHED | {"gamma_eff": {"path": "weights.target.gamma_eff", "low": -1.0,
                                            "high": 1.0, "width": 0.1}}  # fmt: skip
    assert "gamma_eff" not in fitted_specification(SPACE, found, as_discount)
    assert fitted_specification(SPACE, {"rbf": None}, SEARCHED) == {"rbf": None}
    assert "schedule" not in fitted_specification(SPACE, {"schedule": "step"}, SEARCHED)


def test_a_warm_start_is_tried_on_each_observation_map_offered() -> None:
    """A preset's specification, then the same with each other [−1, 1]-map choice; none
    where the map is left to the sampler or only one map is offered."""
    space = SPACE | {"inputs": ParamSpec(path="env.normalize", choices=[False, True])}
    found = {"inputs": True, "schedule": "episode", "per_episode": 1e-3}
    assert with_each_input_map(space, found) == [found | {"inputs": False}]
    assert with_each_input_map(space, {"schedule": "episode"}) == []
    one = space | {"inputs": ParamSpec(path="env.normalize", choices=[False])}
    assert with_each_input_map(one, found | {"inputs": False}) == []


def test_every_shipped_preset_holds_a_specification_and_its_space() -> None:
    for name in ("cartpole", "acrobot", "mountaincar"):
        for agent in ("h2", "hinf", "hinf_f", "ddqn"):
            params, searched = specification_of(f"tuned_{name}-{agent}", "no-such-folder")
            assert params and set(params) <= set(searched), (name, agent)


def test_a_warm_start_keeps_the_settings_its_preset_did_not_search(tmp_path: Path) -> None:
    """A dimension the preset's study did not search (the ε floor, in a study whose space had
    none) starts at the value the preset trained with, fitted like the others; a preset of
    another floor starts at its own, and what its study searched stays its specification's."""
    overrides = [o for o in _overrides(tmp_path, "floor", 1) if o != "~tune.space.eps_end"]
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        study = Study(compose("tune", overrides=overrides))
    assert study.space["eps_end"].choices == [0.01, 0.02, 0.05]
    shipped = OmegaConf.load(CONF_DIR / "weights" / "tuned_cartpole-hinf_f.yaml")
    folder = tmp_path / "presets" / "weights"
    folder.mkdir(parents=True)
    for name, floor, lr in (("unsearched", 0.02, None), ("other", 0.05, 0.125)):
        preset = shipped.copy()
        del preset.extra.tuned.space["eps_end"], preset.extra.tuned.specification["eps_end"]
        preset.train.eps_end = floor
        if lr is not None:  # lr: searched, the specification's stays
            preset.train.lr = lr
        OmegaConf.save(preset, folder / f"tuned_{name}-hinf_f.yaml")
    specification, searched = specification_of("tuned_unsearched-hinf_f", tmp_path / "presets")
    assert "eps_end" not in searched and "eps_end" not in specification
    params, _ = study._preset_specification("tuned_unsearched-hinf_f")
    assert params == specification | {"eps_end": 0.02}
    params, searched = study._preset_specification("tuned_other-hinf_f")
    assert params["eps_end"] == 0.05 and params["lr"] == specification["lr"]
    assert fitted_specification(study.space, params, searched)["eps_end"] == 0.05


def test_an_unknown_warm_start_preset_is_refused_with_one_line() -> None:
    from cdqn.tune import check_tune

    (error,) = check_overrides(["tune.warm_start=[nowhere]"], config_name="tune",
                               check=check_tune)  # fmt: skip
    assert error.startswith("tune.warm_start: nowhere: no preset tuned_nowhere-hinf_f.yaml in "
                            "presets/weights or ")  # fmt: skip


@pytest.mark.slow
def test_a_new_study_starts_from_the_presets_specifications(tmp_path: Path) -> None:
    """A study's preset is the first trial of a second study that starts from it (same space:
    the same values), a shipped preset's specification the next (fitted: the tests' narrow
    step-scale range clips it, their γ_eff as a discount is sampled); each is tagged with the
    preset it came from, counts in ``tune.trials``, and a continued study queues none again."""
    first = _study(_overrides(tmp_path, "first-hinf_f", 1, ["tune.eval_seeds=0"]))
    best = first["best_params"]
    warm = ["tune.warm_start=[first,cartpole]", "tune.eval_seeds=0"]
    second = _study(_overrides(tmp_path, "second", 3, warm))
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    trials = optuna.load_study(study_name="second", storage=storage).trials
    assert sum(second["counts"].values()) == 3
    assert trials[0].params == best
    assert trials[0].user_attrs[Tag.START_FROM] == "tuned_first-hinf_f"
    shipped, searched = specification_of("tuned_cartpole-hinf_f", tmp_path / "presets")
    assert trials[1].user_attrs[Tag.START_FROM] == "tuned_cartpole-hinf_f"
    assert shipped["step_scale"] < trials[1].params["step_scale"] == 0.6  # clipped to low
    assert Tag.START_FROM not in trials[2].user_attrs  # sampled
    runs = {int(r.data.tags["trial"]): r for r in _runs(tmp_path, kind="trial",
                                                         study="second")}  # fmt: skip
    assert runs[0].data.tags[Tag.START_FROM] == "tuned_first-hinf_f"
    assert Tag.START_FROM not in runs[2].data.tags
    _study(_overrides(tmp_path, "second", 4, warm))  # continued: one more sampled trial
    again = optuna.load_study(study_name="second", storage=storage).trials
    assert len(again) == 4 and Tag.START_FROM not in again[3].user_attrs
    assert json.dumps(searched)  # the shipped preset records the space it was searched in
    _study(_overrides(tmp_path, "third", 1, warm))  # one trial: one preset queued, none left
    (only,) = optuna.load_study(study_name="third", storage=storage).trials
    assert only.user_attrs[Tag.START_FROM] == "tuned_first-hinf_f" and only.state.is_finished()


@pytest.mark.slow
def test_a_warm_start_trains_on_each_observation_map(tmp_path: Path) -> None:
    """With the [−1, 1] map searched, a study queues the shipped CartPole preset's
    specification on its own map and then on the other, both tagged with the preset."""
    overrides = [
        o
        for o in _overrides(
            tmp_path, "crossed", 2, ["tune.warm_start=[cartpole]", "tune.eval_seeds=0"]
        )  # fmt: skip
        if o != "~tune.space.normalize"
    ]
    _study(overrides)
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    trials = optuna.load_study(study_name="crossed", storage=storage).trials
    own = specification_of("tuned_cartpole-hinf_f", tmp_path / "presets")[0]["normalize"]
    assert [t.params["normalize"] for t in trials] == [own, not own]
    assert {t.user_attrs[Tag.START_FROM] for t in trials} == {"tuned_cartpole-hinf_f"}
    sampled = {"normalize", "gamma_eff"}  # the tests' γ_eff is a discount: left to the sampler
    kept = [{k: v for k, v in t.params.items() if k not in sampled} for t in trials]
    assert kept[0] == kept[1] and kept[0]
