"""Deck sensors (issue 36): multi-ranger, flow deck v2 and a forward depth camera, by ray casting.

Pure functions over NumPy or ``jax.numpy`` (any leading batch dims before the quad axis N); random
draws come in as arrays (:func:`deck_draw_spec`), ``None`` means noise-free readings. Switched on with
``EnvConfig(sensors=SensorConfig(...))`` (:class:`~quadswarm_mj.sensor_config.SensorConfig`); the
readings are appended after the rest of each quad's observation (:func:`deck_layout`) and reported
as ``info["multiranger"]`` etc. (:func:`deck_info`). Models, constants and sources: ``docs/sensors.md``.

Geometry (world frame, SI): every sensor sits at the quad's centre; a ray from ``p`` along the unit
vector ``d`` ends at the first of

* the room's planes: floor z = 0, ceiling z = H, walls x = +-L/2, y = +-W/2 (from inside the room);
* the obstacle columns: vertical cylinders (centre (x, y), radius r) from floor to ceiling;
* the other quads' hitbox spheres (radius ``cfg.hitbox``; the quad's own is skipped).

A ray that starts inside a column or another quad's hitbox has length 0. Body-frame directions
(x forward, y left, z up) are turned into the world frame by R (body -> world).

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

from quadswarm_mj._xp import array_namespace
from quadswarm_mj.random_draws import DrawSpec, Normal, Uniform
from quadswarm_mj.sensor_config import SensorConfig

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


def depth_directions(shape: tuple[int, int], fov_deg: tuple[float, float]) -> np.ndarray:
    """(H, W, 3) unit body-frame rays of the depth camera's pixel centres (pinhole around +x)."""
    h, w = shape
    tu, tv = (math.tan(math.radians(f) / 2.0) for f in fov_deg)
    u = tu * (2.0 * (np.arange(w) + 0.5) / w - 1.0)  # to the right (body -y)
    v = tv * (1.0 - 2.0 * (np.arange(h) + 0.5) / h)  # up (body +z)
    d = np.stack(np.broadcast_arrays(np.ones((h, w)), -u[None, :], v[:, None]), axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


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


# ------------------------------------------------------------------------------ ray casting


# The casters work axis by axis (x, y, z arrays of shape (..., N, K)), and the ray-versus-object arrays
# are laid out (..., N, objects, K) with the minimum over the objects' axis: both keep XLA:CPU's vector
# loops along the rays instead of along the 3 components or the 8 quads (scripts/sensor_benchmark.py).


def room_hits(pos: Any, dirs: Any, room_low: Any, room_high: Any) -> Any:
    """(..., N, K) distance (m) from ``pos`` (..., N, 3) along the unit rays ``dirs`` (..., N, K, 3) to
    the room's planes (the box [room_low, room_high], seen from inside; >= 0)."""
    xp = array_namespace(pos, dirs)
    t = None
    for a in range(3):  # the three axes x, y, z
        pa = pos[..., :, None, a]  # (..., N, 1)
        # the gaps to the high and low planes, kept > 0 and < 0 (a zero gap would make 0 / 0 for a
        # parallel ray); the plane ahead is the larger quotient (a parallel ray: +inf)
        gap_hi = xp.maximum(room_high[a] - pa, 1e-30)
        gap_lo = xp.minimum(room_low[a] - pa, -1e-30)
        ta = xp.maximum(gap_hi / dirs[..., a], gap_lo / dirs[..., a])
        t = ta if t is None else xp.minimum(t, ta)
    return t


def column_hits(pos: Any, dirs: Any, centres: Any, valid: Any, radius: Any) -> Any:
    """(..., N, K) distance (m) along each ray to the nearest valid vertical column (infinite
    cylinders, centres (..., M, 2), valid (..., M), radius (...,)); inf without a hit, 0 from inside."""
    xp = array_namespace(pos, dirs, centres)
    r = xp.asarray(radius, dtype=pos.dtype)[..., None, None]
    ox = pos[..., :, None, 0] - centres[..., None, :, 0]  # (..., N, M) quad - centre
    oy = pos[..., :, None, 1] - centres[..., None, :, 1]
    c = ox * ox + oy * oy - r * r
    ok = valid[..., None, :]
    inside = xp.any((c < 0.0) & ok, axis=-1)  # (..., N)
    neg_s = xp.where(ok, -xp.sqrt(xp.maximum(c, 0.0)), -xp.inf)[..., None]  # invalid slots: never hit
    dx, dy = dirs[..., :, None, :, 0], dirs[..., :, None, :, 1]  # (..., N, 1, K)
    a = dx * dx + dy * dy
    b = dx * ox[..., None] + dy * oy[..., None]  # (..., N, M, K)
    # |o + t d|^2 = r^2 in the plane: a t^2 + 2 b t + c = 0; a hit ahead from outside needs
    # b < -sqrt(a c) (strict: a vertical ray, a = 0, never hits)
    t = -(b + xp.sqrt(xp.maximum(b * b - a * c[..., None], 0.0))) / xp.maximum(a, 1e-30)
    t = xp.min(xp.where(b < xp.sqrt(a) * neg_s, t, xp.inf), axis=-2)
    return xp.where(inside[..., None], 0.0, t)


def sphere_hits(pos: Any, dirs: Any, radius: float) -> Any:
    """(..., N, K) distance (m) along each ray of quad i to the nearest hitbox sphere (radius m) of
    another quad j != i; inf without a hit, 0 from inside."""
    xp = array_namespace(pos, dirs)
    n = pos.shape[-2]
    o = [pos[..., :, None, a] - pos[..., None, :, a] for a in range(3)]  # (..., N, N) quad i - quad j
    c = xp.where(np.eye(n, dtype=bool), xp.inf, o[0] * o[0] + o[1] * o[1] + o[2] * o[2] - radius * radius)
    inside = xp.any(c < 0.0, axis=-1)  # (..., N); the own sphere (c = inf) never counts
    neg_s = -xp.sqrt(xp.maximum(c, 0.0))[..., None]
    b = sum(dirs[..., :, None, :, a] * o[a][..., None] for a in range(3))  # (..., N, N, K): d_ik . o_ij
    # |o + t d|^2 = r^2: t^2 + 2 b t + c = 0; a hit ahead from outside needs b <= -sqrt(c)
    t = -(b + xp.sqrt(xp.maximum(b * b - c[..., None], 0.0)))
    t = xp.min(xp.where(b <= neg_s, t, xp.inf), axis=-2)
    return xp.where(inside[..., None], 0.0, t)


def cast_rays(pos: Any, dirs: Any, room_low: Any, room_high: Any, columns: Any = None,
              quad_radius: float | None = None) -> Any:
    """(..., N, K) range (m) along the world-frame unit rays ``dirs`` (..., N, K, 3) from the quads'
    centres ``pos`` (..., N, 3) to the first surface: the room, the ``columns`` = (centres, valid,
    radius) of an obstacle map (or None) and the other quads' hitbox spheres (``quad_radius``, or None)."""
    xp = array_namespace(pos, dirs)
    with np.errstate(divide="ignore", invalid="ignore"):  # NumPy: x / 0 = inf for parallel rays (intended)
        t = room_hits(pos, dirs, tuple(room_low), tuple(room_high))
        if columns is not None:
            t = xp.minimum(t, column_hits(pos, dirs, *columns))
        if quad_radius is not None and pos.shape[-2] > 1:
            t = xp.minimum(t, sphere_hits(pos, dirs, quad_radius))
    return t


def world_rays(R: Any, body_dirs: np.ndarray) -> Any:
    """(..., N, K, 3) world-frame rays from the body-frame ``body_dirs`` (K, 3) and R (..., N, 3, 3)."""
    xp = array_namespace(R)
    d = xp.asarray(body_dirs, dtype=R.dtype)
    return sum(R[..., None, :, c] * d[:, c, None] for c in range(3))


# ------------------------------------------------------------------------------ sensor models


def tof_std(d: Any) -> Any:
    """Standard deviation (m) of a VL53L1x range at true range ``d`` (m): zranger2.c's model, with
    ``d`` clipped to [0, 4 m] (beyond, a reading is out of range)."""
    xp = array_namespace(d)
    dc = xp.minimum(xp.maximum(d, 0.0), TOF_POINT_B)
    return TOF_STD_A * (1.0 + xp.exp(TOF_STD_K * (dc - TOF_POINT_A)))


def deck_draw_spec(cfg: Any) -> DrawSpec:
    """Draws of one control step's deck readings per world: ``range_noise`` (N, K) standard normals
    (scaled by :func:`tof_std`), ``range_drop`` (N, K) uniforms (a reading is lost where < dropout)
    and, with the flow deck, ``flow_noise`` (N, 2) standard normals (scaled by FLOW_STD_PX).
    Empty when the sensors or their noise are off (``None`` draws: noise-free readings)."""
    s, n = cfg.sensors, cfg.num_quads
    if not (s.any and s.noise):
        return {}
    k = s.num_rays
    spec: DrawSpec = {"range_noise": Normal(0.0, 1.0, (n, k)), "range_drop": Uniform(0.0, 1.0, (n, k))}
    if s.flow:
        spec["flow_noise"] = Normal(0.0, 1.0, (n, 2))
    return spec


@functools.lru_cache(maxsize=32)
def ray_limits(s: SensorConfig) -> np.ndarray:
    """(K,) reading limit (m) of each ray of :func:`ray_directions`: ``range_limit`` for the multi-ranger
    and the flow deck, ``depth_max_range`` for the depth pixels. Read-only."""
    h, w = s.depth or (0, 0)
    out = np.concatenate([np.full(5 * s.multiranger + s.flow, s.range_limit), np.full(h * w, s.depth_max_range)])
    out.setflags(write=False)
    return out


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


def deck_part(cfg: Any, pos: Any, vel: Any, R: Any, omega: Any, obstacles: Any = None,
              draws: dict[str, Any] | None = None) -> Any:
    """(..., N, sensors.obs_dim) the deck sensors' observation part (:func:`deck_layout` order, flags
    as 0.0 / 1.0; :func:`deck_readings` gives it as named readings) from the TRUE state: ``pos`` (...,
    N, 3) m and ``vel`` (..., N, 3) m/s (world), R (..., N, 3, 3) body -> world, ``omega`` (..., N, 3)
    rad/s (body); ``obstacles`` = (centres, valid, radius) of the column map or None; ``draws`` from
    :func:`deck_draw_spec` (None: noise-free).

    Every ToF reading (VL53L1x model, all rays at once) is valid where the true range ``t`` is within
    its limit and not dropped (draw >= dropout); a valid reading is ``t + tof_std(t) z`` clipped to
    [0, limit], an invalid one reads the limit."""
    xp = array_namespace(pos, vel, R)
    s = cfg.sensors
    t = cast_rays(pos, world_rays(R, ray_directions(s)), cfg.room_low, cfg.room_high, obstacles, cfg.hitbox)
    limit = xp.asarray(ray_limits(s), dtype=t.dtype)
    valid = t <= limit
    r = t
    if draws is not None:
        valid = valid & (draws["range_drop"] >= s.dropout)
        r = t + tof_std(t) * draws["range_noise"]
    r = xp.where(valid, xp.minimum(xp.maximum(r, 0.0), limit), limit)
    flags = valid.astype(t.dtype)
    parts: list[Any] = []
    k = 0
    if s.multiranger:
        parts += [r[..., :5], flags[..., :5]]
        k = 5
    if s.flow:
        d = t[..., k]  # the true range along body -z
        v_body = sum(R[..., c, :] * vel[..., c, None] for c in range(3))  # R^T v
        fx, fy, rate_ok = flow_pixels(v_body, omega, d)
        fvalid = rate_ok & (d >= FLOW_MIN_RANGE)
        if s.light_lux < FLOW_MIN_LUX:  # too dark: never valid
            fvalid = xp.zeros_like(fvalid)
        f = xp.stack([fx, fy], axis=-1)
        if draws is not None:
            f = f + FLOW_STD_PX * draws["flow_noise"]
        f = xp.where(fvalid[..., None], xp.minimum(xp.maximum(f, -FLOW_LIMIT_PX), FLOW_LIMIT_PX), 0.0)
        parts += [r[..., k:k + 1], f, flags[..., k:k + 1], fvalid[..., None].astype(t.dtype)]
        k += 1
    if s.depth is not None:
        parts.append(r[..., k:])
    return parts[0] if len(parts) == 1 else xp.concatenate(parts, axis=-1)


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


def _split(s: SensorConfig, part: Any) -> dict[str, Any]:
    """The named readings (:func:`deck_readings`) of a deck observation part (..., N, S) in metres."""
    out: dict[str, Any] = {}
    k = 0
    for name, w in deck_layout(s):
        v = part[..., k:k + w]
        if name.endswith("_valid"):
            v = v > 0.5
        elif name == "depth":
            v = v.reshape(v.shape[:-1] + s.depth)
        out[name] = v
        k += w
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


def deck_info(cfg: Any, obs: Any, scale: Any = None) -> dict[str, Any]:
    """The info entries of the deck readings from an observation (..., N, obs_dim) (its last
    ``sensors.obs_dim`` components; ``scale``: the observation's normalization, or None):
    ``multiranger`` (..., N, 5) m, ``multiranger_valid`` (..., N, 5) bool, ``flow`` (..., N, 3),
    ``flow_valid`` (..., N, 2) bool, ``depth`` (..., N, H, W) m; {} with the sensors off. NumPy in:
    float32 NumPy copies out; ``jax.numpy`` in: ``jax.numpy`` out."""
    s = cfg.sensors
    if not s.any:
        return {}
    xp = array_namespace(obs)
    o = np.asarray(obs, dtype=np.float32) if xp is np else obs
    start = cfg.obs_dim - s.obs_dim
    part = o[..., start:]
    if scale is not None:
        part = part * xp.asarray(np.asarray(scale)[start:], dtype=part.dtype)
    out = _split(s, part)
    return {k: np.array(v) for k, v in out.items()} if xp is np else out
