"""Observation layout, bounds and variants; episode metrics; MuJoCo collision models."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from quadswarm_mj import EnvConfig, QuadParams, QuadSwarmEnv
from quadswarm_mj import metrics as metrics_lib

HOVER = QuadParams().hover_action


def test_observation_layout_noise_free():
    env = QuadSwarmEnv(EnvConfig(num_quads=4, num_neighbors=2).without_noise())
    pos = np.array([[0.0, 0, 2], [0.5, 0, 2], [0, 1.5, 2], [3, 3, 3]])
    vel = np.array([[0.1, 0, 0], [0, 0.2, 0], [0, 0, 0.3], [1, 1, 1]])
    goals = np.array([[1.0, 1, 1], [0, 0, 2], [0, 0, 2], [0, 0, 2]])
    obs, _ = env.reset(options={"state": {"pos": pos, "vel": vel, "goals": goals,
                                          "rot": np.tile(np.eye(3), (4, 1, 1))}})
    assert obs.shape == (4, 18 + 12)
    np.testing.assert_allclose(obs[0, :3], pos[0] - goals[0], atol=1e-6)
    np.testing.assert_allclose(obs[0, 3:6], vel[0], atol=1e-6)
    np.testing.assert_allclose(obs[0, 6:15], np.eye(3).ravel(), atol=1e-6)
    # neighbours of quad 0, nearest first: quad 1 (0.5 m) then quad 2 (1.5 m)
    np.testing.assert_allclose(obs[0, 18:21], pos[1] - pos[0], atol=1e-6)
    np.testing.assert_allclose(obs[0, 21:24], vel[1] - vel[0], atol=1e-6)
    np.testing.assert_allclose(obs[0, 24:27], pos[2] - pos[0], atol=1e-6)


def test_sensor_noise_on_own_state_only():
    env = QuadSwarmEnv(EnvConfig(num_quads=2))
    pos = np.array([[0.0, 0, 2], [0.5, 0, 2]])
    obs, _ = env.reset(seed=0, options={"state": {"pos": pos, "goals": pos}})
    assert 0 < np.abs(obs[:, :3]).max() < 0.05  # noisy p - goal
    np.testing.assert_allclose(obs[0, 18:21], pos[1] - pos[0], atol=1e-6)  # neighbour terms exact


@pytest.mark.parametrize("kw", [{"obs_self": "floor"}, {"obs_self": "wall"}, {"normalize_obs": True},
                                {"neighbor_sort": "original"}, {"num_neighbors": 0}])
def test_variants_pass_the_checker(kw):
    env = QuadSwarmEnv(EnvConfig(num_quads=3, **kw))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=True)
    assert not caught, [str(w.message) for w in caught]
    obs, _ = env.reset(seed=0)
    assert obs.shape == env.observation_space.shape
    if kw.get("normalize_obs"):
        assert np.abs(obs).max() <= 1.0


def test_observations_clipped_into_bounds():
    env = QuadSwarmEnv(EnvConfig(num_quads=2, room_size=(4, 4, 4)))
    env.reset(seed=0, options={"state": {"pos": [[1.9, 1.9, 3.9], [-1.9, -1.9, 0.5]],
                                         "vel": [[28.0, -28, 28], [0, 0, 0]], "omega": [[100.0, 0, 0], [0, 0, 0]]}})
    obs = env.core.observe()[0].astype(np.float32)
    assert env.observation_space.contains(obs)


def test_metrics_success_and_goal_reach():
    m = metrics_lib.init(np.zeros(2), (), 2)
    dt = 0.01
    for k in range(1, 601):  # 6 s; goal of quad 1 jumps at 3 s and quad 1 never reaches the new one
        t = k * dt
        d = np.array([0.1, 0.1 if t < 3.0 else 1.0])
        jump = np.array([False, abs(t - 3.0) < 1e-9])
        new = np.zeros((2, 2), bool)
        if k == 50:  # a collision inside the 1.5 s grace period is not counted
            new[0, 1] = new[1, 0] = True
        m = metrics_lib.update(m, t, d, new, np.zeros(2, bool), np.zeros(2, bool), np.zeros(2, bool), jump, 1.5)
    out = metrics_lib.finalize(m, 6.0)
    assert out["success"] == pytest.approx(0.5) and out["collisions"] == 0 and out["collision_rate"] == 0
    # quad 0: one 6 s segment reached; quad 1: [0, 3) reached, [3, 6) not -> 2 of 3
    assert out["goal_reach_rate"] == pytest.approx(2 / 3)
    assert out["mean_distance"] == pytest.approx((0.1 + (0.1 * 299 + 1.0 * 301) / 600) / 2, rel=1e-6)


def test_collision_rate_is_the_fraction_of_quads_that_collided_after_the_grace_period():
    m = metrics_lib.init(np.zeros(4), (), 4)
    none = np.zeros(4, bool)
    for k, t in enumerate((1.0, 2.0, 3.0)):
        new = np.zeros((4, 4), bool)
        new[0, 1] = new[1, 0] = True  # quads 0 and 1 touch at every step (the first inside the grace period)
        if k == 2:
            new[0, 2] = new[2, 0] = True  # quad 2 once, after the grace period; quad 3 never
        m = metrics_lib.update(m, t, np.full(4, 0.1), new, none, none, none, none, 1.5)
    out = metrics_lib.finalize(m, 3.0)
    assert out["collision_rate"] == pytest.approx(3 / 4)
    assert out["collisions"] == pytest.approx((3 + 2 + 1 + 0) / 4)  # quad 0: 2 with 1, 1 with 2
    assert out["success"] == pytest.approx(1 / 4)


@pytest.mark.parametrize("mode", ["mujoco", "blend"])
def test_mujoco_contact_models(mode):
    env = QuadSwarmEnv(EnvConfig(num_quads=2, collision_model=mode).without_noise())
    env.reset(seed=0, options={"state": {"pos": [[-0.5, 0, 2], [0.5, 0, 2]], "vel": [[1, 0, 0], [-1, 0, 0]],
                                         "motors": "hover"}})
    for _ in range(80):
        _, _, _, _, info = env.step(np.full((2, 4), HOVER))
    v = info["state"]["vel"][:, 0]
    assert v[0] < 0 < v[1]  # they bounced apart
    assert np.linalg.norm(np.diff(info["state"]["pos"], axis=0)) >= 2 * QuadParams().arm - 0.01  # no overlap
    env = QuadSwarmEnv(EnvConfig(num_quads=1, collision_model=mode).without_noise())
    env.reset(seed=0, options={"state": {"pos": [[0, 0, 0.5]]}})
    for _ in range(100):
        _, _, _, _, info = env.step(-np.ones(4))
    assert info["state"]["pos"][0, 2] == pytest.approx(QuadParams().arm, abs=2e-3) and info["on_floor"][0]


def test_normalized_neighbor_velocity_reaches_plus_minus_one():
    """normalize_obs divides the neighbour relative velocity by its clip (neighbor_vel_clip), so a
    clipped value is exactly +-1, and a value below the clip is v / clip."""
    cfg = EnvConfig(num_quads=3, num_neighbors=2, normalize_obs=True, neighbor_vel_clip=6.0).without_noise()
    env = QuadSwarmEnv(cfg)
    pos = [[0.0, 0, 2], [0.5, 0, 2], [0, 1.5, 2]]
    vel = [[0.0, 0, 0], [10.0, -10.0, 3.0], [-8.0, 0.0, 0.0]]
    obs, _ = env.reset(options={"state": {"pos": pos, "vel": vel, "goals": pos}})
    d = cfg.self_obs_dim
    np.testing.assert_allclose(obs[0, d + 3:d + 6], [1.0, -1.0, 0.5], atol=1e-6)  # quad 1 (nearest), 3 / 6
    np.testing.assert_allclose(obs[0, d + 9:d + 12], [-1.0, 0.0, 0.0], atol=1e-6)  # quad 2
    assert env.observation_space.contains(obs)
