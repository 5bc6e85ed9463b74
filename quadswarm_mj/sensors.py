"""Deck sensors (issue 36): multi-ranger, flow deck v2 and a forward depth camera, by ray casting.

Pure functions over NumPy or ``jax.numpy`` (any leading batch dims before the quad axis N); random
draws come in as arrays (:func:`deck_draw_spec`), ``None`` means noise-free readings. Switched on with
``EnvConfig(sensors=SensorConfig(...))`` (:class:`~quadswarm_mj.sensor_config.SensorConfig`); the
readings are appended after the rest of each quad's observation (:func:`deck_layout`) and reported
as ``info["multiranger"]`` etc. (:func:`deck_info`). Models, constants and sources: ``docs/sensors.md``.

Geometry: the rays are cast analytically against the room's planes, the obstacle columns and the
other quads' hitbox spheres (:mod:`quadswarm_mj.sensor_rays`); every sensor sits at the quad's centre.
Body-frame directions (x forward, y left, z up) are turned into the world frame by R (body -> world).

* Multi-ranger deck (5 VL53L1x): front +x, back -x, left +y, right -y, up +z.
* Flow deck v2: the VL53L1x range along body -z and the PMW3901 flow of the surface seen along that
  ray, from the crazyflie-firmware's flow measurement model (``kalman_core/mm_flow.c``):
  ``flow_x = (dt Npix / thetapix) (v_bx / d - omega_y)``, ``flow_y = (dt Npix / thetapix) (v_by / d +
  omega_x)`` pixels per frame (dt = 10 ms frame of the deck driver, Npix = 35, thetapix = 0.71674 =
  2 sin(42 deg / 2), the field of view 42 deg; d the range along the view axis, = z / R22 over a flat
  floor as in the firmware's ``z / R[2][2]``; v_b the body-frame velocity, omega the body rates).
* Depth camera: H x W pixel rays through a pinhole with field of view ``depth_fov`` (horizontal,
  vertical) around body +x; row 0 is the top (+z side), column 0 the left (+y side); each pixel
  holds the range along its ray (not the z-depth).
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from quadswarm_mj import np_calls
from quadswarm_mj._xp import array_namespace
from quadswarm_mj.random_draws import DrawSpec, Normal, Uniform
from quadswarm_mj.sensor_config import SensorConfig
from quadswarm_mj.sensor_rays import (  # noqa: F401  (re-exported: the casters' home is sensor_rays)
    axis_hits,
    cast_rays,
    column_hits,
    depth_directions,
    depth_hits,
    room_hits,
    sphere_hits,
    world_rays,
)

# ---- VL53L1x (multi-ranger, flow deck range, and the depth camera's pixels): noise model of the
# crazyflie-firmware's zranger2.c: std(d) = A (1 + exp(k (d - dA))), std A = 2.5 mm at dA = 2.5 m,
# B = 0.2 m at dB = 4 m, k = ln(B / A) / (dB - dA)
TOF_STD_A, TOF_POINT_A = 0.0025, 2.5  # m, m
TOF_STD_B, TOF_POINT_B = 0.2, 4.0  # m, m
TOF_STD_K = math.log(TOF_STD_B / TOF_STD_A) / (TOF_POINT_B - TOF_POINT_A)  # 1/m
# ---- PMW3901 (flow deck v2)
FLOW_FRAME_S = 0.01  # s, the deck driver's read period (flowdeck_v1v2.c: vTaskDelay(10))
FLOW_NPIX = 35.0  # pixels across the field of view (mm_flow.c)
FLOW_FOV_DEG = 42.0  # deg, PMW3901 field of view
FLOW_THETAPIX = 2.0 * math.sin(math.radians(FLOW_FOV_DEG / 2.0))  # 0.71674 (mm_flow.c)
FLOW_GAIN = FLOW_FRAME_S * FLOW_NPIX / FLOW_THETAPIX  # pixels per frame per rad/s (0.4883)
FLOW_STD_PX = 0.2  # pixels: flowStdFixed 2.0 raw counts x FLOW_RESOLUTION 0.1 (flowdeck_v1v2.c, mm_flow.c)
FLOW_LIMIT_PX = 10.0  # pixels: the driver's outlier limit, 100 raw counts x 0.1
FLOW_MIN_RANGE = 0.08  # m, PMW3901 working range 80 mm .. infinity
FLOW_MAX_RATE = 7.4  # rad/s, PMW3901 maximum flow rate
FLOW_MIN_LUX = 60.0  # lux, the PMW3901's low-light limit
#: body-frame directions of the multi-ranger's 5 sensors (front, back, left, right, up) and the flow deck's
MULTIRANGER_DIRS = ((1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, 1.0))
MULTIRANGER_NAMES = ("front", "back", "left", "right", "up")
DOWN_DIR = (0.0, 0.0, -1.0)
#: the info entries of the deck readings (:func:`deck_info`)
DECK_INFO_KEYS = ("multiranger", "multiranger_valid", "flow", "flow_valid", "depth")
_EPS = 1e-9
_FLOW_SIGNS = np.array([-1.0, 1.0])  # (-omega_y, +omega_x) in flow_pixels2


@functools.lru_cache(maxsize=32)
def ray_directions(s: SensorConfig) -> np.ndarray:
    """(K, 3) body-frame unit rays of one quad, in deck order: multi-ranger (5), flow deck down (1),
    depth pixels (H W, row-major). Read-only."""
    rays = []
    if s.multiranger:
        rays.append(np.asarray(MULTIRANGER_DIRS))
    if s.flow:
        rays.append(np.asarray([DOWN_DIR]))
    if s.depth is not None:
        rays.append(depth_directions(s.depth, s.depth_fov).reshape(-1, 3))
    out = np.concatenate(rays, axis=0) if rays else np.zeros((0, 3))
    out.setflags(write=False)
    return out


# ------------------------------------------------------------------------------ sensor models


def tof_std(d: Any) -> Any:
    """Standard deviation (m) of a VL53L1x range at true range ``d`` (m): zranger2.c's model, with
    ``d`` clipped to [0, 4 m] (beyond, a reading is out of range)."""
    xp = array_namespace(d)
    dc = xp.minimum(xp.maximum(d, 0.0), TOF_POINT_B)
    return TOF_STD_A * (1.0 + xp.exp(TOF_STD_K * (dc - TOF_POINT_A)))


def deck_draw_spec(cfg: Any) -> DrawSpec:
    """Draws of one control step's deck readings per world: ``range_u`` (N, K) uniforms on [0, 1), one
    per ray (a reading is lost where u < dropout; otherwise its noise is the standard normal
    ``Phi^-1((u - dropout) / (1 - dropout))`` scaled by :func:`tof_std`, see :func:`tof_normal`) and,
    with the flow deck, ``flow_noise`` (N, 2) standard normals (scaled by FLOW_STD_PX). Empty when the
    sensors or their noise are off (``None`` draws: noise-free readings)."""
    s, n = cfg.sensors, cfg.num_quads
    if not (s.any and s.noise):
        return {}
    spec: DrawSpec = {"range_u": Uniform(0.0, 1.0, (n, s.num_rays))}
    if s.flow:
        spec["flow_noise"] = Normal(0.0, 1.0, (n, 2))
    return spec


@functools.lru_cache(maxsize=1)
def _ndtri() -> Any:
    """``scipy.special.ndtri`` (imported once, on first use)."""
    from scipy.special import ndtri

    return ndtri


def tof_normal(u: Any, dropout: float, erf_inv: Any = None) -> Any:
    """The standard normal noise of the kept readings from the uniforms ``u`` on [0, 1) of
    :func:`deck_draw_spec`: ``Phi^-1(w)``, w = (u - dropout) / (1 - dropout) (uniform on [0, 1) given
    u >= dropout, so one uniform gives both the dropout and an exact N(0, 1) noise; two draws per ray
    cost twice the random numbers). w is kept >= 2^-24 (the noise >= -5.3; w = 0 would give -inf).
    NumPy: ``scipy.special.ndtri``; JAX: ``jax.scipy.special.ndtri``, or for float32 sqrt(2) erfinv(2 w -
    1) with ``erf_inv`` when given (the JAX engine passes its own float32 erfinv, a few ulp apart)."""
    xp = array_namespace(u)
    scale = 1.0 / (1.0 - dropout) if dropout < 1.0 else 0.0
    w = xp.maximum((u - dropout) * scale, 2.0 ** -24)
    if xp is np:
        return _ndtri()(w)
    if erf_inv is not None and w.dtype == xp.float32:
        return np.float32(math.sqrt(2.0)) * erf_inv(2.0 * w - 1.0)
    import jax.scipy.special

    return jax.scipy.special.ndtri(w)


TOF_LEVEL_BITS = 16  # random bits per ray of the JAX engine's ToF noise (tof_noise_table)


@functools.lru_cache(maxsize=8)
def tof_noise_table(dropout: float) -> np.ndarray:
    """(2^16,) float32, read-only: :func:`tof_normal` of the uniform levels u = (h + 0.5) / 2^16, h = 0 ..
    2^16 - 1, NaN where the reading is lost (u < ``dropout``): the ToF noise of a ray from 16 random bits.
    The JAX engine makes each ray's noise this way (``random_draws.jax_unit_numbers``' ``own`` numbers,
    :func:`tof_from_words`): half the random bits of a float32 uniform and one table read instead of an
    erfinv per ray. The noise is the normal's 2^16-quantile grid (|z| <= 4.6, the VL53L1x reports whole
    millimetres), the dropout probability ``dropout`` rounded to a multiple of 2^-16."""
    levels = 1 << TOF_LEVEL_BITS
    u = (np.arange(levels) + 0.5) / levels
    out = np.where(u >= dropout, tof_normal(np.maximum(u, dropout), dropout), np.nan).astype(np.float32)
    out.setflags(write=False)
    return out


def tof_from_words(words: Any, count: int, dropout: float) -> Any:
    """(count,) float32 JAX array: the ToF noise of ``count`` rays (NaN: lost), :func:`tof_noise_table` of
    16 bits each of the uint32 ``words`` ((count + 1) // 2: the high then the low half of each); what
    :func:`deck_part` takes as ``draws["range_z"]``."""
    import jax.numpy as jnp

    shifts = jnp.asarray([TOF_LEVEL_BITS, 0], jnp.uint32)
    levels = ((words[:, None] >> shifts) & ((1 << TOF_LEVEL_BITS) - 1)).reshape(-1)[:count]
    return jnp.asarray(tof_noise_table(float(dropout)))[levels]


@functools.lru_cache(maxsize=32)
def ray_limits(s: SensorConfig) -> np.ndarray:
    """(K,) reading limit (m) of each ray of :func:`ray_directions`: ``range_limit`` for the multi-ranger
    and the flow deck, ``depth_max_range`` for the depth pixels. Read-only."""
    h, w = s.depth or (0, 0)
    out = np.concatenate([np.full(5 * s.multiranger + s.flow, s.range_limit), np.full(h * w, s.depth_max_range)])
    out.setflags(write=False)
    return out


def _body_velocity(xp: Any, R: Any, vel: Any) -> Any:
    """(..., N, 3) R^T v: the body-frame velocity (m/s)."""
    if xp is np:
        return (vel[..., None, :] @ R)[..., 0, :]
    return sum(R[..., c, :] * vel[..., c, None] for c in range(3))


def flow_pixels2(v_body: Any, omega: Any, d: Any) -> tuple[Any, Any]:
    """:func:`flow_pixels` as ``(flow (..., 2), rate_ok (...))`` (the same values, fewer array calls)."""
    xp = array_namespace(v_body, d)
    if xp is np:  # ufuncs only (np.all's Python wrapper costs more than the work on these small arrays)
        w = v_body[..., :2] / np.maximum(d, 1e-3)[..., None] + omega[..., 1::-1] * _FLOW_SIGNS
        return FLOW_GAIN * w, np.logical_and.reduce(np.abs(w) <= FLOW_MAX_RATE, axis=-1)
    w = v_body[..., :2] / xp.maximum(d, 1e-3)[..., None] + omega[..., 1::-1] * xp.asarray([-1.0, 1.0], v_body.dtype)
    return FLOW_GAIN * w, xp.all(xp.abs(w) <= FLOW_MAX_RATE, axis=-1)


def flow_pixels(v_body: Any, omega: Any, d: Any) -> tuple[Any, Any, Any]:
    """PMW3901 flow (pixels per frame) ``(flow_x, flow_y, rate_ok)`` from the body velocity (..., 3)
    m/s, body rates omega (..., 3) rad/s and the range ``d`` (...,) m along the view axis (body -z):
    ``FLOW_GAIN (v_bx / d - omega_y)``, ``FLOW_GAIN (v_by / d + omega_x)``; ``rate_ok`` where both
    angular rates are within FLOW_MAX_RATE."""
    xp = array_namespace(v_body, d)
    dd = xp.maximum(d, 1e-3)
    wx = v_body[..., 0] / dd - omega[..., 1]
    wy = v_body[..., 1] / dd + omega[..., 0]
    ok = (xp.abs(wx) <= FLOW_MAX_RATE) & (xp.abs(wy) <= FLOW_MAX_RATE)
    return FLOW_GAIN * wx, FLOW_GAIN * wy, ok


def _own_buffer(t: Any, parts: tuple[Any, ...]) -> tuple[Any, ...]:
    """``parts`` (JAX arrays of ``t``'s shape) unchanged, computed by XLA:CPU into one buffer of their own
    (a ``dynamic_update_slice`` of the whole buffer at a run-time offset, always 0: an exact identity).
    Otherwise XLA fuses the per-ray model (exp, erfinv) into the observation's concatenation, whose
    loops run along the short minor axes (5 ranges, 1 down range) at scalar speed: the multi-ranger's
    deck part ~5x slower. ``t``: the ranges (>= 0), from which the offset is made."""
    import jax

    jnp = jax.numpy
    stacked = jnp.stack(parts)
    zero = (t.reshape(-1)[0] < 0.0).astype(jnp.int32)  # 0 (ranges are >= 0), unknown to the compiler
    out = jax.lax.dynamic_update_slice(jnp.zeros_like(stacked), stacked,
                                       (zero,) + (jnp.zeros((), jnp.int32),) * (stacked.ndim - 1))
    return tuple(out[i] for i in range(len(parts)))


def deck_ranges(cfg: Any, pos: Any, R: Any, obstacles: Any = None, pixel_spheres: Any = None,
                axis_caster: Any = None) -> Any:
    """(..., N, K) true ranges (m) along :func:`ray_directions` (multi-ranger, flow deck down, depth
    pixels) from the quads' centres ``pos`` (..., N, 3), R (..., N, 3, 3) body -> world, against the
    room, the column map ``obstacles`` = (centres, valid, radius) or None, and the other quads'
    hitboxes: the body-frame casters :func:`axis_hits` and :func:`depth_hits` (= :func:`cast_rays` of
    :func:`world_rays`, to round-off); ``pixel_spheres``: see :func:`depth_hits`; ``axis_caster``: an
    engine's same-values form of :func:`axis_hits` (its signature; None: that function)."""
    xp = array_namespace(pos, R)
    s = cfg.sensors
    parts = []
    if s.multiranger or s.flow:
        t6 = (axis_caster or axis_hits)(pos, R, cfg.room_low, cfg.room_high, obstacles, cfg.hitbox)
        parts.append(t6 if s.multiranger and s.flow else t6[..., :5] if s.multiranger else t6[..., 5:])
    if s.depth is not None:
        parts.append(depth_hits(pos, R, s.depth, s.depth_fov, cfg.room_low, cfg.room_high, obstacles, cfg.hitbox,
                                pixel_spheres))
    return parts[0] if len(parts) == 1 else xp.concatenate(parts, axis=-1)


def deck_part(cfg: Any, pos: Any, vel: Any, R: Any, omega: Any, obstacles: Any = None,
              draws: dict[str, Any] | None = None, erf_inv: Any = None, pixel_spheres: Any = None,
              axis_caster: Any = None) -> Any:
    """(..., N, sensors.obs_dim) the deck sensors' observation part (:func:`deck_layout` order, flags
    as 0.0 / 1.0; :func:`deck_readings` gives it as named readings) from the TRUE state: ``pos`` (...,
    N, 3) m and ``vel`` (..., N, 3) m/s (world), R (..., N, 3, 3) body -> world, ``omega`` (..., N, 3)
    rad/s (body); ``obstacles`` = (centres, valid, radius) of the column map or None; ``draws`` from
    :func:`deck_draw_spec` (None: noise-free), where ``range_u`` may be replaced by ``range_z``: the rays'
    :func:`tof_normal` already made, NaN for a lost reading (the JAX engine's carried numbers,
    :func:`tof_from_words`, or with ``draws="fused"`` :func:`quadswarm_mj.perf.fused_draws.tof_numbers`).

    Every ToF reading (VL53L1x model, all rays at once; true ranges :func:`deck_ranges`) is valid where
    the true range ``t`` is within its limit and not dropped (u >= dropout); a valid reading is
    ``t + tof_std(t) z`` (z = :func:`tof_normal`) clipped to [0, limit], an invalid one reads the limit.
    ``erf_inv``, ``pixel_spheres``, ``axis_caster``: an engine's same-values forms (:func:`tof_normal`,
    :func:`depth_hits`, :func:`deck_ranges`)."""
    xp = array_namespace(pos, vel, R)
    s = cfg.sensors
    t = deck_ranges(cfg, pos, R, obstacles, pixel_spheres, axis_caster)
    if xp is np and (draws is None or "range_u" in draws):
        return _deck_part_numpy(s, t, vel, R, omega, draws)
    limit = ray_limits(s)
    u = None if draws is None else draws.get("range_u")
    z = None if draws is None else draws.get("range_z")  # or the ToF noise already made (NaN: lost)
    flat = xp is not np and s.depth is None
    if flat:  # XLA:CPU: the per-ray model on one flat axis of N K rays (a minor axis of K = 6 runs at
        # scalar speed: ~8x slower for the multi-ranger), same values. Not with the depth camera: its
        # K >= 64 rays vectorize, and XLA:CPU then runs the whole cast along the flat axis's layout
        shape = t.shape
        limit = np.tile(limit, shape[-2])
        t = t.reshape(shape[:-2] + (-1,))
        t, = _own_buffer(t, (t,))  # the ranges' stack (6 axis rays) is not fused into the model's loop
        u = None if u is None else u.reshape(t.shape)
        z = None if z is None else z.reshape(t.shape)
    limit = xp.asarray(limit, dtype=t.dtype)
    valid = t <= limit
    r = t
    if u is not None:
        valid = valid & (u >= s.dropout)
        r = t + tof_std(t) * tof_normal(u, s.dropout, erf_inv)
    elif z is not None:
        valid = valid & (z == z)  # not NaN
        r = t + tof_std(t) * z
    r = xp.where(valid, xp.minimum(xp.maximum(r, 0.0), limit), limit)
    if flat:  # not with depth: its long rows vectorize anyway, and XLA:CPU
        # updates a buffer of N (6 + H W) x 3 numbers per world slowly (a scatter under vmap)
        t, r, valid = (x.reshape(shape) for x in _own_buffer(t, (t, r, valid.astype(t.dtype))))
        valid = valid > 0.5
    flags = valid.astype(t.dtype)
    parts: list[Any] = []
    k = 0
    if s.multiranger:
        parts += [r[..., :5], flags[..., :5]]
        k = 5
    if s.flow:
        d = t[..., k]  # the true range along body -z
        f, rate_ok = flow_pixels2(_body_velocity(xp, R, vel), omega, d)
        fvalid = rate_ok & (d >= FLOW_MIN_RANGE)
        if s.light_lux < FLOW_MIN_LUX:  # too dark: never valid
            fvalid = xp.zeros_like(fvalid)
        if draws is not None:
            f = f + FLOW_STD_PX * draws["flow_noise"]
        f = xp.where(fvalid[..., None], xp.minimum(xp.maximum(f, -FLOW_LIMIT_PX), FLOW_LIMIT_PX), 0.0)
        parts += [r[..., k:k + 1], f, flags[..., k:k + 1], fvalid[..., None].astype(t.dtype)]
        k += 1
    if s.depth is not None:
        parts.append(r[..., k:])
    return parts[0] if len(parts) == 1 else xp.concatenate(parts, axis=-1)


@functools.lru_cache(maxsize=32)
def _numpy_plan(s: SensorConfig, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """(limit (K,), out columns (obs_dim,), buffer template (*shape, 2 K + 3), flow ray index) of
    :func:`_deck_part_numpy` for ranges of ``shape`` (..., N, K): the deck part's columns as indices into
    its buffer [r (K) | flags (K) | flow x, y | flow valid]; the template holds the readings of an
    invalid ray (the limit) and of an invalid flow (0). Read-only."""
    k_rays = s.num_rays
    cols: list[int] = []
    k = 0
    if s.multiranger:
        cols += list(range(5)) + list(range(k_rays, k_rays + 5))
        k = 5
    if s.flow:
        cols += [k, 2 * k_rays, 2 * k_rays + 1, k_rays + k, 2 * k_rays + 2]
        k += 1
    if s.depth is not None:
        cols += list(range(k, k_rays))
    template = np.zeros(shape[:-1] + (2 * k_rays + 3,))
    template[..., :k_rays] = ray_limits(s)
    out = (ray_limits(s), np.asarray(cols, np.intp), template)
    for x in out:
        x.setflags(write=False)
    return out[0], out[1], out[2], (5 if s.multiranger else 0)


_clip = np_calls.clip  # the clip ufunc (np.clip's Python wrapper costs more on small arrays)


def _deck_part_numpy(s: SensorConfig, t: np.ndarray, vel: np.ndarray, R: np.ndarray, omega: np.ndarray,
                     draws: dict[str, Any] | None) -> np.ndarray:
    """:func:`deck_part` in NumPy from the true ranges ``t`` (..., N, K), with few calls (the CPU
    engine's arrays are small: the per-call cost dominates): every reading written into a copy of one
    buffer that holds the invalid readings (ufuncs with ``where=`` write the valid ones), the columns
    picked by one ``take``. The same operations on the same values: the same bits."""
    limit, cols, template, kf = _numpy_plan(s, t.shape)
    k_rays = t.shape[-1]
    buf = template.copy()
    r, flags = buf[..., :k_rays], buf[..., k_rays:2 * k_rays]
    valid = np.less_equal(t, limit)
    if draws is not None:
        u = draws["range_u"]
        valid &= u >= s.dropout
        x = _clip(t, 0.0, TOF_POINT_B)  # tof_std(t), in place (the sign of a zero range is lost next)
        x -= TOF_POINT_A
        x *= TOF_STD_K
        np.exp(x, out=x)
        x += 1.0
        x *= TOF_STD_A
        w = np.subtract(u, s.dropout)  # tof_normal(u, s.dropout), in place
        w *= 1.0 / (1.0 - s.dropout) if s.dropout < 1.0 else 0.0
        np.maximum(w, 2.0 ** -24, out=w)
        x *= _ndtri()(w, out=w)
        x += t
        np.maximum(x, 0.0, out=x)
    else:
        x = np.maximum(t, 0.0)
    np.minimum(x, limit, out=r, where=valid)  # the invalid keep the template's limit
    np.copyto(flags, valid)
    if s.flow:
        d = t[..., kf]  # the true range along body -z (flow_pixels2, inlined)
        w = (vel[..., None, :] @ R)[..., 0, :2]  # the body velocity's x, y (_body_velocity)
        w /= np.maximum(d, 1e-3)[..., None]
        w += omega[..., 1::-1] * _FLOW_SIGNS
        rate_ok = np.logical_and.reduce(np.abs(w) <= FLOW_MAX_RATE, axis=-1)
        rate_ok &= d >= FLOW_MIN_RANGE
        if s.light_lux < FLOW_MIN_LUX:  # too dark: never valid
            rate_ok[...] = False
        w *= FLOW_GAIN
        if draws is not None:
            w += FLOW_STD_PX * draws["flow_noise"]
        _clip(w, -FLOW_LIMIT_PX, FLOW_LIMIT_PX, out=buf[..., 2 * k_rays:2 * k_rays + 2], where=rate_ok[..., None])
        np.copyto(buf[..., 2 * k_rays + 2], rate_ok)
    return np.take(buf, cols, axis=-1)


def deck_readings(cfg: Any, pos: Any, vel: Any, R: Any, omega: Any, obstacles: Any = None,
                  draws: dict[str, Any] | None = None) -> dict[str, Any]:
    """The deck readings of every quad (arguments as :func:`deck_part`). Returns the sensors that are
    on: ``multiranger`` (..., N, 5) m and ``multiranger_valid`` (..., N, 5) bool; ``flow`` (..., N, 3)
    = (down range m, flow x, flow y pixels per frame) and ``flow_valid`` (..., N, 2) bool (range,
    flow); ``depth`` (..., N, H, W) m."""
    return _split(cfg.sensors, deck_part(cfg, pos, vel, R, omega, obstacles, draws))


# ------------------------------------------------------------------------------ observation layout


def deck_layout(s: SensorConfig) -> list[tuple[str, int]]:
    """The deck's observation components per quad, in order: ``("multiranger", 5)``,
    ``("multiranger_valid", 5)``, ``("flow", 3)``, ``("flow_valid", 2)``, ``("depth", H W)`` (the
    sensors that are on; flags as 0.0 / 1.0, depth row-major)."""
    out = []
    if s.multiranger:
        out += [("multiranger", 5), ("multiranger_valid", 5)]
    if s.flow:
        out += [("flow", 3), ("flow_valid", 2)]
    if s.depth is not None:
        out.append(("depth", s.depth[0] * s.depth[1]))
    return out


def deck_obs(cfg: Any, readings: dict[str, Any]) -> Any:
    """(..., N, sensors.obs_dim) observation part of :func:`deck_readings`, in :func:`deck_layout` order
    (= :func:`deck_part` of the same state)."""
    first = next(iter(readings.values()))
    xp = array_namespace(first)
    f = readings.get("multiranger", readings.get("flow", readings.get("depth"))).dtype
    parts = []
    for name, w in deck_layout(cfg.sensors):
        v = readings[name]
        parts.append(v.astype(f).reshape(v.shape[:-2 if name == "depth" else -1] + (w,)))
    return xp.concatenate(parts, axis=-1)


@functools.lru_cache(maxsize=32)
def _split_plan(s: SensorConfig) -> tuple[tuple[str, int, int, int], ...]:
    """(name, start, stop, kind) of each reading in a deck part (:func:`deck_layout`); kind 1: a flag,
    2: the depth image, 0: as it is."""
    out, k = [], 0
    for name, w in deck_layout(s):
        out.append((name, k, k + w, 1 if name.endswith("_valid") else 2 if name == "depth" else 0))
        k += w
    return tuple(out)


def _split(s: SensorConfig, part: Any) -> dict[str, Any]:
    """The named readings (:func:`deck_readings`) of a deck observation part (..., N, S) in metres."""
    out: dict[str, Any] = {}
    for name, a, b, kind in _split_plan(s):
        v = part[..., a:b]
        if kind == 1:
            v = v > 0.5
        elif kind == 2:
            v = v.reshape(v.shape[:-1] + s.depth)
        out[name] = v
    return out


def deck_bounds(cfg: Any) -> tuple[np.ndarray, np.ndarray]:
    """Finite (low, high) float32 bounds of :func:`deck_obs` (ranges [0, limit], flags [0, 1], flow
    +-FLOW_LIMIT_PX)."""
    s = cfg.sensors
    lo: list[float] = []
    hi: list[float] = []
    for name, w in deck_layout(s):
        lo += [-FLOW_LIMIT_PX] * w if name == "flow" else [0.0] * w
        if name == "multiranger":
            hi += [s.range_limit] * w
        elif name == "flow":
            hi += [s.range_limit, FLOW_LIMIT_PX, FLOW_LIMIT_PX]
        elif name == "depth":
            hi += [s.depth_max_range] * w
        else:
            hi += [1.0] * w
    if s.flow:  # the down range is >= 0
        i = sum(w for name, w in deck_layout(s)[:deck_layout(s).index(("flow", 3))])
        lo[i] = 0.0
    return np.asarray(lo, dtype=np.float32), np.asarray(hi, dtype=np.float32)


def _entry_keys(s: SensorConfig) -> tuple[tuple[tuple[str, tuple, int], ...], bool]:
    """The info entries' (name, index of the deck part, kind) and whether any is a flags entry."""
    plan = _split_plan(s)
    return tuple((name, (Ellipsis, slice(a, b)), kind) for name, a, b, kind in plan), any(k == 1 for *_, k in plan)


def _numpy_entries(s: SensorConfig, keys: tuple[tuple[str, tuple, int], ...], flagged: bool,
                   part: np.ndarray) -> dict[str, Any]:
    """The info entries as views of ``part`` (a fresh float32 deck part, metres) and of one flags array."""
    flags = part > 0.5 if flagged else None
    out: dict[str, Any] = {}
    for name, key, kind in keys:
        out[name] = part[key] if kind == 0 else flags[key] if kind == 1 else part[key].reshape(
            part.shape[:-1] + s.depth)
    return out


def numpy_deck_info(cfg: Any, scale: Any = None) -> Any:
    """:func:`deck_info` as a function of the observation alone, its plan made once (a gym env's per-step
    info): ``f(obs)`` = ``deck_info(cfg, obs, scale)`` (the same arrays)."""
    s, dim = cfg.sensors, cfg.obs_dim
    if not s.any:
        return lambda obs: {}
    width, (keys, flagged) = s.obs_dim, _entry_keys(s)
    sc = None if scale is None else np.asarray(scale, dtype=np.float32)[dim - width:]
    cut = (Ellipsis, slice(dim - width, None))

    def f(obs: Any) -> dict[str, Any]:
        if type(obs) is not np.ndarray or obs.shape[-1] != dim:
            return deck_info(cfg, obs, scale)
        part = obs[cut].astype(np.float32)
        if sc is not None:
            part *= sc
        return _numpy_entries(s, keys, flagged, part)

    return f


def deck_info(cfg: Any, obs: Any, scale: Any = None) -> dict[str, Any]:
    """The info entries of the deck readings from an observation (..., N, obs_dim) (its last
    ``sensors.obs_dim`` components; ``scale``: the observation's normalization, or None):
    ``multiranger`` (..., N, 5) m, ``multiranger_valid`` (..., N, 5) bool, ``flow`` (..., N, 3),
    ``flow_valid`` (..., N, 2) bool, ``depth`` (..., N, H, W) m; {} with the sensors off. NumPy in:
    float32 NumPy copies out; ``jax.numpy`` in: ``jax.numpy`` out."""
    s = cfg.sensors
    if not s.any:
        return {}
    start = obs.shape[-1] - s.obs_dim  # = cfg.obs_dim - s.obs_dim
    if type(obs) is np.ndarray:  # one fresh float32 array of the deck part and one of its flags; the entries
        # are views of them (no alias of obs)
        part = obs[..., start:].astype(np.float32)
        if scale is not None:
            part *= np.asarray(scale, dtype=np.float32)[start:]
        return _numpy_entries(s, *_entry_keys(s), part)
    xp = array_namespace(obs)
    part = obs[..., start:]
    if scale is not None:
        part = part * xp.asarray(np.asarray(scale)[start:], dtype=part.dtype)
    return _split(s, part)
