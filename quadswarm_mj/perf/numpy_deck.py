"""The multi-ranger and flow decks' observation part in NumPy with few, cheap array calls (the MuJoCo
engine's (1, 8, .) arrays: NumPy's per-call cost dominates, and a call's cost depends on its form).

:func:`deck_part` gives the same bits as :func:`quadswarm_mj.sensors.deck_part` (its NumPy forms
``sensor_rays._axis_hits_numpy`` and ``sensors._deck_part_numpy``; ``tests/test_sensors_speed.py``):
the same floating-point operations on the same operands, only with same-shape or 0-d operands instead
of broadcast constants and Python floats (~3x and ~2x cheaper calls); minima over short axes as
elementwise calls on slices instead of ``ufunc.reduce``; the hitbox minimum on the unsigned integers
of the distances' bits (a hit ahead is a float >= 0, ordered as the floats; a miss (NaN) or a hit
behind (< 0) orders above +inf, as in ``perf/depth_xla.py``) instead of ``where`` and a float minimum;
preallocated work arrays and views (per config, shape and thread); ``np.copyto(where=)`` instead of
ufuncs with ``where=``; ``ndarray.take`` instead of ``np.take``. The two matrix products (the
neighbours' body-frame offsets, the body velocity) stay as the model writes them (they round with FMA).
Other configurations (the depth camera, JAX arrays, noise given as ``range_z``) go to the model's
function. ``core.ops.NumpyOps`` passes it to ``build_obs`` as ``deck_fn``.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from quadswarm_mj import sensors
from quadswarm_mj.sensor_rays import column_hits_xy

_clip = np._core.umath.clip
_SWAP = np.array([1, 0, 2])  # omega (x, y, z) -> (y, x, z)


class _Scratch:
    """Preallocated work arrays of :func:`deck_part` for one (sensors, shape, room, hitbox), with the views
    its calls read and write (no array is allocated or sliced per call but the result). Constants are
    read-only; ``scalars`` holds the model's scalars as 0-d float64 arrays."""

    def __init__(self, s: Any, shape: tuple[int, ...], room_low: tuple, room_high: tuple,
                 radius: float | None) -> None:
        lead, n = shape[:-1], shape[-2]  # lead = (..., N)
        e = np.empty
        self.planes = np.array([room_high, room_low], float)  # (2, 3): the room's high and low planes
        self.g_lo, self.g_hi = (np.broadcast_to(np.array(b, float), lead + (2, 3)).copy() for b in
                                ([[1e-30] * 3, [-np.inf] * 3], [[np.inf] * 3, [-1e-30] * 3]))  # the gaps' bounds
        self.signs = np.array([1.0, -1.0])  # a body axis' two rays
        self.gaps, self.inv, self.q = e(lead + (2, 3)), e(lead + (3, 3, 2)), e(lead + (2, 3, 3, 2))
        self.q0, self.q1 = self.q[..., 0, :, :, :], self.q[..., 1, :, :, :]
        self.m = e(lead + (3, 3, 2))
        self.m0, self.m1, self.m2 = self.m[..., 0, :, :], self.m[..., 1, :, :], self.m[..., 2, :, :]
        self.t = e(lead + (3, 2))  # the 6 axis rays' ranges (+x, -x, +y, -y, +z, -z)
        self.t6, self.tu = self.t.reshape(lead + (6,)), self.t.view(np.uint64)
        self.r2 = None  # (N, N): hitbox radius^2, -inf on the diagonal (None: no hitbox test)
        if radius is not None and n > 1:
            self.r2 = np.full((n, n), radius * radius)
            np.fill_diagonal(self.r2, -np.inf)
            pair = lead + (n, 3)
            self.o, self.ob, self.ob2, self.sq = e(pair), e(pair), e(pair), e(pair)
            self.cc = e(lead + (n,))
            self.ts = e((2,) + pair)  # (+-, ..., N (i), N (j), 3)
            self.ts0, self.ts1, self.tsu = self.ts[0], self.ts[1], self.ts.view(np.uint64)
            # the minimum over the neighbours j by halving: (a, b, out) views of elementwise minima
            self.halving, x, k = [], self.tsu, n
            while k > 1:
                h = k // 2
                out = e((2,) + lead + (h, 3), np.uint64)
                self.halving.append((x[..., :h, :], x[..., h:2 * h, :], out))
                if k % 2:
                    self.halving.append((out[..., :1, :], x[..., 2 * h:, :], out[..., :1, :]))
                x, k = out, h
            near = x[..., 0, :]  # (+-, ..., N, 3): the nearest hit per ray
            self.near_t = near.transpose(tuple(range(1, near.ndim)) + (0,))  # as t: (..., N, 3, +-)
        self.rays = slice(0, 6) if s.multiranger and s.flow else slice(0, 5) if s.multiranger else slice(5, 6)
        self.t_rays = self.t6[..., self.rays]
        k = s.num_rays
        limit, self.cols, self.template, self.kf = sensors._numpy_plan(s, lead + (k,))
        assert np.all(limit == s.range_limit), limit  # no depth: one limit for every ray
        self.buf = e(self.template.shape)  # [r (K) | flags (K) | flow x, y | flow valid]
        self.r, self.flags = self.buf[..., :k], self.buf[..., k:2 * k]
        self.fxy, self.fvalid = self.buf[..., 2 * k:2 * k + 2], self.buf[..., 2 * k + 2]
        self.valid, self.lost = e(lead + (k,), bool), e(lead + (k,), bool)
        self.x, self.w = e(lead + (k,)), e(lead + (k,))
        self.vb, self.dd, self.om = e(lead + (1, 3)), e(lead + (1,)), e(lead + (3,))
        self.v3 = self.vb.reshape(lead + (3,))  # the body velocity (x, y used; the third unused)
        self.v2 = self.v3[..., :2]
        self.aw, self.rate_max, self.fn = e(lead + (3,)), e(lead[:-1] + (n,)), e(lead + (2,))
        self.aw0, self.aw1 = self.aw[..., 0], self.aw[..., 1]
        self.rate_ok, self.far = e(lead[:-1] + (n,), bool), e(lead[:-1] + (n,), bool)
        self.rate_ok2 = self.rate_ok[..., None]
        self.d = self.t_rays[..., self.kf:self.kf + 1]  # (..., N, 1) the true range along body -z (flow deck)
        self.omega_signs = np.broadcast_to(np.array([-1.0, 1.0, 1.0]), lead + (3,)).copy()  # -omega_y, +omega_x
        scale = 1.0 / (1.0 - s.dropout) if s.dropout < 1.0 else 0.0
        self.scalars = {k: np.array(v, float) for k, v in {
            "limit": s.range_limit, "dropout": s.dropout, "scale": scale, "tiny": 2.0 ** -24, "zero": 0.0,
            "one": 1.0, "tof_b": sensors.TOF_POINT_B, "tof_a_point": sensors.TOF_POINT_A,
            "tof_k": sensors.TOF_STD_K, "tof_a": sensors.TOF_STD_A, "d_min": 1e-3,
            "max_rate": sensors.FLOW_MAX_RATE, "min_range": sensors.FLOW_MIN_RANGE, "gain": sensors.FLOW_GAIN,
            "std_px": sensors.FLOW_STD_PX, "lim_px": sensors.FLOW_LIMIT_PX, "neg_lim_px": -sensors.FLOW_LIMIT_PX,
        }.items()}
        for x in (self.planes, self.g_lo, self.g_hi, self.signs, self.r2, self.omega_signs, *self.scalars.values()):
            if x is not None:
                x.setflags(write=False)


_LAST: dict[tuple[int, tuple[int, ...], int], tuple[Any, _Scratch]] = {}  # (id(cfg), shape, thread) -> (cfg, .)
_LAST_LOCK = threading.Lock()


def _scratch(cfg: Any, shape: tuple[int, ...]) -> _Scratch:
    """The :class:`_Scratch` of ``cfg`` for positions of ``shape`` in this thread (made once; the last 32
    kept)."""
    key = (id(cfg), shape, threading.get_ident())
    hit = _LAST.get(key)
    if hit is None or hit[0] is not cfg:
        hit = (cfg, _Scratch(cfg.sensors, shape, tuple(cfg.room_low), tuple(cfg.room_high), cfg.hitbox))
        with _LAST_LOCK:  # envs stepped in several threads share the table
            _LAST[key] = hit
            while len(_LAST) > 32:
                _LAST.pop(next(iter(_LAST)))
    return hit[1]


def _axis_hits(p: _Scratch, pos: np.ndarray, R: np.ndarray) -> None:
    """``sensor_rays._axis_hits_numpy`` (the same bits) into ``p.t`` (..., N, 3, 2): the ranges along the
    +-body axes. Call inside ``np.errstate(divide="ignore", invalid="ignore")``."""
    np.subtract(p.planes, pos[..., None, :], out=p.gaps)  # (..., N, 2, 3): high and low planes minus pos
    _clip(p.gaps, p.g_lo, p.g_hi, out=p.gaps)  # kept > 0 (high) and < 0 (low)
    np.divide(p.signs, R[..., None], out=p.inv)  # (..., N, a, c, +-): 1 / (+-R[a, c])
    np.multiply(p.gaps[..., :, :, None, None], p.inv[..., None, :, :, :], out=p.q)  # (..., N, hi/lo, a, c, +-)
    np.maximum(p.q0, p.q1, out=p.m)  # the plane ahead (the larger quotient)
    np.minimum(p.m0, p.m1, out=p.t)  # the nearest over the 3 axes
    np.minimum(p.t, p.m2, out=p.t)
    if p.r2 is None:
        return
    np.subtract(pos[..., None, :, :], pos[..., :, None, :], out=p.o)  # (..., N (i), N (j), 3): quad j - quad i
    ob = np.matmul(p.o, R, out=p.ob)  # body frame of quad i: ob[i, j, c] = sum_a o[i, j, a] R[i, a, c]
    ob2 = np.multiply(ob, ob, out=p.ob2)
    c = np.add.reduce(ob2, axis=-1, out=p.cc)
    np.subtract(c, p.r2, out=c)  # |offset|^2 - r^2 (a rotation keeps the length); inf on the diagonal
    disc = np.subtract(ob2, c[..., None], out=ob2)  # >= 0: the line of ray +-c meets the sphere
    if np.fmax.reduce(disc, axis=None) >= 0.0:
        # along +c the hit is ob_c - sqrt(disc), along -c -ob_c - sqrt(disc) = -(ob_c + sqrt(disc)); kept
        # where >= 0 (a miss: NaN, behind: < 0; both order above +inf as unsigned integers)
        sq = np.sqrt(disc, out=p.sq)
        np.subtract(ob, sq, out=p.ts0)
        np.add(ob, sq, out=p.ts1)
        np.negative(p.ts1, out=p.ts1)
        for x, y, out in p.halving:  # the nearest over the neighbours
            np.minimum(x, y, out=out)
        np.minimum(p.tu, p.near_t, out=p.tu)  # the room's t: finite, >= 0
        if np.fmin.reduce(c, axis=None) < 0.0:  # (inside another's hitbox: disc > 0 along every axis)
            inside = np.logical_or.reduce(c < 0.0, axis=-1)
            p.t[inside] = 0.0


def deck_part(cfg: Any, pos: Any, vel: Any, R: Any, omega: Any, obstacles: Any = None,
              draws: dict[str, Any] | None = None) -> Any:
    """:func:`quadswarm_mj.sensors.deck_part` (same arguments, the same bits) for NumPy arrays with the
    multi-ranger and/or flow deck (no depth camera, float64); otherwise the model's function."""
    s = cfg.sensors
    if (s.depth is not None or type(pos) is not np.ndarray or pos.dtype != np.float64 or not s.any
            or (draws is not None and "range_u" not in draws)):
        return sensors.deck_part(cfg, pos, vel, R, omega, obstacles, draws)
    p = _scratch(cfg, pos.shape)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # (also the flow's unused third lane)
        _axis_hits(p, pos, R)
        t, d = p.t_rays, p.d
        if obstacles is not None:  # the rays' world x and y components: +-R[0, c], +-R[1, c] (as axis_hits)
            dx, dy = (np.stack([R[..., a, :], -R[..., a, :]], axis=-1).reshape(p.t6.shape) for a in range(2))
            t = np.minimum(p.t6, column_hits_xy(pos, dx, dy, *obstacles))[..., p.rays]
            d = t[..., p.kf:p.kf + 1]
        return _readings(p, s, t, d, vel, R, omega, draws)


def _readings(p: _Scratch, s: Any, t: np.ndarray, d: np.ndarray, vel: np.ndarray, R: np.ndarray, omega: np.ndarray,
              draws: dict[str, Any] | None) -> np.ndarray:
    """``sensors._deck_part_numpy`` (the same bits) from the true ranges ``t`` (..., N, K) and the down
    range ``d`` (..., N, 1): the deck part in :func:`sensors.deck_layout` order (a fresh array)."""
    c = p.scalars
    buf = p.buf
    np.copyto(buf, p.template)  # invalid readings: the limit, flow 0
    valid = np.less_equal(t, c["limit"], out=p.valid)
    x = p.x
    if draws is not None:  # VL53L1x: t + tof_std(t) tof_normal(u), clipped to [0, limit]
        u = draws["range_u"]
        valid &= np.greater_equal(u, c["dropout"], out=p.lost)
        np.maximum(t, c["zero"], out=x)  # tof_std(t) (= its clip(t, 0, 4): the sign of a zero range is lost next)
        np.minimum(x, c["tof_b"], out=x)
        x -= c["tof_a_point"]
        x *= c["tof_k"]
        np.exp(x, out=x)
        x += c["one"]
        x *= c["tof_a"]
        w = np.subtract(u, c["dropout"], out=p.w)  # tof_normal(u, dropout)
        w *= c["scale"]
        np.maximum(w, c["tiny"], out=w)
        x *= sensors._ndtri()(w, out=w)
        x += t
        np.maximum(x, c["zero"], out=x)
    else:
        np.maximum(t, c["zero"], out=x)
    np.minimum(x, c["limit"], out=x)
    np.copyto(p.r, x, where=valid)
    np.copyto(p.flags, valid)
    if s.flow:
        w = np.matmul(vel[..., None, :], R, out=p.vb)  # (..., N, 1, 3) the body velocity (x, y used)
        w = p.v3
        w /= np.maximum(d, c["d_min"], out=p.dd)
        w += np.multiply(omega.take(_SWAP, axis=-1, out=p.om), p.omega_signs, out=p.om)  # + (-omega_y, omega_x, .)
        np.abs(w, out=p.aw)
        rate_ok = np.less_equal(np.maximum(p.aw0, p.aw1, out=p.rate_max), c["max_rate"], out=p.rate_ok)
        rate_ok &= np.greater_equal(d[..., 0], c["min_range"], out=p.far)
        if s.light_lux < sensors.FLOW_MIN_LUX:  # too dark: never valid
            rate_ok[...] = False
        w *= c["gain"]
        if draws is not None:
            np.add(p.v2, np.multiply(draws["flow_noise"], c["std_px"], out=p.fn), out=p.v2)
        np.maximum(w, c["neg_lim_px"], out=w)
        np.minimum(w, c["lim_px"], out=w)
        np.copyto(p.fxy, p.v2, where=p.rate_ok2)
        np.copyto(p.fvalid, rate_ok)
    return buf.take(p.cols, axis=-1)
