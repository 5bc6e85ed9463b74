"""The optional shaping term ``obstacle_approach`` (``ObstacleConfig.approach_reward``, off by default): the
speed towards the nearest column within the falloff, zero for motion around or away from it; on both
engines (the env test: tests/test_obstacle_proximity.py), present only when switched on, NumPy == jit,
and its config check."""

from __future__ import annotations

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, ObstacleConfig
from quadswarm_mj import obstacles as ob
from quadswarm_mj.rewards import env_terms

COLS = np.array([[0.0, 0.0], [2.0, -1.0], [-3.0, 2.5]])


def _cfg(scale: float, n: int = 3, **kw) -> EnvConfig:
    return EnvConfig(num_quads=n, scenario="o_random", episode_seconds=0.5,
                     obstacles=ObstacleConfig(approach_reward=scale, proximity_falloff=0.8, **kw))


def _features(pos: np.ndarray) -> np.ndarray:
    m = ob.map_from_centres(ObstacleConfig(size=0.6), COLS)
    return ob.obstacle_features(pos, m.centres, m.valid, m.radius)


def test_speed_towards_the_column_within_the_falloff():
    """Quad 0.2 m from the surface of the column at the origin (+x side), falloff 0.8 m: moving in -x at
    1 m/s costs 1 m/s x (1 - 0.2 / 0.8); along y (around it), in +x (away) or up costs nothing; a quad
    beyond the falloff costs nothing whatever its velocity."""
    pos = np.array([[0.5, 0.0, 1.0]] * 5 + [[1.5, 0.0, 1.0]])
    vel = np.array([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -2.0], [-2.0, 2.0, 0.0],
                    [-3.0, 0.0, 0.0]])
    got = ob.obstacle_approach(_features(pos), vel, 5.0, 0.8, 0.01)
    want = -0.01 * 5.0 * np.array([1.0, 0.0, 0.0, 0.0, 2.0, 0.0]) * 0.75
    np.testing.assert_allclose(got, want, rtol=2e-3, atol=1e-12)  # the grid's central difference of |x|


def test_numpy_equals_jit():
    jax = pytest.importorskip("jax")
    rng = np.random.default_rng(1)
    pos = np.concatenate([rng.uniform(-1, 1, (16, 2)), np.ones((16, 1))], axis=-1)
    vel = rng.normal(size=(16, 3))
    f = _features(pos)
    ref = ob.obstacle_approach(f, vel, 3.0, 0.8, 0.01)
    got = jax.jit(lambda a, b: ob.obstacle_approach(a, b, 3.0, 0.8, 0.01))(f.astype(np.float32), vel.astype(np.float32))
    np.testing.assert_allclose(np.asarray(got), ref, rtol=1e-4, atol=1e-6)
    assert (ref < 0).any() and (ref == 0).any()


def test_off_by_default_and_listed_when_on():
    assert "obstacle_approach" not in env_terms(_cfg(0.0))
    assert env_terms(_cfg(2.0))[-2:] == ("obstacle_collision", "obstacle_approach")
    both = EnvConfig(num_quads=2, scenario="o_random",
                     obstacles=ObstacleConfig(approach_reward=1.0, proximity_reward=1.0))
    assert env_terms(both)[-3:] == ("obstacle_collision", "obstacle_proximity", "obstacle_approach")


@pytest.mark.parametrize("bad", [-1.0, float("nan")])
def test_bad_values_are_refused(bad):
    with pytest.raises(ValueError, match="approach_reward"):
        ObstacleConfig(approach_reward=bad)
