"""``ObstacleConfig.pos_around_columns``: the reward's ``pos`` cost as the path length around the nearest
column (:func:`quadswarm_mj.obstacles.around_distance`): the geometry, its continuity, NumPy == jit, both
engines' ``pos`` term, the metrics' straight distance, and the config check."""

from __future__ import annotations

import math

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, ObstacleConfig, QuadSwarmEnv
from quadswarm_mj import obstacles as ob

COLS = np.array([[0.0, 0.0], [5.0, 5.0]])
VALID = np.array([True, True])
RADIUS = np.array(0.3)


def _around(pos, goals, valid=VALID):
    return ob.around_distance(np.asarray(pos, float), np.asarray(goals, float), COLS, valid, RADIUS)


def test_path_around_a_blocking_column():
    r = 0.3 + ob.AROUND_MARGIN
    behind = 2 * math.sqrt(1 - r * r) + r * (math.pi - 2 * math.acos(r))  # tangent, arc, tangent
    got = _around([[-1, 0, 1], [-1, 1, 1], [-1, 0, 1]], [[1, 0, 1], [1, 1, 1], [1, 0, 3]])
    np.testing.assert_allclose(got, [behind, 2.0, math.hypot(behind, 2.0)], rtol=1e-12)
    assert behind > 2.0
    no_columns = _around([[-1, 0, 1]], [[1, 0, 1]], valid=np.array([False, False]))
    np.testing.assert_allclose(no_columns, [2.0], rtol=1e-12)


def test_continuous_where_the_segment_touches_the_circle():
    """Moving the segment sideways across the circle's edge: no jump at the edge (blocked on one side)."""
    r = 0.3 + ob.AROUND_MARGIN
    ys = r + np.array([-1e-6, 1e-6])
    pos = np.stack([np.full(2, -1.0), ys, np.ones(2)], axis=-1)
    goals = np.stack([np.full(2, 1.0), ys, np.ones(2)], axis=-1)
    got = _around(pos, goals)
    np.testing.assert_allclose(got, [2.0, 2.0], atol=1e-5)


def test_never_shorter_than_straight_and_finite():
    rng = np.random.default_rng(2)
    pos = np.concatenate([rng.uniform(-2, 2, (256, 2)), rng.uniform(0, 3, (256, 1))], axis=-1)
    goals = np.concatenate([rng.uniform(-2, 2, (256, 2)), rng.uniform(0, 3, (256, 1))], axis=-1)
    got = _around(pos, goals)
    assert np.isfinite(got).all()
    assert (got >= np.linalg.norm(goals - pos, axis=-1) - 1e-12).all()
    assert (got > np.linalg.norm(goals - pos, axis=-1) + 1e-3).any()


def test_numpy_equals_jit():
    jax = pytest.importorskip("jax")
    rng = np.random.default_rng(3)
    pos = np.concatenate([rng.uniform(-2, 2, (4, 8, 2)), np.ones((4, 8, 1))], axis=-1)
    goals = np.concatenate([rng.uniform(-2, 2, (4, 8, 2)), np.ones((4, 8, 1)) * 2], axis=-1)
    cols = np.broadcast_to(COLS, (4, 2, 2))
    valid, radius = np.broadcast_to(VALID, (4, 2)), np.full(4, 0.3)
    ref = ob.around_distance(pos, goals, cols, valid, radius)
    f = jax.jit(ob.around_distance)
    got = f(*(np.asarray(x, np.float32) for x in (pos, goals, cols)), valid, radius.astype(np.float32))
    np.testing.assert_allclose(np.asarray(got), ref, rtol=2e-5, atol=2e-5)


@pytest.mark.parametrize("engine", ["mujoco", "jax"])
def test_env_pos_term_uses_the_path_around(engine):
    cfg = EnvConfig(num_quads=2, scenario="o_random", episode_seconds=0.5,
                    obstacles=ObstacleConfig(pos_around_columns=True))
    env = QuadSwarmEnv(cfg, engine=engine)
    start = np.array([[-1.0, 0.0, 1.5], [-1.0, 2.0, 1.5]])
    goals = np.array([[1.0, 0.0, 1.5], [1.0, 2.0, 1.5]])  # the first behind the column at the origin, the second not
    _, info = env.reset(seed=1, options={"obstacles": COLS,
                                         "state": {"pos": start, "goals": goals, "motors": "hover"}})
    m = ob.map_from_centres(cfg.obstacles, COLS)
    for _ in range(5):
        _, _, _, _, info = env.step(np.zeros((2, 4)))
        pos, goals = np.asarray(info["state"]["pos"], np.float64), np.asarray(info["goals"], np.float64)
        around = ob.around_distance(pos, goals, m.centres, m.valid, m.radius)
        got = np.asarray(info["reward_terms"]["pos"], np.float64)
        np.testing.assert_allclose(got, -cfg.sim_dt * cfg.rewards.pos * around, rtol=1e-5, atol=1e-7)
        straight = np.linalg.norm(goals - pos, axis=-1)
        assert around[0] > straight[0] + 0.1 and abs(around[1] - straight[1]) < 1e-9  # detour for the first only
    np.testing.assert_allclose(goals, [[1.0, 0.0, 1.5], [1.0, 2.0, 1.5]], atol=1e-6)  # o_random kept them


def test_config_must_be_a_bool():
    with pytest.raises(ValueError, match="pos_around_columns"):
        ObstacleConfig(pos_around_columns=1)
