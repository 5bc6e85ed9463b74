"""Deck sensors' speed forms: the body-frame casters (:func:`axis_hits`, :func:`depth_hits`) give the
reference caster's values (:func:`cast_rays` of :func:`world_rays`), in NumPy and under jax.jit, and the
one-uniform-per-ray noise has the VL53L1x model's distribution."""

from __future__ import annotations

import numpy as np
import pytest

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.sensor_config import SensorConfig
from quadswarm_mj.sensor_rays import AXIS_DIRS, axis_hits, cast_rays, depth_directions, depth_hits, world_rays


def _state(rng, n, lead=()):
    from scipy.spatial.transform import Rotation

    pos = rng.uniform([-2.5, -2.5, 0.2], [2.5, 2.5, 2.8], lead + (n, 3))
    R = Rotation.random(int(np.prod(lead + (n,))), random_state=rng).as_matrix().reshape(lead + (n, 3, 3))
    return pos, R


def _scene(seed, n=8, lead=(5,), crowded=True):
    """Random quads (some packed closely so the hitbox spheres are seen and one starts inside another),
    level and axis-aligned quads too (rays parallel to the planes), and a column map."""
    rng = np.random.default_rng(seed)
    pos, R = _state(rng, n, lead)
    if crowded:
        pos[..., 1, :] = pos[..., 0, :] + [0.4, 0.05, -0.03]  # ahead of quad 0
        pos[..., 2, :] = pos[..., 0, :] + [0.05, 0.02, 0.01]  # inside quad 0's hitbox
        pos[..., 3, :] = pos[..., 4, :] + [0.0, 0.0, 0.5]  # straight above quad 4
    R[..., -1, :, :] = np.diag([1.0, -1.0, -1.0])  # upside down
    R[..., 0, :, :] = np.eye(3)  # level, axis-aligned: rays parallel to 4 of the 6 planes
    omap = (rng.uniform(-2.5, 2.5, lead + (6, 2)), rng.uniform(size=lead + (6,)) < 0.7, np.full(lead, 0.25))
    return pos, R, omap


def _reference(c, pos, R, body_dirs, omap):
    return cast_rays(pos, world_rays(R, body_dirs), c.room_low, c.room_high, omap, c.hitbox)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("with_columns", [False, True])
def test_axis_hits_equal_the_reference(seed, with_columns):
    c = EnvConfig(num_quads=8, room_size=(6.0, 5.0, 3.0))
    pos, R, omap = _scene(seed)
    omap = omap if with_columns else None
    ref = _reference(c, pos, R, np.asarray(AXIS_DIRS), omap)
    got = axis_hits(pos, R, c.room_low, c.room_high, omap, c.hitbox)
    assert got.shape == ref.shape == (5, 8, 6) and np.all(np.isfinite(got))
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)
    assert np.all(got[:, 0] == 0.0) and np.all(got[:, 2] == 0.0)  # inside another's hitbox: 0


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("shape", [(8, 8), (3, 5), (1, 1)])
@pytest.mark.parametrize("with_columns", [False, True])
def test_depth_hits_equal_the_reference(seed, shape, with_columns):
    c = EnvConfig(num_quads=8, room_size=(6.0, 5.0, 3.0))
    pos, R, omap = _scene(seed)
    omap = omap if with_columns else None
    fov = (60.0, 45.0)
    ref = _reference(c, pos, R, depth_directions(shape, fov).reshape(-1, 3), omap)
    got = depth_hits(pos, R, shape, fov, c.room_low, c.room_high, omap, c.hitbox)
    assert got.shape == ref.shape == (5, 8, shape[0] * shape[1])
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-10)


def test_speed_forms_without_neighbours_and_one_quad():
    c = EnvConfig(num_quads=1)
    pos, R, _ = _scene(3, n=1, lead=(4,), crowded=False)
    np.testing.assert_allclose(axis_hits(pos, R, c.room_low, c.room_high, None, c.hitbox),
                               _reference(c, pos, R, np.asarray(AXIS_DIRS), None), rtol=1e-12)
    np.testing.assert_allclose(depth_hits(pos, R, (4, 4), (45.0, 45.0), c.room_low, c.room_high),
                               _reference(c, pos, R, depth_directions((4, 4), (45.0, 45.0)).reshape(-1, 3), None),
                               rtol=1e-10)


def test_speed_forms_numpy_equal_jit():
    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    c = EnvConfig(num_quads=8, room_size=(6.0, 5.0, 3.0))
    pos, R, omap = _scene(4)
    f32 = lambda x: jnp.asarray(x, jnp.float32) if np.asarray(x).dtype.kind == "f" else jnp.asarray(x)  # noqa: E731
    jmap = tuple(f32(x) for x in omap)
    ax = jax.jit(lambda p, r, m: axis_hits(p, r, c.room_low, c.room_high, m, c.hitbox))(f32(pos), f32(R), jmap)
    np.testing.assert_allclose(np.asarray(ax), axis_hits(pos, R, c.room_low, c.room_high, omap, c.hitbox),
                               rtol=1e-4, atol=1e-4)
    dp = jax.jit(lambda p, r, m: depth_hits(p, r, (8, 8), (45.0, 45.0), c.room_low, c.room_high, m, c.hitbox))(
        f32(pos), f32(R), jmap)
    np.testing.assert_allclose(np.asarray(dp), depth_hits(pos, R, (8, 8), (45.0, 45.0), c.room_low, c.room_high,
                                                          omap, c.hitbox), rtol=1e-4, atol=1e-4)


def test_jax_engine_deck_forms_equal_the_model_under_jit():
    """The JAX engine's forms (core.ops.jax_deck_part: perf.depth_xla's hitbox test, perf.fused_draws'
    erfinv) give the model's plain values: the hitbox test the same hits (to float32 round-off), the deck
    part with noise to round-off, with and without the depth camera."""
    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    from quadswarm_mj.core.ops import jax_deck_part
    from quadswarm_mj.perf.depth_xla import sphere_pixel_hits as fast
    from quadswarm_mj.sensor_rays import _offsets, _pixel_constants, sphere_pixel_hits
    from quadswarm_mj.sensors import deck_part

    pos, R, omap = _scene(6)
    f32 = lambda x: jnp.asarray(x, jnp.float32) if np.asarray(x).dtype.kind == "f" else jnp.asarray(x)  # noqa: E731
    _, _, uk, vk, norm = _pixel_constants((8, 8), (45.0, 45.0))

    def hits(form):
        def f(p, r):
            ob, c, inside = _offsets(jnp, p, r, 0.1)
            return form(ob, c, f32(uk), f32(vk), f32(norm * norm)), inside
        t, inside = jax.jit(jax.vmap(f))(f32(pos), f32(R))
        return np.asarray(t)[~np.asarray(inside)]  # a quad inside another's hitbox: the caller's 0

    a, b = hits(sphere_pixel_hits), hits(fast)
    assert np.isfinite(a).any() and np.isinf(a).any() and a.shape[0] < 40
    np.testing.assert_array_equal(np.isinf(b), np.isinf(a))
    np.testing.assert_allclose(b, a, rtol=1e-6, atol=1e-6)
    rng = np.random.default_rng(3)
    for s in (SensorConfig(multiranger=True, flow=True, depth=(8, 8), dropout=0.1),
              SensorConfig(multiranger=True, flow=True, dropout=0.1)):
        c = EnvConfig(num_quads=8, room_size=(6.0, 5.0, 3.0), sensors=s)
        d = {"range_u": f32(rng.uniform(size=(5, 8, s.num_rays))), "flow_noise": f32(rng.normal(size=(5, 8, 2)))}
        args = (f32(pos), f32(rng.normal(size=(5, 8, 3))), f32(R), f32(rng.normal(size=(5, 8, 3))),
                tuple(f32(x) for x in omap), d)
        plain = np.asarray(jax.jit(jax.vmap(lambda *a, c=c: deck_part(c, *a)))(*args))
        engine = np.asarray(jax.jit(jax.vmap(lambda *a, c=c: jax_deck_part()(c, *a)))(*args))
        np.testing.assert_allclose(engine, plain, rtol=1e-5, atol=1e-5)


def test_sensor_config_rays_match_the_speed_forms():
    from quadswarm_mj.sensors import ray_directions

    s = SensorConfig(multiranger=True, flow=True, depth=(2, 3))
    np.testing.assert_array_equal(ray_directions(s)[:6], np.asarray(AXIS_DIRS))
    np.testing.assert_allclose(ray_directions(s)[6:], depth_directions((2, 3), s.depth_fov).reshape(-1, 3))


def test_flow_pixels2_equals_flow_pixels():
    from quadswarm_mj.sensors import flow_pixels, flow_pixels2

    rng = np.random.default_rng(7)
    v, w, d = rng.normal(0, 2, (3, 8, 3)), rng.normal(0, 4, (3, 8, 3)), rng.uniform(0, 3, (3, 8))
    d[0, 0] = 0.0  # the range floor 1 mm
    fx, fy, ok = flow_pixels(v, w, d)
    f, ok2 = flow_pixels2(v, w, d)
    np.testing.assert_allclose(f, np.stack([fx, fy], axis=-1), rtol=1e-14)
    np.testing.assert_array_equal(ok2, ok)
    assert not ok.all() and ok.any()


def test_one_uniform_gives_the_dropout_and_a_standard_normal_noise():
    from scipy import stats

    from quadswarm_mj.sensors import tof_normal

    p = 0.2
    u = np.random.default_rng(8).uniform(size=200_000)
    kept = u >= p
    z = tof_normal(u[kept], p)
    assert abs(kept.mean() - (1 - p)) < 0.005
    assert stats.kstest(z, "norm").pvalue > 1e-3
    assert np.all(np.isfinite(tof_normal(np.array([p, 0.0, 1.0 - 1e-12]), p)))
    # JAX float32 (the engine's erfinv) == NumPy (scipy's ndtri) to float32 round-off
    jax = pytest.importorskip("jax")
    w = np.linspace(p, 1.0, 1001, endpoint=False)
    got = np.asarray(jax.jit(lambda x: tof_normal(x, p))(jax.numpy.asarray(w, jax.numpy.float32)))
    np.testing.assert_allclose(got, tof_normal(w.astype(np.float32).astype(np.float64), p), atol=2e-4, rtol=1e-4)


def test_deck_part_under_jit_with_x64_equals_numpy():
    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    from quadswarm_mj.sensors import deck_part

    jax.config.update("jax_enable_x64", True)  # restored by tests/conftest.py
    for s in (SensorConfig(multiranger=True, flow=True, depth=(2, 3)), SensorConfig(multiranger=True, flow=True)):
        c = EnvConfig(num_quads=4, sensors=s)
        rng = np.random.default_rng(9)
        pos, R = _state(rng, 4, (2,))
        vel, omega = rng.normal(size=(2, 4, 3)), rng.normal(size=(2, 4, 3))
        d = {"range_u": rng.uniform(size=(2, 4, s.num_rays)), "flow_noise": rng.normal(size=(2, 4, 2))}
        ref = deck_part(c, pos, vel, R, omega, None, d)
        out = jax.jit(lambda *a, c=c: deck_part(c, *a[:4], None, a[4]))(
            *(jnp.asarray(x) for x in (pos, vel, R, omega)), {k: jnp.asarray(v) for k, v in d.items()})
        assert out.dtype == jnp.float64
        np.testing.assert_allclose(np.asarray(out), ref, rtol=1e-9, atol=1e-9)


def test_deck_part_takes_the_tof_noise_made_in_advance():
    """draws["range_z"] (perf.fused_draws.tof_numbers of the uniforms: the JAX engine's carried numbers)
    gives the readings of draws["range_u"], under jit, with and without the depth camera."""
    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    from quadswarm_mj.perf.fused_draws import tof_numbers
    from quadswarm_mj.sensors import deck_part

    for s in (SensorConfig(multiranger=True, flow=True, depth=(4, 4), dropout=0.2),
              SensorConfig(multiranger=True, flow=True, dropout=0.2)):
        c = EnvConfig(num_quads=4, sensors=s)
        rng = np.random.default_rng(2)
        pos, R = _state(rng, 4, (3,))
        vel, omega = rng.normal(size=(3, 4, 3)), rng.normal(size=(3, 4, 3))
        u, fn = rng.uniform(size=(3, 4, s.num_rays)), rng.normal(size=(3, 4, 2))
        args = tuple(jnp.asarray(x, jnp.float32) for x in (pos, vel, R, omega, u, fn))
        with_u = jax.jit(lambda p, v, r, o, u, f, c=c: deck_part(c, p, v, r, o, None, {"range_u": u, "flow_noise": f}))
        with_z = jax.jit(lambda p, v, r, o, u, f, c=c, s=s: deck_part(
            c, p, v, r, o, None, {"range_z": tof_numbers(u, s.dropout), "flow_noise": f}))
        a, b = np.asarray(with_u(*args)), np.asarray(with_z(*args))
        assert (u < s.dropout).any()
        np.testing.assert_allclose(b, a, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("noise", [True, False])
def test_numpy_deck_part_is_the_plain_model_bit_for_bit(noise):
    """The NumPy deck part (one buffer, one take) equals the sensor model written plainly from
    tof_std, tof_normal and flow_pixels2, bit for bit, with readings out of range and lost."""
    from quadswarm_mj.sensors import (
        FLOW_LIMIT_PX,
        FLOW_MIN_RANGE,
        FLOW_STD_PX,
        deck_part,
        deck_ranges,
        flow_pixels2,
        ray_limits,
        tof_normal,
        tof_std,
    )

    s = SensorConfig(multiranger=True, flow=True, depth=(2, 3), dropout=0.2)
    c = EnvConfig(num_quads=8, sensors=s)
    rng = np.random.default_rng(5)
    pos, R = _state(rng, 8, (3,))
    vel, omega = 3 * rng.normal(size=(3, 8, 3)), rng.normal(size=(3, 8, 3))
    d = {"range_u": rng.uniform(size=(3, 8, s.num_rays)), "flow_noise": rng.normal(size=(3, 8, 2))} if noise else None
    t = deck_ranges(c, pos, R)
    limit = ray_limits(s)
    valid, r = t <= limit, t
    if noise:
        valid = valid & (d["range_u"] >= s.dropout)
        r = t + tof_std(t) * tof_normal(d["range_u"], s.dropout)
    r = np.where(valid, np.minimum(np.maximum(r, 0.0), limit), limit)
    f, ok = flow_pixels2((vel[..., None, :] @ R)[..., 0, :], omega, t[..., 5])
    ok = ok & (t[..., 5] >= FLOW_MIN_RANGE)
    f = f + FLOW_STD_PX * d["flow_noise"] if noise else f
    f = np.where(ok[..., None], np.clip(f, -FLOW_LIMIT_PX, FLOW_LIMIT_PX), 0.0)
    want = np.concatenate([r[..., :5], valid[..., :5], r[..., 5:6], f, valid[..., 5:6], ok[..., None], r[..., 6:]],
                          axis=-1)
    got = deck_part(c, pos, vel, R, omega, None, d)
    assert (~valid).any() and got.shape == want.shape
    assert got.tobytes() == want.astype(float).tobytes()


@pytest.mark.parametrize("sensors", [{"multiranger": True, "flow": True}, {"multiranger": True}, {"flow": True},
                                     {"multiranger": True, "flow": True, "noise": False},
                                     {"multiranger": True, "flow": True, "light_lux": 10.0, "dropout": 0.2},
                                     {"multiranger": True, "flow": True, "depth": (3, 5), "dropout": 0.2},
                                     {"multiranger": True, "depth": (8, 8)},
                                     {"flow": True, "depth": (4, 4), "noise": False}])
def test_numpy_deck_speed_form_is_the_model_bit_for_bit(sensors):
    """perf.numpy_deck.deck_part (the MuJoCo engine's form, through core.ops.NumpyOps; with the depth camera
    too, its part by perf.numpy_depth) gives the model's bits: crowded scenes (a quad inside another's hitbox,
    rays meeting hitboxes), level quads on the floor (rays parallel to the room's planes), columns, one world,
    three worlds, one quad, no leading dims."""
    from quadswarm_mj.perf import numpy_deck
    from quadswarm_mj.sensors import deck_part

    s = SensorConfig(**sensors)
    hit_rays = 0
    for seed in range(6):
        for n, lead in ((8, (1,)), (8, (3,)), (1, (1,)), (3, ())):
            c = EnvConfig(num_quads=n, room_size=(6.0, 5.0, 3.0), sensors=s)
            pos, R, omap = _scene(seed, n=n, lead=lead, crowded=n >= 5)
            rng = np.random.default_rng(seed)
            vel, omega = 2.0 * rng.normal(size=lead + (n, 3)), 3.0 * rng.normal(size=lead + (n, 3))
            if seed % 2:  # level quads on the floor
                pos[..., 2], R[...] = 0.046, np.eye(3)
            draws = None
            if s.noise:
                draws = {"range_u": rng.uniform(size=lead + (n, s.num_rays))}
                if s.flow:
                    draws["flow_noise"] = rng.normal(size=lead + (n, 2))
            for cols in (None, omap):
                want = deck_part(c, pos, vel, R, omega, cols, draws)
                assert numpy_deck.deck_part(c, pos, vel, R, omega, cols, draws).tobytes() == want.tobytes()
            if n > 1:
                free = axis_hits(pos, R, c.room_low, c.room_high)
                hit_rays += np.count_nonzero((axis_hits(pos, R, c.room_low, c.room_high, None, c.hitbox) < free) & (
                    axis_hits(pos, R, c.room_low, c.room_high, None, c.hitbox) > 0.0))
    assert hit_rays > 0  # the hitbox hits are exercised


def test_numpy_deck_part_keeps_the_callers_error_state():
    """perf.numpy_deck ignores the divide, invalid and overflow errors of its cast (as the model's
    np.errstate) on top of the caller's state, and gives that state back: no warning, the caller's other
    settings kept, a changed state seen on the next call."""
    import warnings

    from quadswarm_mj.perf import numpy_deck
    from quadswarm_mj.sensors import deck_part

    c = EnvConfig(num_quads=8, sensors=SensorConfig(multiranger=True, flow=True, noise=False))
    pos, R, _ = _scene(0, lead=(1,))
    pos[..., 0, 2], R[..., 0, :, :] = 0.046, np.eye(3)  # zeros in R: 1 / 0 in the cast
    vel = omega = np.zeros_like(pos)
    want = deck_part(c, pos, vel, R, omega)
    for state in ({"all": "raise"}, {"divide": "warn", "under": "ignore"}, {"all": "raise"}):
        with np.errstate(**state), warnings.catch_warnings():
            warnings.simplefilter("error")
            before = np.geterr()
            assert numpy_deck.deck_part(c, pos, vel, R, omega).tobytes() == want.tobytes()
            assert np.geterr() == before


def test_deck_scratch_table_is_bounded_and_safe_across_threads():
    """Threads making scratch arrays for many configs at once (more than the table keeps, so they evict
    each other's entries): no error, and the table keeps at most 32."""
    import threading

    from quadswarm_mj.perf import numpy_deck

    cfgs = [EnvConfig(num_quads=n % 4 + 1, sensors=SensorConfig(multiranger=True, flow=True)) for n in range(48)]
    errors: list[BaseException] = []

    def work(offset: int) -> None:
        try:
            for k in range(200):
                cfg = cfgs[(k + offset) % len(cfgs)]
                numpy_deck._scratch(cfg, (1, cfg.num_quads, 3))
        except BaseException as e:  # noqa: BLE001
            errors.append(e)

    threads = [threading.Thread(target=work, args=(i * 7,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(numpy_deck._CACHE.table) <= 32


@pytest.mark.parametrize("sensors", [{"multiranger": True, "flow": True}, {"depth": (4, 4)},
                                     {"multiranger": True, "flow": True, "depth": (3, 5), "dropout": 0.2},
                                     {"flow": True, "light_lux": 10.0}, {"multiranger": True, "noise": False}])
def test_jax_engine_deck_part_is_the_model_under_jit(sensors):
    """perf.jax_deck.deck_part (core.ops.jax_deck_part: the model's part with the engine's forms, with the
    depth camera closed by a kernel boundary) gives the model's values with the same forms under
    jit(vmap), bit for bit: noise as uniforms, as ToF noise made in advance, none; with and without
    columns."""
    import functools

    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    from quadswarm_mj.core.ops import jax_deck_part
    from quadswarm_mj.perf.depth_xla import sphere_pixel_hits
    from quadswarm_mj.perf.fused_draws import erf_inv_f32, tof_numbers
    from quadswarm_mj.perf.jax_deck import deck_part as engine_form
    from quadswarm_mj.sensors import deck_part

    assert jax_deck_part() is engine_form
    s = SensorConfig(**sensors)
    c = EnvConfig(num_quads=8, room_size=(6.0, 5.0, 3.0), sensors=s)
    plain_form = functools.partial(deck_part, erf_inv=erf_inv_f32, pixel_spheres=sphere_pixel_hits)
    pos, R, omap = _scene(4)
    rng = np.random.default_rng(4)
    f32 = lambda x: jnp.asarray(x, jnp.float32) if np.asarray(x).dtype.kind == "f" else jnp.asarray(x)  # noqa: E731
    u = f32(rng.uniform(size=(5, 8, s.num_rays)))
    fn = f32(3.0 * rng.normal(size=(5, 8, 2)))
    for draws in ({"range_u": u, "flow_noise": fn}, {"range_z": tof_numbers(u, s.dropout), "flow_noise": fn}, None):
        if not s.noise and draws is not None:
            continue
        for cols in (None, tuple(f32(x) for x in omap)):
            args = (f32(pos), f32(2.0 * rng.normal(size=(5, 8, 3))), f32(R), f32(rng.normal(size=(5, 8, 3))), cols,
                    draws)
            a, b = (np.asarray(jax.jit(jax.vmap(lambda *x, g=g: g(c, *x)))(*args)) for g in (plain_form, engine_form))
            assert a.shape == (5, 8, s.obs_dim)
            assert a.tobytes() == b.tobytes()


def test_jax_engine_axis_caster_is_the_model_under_jit():
    """perf.jax_deck.axis_hits (the body-axis caster with the hitbox test's pair arrays closed by the kernel
    boundary) gives sensor_rays.axis_hits' JAX values bit for bit under jit(vmap): crowded scenes (a quad
    inside another's hitbox, rays meeting hitboxes), level and upside-down quads, with and without columns,
    one quad."""
    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    from quadswarm_mj.perf.jax_deck import axis_hits as engine_form

    for n in (8, 1):
        c = EnvConfig(num_quads=n, room_size=(6.0, 5.0, 3.0))
        for seed in range(3):
            pos, R, omap = _scene(seed, n=n, crowded=n > 1)
            args = (jnp.asarray(pos, jnp.float32), jnp.asarray(R, jnp.float32))
            jmap = (jnp.asarray(omap[0], jnp.float32), jnp.asarray(omap[1]), jnp.asarray(omap[2], jnp.float32))
            for cols in (None, jmap):
                a, b = (np.asarray(jax.jit(jax.vmap(lambda p, r, m, g=g, c=c: g(p, r, c.room_low, c.room_high, m,
                                                                                   c.hitbox)))(*args, cols))
                        for g in (axis_hits, engine_form))
                assert np.isfinite(a).all() and a.tobytes() == b.tobytes()
                if n > 1:
                    assert (a[:, 0] == 0.0).all()  # inside another's hitbox: 0


def test_jax_deck_kernel_boundary_is_an_identity():
    """perf.jax_deck's kernel boundary returns its input bit for bit (NaN, infinities, signed zeros; normal
    floats: XLA:CPU flushes subnormals in any arithmetic), under jit and vmap."""
    jax = pytest.importorskip("jax")
    from quadswarm_mj.perf.jax_deck import divided_by_ones

    x = np.array([[0.0, -0.0, 1.5, -10.0, np.inf, np.nan, 4.0], [2.0, 3.0, -1e30, 1e-30, 1.0, 0.5, -2.0]],
                 np.float32)
    f = divided_by_ones
    for g in (jax.jit(f), jax.jit(jax.vmap(f)), jax.jit(lambda y: f(y[0]))):
        got = np.asarray(g(x))
        want = x[0] if got.ndim == 1 else x
        assert got.dtype == want.dtype and got.tobytes() == want.tobytes()


def test_decks_on_the_lean_model_are_the_visual_models_bitwise():
    """The gym env steps a model without visual geoms also with decks on: the decks cast analytically, so
    readings, observations and rewards are the visual model's bit for bit."""
    from quadswarm_mj import SensorConfig
    from quadswarm_mj.envs.cpu_core import CpuSwarm

    cfg = EnvConfig(num_quads=8, sensors=SensorConfig(multiranger=True, flow=True, depth=(8, 8)))
    runs = []
    for visual in (True, False):
        core = CpuSwarm(cfg, num_worlds=1, visual=visual)
        core.seed(3)
        core.reset()
        rng = np.random.default_rng(1)
        run = []
        for _ in range(200):
            o = core.step(np.clip(rng.standard_normal((1, 8, 4)), -1, 1))
            run += [o["obs"], o["rewards"]]
        runs.append(run)
    assert all(a.tobytes() == b.tobytes() for a, b in zip(*runs))


@pytest.mark.parametrize("lead", [(), (1,), (3,), (2, 2)])
def test_numpy_depth_hitbox_test_is_the_array_form_bitwise(lead):
    """sensor_rays' NumPy depth caster casts only the pairs whose hitbox can meet the camera's pyramid and
    scatters each quad's nearest hit by one minimum.reduceat over its run of pairs: the same bits as the
    array-API form (every pair, :func:`sphere_pixel_hits`) in crowded scenes, a quad inside another's hitbox,
    any leading batch shape."""
    from quadswarm_mj import sensor_rays as sr

    c = EnvConfig(num_quads=8, room_size=(6.0, 5.0, 3.0))
    for seed in range(4):
        pos, R, _ = _scene(seed, lead=lead)
        for shape, fov in (((8, 8), (87.0, 58.0)), ((3, 5), (60.0, 45.0))):
            got = depth_hits(pos, R, shape, fov, c.room_low, c.room_high, None, c.hitbox)
            room = depth_hits(pos, R, shape, fov, c.room_low, c.room_high, None, None)
            norm = sr._pixel_constants(shape, fov)[4]
            uk, vk = sr._pixel_constants(shape, fov)[2:4]
            ob, cc, inside = sr._offsets(np, pos, R, c.hitbox)
            ts = sr.sphere_pixel_hits(ob, cc, uk, vk, norm * norm)
            want = np.where(inside[..., None], 0.0, np.minimum(room, ts * (1.0 / norm)))
            assert (got < room).any() and (got == 0.0).any()  # hitboxes seen, one quad inside another's
            assert got.tobytes() == want.tobytes()


@pytest.mark.parametrize("noise", [True, False])
def test_numpy_depth_speed_form_is_the_model_bit_for_bit(noise):
    """perf.numpy_depth.deck_part (the MuJoCo engine's form of the depth camera alone, through
    perf.numpy_deck and core.ops.NumpyOps) gives the model's bits over many random scenes: crowded quads
    (rays meeting hitboxes), a quad inside another's hitbox, level axis-aligned and upside-down quads, quads
    packed within 0.3 m, columns on and off, odd and even images, any leading batch shape, one quad; and a
    quad exactly on another's hitbox sphere (its call goes to the model)."""
    from quadswarm_mj.perf import numpy_deck, numpy_depth
    from quadswarm_mj.sensors import deck_part

    seen = {"hit": 0, "inside": 0, "calls": 0}
    for shape, fov in (((8, 8), (45.0, 45.0)), ((3, 5), (60.0, 45.0)), ((7, 7), (87.0, 58.0)), ((1, 1), (45.0, 45.0))):
        s = SensorConfig(depth=shape, depth_fov=fov, noise=noise, dropout=0.2)
        for seed in range(12):
            for n, lead in ((8, (1,)), (8, (3,)), (8, (2, 2)), (1, (1,)), (3, ())):
                c = EnvConfig(num_quads=n, room_size=(6.0, 5.0, 3.0), sensors=s)
                pos, R, omap = _scene(seed, n=n, lead=lead, crowded=n >= 5)
                rng = np.random.default_rng(seed)
                if seed % 3 == 1:  # level quads on the floor
                    pos[..., 2], R[...] = 0.046, np.eye(3)
                elif seed % 3 == 2 and n > 1:  # packed within 0.3 m of quad 0
                    pos[...] = pos[..., :1, :] + rng.uniform(-0.3, 0.3, pos.shape)
                vel, omega = rng.normal(size=lead + (n, 3)), rng.normal(size=lead + (n, 3))
                draws = {"range_u": rng.uniform(size=lead + (n, s.num_rays))} if noise else None
                for cols in (None, omap):
                    want = deck_part(c, pos, vel, R, omega, cols, draws)
                    got = numpy_deck.deck_part(c, pos, vel, R, omega, cols, draws)
                    assert np.all(np.isfinite(got)) and got.tobytes() == want.tobytes()
                    seen["calls"] += 1
                if n > 1 and not noise:
                    room = depth_hits(pos, R, shape, fov, c.room_low, c.room_high)
                    t = depth_hits(pos, R, shape, fov, c.room_low, c.room_high, None, c.hitbox)
                    seen["hit"] += np.count_nonzero((t < room) & (t > 0.0))
                    seen["inside"] += np.count_nonzero(np.all(t == 0.0, axis=-1))
    assert seen["calls"] == 480 and (noise or (seen["hit"] > 0 and seen["inside"] > 0))
    # quad 1 exactly on quad 0's sphere, straight to its left (|offset|^2 - r^2 = 0; an odd image has a
    # centre column: beta = +0 there)
    c = EnvConfig(num_quads=2, sensors=SensorConfig(depth=(3, 3), noise=False))
    pos, R = np.array([[[0.0, 0.0, 1.0], [0.0, c.hitbox, 1.0]]]), np.broadcast_to(np.eye(3), (1, 2, 3, 3)).copy()
    zeros = np.zeros_like(pos)
    p = numpy_depth._scratch(c, pos.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        assert numpy_depth._ranges(p, pos, R, None) is None  # the fallback
    want = deck_part(c, pos, zeros, R, zeros)
    assert numpy_deck.deck_part(c, pos, zeros, R, zeros).tobytes() == want.tobytes()


@pytest.mark.parametrize("sensors", [{"multiranger": True, "flow": True}, {"depth": (4, 4)},
                                     {"multiranger": True, "flow": True, "depth": (3, 3)}])
def test_fused_task_with_decks_is_the_model_task_bitwise(sensors):
    """Three worlds of 5 quads with decks: the fused NumPy task (perf.numpy_swarm_task, the deck part written
    into its observation) gives the model's task_step observations bit for bit."""
    from quadswarm_mj.envs.cpu_core import CpuSwarm
    from quadswarm_mj.perf import numpy_fast_forms

    cfg = EnvConfig(num_quads=5, sensors=SensorConfig(**sensors))
    runs = []
    for fast in (True, False):
        with numpy_fast_forms(fast):
            core = CpuSwarm(cfg, 3)
            core.seed(4)
            core.reset()
            rng = np.random.default_rng(0)
            runs.append([core.step(np.clip(rng.standard_normal((3, 5, 4)), -1, 1))["obs"].tobytes()
                         for _ in range(40)])
    assert runs[0] == runs[1]
