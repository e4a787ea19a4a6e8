"""The environment presets shipped in ``conf/env/`` (``cartpole``, ``acrobot``, ...)."""

from __future__ import annotations

import functools
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from cdqn.config import CONF_DIR, EnvConfig


@functools.lru_cache(maxsize=4)
def env_presets(conf_dir: Path = CONF_DIR) -> dict[str, EnvConfig]:
    """The environment presets of ``conf_dir/env/*.yaml`` by their ``name``."""
    folder = conf_dir / "env"

    def load(stem: str) -> DictConfig:
        node = OmegaConf.load(folder / f"{stem}.yaml")
        assert isinstance(node, DictConfig)
        bases = [d for d in node.pop("defaults", []) if d != "_self_"]
        return OmegaConf.merge(*[load(b) for b in bases], node)

    out: dict[str, EnvConfig] = {}
    for path in sorted(folder.glob("*.yaml")):
        preset = OmegaConf.merge(OmegaConf.structured(EnvConfig), load(path.stem))
        env: EnvConfig = OmegaConf.to_object(preset)
        out[env.name] = env
    return out
