"""Hydra entry point: compose the config, build env, network, controller and agent,
train, record to MLflow.

    python -m cdqn.train                                   # env=cartpole controller=hinf
    python -m cdqn.train env=acrobot controller=hinf_f seed=3 train.episodes=500
    python -m cdqn.train -m controller=h2,hinf,hinf_f,ddqn seed='range(10)'
"""

from __future__ import annotations

import logging
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import hydra
import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from cdqn.agents import make_agent
from cdqn.config import Config, ConfigError, register_configs, validate
from cdqn.control.factory import make_controller
from cdqn.envs import env_sizes, make_env
from cdqn.network import NetworkSpec, QNetwork, save_network
from cdqn.signals import SignalBuffer
from cdqn.tracking import Recorder, flatten, git_commit
from cdqn.trainer import DivergenceError, EpisodeStats, TrainState, train

log = logging.getLogger("cdqn")
register_configs()


@dataclass
class RunResult:
    run_id: str
    status: str
    final_score: float
    """Mean return of the last 100 episodes."""


def resolve_tracking_uri(uri: str) -> str:
    """Make a relative ``sqlite:///`` or plain-path store absolute (stable across launchers)."""
    if uri.startswith("sqlite:///") and not uri.startswith("sqlite:////"):
        return "sqlite:///" + str(Path(uri[len("sqlite:///") :]).resolve())
    if "://" not in uri and not uri.startswith("file:"):
        return Path(uri).resolve().as_uri()
    return uri


def run(cfg: DictConfig, progress: bool = True) -> RunResult:
    """Train one configuration and record it as one MLflow run."""
    conf: Config = OmegaConf.to_object(cfg)  # type: ignore[assignment]
    validate(conf)
    env = make_env(conf.env)
    n_obs, n_actions = env_sizes(env)
    setup = make_controller(conf.controller, conf.weights, conf.train.discount, conf.train.lr)

    torch.manual_seed(conf.seed)
    rng = np.random.default_rng(conf.seed)
    net = QNetwork(NetworkSpec(n_obs, n_actions, conf.network.width, conf.network.dtype))
    agent = make_agent(conf.controller, conf.train, net, setup, rng)

    params = flatten(OmegaConf.to_container(cfg, resolve=True))  # type: ignore[arg-type]
    tags = {
        "env": conf.env.name,
        "env_id": conf.env.id,
        "controller": conf.controller.name,
        "seed": str(conf.seed),
        "git_commit": git_commit(),
        "design_source": setup.source,
    }
    recorder = Recorder.start(
        resolve_tracking_uri(conf.tracking.uri),
        conf.tracking.experiment,
        f"{conf.env.name}-{conf.controller.name}-s{conf.seed}",
        params,
        tags,
    )
    if setup.design:
        recorder.log_dict(setup.design, "design/controller.json")
    if setup.artifacts is not None:
        recorder.log_dir(setup.artifacts, "design")
    log.info(
        "MLflow run %s (%s, %s, seed %d)",
        recorder.run_id,
        conf.env.name,
        conf.controller.name,
        conf.seed,
    )

    signals = SignalBuffer()
    state = TrainState()

    def on_episode(stats: EpisodeStats, _: TrainState) -> None:
        recorder.log_episode(stats)

    status, reason = "FINISHED", None
    try:
        train(
            env,
            agent,
            episodes=conf.train.episodes,
            seed=conf.seed,
            discount=conf.train.discount,
            q_limit=conf.train.q_limit,
            signals=signals,
            state=state,
            on_episode=on_episode,
            progress=progress and conf.train.progress,
            desc=f"{conf.env.name}/{conf.controller.name}/s{conf.seed}",
        )
    except DivergenceError as err:
        status, reason = "FAILED", f"diverged: {err}"
        log.error("run %s diverged: %s", recorder.run_id, err)
    except KeyboardInterrupt:
        status, reason = "KILLED", "interrupted"
        raise
    except Exception as err:
        status, reason = "FAILED", f"{type(err).__name__}: {err}"
        raise
    finally:
        if conf.train.signals:
            recorder.log_signals(signals, conf.train.lr)
        if conf.tracking.log_model:
            with tempfile.TemporaryDirectory() as tmp:
                save_network(net, Path(tmp))
                recorder.log_dir(Path(tmp), "model")
        recorder.finish(status, reason)
        env.close()
    score = float(np.mean(state.returns[-100:])) if state.returns else float("nan")
    return RunResult(recorder.run_id, status, score)


def _is_multirun() -> bool:
    try:
        return HydraConfig.get().mode == RunMode.MULTIRUN
    except ValueError:
        return False


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> float:
    try:
        result = run(cfg, progress=not _is_multirun() and sys.stderr.isatty())
    except ConfigError as err:
        log.error("%s", err)
        if not _is_multirun():
            sys.exit(2)
        return float("nan")
    return result.final_score


if __name__ == "__main__":
    main()
