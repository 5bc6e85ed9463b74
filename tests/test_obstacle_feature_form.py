"""``ObstacleConfig.feature_form="slopes"``: the 9 column features as the centre distance and 8 slopes."""

import numpy as np
import pytest

from quadswarm_mj import QuadSwarmEnv
from quadswarm_mj.config import EnvConfig, ObstacleConfig
from quadswarm_mj.obstacles import CENTRE_FEATURE, SDF_RESOLUTION, observed_features, obstacle_features

OBST = {"density": 0.2, "size": 0.6}


def _random_features(seed: int, batch: int = 64) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-4.0, 4.0, (batch, 8, 3))
    centres = rng.uniform(-4.0, 4.0, (batch, 12, 2))
    valid = rng.random((batch, 12)) < 0.7
    return obstacle_features(pos, centres, valid, np.full(batch, 0.3))


def test_slopes_are_the_centre_and_the_differences_per_grid_step():
    f = _random_features(0)
    s = observed_features(f, "slopes")
    assert s.shape == f.shape
    np.testing.assert_array_equal(s[..., CENTRE_FEATURE], f[..., CENTRE_FEATURE])
    others = [k for k in range(9) if k != CENTRE_FEATURE]
    np.testing.assert_allclose(s[..., others], (f[..., others] - f[..., CENTRE_FEATURE:CENTRE_FEATURE + 1])
                               / SDF_RESOLUTION)
    # invertible: the grid comes back
    back = s[..., others] * SDF_RESOLUTION + s[..., CENTRE_FEATURE:CENTRE_FEATURE + 1]
    np.testing.assert_allclose(back, f[..., others], atol=1e-12)
    assert observed_features(f, "grid") is f


def test_slopes_stay_within_their_bounds():
    """The distance to the nearest column is 1-Lipschitz, so a slope over a 0.1 m or 0.14 m offset
    is within +-sqrt(2); the bound of the observation is 1.5."""
    for seed in range(5):
        s = observed_features(_random_features(seed), "slopes")
        others = [k for k in range(9) if k != CENTRE_FEATURE]
        assert np.abs(s[..., others]).max() <= np.sqrt(2) + 1e-9


def test_slopes_numpy_equals_jit():
    jax = pytest.importorskip("jax")
    f = _random_features(1).astype(np.float32)
    got = jax.jit(lambda x: observed_features(x, "slopes"))(f)
    np.testing.assert_allclose(np.asarray(got), observed_features(f, "slopes"), rtol=1e-6, atol=1e-6)


def test_env_observes_slopes_in_place_of_the_grid():
    grid = QuadSwarmEnv(EnvConfig(num_quads=2, obstacles=ObstacleConfig(**OBST)))
    slopes = QuadSwarmEnv(EnvConfig(num_quads=2, obstacles=ObstacleConfig(**OBST, feature_form="slopes")))
    assert grid.observation_space.shape == slopes.observation_space.shape
    og, _ = grid.reset(seed=3)
    os_, _ = slopes.reset(seed=3)
    tail = slice(og.shape[-1] - 9, og.shape[-1])
    np.testing.assert_array_equal(og[..., :tail.start], os_[..., :tail.start])
    np.testing.assert_allclose(os_[..., tail], observed_features(og[..., tail].astype(np.float64), "slopes"),
                               rtol=1e-5, atol=1e-5)
    for _ in range(20):
        a = grid.action_space.sample()
        og, *_ = grid.step(a)
        os_, *_ = slopes.step(a)
        assert slopes.observation_space.contains(os_)
    hi = slopes.observation_space.high[..., tail]
    assert np.isclose(hi[..., CENTRE_FEATURE], grid.observation_space.high[..., tail][..., CENTRE_FEATURE]).all()
    assert np.allclose(np.delete(hi, CENTRE_FEATURE, axis=-1), 1.5)


def test_unknown_feature_form_names_the_field():
    with pytest.raises(ValueError, match=r"obstacles.feature_form must be one of \('grid', 'slopes'\)"):
        ObstacleConfig(feature_form="sdf")
