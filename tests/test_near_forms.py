"""Local observation forms: ``EnvConfig.neighbor_form="near"`` (the neighbour inputs are 0 beyond
``neighbor_near_range``) and ``ObstacleConfig.near_range`` (the reach of ``feature_form="near"``), lengthened by
``near_speed_reach`` times the closing speed towards the column.

Both make a policy's inputs exactly 0 where nothing is near, so its hover at a goal does not depend on
where far quads or columns are."""

from __future__ import annotations

import numpy as np
import pytest

from quadswarm_mj import QuadSwarmEnv
from quadswarm_mj.config import EnvConfig, ObstacleConfig
from quadswarm_mj.observations import near_neighbors
from quadswarm_mj.obstacles import CENTRE_FEATURE, closing_speed, observed_features, obstacle_features
from quadswarm_mj.policies import load_policy, save_policy
from quadswarm_mj.training.evaluation import make_eval_config
from quadswarm_mj.training.learner import env_meta, obs_layout

SELF = 18


def test_near_neighbors_values():
    r, v = np.array([0.3, 0.0, 0.0]), np.array([1.0, -2.0, 0.5])
    far_r = np.array([0.0, 2.0, 0.0])
    nb = np.concatenate([r, v, far_r, v])[None, :]  # one quad, K = 2: a near and a far neighbour
    got = near_neighbors(nb, 0.8)
    w = 1.0 - 0.3 / 0.8
    np.testing.assert_allclose(got[0, :6], np.concatenate([[w, 0.0, 0.0], w * v]))
    assert not got[0, 6:].any()  # beyond the range: exactly 0
    touching = near_neighbors(np.zeros((1, 6)), 0.8)  # two quads at one point: finite, direction 0
    assert np.isfinite(touching).all() and not touching[0, :3].any()


def test_near_neighbors_numpy_equals_jit():
    jax = pytest.importorskip("jax")
    rng = np.random.default_rng(0)
    nb = rng.uniform(-1.5, 1.5, (4, 8, 36))
    want = near_neighbors(nb, 0.8)
    got = np.asarray(jax.jit(lambda x: near_neighbors(x, 0.8))(jax.numpy.asarray(nb, dtype=jax.numpy.float32)))
    np.testing.assert_allclose(got, want, atol=1e-5)
    assert (np.abs(want[..., 0::6]) <= 1).all() and (want != 0).any() and (want == 0).any()


def _pair(engine: str, **kw):
    envs = []
    for form in ("raw", "near"):
        cfg = EnvConfig(num_quads=4, scenario="static_same_goal", neighbor_form=form, neighbor_near_range=0.8, **kw)
        envs.append(QuadSwarmEnv(cfg, engine=engine) if engine == "jax" else QuadSwarmEnv(cfg))
    return envs


@pytest.mark.parametrize("engine", ["mujoco", "jax"])
def test_env_neighbor_inputs_are_the_near_form_of_the_raw_ones(engine):
    raw_env, near_env = _pair(engine)
    raw, _ = raw_env.reset(seed=4)
    near, _ = near_env.reset(seed=4)
    seen_near = False
    for _ in range(80):  # static_same_goal: the quads converge on one goal and come within range
        raw, near = np.asarray(raw), np.asarray(near)
        np.testing.assert_array_equal(near[:, :SELF], raw[:, :SELF])
        np.testing.assert_allclose(near[:, SELF:], near_neighbors(raw[:, SELF:], 0.8), atol=1e-5)
        seen_near |= bool((near[:, SELF:] != 0).any())
        assert np.isfinite(near).all() and near_env.observation_space.contains(near.astype(np.float32))
        a = np.full((4, 4), 0.3)
        raw = raw_env.step(a)[0]
        near = near_env.step(a)[0]
    assert seen_near


def test_config_errors_name_the_field():
    with pytest.raises(ValueError, match=r"neighbor_form must be one of \('raw', 'near'\), got 'close'"):
        EnvConfig(neighbor_form="close")
    with pytest.raises(ValueError, match=r"neighbor_near_range must be a finite number > 0.0 and <= 10.0"):
        EnvConfig(neighbor_near_range=0.0)
    with pytest.raises(ValueError, match=r"obstacles.near_range must be a finite number > 0.0 and <= 10.0"):
        ObstacleConfig(feature_form="near", near_range=float("nan"))


def test_obstacle_near_range_sets_the_reach():
    rng = np.random.default_rng(1)
    f = obstacle_features(rng.uniform(-4, 4, (64, 8, 3)), rng.uniform(-4, 4, (64, 12, 2)),
                          np.ones((64, 12), bool), np.full(64, 0.3))
    d = f[..., CENTRE_FEATURE]
    half = observed_features(f, "near", 0.5)
    np.testing.assert_allclose(half[..., CENTRE_FEATURE], np.clip(1.0 - d / 0.5, 0.0, 2.0))
    assert not half[d >= 0.5].any() and half[d < 0.5].any()
    np.testing.assert_array_equal(observed_features(f, "near", 1.0), observed_features(f, "near"))
    # a goal cell's centre next to a 0.6 m column (0.7 m from its surface) sees nothing at the 0.5 m reach
    cfg = EnvConfig(num_quads=1, scenario="o_random",
                    obstacles=ObstacleConfig(density=0.2, size=0.6, feature_form="near", near_range=0.5))
    one = obstacle_features(np.array([[1.0, 0.0, 1.5]]), np.array([[0.0, 0.0]]), np.array([True]), np.array(0.3))
    assert not observed_features(one, "near", cfg.obstacles.near_range).any()


def _policy(tmp_path, cfg):
    d = cfg.obs_dim
    ks = [np.zeros((d, 8)), np.zeros((8, 8))]
    meta = {"activation": "tanh", "obs_dim": d, "action_dim": 4, "env": env_meta(cfg), "obs_layout": obs_layout(cfg)}
    path = tmp_path / "p.npz"
    save_policy(path, ks, [np.zeros(8), np.zeros(8)], np.zeros(d), np.ones(d), meta)
    return load_policy(str(path)), path, meta


def test_policy_file_records_the_forms_and_evaluation_applies_them(tmp_path):
    from quadswarm_mj.export import generate_c

    assert "neighbor_form" not in env_meta(EnvConfig()) and "neighbor_near_range" not in env_meta(EnvConfig())
    obst = ObstacleConfig(density=0.2, size=0.6, feature_form="near", near_range=0.5)
    cfg = EnvConfig(num_quads=4, neighbor_form="near", neighbor_near_range=0.8, obstacles=obst)
    pol, path, meta = _policy(tmp_path, cfg)
    ev = make_eval_config(pol, "o_random")
    assert (ev.neighbor_form, ev.neighbor_near_range, ev.obstacles.near_range) == ("near", 0.8, 0.5)
    _, hdr = generate_c(pol)
    assert "#define QS_POLICY_NEIGHBOR_FORM 1" in hdr and "#define QS_POLICY_NEIGHBOR_NEAR_RANGE 0.8f" in hdr
    assert "#define QS_POLICY_OBSTACLE_NEAR_RANGE 0.5f" in hdr
    raw_pol, _, _ = _policy(tmp_path, EnvConfig(num_quads=4))
    assert "QS_POLICY_NEIGHBOR_FORM" not in generate_c(raw_pol)[1]
    meta["env"]["neighbor_form"] = "far"
    save_policy(path, [np.zeros((cfg.obs_dim, 8)), np.zeros((8, 8))], [np.zeros(8), np.zeros(8)],
                np.zeros(cfg.obs_dim), np.ones(cfg.obs_dim), meta)
    with pytest.raises(ValueError, match=r"meta env neighbor_form must be one of \('raw', 'near'\), got 'far'"):
        load_policy(str(path))


def test_an_obstacles_override_keeps_the_policys_column_inputs_unless_it_names_them(tmp_path):
    obst = ObstacleConfig(density=0.1, size=0.4, density_random=True, feature_form="near", near_range=0.85)
    pol, _, _ = _policy(tmp_path, EnvConfig(num_quads=4, obstacles=obst))
    ev = make_eval_config(pol, "o_random", env={"obstacles": {"density": 0.2, "size": 0.6}})
    o = ev.obstacles
    assert (o.feature_form, o.near_range, o.density, o.size, o.density_random) == ("near", 0.85, 0.2, 0.6, False)
    ev = make_eval_config(pol, "o_random", env={"obstacles": {"density": 0.2, "near_range": 1.0}})
    assert ev.obstacles.near_range == 1.0  # named: the override wins


@pytest.mark.parametrize("bad", ["far", 0, -1.0, 11.0, True, None])
def test_a_bad_neighbor_near_range_in_a_policy_file_is_refused(tmp_path, bad):
    cfg = EnvConfig(num_quads=4, neighbor_form="near", neighbor_near_range=0.8)
    _, path, meta = _policy(tmp_path, cfg)
    meta["env"]["neighbor_near_range"] = bad
    d = cfg.obs_dim
    save_policy(path, [np.zeros((d, 8)), np.zeros((8, 8))], [np.zeros(8), np.zeros(8)], np.zeros(d), np.ones(d), meta)
    with pytest.raises(ValueError, match=r"meta env neighbor_near_range must be a number in \(0, 10\] \(m\)"):
        load_policy(str(path))


def _one_column(pos, vel):
    """Features and the true closing speed of quads at ``pos`` (K, 3) moving at ``vel`` beside one 0.6 m column at 0."""
    f = obstacle_features(pos[None], np.zeros((1, 1, 2)), np.ones((1, 1), bool), np.array([0.3]))
    away = pos[:, :2] / np.linalg.norm(pos[:, :2], axis=-1, keepdims=True)  # grad of the distance
    return f, np.maximum(-(vel[:, :2] * away).sum(-1), 0.0)[None]


def test_speed_reach_lengthens_the_reach_by_the_closing_speed():
    rng = np.random.default_rng(3)
    ang = rng.uniform(0, 2 * np.pi, 256)
    rad = rng.uniform(0.45, 2.0, 256)
    pos = np.stack([rad * np.cos(ang), rad * np.sin(ang), np.full(256, 1.5)], axis=-1)
    vel = rng.uniform(-2, 2, (256, 3))
    f, closing = _one_column(pos, vel)
    # the grid's central differences: within 2 % of the true gradient (curvature, 0.15-1.7 m from the surface)
    np.testing.assert_allclose(closing_speed(f, vel[None]), closing, rtol=0.02, atol=0.01)
    got = observed_features(f, "near", 0.5, 0.5, vel[None])
    d = f[..., CENTRE_FEATURE]
    np.testing.assert_allclose(got[..., CENTRE_FEATURE], np.clip(1.0 - d / (0.5 + 0.5 * closing), 0.0, 2.0),
                               rtol=0.02, atol=0.01)
    assert (got[..., CENTRE_FEATURE] > 0).sum() > (observed_features(f, "near", 0.5)[..., CENTRE_FEATURE] > 0).sum()
    np.testing.assert_array_equal(observed_features(f, "near", 0.5, 0.0, vel[None]), observed_features(f, "near", 0.5))
    with pytest.raises(ValueError, match="speed_reach > 0 needs the velocities"):
        observed_features(f, "near", 0.5, 0.5)
    # beside a column at a goal cell's centre (0.7 m from its surface): unseen at rest and moving away or along
    # it, seen when closing in at 1 m/s (reach 0.5 + 0.5 * 1 = 1 m)
    at = np.array([[1.0, 0.0, 1.5]] * 4)
    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    f, _ = _one_column(at, v)
    seen = observed_features(f, "near", 0.5, 0.5, v[None])[0, :, CENTRE_FEATURE]
    assert (seen[:3] == 0).all() and seen[3] == pytest.approx(1.0 - 0.7 / 1.0, abs=1e-3)


def test_speed_reach_numpy_equals_jit_and_runs_on_both_engines():
    jax = pytest.importorskip("jax")
    rng = np.random.default_rng(5)
    f = obstacle_features(rng.uniform(-4, 4, (16, 8, 3)), rng.uniform(-4, 4, (16, 12, 2)),
                          np.ones((16, 12), bool), np.full(16, 0.3))
    vel = rng.uniform(-2, 2, (16, 8, 3))
    want = observed_features(f, "near", 0.5, 0.5, vel)
    fn = jax.jit(lambda a, b: observed_features(a, "near", 0.5, 0.5, b))
    got = np.asarray(fn(jax.numpy.asarray(f, jax.numpy.float32), jax.numpy.asarray(vel, jax.numpy.float32)))
    np.testing.assert_allclose(got, want, atol=1e-4)
    obst = ObstacleConfig(density=0.2, size=0.6, feature_form="near", near_range=0.5, near_speed_reach=0.5)
    for engine in ("mujoco", "jax"):
        env = QuadSwarmEnv(EnvConfig(num_quads=4, scenario="o_random", obstacles=obst), engine=engine)
        obs, _ = env.reset(seed=2)
        for _ in range(30):
            obs = env.step(np.full((4, 4), 0.5))[0]
        obs = np.asarray(obs)
        assert np.isfinite(obs).all() and env.observation_space.contains(obs.astype(np.float32))
        env.close()


def test_speed_reach_is_validated_recorded_exported_and_kept_by_evaluation(tmp_path):
    from quadswarm_mj.export import generate_c

    with pytest.raises(ValueError, match=r"obstacles.near_speed_reach must be a finite number >= 0.0 and <= 5.0"):
        ObstacleConfig(feature_form="near", near_speed_reach=-0.1)
    obst = ObstacleConfig(density=0.1, feature_form="near", near_range=0.5, near_speed_reach=0.5)
    pol, _, _ = _policy(tmp_path, EnvConfig(num_quads=4, obstacles=obst))
    ev = make_eval_config(pol, "o_random", env={"obstacles": {"density": 0.2, "size": 0.6}})
    assert (ev.obstacles.near_range, ev.obstacles.near_speed_reach) == (0.5, 0.5)
    hdr = generate_c(pol)[1]
    assert "#define QS_POLICY_OBSTACLE_NEAR_SPEED_REACH 0.5f" in hdr
    fixed, _, _ = _policy(tmp_path, EnvConfig(num_quads=4, obstacles=ObstacleConfig(feature_form="near")))
    assert "NEAR_SPEED_REACH" not in generate_c(fixed)[1]
