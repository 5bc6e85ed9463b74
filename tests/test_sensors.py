"""Deck sensors (issue 36): analytic ray-cast cases, flow, noise, NumPy == jax.jit, config, spaces."""

from __future__ import annotations

import math

import numpy as np
import pytest

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.observations import obs_bounds
from quadswarm_mj.sensor_config import SensorConfig
from quadswarm_mj.sensors import (
    FLOW_GAIN,
    FLOW_MIN_RANGE,
    cast_rays,
    deck_bounds,
    deck_draw_spec,
    deck_info,
    deck_obs,
    deck_part,
    deck_readings,
    depth_directions,
    tof_std,
    world_rays,
)

ALL = SensorConfig(multiranger=True, flow=True, depth=(3, 3))


def cfg(n: int = 1, room: tuple = (6.0, 6.0, 3.0), sensors: SensorConfig = ALL, **kw) -> EnvConfig:
    return EnvConfig(num_quads=n, room_size=room, sensors=sensors, **kw)


def yaw(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def roll(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def read(c: EnvConfig, pos, R=None, vel=None, omega=None, obstacles=None, draws=None):
    pos = np.asarray(pos, float).reshape(-1, 3)
    n = len(pos)
    R = np.broadcast_to(np.eye(3) if R is None else np.asarray(R, float), (n, 3, 3))
    vel = np.zeros((n, 3)) if vel is None else np.asarray(vel, float).reshape(n, 3)
    omega = np.zeros((n, 3)) if omega is None else np.asarray(omega, float).reshape(n, 3)
    return deck_readings(c, pos, vel, R, omega, obstacles, draws)


def columns(centres, radius):
    c = np.asarray(centres, float).reshape(-1, 2)
    return (c, np.ones(len(c), bool), np.asarray(radius, float))


# ------------------------------------------------------------------------------------ walls


def test_walls_at_known_distances_level():
    r = read(cfg(), [1.0, 0.5, 1.0])
    # room [-3, 3] x [-3, 3] x [0, 3]: front +x 2, back 4 (= the limit, still valid), left +y 2.5,
    # right 3.5, up 2; flow deck down 1
    np.testing.assert_allclose(r["multiranger"][0], [2.0, 4.0, 2.5, 3.5, 2.0], atol=1e-12)
    assert r["multiranger_valid"][0].all()
    np.testing.assert_allclose(r["flow"][0], [1.0, 0.0, 0.0], atol=1e-12)
    assert r["flow_valid"][0].all()


def test_yawed_quad_front_is_body_x():
    r = read(cfg(), [1.0, 0.5, 1.0], R=yaw(math.pi / 2))  # body +x = world +y
    np.testing.assert_allclose(r["multiranger"][0], [2.5, 3.5, 4.0, 2.0, 2.0], atol=1e-12)


def test_beyond_the_limit_is_clipped_and_flagged():
    r = read(cfg(room=(10.0, 10.0, 3.0)), [0.0, 0.0, 1.0])
    np.testing.assert_allclose(r["multiranger"][0], [4.0, 4.0, 4.0, 4.0, 2.0])
    np.testing.assert_array_equal(r["multiranger_valid"][0], [False] * 4 + [True])


def test_upside_down_and_tilted():
    # upside down (roll pi): the "up" sensor looks at the floor, the flow deck at the ceiling
    r = read(cfg(), [0.0, 0.0, 1.0], R=roll(math.pi))
    assert r["multiranger"][0, 4] == pytest.approx(1.0)
    assert r["flow"][0, 0] == pytest.approx(2.0)
    # left is body +y = world -y after the roll: 3 m to the wall either way
    assert r["multiranger"][0, 2] == pytest.approx(3.0)
    # tilted 30 deg about x: the down ray meets the floor at z / cos(30 deg), the up ray the ceiling
    a = math.radians(30.0)
    r = read(cfg(), [0.0, 0.0, 1.0], R=roll(a))
    assert r["flow"][0, 0] == pytest.approx(1.0 / math.cos(a))
    assert r["multiranger"][0, 4] == pytest.approx(2.0 / math.cos(a))


# ------------------------------------------------------------------------------- columns, quads


def test_column_at_known_bearing():
    c = cfg()
    omap = columns([[2.0 / math.sqrt(2), 2.0 / math.sqrt(2)]], 0.3)  # 2 m away at bearing 45 deg
    r = read(c, [0.0, 0.0, 1.0], R=yaw(math.pi / 4), obstacles=omap)
    assert r["multiranger"][0, 0] == pytest.approx(1.7)
    # level and facing +x the column is off every beam: the walls at 3 m
    r = read(c, [0.0, 0.0, 1.0], obstacles=omap)
    np.testing.assert_allclose(r["multiranger"][0, :4], 3.0)
    # a ray that nearly grazes the side: column at (2, 0.299) with radius 0.3 is hit just before x = 2
    r = read(c, [0.0, 0.0, 1.0], obstacles=columns([[2.0, 0.299]], 0.3))
    assert 1.9 < r["multiranger"][0, 0] < 2.0
    # invalid slots are ignored (no column at x = 1 ahead: the wall at 3 m)
    c_map = (np.array([[1.0, 0.0], [0.0, 2.0]]), np.array([False, True]), np.asarray(0.3))
    r = read(c, [0.0, 0.0, 1.0], obstacles=c_map)
    assert r["multiranger"][0, 0] == pytest.approx(3.0)
    assert r["multiranger"][0, 2] == pytest.approx(1.7)  # left (+y): the valid column at y = 2
    # from inside a (solid) column every range is 0
    r = read(c, [0.0, 1.9, 1.0], obstacles=c_map)
    np.testing.assert_allclose(r["multiranger"][0], 0.0)


def test_neighbour_straight_ahead():
    c = cfg(n=2)
    r = read(c, [[0.0, 0.0, 1.0], [1.5, 0.0, 1.0]])
    hb = c.hitbox
    assert r["multiranger"][0, 0] == pytest.approx(1.5 - hb)  # quad 0 sees quad 1 ahead
    assert r["multiranger"][1, 1] == pytest.approx(1.5 - hb)  # quad 1 sees quad 0 behind
    assert r["multiranger"][1, 0] == pytest.approx(1.5)  # quad 1's front: the wall at x = 3
    # a neighbour 1 m below: quad 1's flow range sees its hitbox, quad 0's up range too
    r = read(c, [[0.0, 0.0, 1.0], [0.0, 0.0, 2.0]])
    assert r["multiranger"][0, 4] == pytest.approx(1.0 - hb)
    assert r["flow"][1, 0] == pytest.approx(1.0 - hb)


# ------------------------------------------------------------------------------------- flow


def test_flow_of_known_velocity_and_height():
    c = cfg()
    r = read(c, [0.0, 0.0, 1.5], vel=[0.6, -0.3, 0.0])
    np.testing.assert_allclose(r["flow"][0], [1.5, FLOW_GAIN * 0.4, FLOW_GAIN * -0.2], atol=1e-12)
    assert FLOW_GAIN == pytest.approx(0.01 * 35.0 / 0.71674, rel=1e-4)
    # rotation: omega_y gives -flow x, omega_x gives +flow y (mm_flow.c's signs)
    r = read(c, [0.0, 0.0, 1.5], omega=[0.5, 0.25, 0.0])
    np.testing.assert_allclose(r["flow"][0, 1:], [-FLOW_GAIN * 0.25, FLOW_GAIN * 0.5], atol=1e-12)
    # body velocity: yawed 90 deg, a world +y velocity is body +x flow
    r = read(c, [0.0, 0.0, 1.0], R=yaw(math.pi / 2), vel=[0.0, 0.5, 0.0])
    np.testing.assert_allclose(r["flow"][0, 1:], [FLOW_GAIN * 0.5, 0.0], atol=1e-12)


def test_flow_validity_limits():
    c = cfg()
    low = read(c, [0.0, 0.0, FLOW_MIN_RANGE / 2], vel=[0.01, 0.0, 0.0])
    assert not low["flow_valid"][0, 1] and np.all(low["flow"][0, 1:] == 0.0)
    fast = read(c, [0.0, 0.0, 0.5], vel=[5.0, 0.0, 0.0])  # 10 rad/s > 7.4
    assert not fast["flow_valid"][0, 1]
    dark = read(cfg(sensors=SensorConfig(flow=True, light_lux=10.0)), [0.0, 0.0, 1.0], vel=[0.5, 0.0, 0.0])
    assert not dark["flow_valid"][0, 1] and dark["flow_valid"][0, 0]


# ------------------------------------------------------------------------------------ depth


def test_depth_centre_and_corner_pixels():
    c = cfg()
    r = read(c, [1.0, 0.0, 1.5])  # 2 m from the +x wall
    d = r["depth"][0]
    assert d.shape == (3, 3)
    assert d[1, 1] == pytest.approx(2.0)
    dirs = depth_directions((3, 3), (45.0, 45.0))
    assert dirs[0, 0, 1] > 0 and dirs[0, 0, 2] > 0  # top-left pixel: left (+y) and up (+z)
    np.testing.assert_allclose(d, 2.0 / dirs[..., 0], rtol=1e-12)  # ranges along the rays


# ------------------------------------------------------------------------------------ noise


def test_noise_and_dropout_draws():
    c = cfg()
    spec = deck_draw_spec(c)
    k = c.sensors.num_rays
    assert spec["range_u"].shape == (1, k) and spec["flow_noise"].shape == (1, 2)
    assert deck_draw_spec(c.without_noise()) == {}
    from scipy.special import ndtr

    p = c.sensors.dropout
    keep = np.full((1, k), p + (1.0 - p) * ndtr(1.0))  # kept, noise +1 std
    draws = {"range_u": keep, "flow_noise": np.ones((1, 2))}
    r = read(c, [1.0, 0.5, 1.0], vel=[0.6, 0.0, 0.0], draws=draws)
    t = np.array([2.0, 4.0, 2.5, 3.5, 2.0])
    np.testing.assert_allclose(r["multiranger"][0], np.minimum(t + tof_std(t), 4.0))
    assert r["flow"][0, 1] == pytest.approx(FLOW_GAIN * 0.6 + 0.2)
    drop = np.full((1, k), 0.999 * p)  # every reading lost: invalid, at the limit
    r = read(c, [1.0, 0.5, 1.0], draws={**draws, "range_u": drop})
    assert not r["multiranger_valid"].any() and np.all(r["multiranger"] == 4.0)
    assert tof_std(np.array(2.5)) == pytest.approx(0.005)
    assert tof_std(np.array(4.0)) == pytest.approx(0.2025)


# ------------------------------------------------------------------------------ NumPy == jit


def _random_state(rng, n, lead=()):
    from scipy.spatial.transform import Rotation

    pos = rng.uniform([-2.5, -2.5, 0.2], [2.5, 2.5, 2.8], lead + (n, 3))
    R = Rotation.random(int(np.prod(lead + (n,))), random_state=rng).as_matrix().reshape(lead + (n, 3, 3))
    vel = rng.normal(0, 1, lead + (n, 3))
    omega = rng.normal(0, 1, lead + (n, 3))
    return pos, vel, R, omega


def _random_deck_draws(rng: np.random.Generator, c, B: int) -> dict[str, np.ndarray]:
    """Standard normals for every deck draw of ``c`` (uniforms for ``range_u``), leading dim B."""
    return {k: (rng.normal(size=(B,) + d.shape) if k != "range_u" else rng.uniform(size=(B,) + d.shape))
            for k, d in deck_draw_spec(c).items()}


def test_numpy_equals_jax_jit():
    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    c = cfg(n=6, sensors=SensorConfig(multiranger=True, flow=True, depth=(4, 5)))
    rng = np.random.default_rng(3)
    B = 4
    pos, vel, R, omega = _random_state(rng, 6, (B,))
    omap = (rng.uniform(-2.5, 2.5, (B, 5, 2)), rng.uniform(size=(B, 5)) < 0.7, np.full(B, 0.25))
    draws = _random_deck_draws(rng, c, B)
    ref = deck_readings(c, pos, vel, R, omega, omap, draws)

    @jax.jit
    def f(pos, vel, R, omega, omap, draws):
        return deck_readings(c, pos, vel, R, omega, omap, draws)

    f32 = lambda x: jnp.asarray(x, jnp.float32) if np.asarray(x).dtype.kind == "f" else jnp.asarray(x)  # noqa: E731
    out = f(*(f32(x) for x in (pos, vel, R, omega)), tuple(f32(x) for x in omap),
            {k: f32(v) for k, v in draws.items()})
    for k, v in ref.items():
        o = np.asarray(out[k])
        if v.dtype == bool:  # a flag may differ only where a range sits at a limit within float32 round-off
            assert np.mean(o != v) < 0.01, k
        else:
            np.testing.assert_allclose(o, v, atol=2e-3, err_msg=k)


def test_deck_part_numpy_equals_vmapped_jit_and_the_named_readings():
    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    c = cfg(n=5, sensors=SensorConfig(multiranger=True, flow=True, depth=(3, 4)))
    rng = np.random.default_rng(5)
    B = 3
    pos, vel, R, omega = _random_state(rng, 5, (B,))
    pos[0, 1] = pos[0, 0] + [0.05, 0.0, 0.0]  # quad 0 inside quad 1's hitbox: its ranges are 0
    omap = (rng.uniform(-2.5, 2.5, (B, 4, 2)), rng.uniform(size=(B, 4)) < 0.7, np.full(B, 0.3))
    draws = _random_deck_draws(rng, c, B)
    ref = deck_part(c, pos, vel, R, omega, omap, draws)
    assert ref.shape == (B, 5, c.sensors.obs_dim)
    np.testing.assert_array_equal(ref, deck_obs(c, deck_readings(c, pos, vel, R, omega, omap, draws)))
    quiet = deck_part(c, pos, vel, R, omega, omap)  # noise-free
    assert np.all(quiet[0, 0, :5] == 0.0) and np.all(quiet[0, 0, 5:10] == 1.0)
    f = jax.jit(jax.vmap(lambda *a: deck_part(c, *a[:4], tuple(a[4:7]), dict(zip(sorted(draws), a[7:])))))
    out = f(*(jnp.asarray(x, jnp.float32) for x in (pos, vel, R, omega)), jnp.asarray(omap[0], jnp.float32),
            jnp.asarray(omap[1]), jnp.asarray(omap[2], jnp.float32),
            *(jnp.asarray(draws[k], jnp.float32) for k in sorted(draws)))
    flags = np.zeros(c.sensors.obs_dim, bool)
    flags[[*range(5, 10), 13, 14]] = True  # a flag may differ only where a range sits at a limit
    o = np.asarray(out)
    np.testing.assert_allclose(o[..., ~flags], ref[..., ~flags], atol=2e-3)
    assert np.mean(o[..., flags] != ref[..., flags]) < 0.01


def test_cast_rays_batched_and_never_past_the_room():
    c = cfg(n=8)
    rng = np.random.default_rng(0)
    pos, vel, R, omega = _random_state(rng, 8, (3,))
    dirs = world_rays(R, np.asarray([[1.0, 0, 0], [0, 0, -1.0]]))
    t = cast_rays(pos, dirs, c.room_low, c.room_high, None, c.hitbox)
    assert t.shape == (3, 8, 2) and np.all(np.isfinite(t)) and np.all(t >= 0)
    end = pos[..., None, :] + t[..., None] * dirs
    assert np.all(end >= np.asarray(c.room_low) - 1e-9) and np.all(end <= np.asarray(c.room_high) + 1e-9)


# --------------------------------------------------------------------------- config, layout


def test_config_validation_and_obs_dim():
    assert EnvConfig().sensors == SensorConfig() and not SensorConfig().any
    assert EnvConfig().obs_dim == EnvConfig(sensors={}).obs_dim
    base = EnvConfig(num_quads=4).obs_dim
    assert EnvConfig(num_quads=4, sensors={"multiranger": True, "flow": True, "depth": (8, 8)}).obs_dim == base + 79
    for bad, field in [({"depth": (33, 8)}, "sensors.depth"), ({"depth": (0, 4)}, "sensors.depth"),
                       ({"depth": "8x8"}, "sensors.depth"), ({"dropout": 1.5}, "sensors.dropout"),
                       ({"range_limit": 0.0}, "sensors.range_limit"), ({"flow": "yes"}, "sensors.flow"),
                       ({"depth_fov": (45.0,)}, "sensors.depth_fov"), ({"light_lux": -1.0}, "sensors.light_lux")]:
        with pytest.raises(ValueError, match=field.replace(".", r"\.")):
            EnvConfig(sensors=bad)
    with pytest.raises(ValueError, match="sensors"):
        EnvConfig(sensors={"unknown": 1})
    assert not EnvConfig(sensors=ALL).without_noise().sensors.noise


def test_obs_layout_bounds_and_info_roundtrip():
    c = cfg(n=3)
    lo, hi = deck_bounds(c)
    assert lo.shape == (c.sensors.obs_dim,) and np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))
    assert np.all(lo < hi)
    full_lo, full_hi = obs_bounds(c)
    assert full_lo.shape == (c.obs_dim,) and np.all(np.isfinite(full_lo)) and np.all(np.isfinite(full_hi))
    rng = np.random.default_rng(1)
    pos, vel, R, omega = _random_state(rng, 3)
    r = deck_readings(c, pos, vel, R, omega)
    o = deck_obs(c, r)
    assert np.all(o >= lo - 1e-6) and np.all(o <= hi + 1e-6)
    obs = np.concatenate([np.zeros((3, c.obs_dim - c.sensors.obs_dim)), o], axis=-1)
    info = deck_info(c, obs)
    for k, v in r.items():
        np.testing.assert_allclose(info[k], v, atol=1e-6, err_msg=k)
    assert info["multiranger"].shape == (3, 5) and info["flow"].shape == (3, 3) and info["depth"].shape == (3, 3, 3)


# ------------------------------------------------------------------------------ front ends

DECK = SensorConfig(multiranger=True, flow=True, depth=(2, 3))


def _env_cfg(**kw) -> EnvConfig:
    return EnvConfig(num_quads=2, episode_seconds=0.05, sensors=DECK, **kw)


def _check_deck_info(info: dict, lead: tuple) -> None:
    assert info["multiranger"].shape == lead + (2, 5) and info["multiranger_valid"].dtype == bool
    assert info["flow"].shape == lead + (2, 3) and info["flow_valid"].shape == lead + (2, 2)
    assert info["depth"].shape == lead + (2, 2, 3)
    assert np.all(np.isfinite(info["multiranger"])) and np.all((info["depth"] >= 0) & (info["depth"] <= 4.0))


@pytest.mark.parametrize("engine", ["mujoco", "jax"])
def test_gym_env_check_env_and_info(engine):
    from gymnasium.utils.env_checker import check_env

    from quadswarm_mj import QuadSwarmEnv

    env = QuadSwarmEnv(_env_cfg(), engine=engine)
    check_env(env, skip_render_check=True)
    obs, info = env.reset(seed=1)
    _check_deck_info(info, ())
    np.testing.assert_allclose(info["multiranger"], obs[:, -env.cfg.sensors.obs_dim:][:, :5])
    obs, _, _, _, info = env.step(np.full((2, 4), env.cfg.quad.hover_action))
    _check_deck_info(info, ())
    assert env.observation_space.contains(obs)
    flat = QuadSwarmEnv(_env_cfg(info_mode="flat", normalize_obs=True), engine=engine)
    _, finfo = flat.reset(seed=1)
    _check_deck_info(finfo, ())
    env.close()
    flat.close()


def test_normalized_obs_info_in_metres():
    from quadswarm_mj import QuadSwarmEnv

    raw, norm = (QuadSwarmEnv(_env_cfg(normalize_obs=b).without_noise()) for b in (False, True))
    _, a = raw.reset(seed=2)
    _, b = norm.reset(seed=2)
    for k in ("multiranger", "flow", "depth"):
        np.testing.assert_allclose(a[k], b[k], rtol=1e-5, atol=1e-6)


def test_parallel_env_api_with_every_sensor():
    from pettingzoo.test import parallel_api_test

    from quadswarm_mj import QuadSwarmParallelEnv

    env = QuadSwarmParallelEnv(_env_cfg())
    parallel_api_test(env, num_cycles=5)
    _, infos = env.reset(seed=0)
    assert infos["quad_1"]["multiranger"].shape == (5,) and infos["quad_0"]["depth"].shape == (2, 3)


@pytest.mark.parametrize("engine", ["mujoco", "jax"])
def test_vector_env_info(engine):
    from quadswarm_mj import QuadSwarmVectorEnv

    env = QuadSwarmVectorEnv(_env_cfg(), num_envs=3, engine=engine)
    obs, info = env.reset(seed=0)
    _check_deck_info(info, (3,))
    obs, *_, info = env.step(np.full((3, 2, 4), env.cfg.quad.hover_action, np.float32))
    _check_deck_info(info, (3,))
    assert env.observation_space.contains(obs)
    env.close()


def test_mjx_env_state_info_and_noise_off():
    jax = pytest.importorskip("jax")
    from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv

    env = MjxQuadSwarmEnv(_env_cfg())
    s = jax.jit(env.reset)(jax.random.key(0))
    s = jax.jit(env.step)(s, jax.numpy.full((2, 4), env.cfg.quad.hover_action))
    _check_deck_info({k: np.asarray(v) for k, v in s.info.items() if k in ("multiranger", "multiranger_valid",
                                                                            "flow", "flow_valid", "depth")}, ())
    # without noise the MJX readings equal the pure function on the state's true pose
    quiet = MjxQuadSwarmEnv(_env_cfg().without_noise())
    s = jax.jit(quiet.reset)(jax.random.key(0))
    st = {k: np.asarray(v, np.float64) for k, v in s.info["state"].items()}
    ref = deck_readings(quiet.cfg, st["pos"], st["vel"], st["rot"], st["omega"])
    np.testing.assert_allclose(np.asarray(s.info["multiranger"]), ref["multiranger"], atol=1e-4)
    np.testing.assert_allclose(np.asarray(s.info["depth"]), ref["depth"], atol=1e-4)


def test_mjx_engine_deck_noise_and_dropout_from_the_carried_numbers():
    """The JAX engine's stepped deck readings (their ToF noise made with the carried step numbers,
    perf.fused_draws.tof_numbers): lost readings at the dropout rate, flagged and reading the limit, and
    the kept ones within 6 standard deviations of the noise-free readings of the same state."""
    jax = pytest.importorskip("jax")
    from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv

    s = SensorConfig(multiranger=True, flow=True, depth=(2, 3), dropout=0.3)
    env = MjxQuadSwarmEnv(EnvConfig(num_quads=4, sensors=s))
    states = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(3), 64))
    hover = jax.numpy.full((64, 4, 4), env.cfg.quad.hover_action)
    states = jax.jit(jax.vmap(env.step))(states, hover)
    st = {k: np.asarray(v, np.float64) for k, v in states.info["state"].items()}
    true = deck_readings(env.cfg, st["pos"], st["vel"], st["rot"], st["omega"])
    got, ok = np.asarray(states.info["multiranger"]), np.asarray(states.info["multiranger_valid"])
    in_range = true["multiranger"] < s.range_limit - 0.05
    lost = in_range & ~ok
    assert 0.2 < lost.sum() / in_range.sum() < 0.4
    np.testing.assert_array_equal(got[lost], s.range_limit)
    kept = in_range & ok
    std = np.asarray(tof_std(true["multiranger"]))
    assert np.all(np.abs(got[kept] - true["multiranger"][kept]) <= 6.0 * std[kept] + 1e-4)
    assert np.any(got[kept] != true["multiranger"][kept].astype(np.float32))  # noisy
