"""``env.normalize`` and ``env.normalize_scale``: each bounded feature mapped affinely to
[−1, 1] or to [−w, w], on the real gymnasium environments."""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf

from cdqn.config import Config, ConfigError
from cdqn.envs import make_env
from tests.conftest import compose_config


def _env(*overrides: str):
    conf: Config = OmegaConf.to_object(compose_config(list(overrides)))
    return make_env(conf.env)


def test_normalize_maps_each_bound_to_plus_minus_one() -> None:
    env = _env("env=mountaincar", "env.normalize=true", "env.rbf_centres=null")
    raw = env.unwrapped.observation_space
    np.testing.assert_allclose(env.observation(raw.low), [-1.0, -1.0], atol=1e-6)
    np.testing.assert_allclose(env.observation(raw.high), [1.0, 1.0], atol=1e-6)
    env.close()


def test_normalize_scale_gives_each_feature_its_half_width() -> None:
    widths = [1.0, 1.0, 1.0, 1.0, 2.0, 2.0]
    env = _env("env=acrobot", f"env.normalize_scale={widths}")
    raw = env.unwrapped.observation_space
    np.testing.assert_allclose(env.observation(raw.high), widths, atol=1e-6)
    np.testing.assert_allclose(env.observation(raw.low), [-w for w in widths], atol=1e-6)
    np.testing.assert_allclose(env.observation_space.high, widths)
    plain = _env("env=acrobot", "env.normalize_scale=null")
    obs, _ = env.reset(seed=3)
    ref, _ = plain.reset(seed=3)
    for _ in range(50):  # the same trajectory, the velocities doubled
        np.testing.assert_allclose(obs, ref * np.array(widths), rtol=1e-6, atol=1e-7)
        obs, *_ = env.step(1)
        ref, *_ = plain.step(1)
    env.close()
    plain.close()


@pytest.mark.parametrize("widths", ["[1,1]", "[1,1,1,1,0,2]"])
def test_a_wrong_normalize_scale_is_refused_naming_the_key(widths: str) -> None:
    with pytest.raises(ConfigError, match=r"env\.normalize_scale=.*6 half-widths > 0"):
        _env("env=acrobot", f"env.normalize_scale={widths}")


def test_radial_features_are_gaussians_on_a_grid_over_the_scaled_box() -> None:
    env = _env("env=mountaincar", "env.rbf_centres=5", "env.rbf_width=1.0")
    assert env.observation_space.shape == (25,)
    np.testing.assert_allclose(env.centres[[0, 4, 24]], [[-1, -1], [-1, 1], [1, 1]])
    np.testing.assert_allclose(env.sigma, [0.5, 0.5])  # one grid spacing on [-1, 1]
    phi = env.observation(np.array([1.0, 1.0], np.float32))  # at the last centre
    assert phi[24] == pytest.approx(1.0)
    assert phi[23] == pytest.approx(np.exp(-0.5))  # one spacing away
    assert phi[0] == pytest.approx(np.exp(-0.5 * 2 * 16))  # four spacings in both features
    obs, _ = env.reset(seed=2)
    ref, _ = _env("env=mountaincar", "env.rbf_centres=null").reset(seed=2)  # in [-1, 1]
    np.testing.assert_array_equal(obs, env.features(ref[None])[0])
    for _ in range(20):
        obs, *_ = env.step(2)
        assert obs.shape == (25,) and 0.0 < obs.max() <= 1.0
    env.close()


def test_radial_features_need_finite_bounds_and_a_modest_count() -> None:
    with pytest.raises(ConfigError, match=r"env\.rbf_centres=6: observed features \[1, 3\]"):
        _env("env=cartpole", "env.rbf_centres=6")
    env = _env("env=cartpole", "env.obs_indices=[0,2]", "env.rbf_centres=6")  # bounded ones
    assert env.observation_space.shape == (36,)
    env.close()
    with pytest.raises(ConfigError, match=r"env\.rbf_centres=5: 5\^6 = 15625 features"):
        _env("env=acrobot", "env.rbf_centres=5")
