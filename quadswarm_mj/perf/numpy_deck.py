"""The multi-ranger and flow decks' observation part in NumPy with few, cheap array calls (the MuJoCo
engine's (1, 8, .) arrays: NumPy's per-call cost dominates, and a call's cost depends on its form).

:func:`deck_part` gives the same bits as :func:`quadswarm_mj.sensors.deck_part` (its NumPy forms
``sensor_rays._axis_hits_numpy`` and ``sensors._deck_part_numpy``; ``tests/test_sensors_speed.py``): the
same floating-point operations on the same operands, only

* same-shape or 0-d operands instead of broadcast constants and Python floats (a broadcast binary
  ufunc call costs ~3x a same-shape one, a Python float ~2x a 0-d array);
* minima and maxima over short axes as elementwise calls on slices instead of ``ufunc.reduce``;
* the hitbox minimum on the unsigned integers of the distances' bits (a hit ahead is a float >= 0,
  whose bits order as the floats do; a miss (NaN) or a hit behind (< 0) orders above +inf: see
  ``perf/depth_xla.py``) instead of ``where`` and a float minimum; the body velocity on its contiguous
  3 components (the third unused);
* ``np.copyto(where=)`` (a plain copy loop) instead of ufuncs with ``where=``; ``ndarray.take``
  instead of ``np.take``; a ``(-omega_y, omega_x)`` term as one subtract and one add.

The two matrix products (the neighbours' body-frame offsets, the body velocity) stay as the model
writes them (they round with FMA). Other configurations (the depth camera, JAX arrays, noise given
as ``range_z``) go to the model's function.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import numpy as np

from quadswarm_mj import sensors
from quadswarm_mj.sensor_rays import column_hits_xy

_clip = np._core.umath.clip
_SWAP = np.array([1, 0, 2])  # omega (x, y, z) -> (y, x, z)


class _Plan(NamedTuple):
    """Per (sensors, shape, room, hitbox) constants of :func:`deck_part` (read-only arrays)."""

    planes: np.ndarray  # (2, 3): the room's high and low planes
    g_lo: np.ndarray  # (..., N, 2, 3): the gaps' bounds (kept > 0 high, < 0 low)
    g_hi: np.ndarray
    signs: np.ndarray  # (2,): +1, -1 (a body axis' two rays)
    r2: np.ndarray | None  # (N, N): hitbox radius^2, -inf on the diagonal (None: no hitbox test)
    rays: slice  # the deck's rays among the 6 body-axis rays
    kf: int  # the flow deck's ray among the deck's rays
    cols: np.ndarray  # the deck part's columns in the buffer [r (K) | flags (K) | flow x, y | flow valid]
    template: np.ndarray  # the buffer with every reading invalid (r = the limit, flow = 0)
    c: dict[str, np.ndarray]  # the model's scalars as 0-d float64 arrays
    omega_signs: np.ndarray  # (..., N, 3): -1, 1, 1 (the flow's -omega_y, +omega_x; the third unused)


@functools.lru_cache(maxsize=32)
def _plan(s: Any, shape: tuple[int, ...], room_low: tuple, room_high: tuple, radius: float | None) -> _Plan:
    """The constants of :func:`deck_part` for positions of ``shape`` (..., N, 3)."""
    lead = shape[:-1]
    n = shape[-2]
    bounds = [np.broadcast_to(np.array(b, float), lead + (2, 3)).copy() for b in
              ([[1e-30] * 3, [-np.inf] * 3], [[np.inf] * 3, [-1e-30] * 3])]
    r2 = None
    if radius is not None and n > 1:
        r2 = np.full((n, n), radius * radius)
        np.fill_diagonal(r2, -np.inf)
    k_rays = s.num_rays
    limit, cols, template, kf = sensors._numpy_plan(s, lead + (k_rays,))
    assert np.all(limit == s.range_limit), limit  # no depth: one limit for every ray
    scale = 1.0 / (1.0 - s.dropout) if s.dropout < 1.0 else 0.0
    c = {k: np.array(v, float) for k, v in {
        "limit": s.range_limit, "dropout": s.dropout, "scale": scale, "tiny": 2.0 ** -24, "zero": 0.0,
        "one": 1.0, "tof_b": sensors.TOF_POINT_B, "tof_a_point": sensors.TOF_POINT_A, "tof_k": sensors.TOF_STD_K,
        "tof_a": sensors.TOF_STD_A, "d_min": 1e-3, "max_rate": sensors.FLOW_MAX_RATE,
        "min_range": sensors.FLOW_MIN_RANGE, "gain": sensors.FLOW_GAIN, "std_px": sensors.FLOW_STD_PX,
        "lim_px": sensors.FLOW_LIMIT_PX, "neg_lim_px": -sensors.FLOW_LIMIT_PX}.items()}
    rays = slice(0, 6) if s.multiranger and s.flow else slice(0, 5) if s.multiranger else slice(5, 6)
    out = _Plan(np.array([room_high, room_low], float), bounds[0], bounds[1], np.array([1.0, -1.0]), r2, rays,
                kf, cols, template, c, np.broadcast_to(np.array([-1.0, 1.0, 1.0]), shape).copy())
    for x in (out.planes, out.g_lo, out.g_hi, out.signs, out.r2, out.omega_signs, *c.values()):
        if x is not None:
            x.setflags(write=False)
    return out


_LAST: dict[tuple[int, tuple[int, ...]], tuple[Any, _Plan]] = {}  # (id(cfg), shape) -> (cfg, plan)


def _axis_hits(p: _Plan, pos: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``sensor_rays._axis_hits_numpy`` (the same bits): (..., N, 3, 2) ranges along +-body axes.
    Call inside ``np.errstate(divide="ignore", invalid="ignore")``."""
    gaps = np.subtract(p.planes, pos[..., None, :])  # (..., N, 2, 3): high and low planes minus pos
    _clip(gaps, p.g_lo, p.g_hi, out=gaps)  # kept > 0 (high) and < 0 (low)
    inv = np.divide(p.signs, R[..., None])  # (..., N, a, c, +-): 1 / (+-R[a, c])
    q = np.multiply(gaps[..., :, :, None, None], inv[..., None, :, :, :])  # (..., N, hi/lo, a, c, +-)
    m = np.maximum(q[..., 0, :, :, :], q[..., 1, :, :, :])  # the plane ahead (the larger quotient)
    t = np.minimum(m[..., 0, :, :], m[..., 1, :, :])  # the nearest over the 3 axes
    np.minimum(t, m[..., 2, :, :], out=t)
    if p.r2 is None:
        return t
    o = pos[..., None, :, :] - pos[..., :, None, :]  # (..., N (i), N (j), 3) world: quad j - quad i
    ob = o @ R  # body frame of quad i: ob[i, j, c] = sum_a o[i, j, a] R[i, a, c]
    ob2 = ob * ob
    c = np.add.reduce(ob2, axis=-1)
    np.subtract(c, p.r2, out=c)  # |offset|^2 - r^2 (a rotation keeps the length); inf on the diagonal
    disc = np.subtract(ob2, c[..., None], out=ob2)  # >= 0: the line of ray +-c meets the sphere
    if np.fmax.reduce(disc, axis=None) >= 0.0:
        # along +c the hit is ob_c - sqrt(disc), along -c -ob_c - sqrt(disc) = -(ob_c + sqrt(disc)); kept
        # where >= 0 (a miss: NaN, behind: < 0; both order above +inf as unsigned integers)
        sq = np.sqrt(disc)
        ts = np.empty((2,) + ob.shape)  # (+-, ..., N (i), N (j), 3)
        np.subtract(ob, sq, out=ts[0])
        np.add(ob, sq, out=ts[1])
        np.negative(ts[1], out=ts[1])
        near = np.minimum.reduce(ts.view(np.uint64), axis=-2)  # (+-, ..., N, 3): the nearest hit per ray
        tu = t.view(np.uint64)
        np.minimum(tu, near.transpose(tuple(range(1, near.ndim)) + (0,)), out=tu)  # the room's t: finite, >= 0
    if np.fmin.reduce(c, axis=None) < 0.0:
        inside = np.logical_or.reduce(c < 0.0, axis=-1)
        t[inside] = 0.0
    return t


def deck_part(cfg: Any, pos: Any, vel: Any, R: Any, omega: Any, obstacles: Any = None,
              draws: dict[str, Any] | None = None) -> Any:
    """:func:`quadswarm_mj.sensors.deck_part` (same arguments, the same bits) for NumPy arrays with the
    multi-ranger and/or flow deck (no depth camera); otherwise the model's function."""
    s = cfg.sensors
    if (s.depth is not None or type(pos) is not np.ndarray or (draws is not None and "range_u" not in draws)
            or not s.any):
        return sensors.deck_part(cfg, pos, vel, R, omega, obstacles, draws)
    hit = _LAST.get((id(cfg), pos.shape))
    if hit is None or hit[0] is not cfg:
        hit = _LAST[(id(cfg), pos.shape)] = (cfg, _plan(s, pos.shape, tuple(cfg.room_low), tuple(cfg.room_high),
                                                         cfg.hitbox))
        if len(_LAST) > 32:
            _LAST.pop(next(iter(_LAST)))
    p = hit[1]
    c = p.c
    with np.errstate(divide="ignore", invalid="ignore"):
        t = _axis_hits(p, pos, R).reshape(pos.shape[:-1] + (6,))
        if obstacles is not None:  # the rays' world x and y components: +-R[0, c], +-R[1, c] (as axis_hits)
            dx, dy = (np.stack([R[..., a, :], -R[..., a, :]], axis=-1).reshape(t.shape) for a in range(2))
            t = np.minimum(t, column_hits_xy(pos, dx, dy, *obstacles))
    t = t[..., p.rays]
    k_rays = t.shape[-1]
    buf = p.template.copy()  # invalid readings: the limit, flow 0
    valid = np.less_equal(t, c["limit"])
    if draws is not None:  # VL53L1x: t + tof_std(t) tof_normal(u), clipped to [0, limit]
        u = draws["range_u"]
        valid &= np.greater_equal(u, c["dropout"])
        x = np.maximum(t, c["zero"])  # tof_std(t) (= its clip(t, 0, 4): the sign of a zero range is lost next)
        np.minimum(x, c["tof_b"], out=x)
        x -= c["tof_a_point"]
        x *= c["tof_k"]
        np.exp(x, out=x)
        x += c["one"]
        x *= c["tof_a"]
        w = np.subtract(u, c["dropout"])  # tof_normal(u, dropout)
        w *= c["scale"]
        np.maximum(w, c["tiny"], out=w)
        x *= sensors._ndtri()(w, out=w)
        x += t
        np.maximum(x, c["zero"], out=x)
    else:
        x = np.maximum(t, c["zero"])
    np.minimum(x, c["limit"], out=x)
    np.copyto(buf[..., :k_rays], x, where=valid)
    np.copyto(buf[..., k_rays:2 * k_rays], valid)
    if s.flow:
        d = t[..., p.kf:p.kf + 1]  # (..., N, 1) the true range along body -z
        w = (vel[..., None, :] @ R).reshape(vel.shape)  # the body velocity (x, y used; contiguous)
        w /= np.maximum(d, c["d_min"])
        w += np.multiply(omega.take(_SWAP, axis=-1), p.omega_signs)  # + (-omega_y, omega_x, .)
        aw = np.abs(w)
        rate_ok = np.less_equal(np.maximum(aw[..., 0], aw[..., 1]), c["max_rate"])
        rate_ok &= np.greater_equal(d[..., 0], c["min_range"])
        if s.light_lux < sensors.FLOW_MIN_LUX:  # too dark: never valid
            rate_ok[...] = False
        w *= c["gain"]
        if draws is not None:
            np.add(w[..., :2], np.multiply(draws["flow_noise"], c["std_px"]), out=w[..., :2])
        np.maximum(w, c["neg_lim_px"], out=w)
        np.minimum(w, c["lim_px"], out=w)
        np.copyto(buf[..., 2 * k_rays:2 * k_rays + 2], w[..., :2], where=rate_ok[..., None])
        np.copyto(buf[..., 2 * k_rays + 2], rate_ok)
    return buf.take(p.cols, axis=-1)
