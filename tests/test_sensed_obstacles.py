"""Columns sensed, not given (issue 36 item 4): ``ObstacleConfig(observe_features=False)`` keeps the columns
in the world but drops their 9 privileged features from the observation, on both engines; the deck
readings then end the observation and feed the encoder's tail branch."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, ObstacleConfig, QuadSwarmEnv
from quadswarm_mj.observations import build_obs, obs_bounds
from quadswarm_mj.sensor_config import SensorConfig

COLS = np.array([[0.0, 0.0], [2.0, -1.0], [-3.0, 2.5], [1.0, 2.0]])
RANGER = SensorConfig(multiranger=True)


def cfg_s(observe: bool, sensors: SensorConfig = RANGER, n: int = 3, seconds: float = 0.3, **kw) -> EnvConfig:
    return EnvConfig(num_quads=n, scenario="o_random", episode_seconds=seconds, sensors=sensors,
                     obstacles=ObstacleConfig(observe_features=observe), **kw)


def test_switch_validation_obs_dim_and_bounds():
    with pytest.raises(ValueError, match="obstacles.observe_features"):
        ObstacleConfig(observe_features="no")
    with pytest.raises(ValueError, match="obstacles.observe_features"):
        EnvConfig(obstacles={"observe_features": 0})
    on, off = cfg_s(True, SensorConfig()), cfg_s(False, SensorConfig())
    assert ObstacleConfig().observe_features and ObstacleConfig().feature_dim == 9
    assert on.obs_dim == off.obs_dim + 9 == off.self_obs_dim + 6 * off.neighbors + 9
    assert cfg_s(False).obs_dim == off.obs_dim + 10  # the multi-ranger's 5 ranges + 5 flags
    for c in (on, off, cfg_s(False), cfg_s(True)):
        lo, hi = obs_bounds(c)
        assert lo.shape == hi.shape == (c.obs_dim,) and np.all(np.isfinite(lo)) and np.all(lo <= hi)
    lo_on, _ = obs_bounds(cfg_s(True))
    lo_off, _ = obs_bounds(cfg_s(False))
    np.testing.assert_array_equal(np.delete(lo_on, _feature_slice(cfg_s(True))), lo_off)


def _feature_slice(c: EnvConfig) -> slice:
    start = c.self_obs_dim + 6 * c.neighbors
    return slice(start, start + 9)


@pytest.mark.parametrize("engine", ["mujoco", "jax"])
def test_both_engines_drop_exactly_the_features_and_pass_check_env(engine):
    """The same seed and columns: the observation without the features is the one with them, minus
    the 9 features (the columns still act: the multi-ranger readings are equal)."""
    from gymnasium.utils.env_checker import check_env

    envs = [QuadSwarmEnv(cfg_s(b), engine=engine) for b in (True, False)]
    on, off = envs
    assert off.observation_space.shape == (3, off.cfg.obs_dim) and off.cfg.obs_dim == on.cfg.obs_dim - 9
    sl = _feature_slice(on.cfg)
    np.testing.assert_array_equal(np.delete(on.observation_space.low, sl, axis=-1), off.observation_space.low)
    a, _ = on.reset(seed=4, options={"obstacles": COLS})
    b, _ = off.reset(seed=4, options={"obstacles": COLS})
    act = np.full((3, 4), on.cfg.quad.hover_action)
    for _ in range(3):
        np.testing.assert_array_equal(np.delete(a, sl, axis=-1), b)
        assert off.observation_space.contains(b)
        a = on.step(act)[0]
        b = off.step(act)[0]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(QuadSwarmEnv(cfg_s(False, seconds=15.0), engine=engine), skip_render_check=True)
    assert not caught, [str(w.message) for w in caught]
    for e in envs:
        e.close()


def test_build_obs_numpy_equals_jit_without_the_features():
    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    c = cfg_s(False, n=4).without_noise()
    rng = np.random.default_rng(1)
    pos = rng.uniform(-3.0, 3.0, (2, 4, 3)) + [0.0, 0.0, 4.0]
    vel, omega = rng.normal(0, 1, (2, 4, 3)), rng.normal(0, 1, (2, 4, 3))
    R = np.broadcast_to(np.eye(3), (2, 4, 3, 3)).copy()
    goals = rng.uniform(-3.0, 3.0, (2, 4, 3))
    omap = (np.broadcast_to(COLS, (2,) + COLS.shape).copy(), np.ones((2, len(COLS)), bool), np.full(2, 0.3))
    lo, hi = obs_bounds(c)
    ref = build_obs(c, pos, vel, R, omega, goals, None, lo, hi, obstacles=omap)
    assert ref.shape == (2, 4, c.obs_dim)
    f = jax.jit(lambda *a: build_obs(c, *a[:5], None, lo, hi, obstacles=tuple(a[5:])))
    f32 = [jnp.asarray(x, jnp.float32) for x in (pos, vel, R, omega, goals, omap[0])]
    out = np.asarray(f(*f32, jnp.asarray(omap[1]), jnp.asarray(omap[2], jnp.float32)))
    np.testing.assert_allclose(out, ref, atol=2e-4)
    # the tail is the multi-ranger (ranges, then flags): no column feature anywhere
    tail = ref[..., c.obs_dim - 10:]
    assert np.all((tail[..., :5] >= 0.0) & (tail[..., :5] <= 4.0)) and set(np.unique(tail[..., 5:])) <= {0.0, 1.0}


def test_layout_meta_and_an_encoder_policy_on_the_sensed_observation(tmp_path):
    pytest.importorskip("flax")
    from quadswarm_mj.encoder_policy import save_encoder_policy
    from quadswarm_mj.policies import ARCH_PRESETS, load_policy, random_encoder_policy, validate_layout
    from quadswarm_mj.training.learner import env_meta, obs_layout

    c = cfg_s(False, n=8)
    lay = obs_layout(c)
    assert lay == {"self_dim": 18, "num_neighbors": 6, "neighbor_dim": 6, "obstacle_dim": 10}
    assert obs_layout(cfg_s(True, n=8))["obstacle_dim"] == 19 and obs_layout(EnvConfig())["obstacle_dim"] == 0
    for bad in (-1, 4096, True, 2.5):
        with pytest.raises(ValueError, match="obstacle_dim"):
            validate_layout({**lay, "obstacle_dim": bad})
    meta = env_meta(c)
    assert meta["obstacles"]["observe_features"] is False and meta["sensors"]["multiranger"] is True
    assert "sensors" not in env_meta(EnvConfig())
    rebuilt = EnvConfig(**{**meta, "scenario": "o_random"})
    assert rebuilt.obs_dim == c.obs_dim and rebuilt.sensors == c.sensors and rebuilt.obstacles == c.obstacles
    pol = random_encoder_policy(ARCH_PRESETS["deepsets_deployable"], lay, seed=0, meta={"env": meta})
    path = tmp_path / "p.npz"
    save_encoder_policy(path, pol)
    loaded = load_policy(str(path))
    env = QuadSwarmEnv(EnvConfig(**{**loaded.env_kwargs, "scenario": "o_random", "episode_seconds": 0.1}))
    obs, _ = env.reset(seed=0)
    act = loaded(obs)
    assert act.shape == (8, 4) and np.all(np.abs(act) <= 1.0)
    env.close()
