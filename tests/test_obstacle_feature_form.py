"""``ObstacleConfig.feature_form``: the 9 column features as the centre distance and 8 slopes ("slopes"), or as a
bounded local proximity and its weighted slopes ("near")."""

import numpy as np
import pytest

from quadswarm_mj import QuadSwarmEnv
from quadswarm_mj.config import EnvConfig, ObstacleConfig
from quadswarm_mj.obstacles import (
    CENTRE_FEATURE,
    NEAR_MAX,
    NEAR_RANGE,
    SDF_RESOLUTION,
    observed_features,
    obstacle_features,
)

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


@pytest.mark.parametrize("form", ["slopes", "near"])
def test_feature_form_numpy_equals_jit(form):
    jax = pytest.importorskip("jax")
    f = _random_features(1).astype(np.float32)
    got = jax.jit(lambda x: observed_features(x, form))(f)
    np.testing.assert_allclose(np.asarray(got), observed_features(f, form), rtol=1e-6, atol=1e-6)


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
    with pytest.raises(ValueError, match=r"obstacles.feature_form must be one of \('grid', 'slopes', 'near'\)"):
        ObstacleConfig(feature_form="sdf")


def test_near_is_zero_in_open_space_and_the_weighted_slopes_near_a_column():
    f = _random_features(2)
    n, s = observed_features(f, "near"), observed_features(f, "slopes")
    d = f[..., CENTRE_FEATURE]
    w = np.clip(1.0 - d / NEAR_RANGE, 0.0, NEAR_MAX)
    np.testing.assert_allclose(n[..., CENTRE_FEATURE], w)
    others = [k for k in range(9) if k != CENTRE_FEATURE]
    np.testing.assert_allclose(n[..., others], s[..., others] * w[..., None])
    far = d >= NEAR_RANGE
    assert far.any() and (~far).any()
    assert not n[far].any()  # all 9 exactly 0 beyond 1 m of the nearest surface
    # one column 0.4 m from the quad's centre to its surface along +x: proximity 0.6, slope towards it negative in x
    one = obstacle_features(np.array([[0.0, 0.0, 1.0]]), np.array([[0.7, 0.0]]), np.array([True]), np.array(0.3))
    got = observed_features(one, "near")[0]
    assert got[CENTRE_FEATURE] == pytest.approx(0.6)
    assert got[7] == pytest.approx(-0.6) and got[1] == pytest.approx(0.6)  # (x+0.1, y) nearer, (x-0.1, y) farther
    # no column at all: nothing seen
    none = obstacle_features(np.zeros((1, 3)), np.zeros((1, 2)), np.array([False]), np.array(0.3))
    assert not observed_features(none, "near").any()


def test_env_observes_near_within_its_bounds():
    env = QuadSwarmEnv(EnvConfig(num_quads=4, obstacles=ObstacleConfig(**OBST, feature_form="near")))
    obs, _ = env.reset(seed=5)
    tail = slice(obs.shape[-1] - 9, obs.shape[-1])
    hi = env.observation_space.high[..., tail]
    assert np.allclose(hi[..., CENTRE_FEATURE], NEAR_MAX)
    assert np.allclose(np.delete(hi, CENTRE_FEATURE, axis=-1), 1.5 * NEAR_MAX)
    for _ in range(30):
        obs, *_ = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs)
        assert (obs[..., tail][..., CENTRE_FEATURE] >= 0).all()
