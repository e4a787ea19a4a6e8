"""Environments: any gymnasium id with a discrete action space.

* :mod:`cdqn.envs.adopt` — :func:`adopt`, a configuration made a run of its environment
  (name, episode cap, threshold, NTK box source), once per entry point, and
  :func:`env_presets`, the presets of ``conf/env/`` it compares with;
* :mod:`cdqn.envs.make` — :func:`make_env` (``<module>:<Id>``, ``env.kwargs``, one clear
  line per problem) and :func:`env_sizes`;
* :mod:`cdqn.envs.wrappers` — what the network sees: one-hot encoding of discrete
  observations, feature subset, scaling, radial basis features.
"""

from cdqn.config import CONF_DIR
from cdqn.envs.adopt import BOX_SOURCES, Adopted, adopt, env_presets
from cdqn.envs.make import (
    EXTRAS,
    EnvId,
    env_label,
    env_sizes,
    episode_cap,
    make_env,
    registration,
)
from cdqn.envs.wrappers import ObservationScale, ObservationSubset, OneHot, RadialFeatures

__all__ = [
    "BOX_SOURCES",
    "CONF_DIR",
    "EXTRAS",
    "Adopted",
    "EnvId",
    "ObservationScale",
    "ObservationSubset",
    "OneHot",
    "RadialFeatures",
    "adopt",
    "env_label",
    "env_presets",
    "env_sizes",
    "episode_cap",
    "make_env",
    "registration",
]
