"""Greedy evaluation of a trained run.

    python -m cdqn.evaluate run_id=<id> episodes=100 [seed=1000000] [tracking.uri=...]

Loads the network the run stored (artifact ``model/``) and the environment settings from its
``config.yaml``, plays ``episodes`` episodes with the greedy policy ``argmax_a Q(s, a)`` (no
exploration, no learning), episode ``i`` seeded with ``seed + i``, prints the mean ± standard
deviation of the return and logs into the same run:

- metrics ``eval_return_mean``, ``eval_return_std``, ``eval_return_min``, ``eval_return_max``
  and ``eval_episodes``, at step = the number of training episodes;
- artifact ``evaluation/returns-seed<seed>-n<episodes>.csv`` (seed, return, length per
  episode) and the tag ``eval_seed``.

Logging does not change the run's status.  Exit status 2 when the run or its store cannot be
used.
"""

from __future__ import annotations

import logging
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import hydra
import numpy as np
import yaml
from omegaconf import DictConfig, OmegaConf

from cdqn.cli import check_evaluate, start_hydra
from cdqn.config import (
    CONF_DIR,
    ConfigError,
    EnvConfig,
    EvaluateConfig,
    merged,
    register_configs,
    resolve_tracking_uri,
    to_schema,
    validate_evaluate,
)
from cdqn.records import Artifact, Tag, folder
from cdqn.records import Metric as M

if TYPE_CHECKING:  # torch, gymnasium and MLflow load when a run is evaluated, not to refuse one
    from mlflow.tracking import MlflowClient

    from cdqn.network import QNetwork

log = logging.getLogger("cdqn")
register_configs()


@dataclass
class EvalResult:
    run_id: str
    env_id: str
    seed: int
    returns: np.ndarray
    lengths: np.ndarray

    @property
    def mean(self) -> float:
        return float(np.mean(self.returns))

    @property
    def std(self) -> float:
        return float(np.std(self.returns))

    def summary(self) -> str:
        n = len(self.returns)
        return (
            f"run {self.run_id} on {self.env_id}: greedy return {self.mean:.2f} ± {self.std:.2f} "
            f"over {n} episodes (min {self.returns.min():g}, max {self.returns.max():g}; "
            f"seeds {self.seed}..{self.seed + n - 1})"
        )


def greedy_returns(
    net: QNetwork, env_cfg: EnvConfig, episodes: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Returns and lengths of ``episodes`` greedy episodes, episode ``i`` seeded ``seed + i``."""
    from cdqn.envs import make_env
    from cdqn.network import FastTwoLayer

    env = make_env(env_cfg)
    fast = FastTwoLayer(net)
    returns, lengths = np.zeros(episodes), np.zeros(episodes, dtype=np.int64)
    try:
        for i in range(episodes):
            obs, _ = env.reset(seed=seed + i)
            done = False
            while not done:
                action = int(np.argmax(fast.forward(obs).q))
                obs, reward, terminated, truncated, _ = env.step(action)
                returns[i] += float(reward)
                lengths[i] += 1
                done = terminated or truncated
    finally:
        env.close()
    return returns, lengths


def evaluate(cfg: EvaluateConfig) -> EvalResult:
    """Evaluate run ``cfg.run_id`` (module docstring); log to the run when ``cfg.log``."""
    validate_evaluate(cfg)
    from mlflow.exceptions import MlflowException
    from mlflow.tracking import MlflowClient

    from cdqn.network import load_network
    from cdqn.training.tracking import TrackingError, check_tracking

    uri = resolve_tracking_uri(cfg.tracking.uri)
    check_tracking(uri, cfg.tracking.timeout)
    client = MlflowClient(uri)
    try:
        run = client.get_run(cfg.run_id)
    except MlflowException:
        raise TrackingError(f"run_id={cfg.run_id}: no such run in tracking.uri={uri!r}") from None
    if run.info.status != "FINISHED":
        log.warning(
            "run %s is %s; evaluating the network it stored last", cfg.run_id, run.info.status
        )
    with tempfile.TemporaryDirectory() as tmp:
        try:
            model_dir = client.download_artifacts(cfg.run_id, folder(Artifact.MODEL), tmp)
            net = load_network(Path(model_dir))
        except Exception as err:
            raise ConfigError(
                f"run_id={cfg.run_id}: the run has no usable model/ artifact ({err}); was it "
                "trained with tracking.log_model=true?"
            ) from None
        env_cfg = _env_config(client, cfg.run_id, Path(tmp))
    returns, lengths = greedy_returns(net, env_cfg, cfg.episodes, cfg.seed)
    result = EvalResult(cfg.run_id, env_cfg.id, cfg.seed, returns, lengths)
    if cfg.log:
        _log(client, result, run.data.params)
    return result


def _env_config(client: MlflowClient, run_id: str, tmp: Path) -> EnvConfig:
    """The environment the run trained on: the ``env`` of its ``config.yaml`` as stored
    (adopted when the run started: id with its module, ``env.kwargs``, cap), else rebuilt
    from its params."""
    from cdqn.training.tracking import CONFIG_ARTIFACT

    try:
        path = client.download_artifacts(run_id, CONFIG_ARTIFACT, str(tmp))
        stored = OmegaConf.load(path)
        env = merged(OmegaConf.structured(EnvConfig), stored.env)
        return to_schema(env, EnvConfig)
    except Exception:
        params = client.get_run(run_id).data.params
        if "env.id" not in params:
            raise ConfigError(
                f"run_id={run_id}: neither {CONFIG_ARTIFACT} nor env.* params; not a cdqn run"
            ) from None
        steps = params.get("env.max_episode_steps", "None")
        indices = params.get("env.obs_indices", "None")
        prefix = "env.kwargs."
        kwargs = {
            k[len(prefix) :]: yaml.safe_load(v) for k, v in params.items() if k.startswith(prefix)
        }
        return EnvConfig(
            id=params["env.id"],
            kwargs=kwargs,
            max_episode_steps=None if steps == "None" else int(steps),
            obs_indices=None if indices in ("None", "null") else list(OmegaConf.create(indices)),
        )


def _log(client: MlflowClient, result: EvalResult, params: dict[str, str]) -> None:
    import pandas as pd
    from mlflow.entities import Metric, RunTag

    step = int(params.get("train.episodes", "0"))
    ts = int(time.time() * 1000)
    values = {
        M.EVAL_RETURN_MEAN: result.mean,
        M.EVAL_RETURN_STD: result.std,
        M.EVAL_RETURN_MIN: float(result.returns.min()),
        M.EVAL_RETURN_MAX: float(result.returns.max()),
        M.EVAL_EPISODES: float(len(result.returns)),
    }
    client.log_batch(
        result.run_id,
        metrics=[Metric(k, v, ts, step) for k, v in values.items()],
        tags=[RunTag(Tag.EVAL_SEED, str(result.seed))],
    )
    n = len(result.returns)
    frame = pd.DataFrame(
        {
            "seed": result.seed + np.arange(n),
            "return": result.returns,
            "length": result.lengths,
        }
    )
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"returns-seed{result.seed}-n{n}.csv"
        frame.to_csv(path, index=False)
        client.log_artifact(result.run_id, str(path), folder(Artifact.EVALUATION))


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="evaluate")
def main(cfg: DictConfig) -> float:
    conf = to_schema(cfg, EvaluateConfig)
    try:
        result = evaluate(conf)
    except ConfigError as err:
        log.error("%s", err)
        sys.exit(2)
    print(result.summary(), flush=True)
    return result.mean


if __name__ == "__main__":
    start_hydra(main, "evaluate", check_evaluate)
