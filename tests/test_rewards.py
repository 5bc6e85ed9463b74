"""Reward time scaling as the original (SPEC §8): state terms x sim_dt, proximity x control_dt,
event terms (collisions, floor/wall/ceiling hits) not time-scaled."""

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, QuadSwarmEnv
from quadswarm_mj.rewards import (
    CONTROL_DT_TERMS,
    EVENT_TERMS,
    OBSTACLE_TERMS,
    STATE_TERMS,
    TERMS,
    reward_terms,
    term_dt,
)


def _terms(cfg, pos, goals, new_contact=None, action=None, hit_floor=None):
    n = pos.shape[0]
    z = np.zeros((n, 3))
    R = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    f = np.zeros((n, 4))
    nof = np.zeros(n, bool)
    new = np.zeros((n, n), bool) if new_contact is None else new_contact
    a = np.zeros((n, 4)) if action is None else action
    dist = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    return reward_terms(cfg, pos, z, R, z, goals, a, f, f, nof, nof if hit_floor is None else hit_floor, nof, nof,
                        new, dist)


def test_every_term_has_one_time_scaling():
    groups = (set(STATE_TERMS), set(CONTROL_DT_TERMS), set(EVENT_TERMS))
    every = set(TERMS) | set(OBSTACLE_TERMS)
    assert set().union(*groups) == every and sum(len(g) for g in groups) == len(every)  # one scaling each
    cfg = EnvConfig()
    assert term_dt(cfg, "pos") == 0.005 and term_dt(cfg, "proximity") == 0.01 and term_dt(cfg, "quad_collision") == 1.0
    assert term_dt(cfg, "obstacle_proximity") == 0.01 and term_dt(cfg, "obstacle_collision") == 1.0
    with pytest.raises(ValueError, match="unknown reward term 'nope'"):
        term_dt(cfg, "nope")


def test_one_step_one_metre_from_goal_costs_0_005():
    cfg = EnvConfig(num_quads=1)
    t = _terms(cfg, np.array([[0.0, 0, 2]]), np.array([[1.0, 0, 2]]))
    assert t["pos"][0] == -0.005
    # the factor is the simulation step: twice the physics rate halves the state terms
    t = _terms(cfg.replace(sim_hz=400), np.array([[0.0, 0, 2]]), np.array([[1.0, 0, 2]]))
    assert t["pos"][0] == -0.0025
    t = _terms(cfg, np.array([[0.0, 0, 2]]), np.array([[0.0, 0, 2]]), action=np.ones((1, 4)))
    assert t["effort"][0] == pytest.approx(-0.005 * 0.05 * 2.0, rel=1e-12)  # ||a|| = 2


def test_one_new_collision_costs_exactly_5_per_quad_involved():
    cfg = EnvConfig(num_quads=3)
    pos = np.array([[0.0, 0, 2], [3.0, 0, 2], [-3.0, 0, 2]])
    new = np.zeros((3, 3), bool)
    new[0, 1] = new[1, 0] = True
    t = _terms(cfg, pos, pos, new_contact=new)
    np.testing.assert_array_equal(t["quad_collision"], [-5.0, -5.0, 0.0])
    # not time-scaled: the same at another control rate
    t = _terms(cfg.replace(control_hz=50), pos, pos, new_contact=new)
    np.testing.assert_array_equal(t["quad_collision"], [-5.0, -5.0, 0.0])


def test_proximity_uses_control_dt_and_hits_are_counts():
    cfg = EnvConfig(num_quads=2, rewards={"floor_hit": 2.0})
    falloff = 4 * cfg.quad.arm
    pos = np.array([[0.0, 0, 2], [0.5 * falloff, 0, 2]])
    t = _terms(cfg, pos, pos, hit_floor=np.array([True, False]))
    np.testing.assert_allclose(t["proximity"], [-0.01 * 10.0 * 0.5] * 2, rtol=1e-12)
    np.testing.assert_array_equal(t["floor_hit"], [-2.0, 0.0])


def test_env_collision_in_grace_period_is_penalized_but_not_counted():
    """Two quads flying head-on collide at t < 1.5 s: the step of the new contact costs -5.0 per
    quad (reward_terms), the episode metrics do not count it (grace period)."""
    cfg = EnvConfig(num_quads=2, episode_seconds=0.5).without_noise()
    env = QuadSwarmEnv(cfg)
    env.reset(seed=0, options={"state": {"pos": [[-0.2, 0, 2], [0.2, 0, 2]], "vel": [[1.0, 0, 0], [-1.0, 0, 0]],
                                         "motors": "hover", "goals": [[-0.2, 0, 2], [0.2, 0, 2]]}})
    hits = []
    for _ in range(cfg.episode_steps):
        _, _, _, truncated, info = env.step(np.full((2, 4), cfg.quad.hover_action))
        hits.append(info["reward_terms"]["quad_collision"].copy())
        if info["new_collisions"].any():
            np.testing.assert_array_equal(info["reward_terms"]["quad_collision"], -5.0 * info["new_collisions"])
    hits = np.array(hits)
    assert (hits == -5.0).sum() == 2  # one event, both quads, once
    assert truncated and info["episode_metrics"]["collisions"] == 0.0
