"""The preset a study writes for its best trial: what ``python -m cdqn.train`` needs to
train that agent again as it was tuned."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from cdqn.config import CONF_DIR, ConfigError

ENV_KEYS = ("name", "id", "kwargs", "max_episode_steps", "obs_indices", "normalize",
            "normalize_scale", "rbf_centres", "rbf_width", "solve_threshold", "eps_dec",
            "eps_schedule")  # fmt: skip
"""The environment settings a preset carries (cap, threshold, kwargs, observation maps,
exploration): a preset trains the environment it was tuned on, as it was tuned."""
TRAIN_KEYS = ("episodes", "lr", "discount", "eps_start", "eps_end", "eps_dec", "eps_schedule")
"""The training settings a preset carries: the episodes per member the study trained (its
per-episode ε schedule is fitted to them), α and exploration; trained with the preset on the
evaluation's seeds, it repeats the study's evaluation."""
NETWORK_KEYS = ("width", "dtype")
"""The network a preset carries: its design's NTK box was measured on that network, and its
α and exploration were tuned on it."""
DDQN_KEYS = ("train_freq", "batch_size", "buffer_size", "learning_starts", "discount")
"""Double DQN's controller settings a preset carries."""


def specification_of(
    name: str, preset_dir: str | Path
) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    """The best specification of the preset ``name`` and the space it was searched in
    (``extra.tuned.specification``, ``extra.tuned.space``), from
    ``<preset_dir>/weights/<name>.yaml`` or else the shipped ``conf/weights/<name>.yaml``;
    :class:`~cdqn.config.ConfigError` when neither holds them."""
    path = _preset_file(name, preset_dir)
    tuned = OmegaConf.select(OmegaConf.load(path), "extra.tuned")
    tuned = OmegaConf.to_container(tuned) if OmegaConf.is_dict(tuned) else None
    if not isinstance(tuned, dict) or not isinstance(tuned.get("specification"), dict):
        raise ConfigError(f"{path} is no tuned preset (no extra.tuned.specification)")
    return tuned["specification"], tuned.get("space") or {}


def preset_settings(name: str, preset_dir: str | Path, paths: dict[str, str]) -> dict[str, Any]:
    """The values the preset ``name`` sets at ``paths`` (dimension name → configuration
    path), for the dimensions its study did not search: a warm start keeps them as the
    preset trained them (e.g. ``train.eps_end``).  Paths the preset does not set are left
    out."""
    preset = OmegaConf.load(_preset_file(name, preset_dir))
    out: dict[str, Any] = {}
    for dim, path in paths.items():
        value = OmegaConf.select(preset, path, default=None)
        if value is not None and not OmegaConf.is_config(value):
            out[dim] = value
    return out


def _preset_file(name: str, preset_dir: str | Path) -> Path:
    """``<preset_dir>/weights/<name>.yaml`` or else the shipped ``conf/weights/<name>.yaml``."""
    folders = [Path(preset_dir) / "weights", CONF_DIR / "weights"]
    for folder in folders:
        if (folder / f"{name}.yaml").is_file():
            return folder / f"{name}.yaml"
    raise ConfigError(f"no preset {name}.yaml in {' or '.join(map(str, folders))}")


def write_preset(cfg: DictConfig, name: str, folder: Path, best: Any, tune: Any) -> Path:
    """``<folder>/weights/<name>.yaml``: the best trial's configuration as a weights preset in
    Hydra's global package, so that ``weights=<name>`` sets, besides the ``weights`` group,
    the environment (id, kwargs, cap, threshold, observation maps, exploration), the episodes
    per member, α, the network's width and data type and, for Double DQN, its controller
    settings; a controlled agent's preset keeps the NTK box its design was certified on
    (``controller.synthesis.ntk_bounds=config``).
    ``extra.tuned`` records the study, the id it was tuned on, its budget and its search space
    (on another id, :func:`cdqn.envs.adopt` gives way to that id's settings)."""
    plain = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(plain, dict)
    weights = dict(plain["weights"], name=name)
    env = {k: plain["env"][k] for k in ENV_KEYS if k in plain["env"]}
    train = {k: plain["train"][k] for k in TRAIN_KEYS}
    network = {k: plain["network"][k] for k in NETWORK_KEYS}
    controller: dict[str, Any] = {}
    agent = str(plain["controller"]["name"])
    if agent == "ddqn":
        controller = {k: plain["controller"][k] for k in DDQN_KEYS}
    else:
        controller = {"synthesis": {"ntk_bounds": plain["controller"]["synthesis"]["ntk_bounds"]}}
    tuned = {
        "study": tune.study, "env_id": env["id"], "agent": agent, "trial": best.number,
        "objective": best.value,
        "budget": {"trials": tune.trials, "seeds": tune.seeds, "first_seed": tune.seed,
                   "episodes": int(plain["train"]["episodes"])},
        "space": {k: {f: v for f, v in asdict(p).items() if v not in (None, False)}
                  for k, p in tune.space.items()},
        "specification": best.params,
    }  # fmt: skip
    preset = {"weights": weights, "env": env, "train": train, "network": network,
              "controller": controller, "extra": {"tuned": tuned}}  # fmt: skip
    out = folder / "weights" / f"{name}.yaml"
    out.parent.mkdir(parents=True, exist_ok=True)
    header = [
        "# @package _global_",
        f"# Written by python -m cdqn.tune (study {tune.study!r}, trial {best.number}, "
        f"objective {best.value:.4g}) for {agent} on {env['id']}.",
        f"# Train with: python -m cdqn.train controller={agent} weights={name} "
        f"hydra.searchpath=[file://{folder.resolve()}]",
        f"# Specification: {json.dumps(best.params)}",
    ]
    out.write_text("\n".join(header) + "\n" + OmegaConf.to_yaml(OmegaConf.create(preset)))
    return out
