"""The optional shaping term ``obstacle_proximity`` (``ObstacleConfig.proximity_reward``, off by default):
the formula against the column clearance on both engines, present only when switched on, counted in the
reward, and its config checks."""

from __future__ import annotations

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, ObstacleConfig, QuadSwarmEnv
from quadswarm_mj import obstacles as ob
from quadswarm_mj.rewards import env_terms

COLS = np.array([[0.0, 0.0], [2.0, -1.0], [-3.0, 2.5]])


def _cfg(scale: float, n: int = 3, **kw) -> EnvConfig:
    return EnvConfig(num_quads=n, scenario="o_random", episode_seconds=0.5,
                     obstacles=ObstacleConfig(proximity_reward=scale, proximity_falloff=0.8, **kw))


def test_clearance_is_the_centre_feature():
    """The term's clearance: the centre one of the 9 features, the xy distance to the nearest column surface."""
    m = ob.map_from_centres(ObstacleConfig(size=0.6), COLS)
    pos = np.array([[0.5, 0.0, 1.0], [2.0, -0.4, 2.0], [-3.0, 2.5, 1.0], [0.0, 0.1, 1.0]])
    clear = ob.obstacle_features(pos, m.centres, m.valid, m.radius)[..., ob.CENTRE_FEATURE]
    np.testing.assert_allclose(clear, [0.2, 0.3, -0.3, -0.2], atol=1e-12)


def test_term_formula_and_off_by_default():
    c = np.array([-0.1, 0.0, 0.4, 0.8, 3.0])
    np.testing.assert_allclose(ob.obstacle_proximity(c, 5.0, 0.8, 0.01),
                               -0.01 * 5.0 * np.array([1.125, 1.0, 0.5, 0.0, 0.0]), rtol=1e-12)
    assert "obstacle_proximity" not in env_terms(_cfg(0.0))
    assert env_terms(_cfg(2.0))[-2:] == ("obstacle_collision", "obstacle_proximity")


def _expected(term: str, cfg: EnvConfig, feats: np.ndarray, vel: np.ndarray) -> np.ndarray:
    o = cfg.obstacles
    if term == "obstacle_proximity":
        return ob.obstacle_proximity(feats[..., ob.CENTRE_FEATURE], o.proximity_reward, o.proximity_falloff,
                                     cfg.control_dt)
    return ob.obstacle_approach(feats, vel, o.approach_reward, o.proximity_falloff, cfg.control_dt)


@pytest.mark.parametrize("term", ["obstacle_proximity", "obstacle_approach"])
@pytest.mark.parametrize("engine", ["mujoco", "jax"])
def test_env_reports_the_term_of_its_state(engine, term):
    """Both shaping terms (``obstacle_approach``: tests/test_obstacle_approach.py) as the env reports them,
    against their formulas on the state it reports, and summed into the reward."""
    cfg = _cfg(4.0) if term == "obstacle_proximity" else _cfg(0.0, approach_reward=4.0)
    env = QuadSwarmEnv(cfg, engine=engine)
    start = np.array([[0.5, 0.0, 1.5], [2.0, -0.4, 1.5], [1.0, 2.0, 1.5]])  # near, near, far from a column
    vel = np.array([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, -1.0, 0.0]])  # the first two towards a column
    _, info = env.reset(seed=3, options={"obstacles": COLS, "state": {"pos": start, "vel": vel, "motors": "hover"}})
    m = ob.map_from_centres(cfg.obstacles, COLS)
    seen = 0.0
    for _ in range(10):
        _, reward, _, _, info = env.step(np.zeros((cfg.num_quads, 4)))
        got = np.asarray(info["reward_terms"][term], dtype=np.float64)
        pos, v = (np.asarray(info["state"][k], np.float64) for k in ("pos", "vel"))
        want = _expected(term, cfg, ob.obstacle_features(pos, m.centres, m.valid, m.radius), v)
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6)
        total = sum(np.asarray(x, np.float64) for x in info["reward_terms"].values())
        np.testing.assert_allclose(np.asarray(info["rewards"], np.float64), total, rtol=1e-5, atol=1e-6)
        seen += float(-got.sum())
    assert seen > 0  # the first two quads start within the falloff, moving towards a column


@pytest.mark.parametrize("kw, word", [({"proximity_reward": -1.0}, "proximity_reward"),
                                      ({"proximity_falloff": 0.0}, "proximity_falloff"),
                                      ({"proximity_falloff": float("nan")}, "proximity_falloff")])
def test_bad_values_are_refused(kw, word):
    with pytest.raises(ValueError, match=word):
        ObstacleConfig(**kw)
