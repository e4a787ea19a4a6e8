"""Bad configurations are refused at start, naming key, value and what is allowed."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from cdqn.cli import EXIT_CONFIG, check_overrides, preflight
from cdqn.config import Config, ConfigError, validate
from cdqn.training.run import run
from tests.conftest import TINY, compose_config
from tests.helpers import run_cli

# (overrides, fragments the single error message must contain)
BAD = [
    (["controller=foo"], ["controller=foo", "unknown controller", "ddqn, h2, hinf, hinf_f, none"]),
    (["env=nope"], ["env=nope", "allowed: acrobot, cartpole"]),
    (["env.id=NoSuchEnv-v0"], ["env.id='NoSuchEnv-v0'", "not a registered gymnasium"]),
    (["env.id=Pendulum-v1"], ["env.id='Pendulum-v1'", "Box", "Discrete"]),
    (["network.width=0"], ["network.width=0", "positive integer"]),
    (["network.width=-3"], ["network.width=-3", "positive integer"]),
    (["network.width=abc"], ["network.width=abc", "Integer", "takes int"]),
    (["train.lr=0"], ["train.lr=0", "α must be > 0"]),
    (["train.lr=-1e-3"], ["train.lr=-0.001", "α must be > 0"]),
    (["train.discount=0"], ["train.discount=0", "(0, 1]"]),
    (["train.discount=1.5"], ["train.discount=1.5", "(0, 1]"]),
    (["train.eps_start=1.2"], ["train.eps_start=1.2", "[0, 1]"]),
    (["train.eps_end=-0.1"], ["train.eps_end=-0.1", "[0, 1]"]),
    (
        ["weights.hinf.w_p.num=[1,2,3]"],
        ["weights.hinf.w_p=num [1.0, 2.0, 3.0] / den [0.1, 1.0]", "not a proper"],
    ),
    (["weights.hinf_f.w_u.den=[0,0]"], ["weights.hinf_f.w_u", "not a proper"]),
    (
        ["weights.theta_bounds.theta1=[500,200]"],
        ["weights.theta_bounds.theta1=[500.0, 200.0]", "lower <= upper"],
    ),
    (["weights.theta_bounds.ratio=[1.2,0.8]"], ["weights.theta_bounds.ratio", "lower <= upper"]),
    (["foo=1"], ["foo: no such setting", "allowed: env, network"]),
    (["network.depth=2"], ["network.depth: no such setting in network", "width, dtype"]),
    (["tracking=nope"], ["tracking=nope", "allowed: local, server"]),
    (["train.checkpoint_every=-1"], ["train.checkpoint_every=-1", ">= 0"]),
    (["tracking.timeout=0"], ["tracking.timeout=0", "> 0"]),
    (["seed=1.5"], ["seed=1.5", "takes int"]),
    (["network.width=[1"], ["network.width=[1", "cannot parse"]),
    (["resume=abc", "train.lr=0.1"], ["train.lr=0.1", "resume=<run_id> continues"]),
    (["seed=-1"], ["seed=-1", ">= 0"]),
    (["controller=ddqn", "controller.lr=0"], ["controller.lr=0", "α must be > 0"]),
    (
        ["controller=hinf", "controller.lr=0.001"],
        ["controller.lr=0.001", "controller=ddqn", "train.lr"],
    ),
    (["controller.discount=0.9"], ["controller.discount=0.9", "Double DQN", "train.discount"]),
    (["resume="], ["resume=''", "give the MLflow run id", "resume=<run_id>"]),
    (["env.id=Taxi-v3"], ["env.id='Taxi-v3'", "not a registered", "did you mean Taxi-v4?"]),
    (["env.rbf_centres=1"], ["env.rbf_centres=1", "must be >= 2"]),
    (["weights.replay.sample=-1"], ["weights.replay.sample=-1", ">= 0 (0: off)"]),
    (["weights.replay.buffer=0"], ["weights.replay.buffer=0", ">= 1"]),
    (["env=mountaincar", "env.rbf_width=0"], ["env.rbf_width=0", "> 0"]),
    (
        ["env.eps_schedule=time"],
        ["train.eps_schedule='time'", "allowed random_action, step, episode"],
    ),
    (["train.eps_schedule=linear"], ["train.eps_schedule='linear'", "allowed random_action, step"]),
    (["env.rbf_centres=6"], ["env.rbf_centres=6", "observed features [1, 3]", "no finite bounds"]),
    (["env=acrobot", "env.rbf_centres=5"], ["env.rbf_centres=5", "5^6 = 15625", "4096"]),
    (["env=acrobot", "env.normalize_scale=[1,1]"], ["env.normalize_scale=[1.0, 1.0]", "6 half"]),
    (
        ["weights.controller_target.hinf_f.step_scale=[0.6,0.2]"],
        ["weights.controller_target.hinf_f.step_scale=[0.6, 0.2]", "0 < lower <= upper"],
    ),
    (
        ["weights.controller_target.dqn.gamma_eff=[0.1,0.2]"],
        ["weights.controller_target.dqn: no such setting", "allowed: h2, hinf, hinf_f"],
    ),
]


@pytest.mark.parametrize(("overrides", "fragments"), BAD, ids=[" ".join(o) for o, _ in BAD])
def test_bad_override_named_with_what_is_allowed(overrides: list[str], fragments: list[str]):
    errors = check_overrides(overrides)
    assert len(errors) == 1, errors
    for fragment in fragments:
        assert fragment in errors[0], (fragment, errors[0])


def test_every_problem_reported_at_once():
    errors = check_overrides(
        ["network.width=0", "train.lr=0", "train.discount=2", "train.eps_start=3"]
    )
    assert [e.split("=")[0] for e in errors] == [
        "network.width",
        "train.lr",
        "train.discount",
        "train.eps_start",
    ]


def test_multirun_checks_every_swept_value():
    assert check_overrides(["controller=h2,foo"], multirun=True) == [
        "controller=foo: unknown controller; allowed: ddqn, h2, hinf, hinf_f, none"
    ]
    errors = check_overrides(["network.width=8,0", "seed=0,1"], multirun=True)
    assert errors == ["network.width=0: must be a positive integer"]
    assert check_overrides(["controller=h2,hinf_f", "env=acrobot,cartpole"], multirun=True) == []


def test_good_configs_pass():
    assert check_overrides([]) == []
    assert check_overrides(["env=acrobot", "controller=ddqn", "network=small"]) == []
    assert check_overrides(["resume=0123abcd", "tracking.uri=sqlite:///x.db"]) == []


def test_preflight_exits_2_with_message(capsys: pytest.CaptureFixture[str]):
    with pytest.raises(SystemExit) as exc:
        preflight(["controller=foo", "train.episodes=3"])
    assert exc.value.code == EXIT_CONFIG
    err = capsys.readouterr().err
    assert err.startswith("cdqn: invalid configuration, nothing was started:\n")
    assert "controller=foo: unknown controller" in err
    preflight(["--cfg", "job", "controller=foo"])  # Hydra's own flags: left to Hydra


def test_argparse_command_refuses_in_one_line(tmp_path: Path):
    """``python -m cdqn.profile`` (as ``cdqn.bench``, through :func:`cdqn.cli.run_command`)
    turns a refused configuration into one ``error:`` line and exit status 2."""
    proc = run_cli("cdqn.profile", ["--env", "nope", "--steps", "1", "--warmup", "1"], tmp_path)
    assert proc.returncode == EXIT_CONFIG
    assert proc.stderr.startswith("error: env.id='nope' is not a registered")
    assert "Traceback" not in proc.stderr


def test_validate_schema_directly():
    conf: Config = OmegaConf.to_object(compose_config(["train.discount=0"]))
    with pytest.raises(ConfigError, match=r"train\.discount=0\.0: the discount γ"):
        validate(conf)


def test_run_refuses_before_creating_anything(tracking_uri: str, tmp_path: Path):
    cfg = compose_config([*TINY, "network.width=0", f"tracking.uri={tracking_uri}"])
    with pytest.raises(ConfigError, match="network.width=0"):
        run(cfg, progress=False)
    cfg = compose_config([*TINY, "env.id=MountainCarContinuous-v0", f"tracking.uri={tracking_uri}"])
    with pytest.raises(ConfigError, match="Discrete"):
        run(cfg, progress=False)
    assert not Path(tracking_uri.removeprefix("sqlite:///")).exists()  # no store, no run


# The real command line, in a subprocess: exit status 2, the message, no traceback.
CLI = [
    (
        ["controller=foo"],
        "controller=foo: unknown controller; allowed: ddqn, h2, hinf, hinf_f, none",
    ),
    (["network.width=abc"], "network.width=abc: Value 'abc' of type 'str' could not be converted"),
    (
        ["network.width=0", "train.discount=1.5", "train.eps_start=-1"],
        "network.width=0: must be a positive integer\n"
        "  - train.discount=1.5: the discount γ must lie in (0, 1]\n"
        "  - train.eps_start=-1.0: ε must lie in [0, 1]",
    ),
    (["seed=-1"], "seed=-1: must be >= 0"),
    (["resume="], "resume='': give the MLflow run id of the run to continue, resume=<run_id>"),
    (["env.id=Taxi-v3"], "env.id='Taxi-v3' is not a registered gymnasium environment; did you "),
]
if importlib.util.find_spec("Box2D") is None:  # the optional dependency missing, as here
    CLI.append(
        (
            ["env.id=LunarLander-v3"],
            "env.id='LunarLander-v3' needs an optional package that is not installed; pip "
            'install swig, then pip install "gymnasium[box2d]"',
        )
    )


@pytest.mark.parametrize(("overrides", "expected"), CLI, ids=[o[0] for o, _ in CLI])
def test_cli_refuses_bad_config(overrides: list[str], expected: str, tmp_path: Path):
    proc = run_cli("cdqn.train", [*overrides, f"tracking.uri=sqlite:///{tmp_path}/m.db"], tmp_path)
    assert proc.returncode == EXIT_CONFIG, proc.stderr
    assert expected in proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout
    assert len(proc.stderr.strip().splitlines()) == 1 + expected.count("\n") + 1  # head + items
    assert not (tmp_path / "m.db").exists()


def test_cli_refused_design_names_its_reason_and_where_a_design_comes_from(tmp_path: Path):
    """A learning target the box cannot certify: one error line with the reason and the
    command that tunes a design for the environment, exit 2, no traceback."""
    args = ["controller=hinf_f", "weights.target.gamma_eff=[0.9,0.95]", *TINY,
            f"tracking.uri=sqlite:///{tmp_path}/m.db"]  # fmt: skip
    proc = run_cli("cdqn.train", args, tmp_path)
    assert proc.returncode == EXIT_CONFIG, proc.stderr[-3000:]
    (line,) = [x for x in (proc.stdout + proc.stderr).splitlines() if "[ERROR]" in x]
    assert "conflicts with the NTK box" in line and "1/ρ_max" in line
    assert "python -m cdqn.tune env.id=CartPole-v1 controller=hinf_f" in line
    assert "Traceback" not in proc.stderr + proc.stdout


SWEEPS = Path(__file__).resolve().parents[1] / "sweeps"


def test_config_dir_sweeps_are_checked_too(capsys: pytest.CaptureFixture[str]):
    """``--config-dir sweeps --config-name <sweep>``: the sweep config is composed from
    there, its own swept values (``hydra.sweeper.params``) included, before any job runs."""
    sweep = ["-m", "--config-dir", str(SWEEPS), "--config-name", "smoke"]
    preflight([*sweep, "train.episodes=2"])  # a valid sweep passes
    preflight([f"--config-dir={SWEEPS}", "-cn", "paper", "-m", "controller=h2,hinf"])
    with pytest.raises(SystemExit) as exc:
        preflight([*sweep, "controller=hinf,foo"])
    assert exc.value.code == EXIT_CONFIG
    assert "controller=foo: unknown controller" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        preflight([*sweep, "network.width=abc"])
    err = capsys.readouterr().err
    assert "network.width=abc: Value 'abc' of type 'str' could not be converted" in err
    # a value the sweep config sweeps itself (env: cartpole,acrobot,mountaincar) with a
    # setting that breaks only one of them: found before the first job
    errors = check_overrides(["env.obs_indices=[2,3,5]"], True, "smoke", config_dir=SWEEPS)
    assert errors and all("obs_indices" in e for e in errors), errors
    with pytest.raises(SystemExit):
        preflight(["-m", "--config-dir", str(SWEEPS), "--config-name", "nope"])
    assert "Cannot find primary config 'nope'" in capsys.readouterr().err


def test_cli_refuses_a_bad_config_dir_sweep_before_any_job(tmp_path: Path):
    args = [
        "-m",
        "--config-dir",
        str(SWEEPS),
        "--config-name",
        "smoke",
        "train.lr=0",
        f"hydra.sweep.dir={tmp_path / 'multirun'}",
        f"tracking.uri=sqlite:///{tmp_path}/m.db",
    ]
    proc = run_cli("cdqn.train", args, tmp_path)
    assert proc.returncode == EXIT_CONFIG, proc.stderr[-2000:]
    assert "train.lr=0.0: the learning rate α must be > 0" in proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout
    assert not (tmp_path / "m.db").exists() and not (tmp_path / "multirun").exists()


def test_each_group_checks_its_own_keys():
    """``validate`` is each group's ``check()`` in turn: a group's problems name only its
    own keys, and together they are exactly what ``validate`` refuses."""
    conf: Config = OmegaConf.to_object(compose_config())
    assert conf.check() == []
    conf.network.width = 0
    conf.train.lr = 0.0
    conf.env.rbf_width = 0.0
    conf.controller.design = "guess"
    conf.tracking.timeout = 0.0
    conf.weights.hinf_f.w_delta = -1.0
    conf.weights.controller_target.h2.gamma_eff = [0.5, 0.1]
    groups = {
        "controller": conf.controller,
        "network": conf.network,
        "train": conf.train,
        "env": conf.env,
        "tracking": conf.tracking,
        "weights": conf.weights,
    }
    found = {name: group.check() for name, group in groups.items()}
    for name, problems in found.items():
        assert len(problems) == (2 if name == "weights" else 1), (name, problems)
        assert all(p.startswith(f"{name}.") for p in problems), (name, problems)
    assert conf.check() == [p for problems in found.values() for p in problems]
    with pytest.raises(ConfigError) as err:
        validate(conf)
    assert str(err.value).splitlines()[1:] == [f"  - {p}" for p in conf.check()]
    assert found["weights"] == [
        "weights.hinf_f.w_delta=-1.0: must be > 0",
        "weights.controller_target.h2.gamma_eff=[0.5, 0.1]: need [lower, upper] with "
        "lower <= upper",
    ]
