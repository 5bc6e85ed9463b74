"""The multi-ranger and flow decks' observation part in NumPy with few, cheap array calls (the MuJoCo
engine's (1, 8, .) arrays: NumPy's per-call cost dominates, and a call's cost depends on its form).

:func:`deck_part` gives the same bits as :func:`quadswarm_mj.sensors.deck_part` (its NumPy forms
``sensor_rays._axis_hits_numpy`` and ``sensors._deck_part_numpy``; ``tests/test_sensors_speed.py``):
the same floating-point operations on the same operands, nearly every call in NumPy's cheapest form
(contiguous operands of one shape or 0-d; ``maximum``, ``minimum`` and reductions with a keyword ``out``).
Each input is gathered once (``ndarray.take``) into work arrays (per config, shape and thread) laid out so
that reductions are calls on contiguous blocks: the room's quotients world axis first; the hitbox hits
neighbour first, the room's ranges beside them, one minimum over both on the unsigned integers of their
bits (a hit ahead is a float >= 0, ordered as the floats; a miss (NaN) or a hit behind (< 0) orders
above +inf, as in ``perf/depth_xla.py``). The readings: one row of the ranges, then the flow lanes (x, y,
unused), so the noise, the clip and the masked copy are one call each (per-lane constants make the
ToF-noise chain give the flow's noise scale on its lanes: clip to 0, exp(0) = 1). The body-frame
products stay BLAS products as the model's (they round with FMA); with the flow deck the body velocity is
row N of the neighbours' product (offset vel - 0), one product instead of two (the same bits here; the
bitwise tests check it). With the depth camera its part comes from :mod:`quadswarm_mj.perf.numpy_depth`
(joined after this one's); other inputs (JAX arrays, float32, noise given as ``range_z``) go to the model's
function. ``core.ops.NumpyOps`` passes it to ``build_obs`` as ``deck_fn``.
"""

from __future__ import annotations

import dataclasses
import threading
from typing import Any

import numpy as np

from quadswarm_mj import sensors
from quadswarm_mj.perf import numpy_depth
from quadswarm_mj.sensor_rays import column_hits_xy

_clip = np._core.umath.clip
_add, _sub, _mul, _div, _abs = np.add, np.subtract, np.multiply, np.divide, np.abs
_max, _min, _le, _ge, _exp, _sqrt, _matmul = np.maximum, np.minimum, np.less_equal, np.greater_equal, np.exp, \
    np.sqrt, np.matmul
_and, _putmask = np.logical_and, np.putmask
_add_reduce, _min_reduce, _fmax_reduce, _fmin_reduce = np.add.reduce, np.minimum.reduce, np.fmax.reduce, \
    np.fmin.reduce


class _Scratch:
    """Preallocated work arrays of :func:`deck_part` for one (sensors, shape, room, hitbox), the gather
    indices that fill them and the views its calls read and write (nothing is allocated or sliced per
    call but the result). Constants are read-only and of their operands' shapes (or 0-d)."""

    def __init__(self, s: Any, shape: tuple[int, ...], room_low: tuple, room_high: tuple,
                 radius: float | None) -> None:
        lead, n = shape[:-1], shape[-2]  # lead = (..., N)
        e, full = np.empty, (lambda x, shp: np.broadcast_to(np.asarray(x, float), shp).copy())
        k, f = s.num_rays, (3 if s.flow else 0)  # range lanes; flow lanes x, y, unused (per quad)
        nq, rs = int(np.prod(lead)), int(np.prod(lead)) * (k + f)
        self.shape, self.k, self.f = shape, k, f
        # --- the cast. The room: (hi/lo, a, ..., N, c, +-) quotients gap_a / (+-R[a, c]), gathered from pos, R
        room = (2, 3) + lead + (3, 2)
        pos_id = np.arange(nq * 3).reshape(shape)
        self.pos_idx = np.broadcast_to(np.moveaxis(pos_id, -1, 0)[(None, ...) + (None,) * 2], room).ravel()
        self.r_idx = np.broadcast_to(np.moveaxis(np.arange(nq * 9).reshape(lead + (3, 3)), -2, 0)[None, ..., None],
                                     room).copy()
        ex = (...,) + (None,) * (len(lead) + 2)
        self.planes = full(np.array([room_high, room_low], float)[ex], room)
        self.g_lo = full(np.array([[1e-30] * 3, [-np.inf] * 3])[ex], room)  # the gaps kept > 0 (high), < 0 (low)
        self.g_hi = full(np.array([[np.inf] * 3, [-1e-30] * 3])[ex], room)
        self.signs = full(np.array([1.0, -1.0]), room)  # a body axis' two rays
        self.inv, self.q, self.m = e(room), e(room), e(room[1:])
        self.q0, self.q1, self.m0, self.m1, self.m2 = self.q[0], self.q[1], self.m[0], self.m[1], self.m[2]
        # hb = [ob | sqrt(disc) (the hitboxes) | 0 | t6 (the ranges along the 6 body axes)], with both decks t6
        # the first 6 lanes of the rows [ranges (..., N, K) | flow (..., N, 1, 3)]. With the flow deck the body
        # velocity is the pairs' matrix product's row N (its offset row: vel - 0; never a hit)
        hit = radius is not None and n > 1
        self.vel_row = hit and f > 0
        nv = n + self.vel_row
        pair = lead + (nv, 3)
        size = int(np.prod(pair)) if hit else 0
        both = s.multiranger and s.flow
        self.hb = np.zeros(2 * size + 1 + (rs if both else nq * 6))
        self.rows = self.hb[2 * size + 1:] if both else e(rs)
        self.ranges = self.rows[:nq * k].reshape(lead + (k,))
        self.t6 = self.hb[2 * size + 1:2 * size + 1 + nq * 6].reshape(lead + (6,))
        self.t = self.t6.reshape(lead + (3, 2))
        self.tu = self.t.view(np.uint64)
        self.t_rays = None if both else self.t6[..., slice(0, 5) if s.multiranger else slice(5, 6)]
        self.r2 = None  # (..., N, N (+ 1)) hitbox radius^2, -inf on the diagonal (None: no hitbox test)
        self.pv = np.zeros(2 * nq * 3 + 1)  # [pos | vel | 0]: the gathers' source with the velocity row
        self.pv_pos, self.pv_vel = self.pv[:nq * 3].reshape(shape), self.pv[nq * 3:2 * nq * 3].reshape(shape)
        if hit:  # offsets, body frame, disc and its root; the hits and the room's t gathered (j, ..., N, c, +-)
            r2 = np.full((n, nv), radius * radius)
            r2[:, n:] = -np.inf
            np.fill_diagonal(r2, -np.inf)
            self.r2 = full(r2, lead + (nv,))
            pj = np.broadcast_to(pos_id[..., None, :, :], lead + (n, 3))  # (..., N (i), N (j), 3): quad j, quad i
            pi = np.broadcast_to(pos_id[..., :, None, :], lead + (n, 3))
            if self.vel_row:
                pj = np.concatenate([pj, (nq * 3 + pos_id)[..., None, :]], axis=-2)
                pi = np.concatenate([pi, np.full(lead + (1, 3), 2 * nq * 3)], axis=-2)
            self.pos_idx = np.concatenate([self.pos_idx, pj.ravel(), pi.ravel()])
            self.cc = e(lead + (nv,))
            self.ob, self.disc = self.hb[:size].reshape(pair), self.hb[size:2 * size].reshape(pair)
            self.ob_vel = self.ob[..., n:, :]  # (..., N, 1, 3) the body velocity (with the flow deck)
            self.cc3 = self.cc[..., None]
            hits = (n + 1,) + lead + (3, 2)  # row N: the room's t (times 1, minus 0)
            ob_id = np.moveaxis(np.arange(size).reshape(pair)[..., :n, :], -2, 0)[..., None]
            ob_id = np.concatenate([np.broadcast_to(ob_id, (n,) + hits[1:]),
                                    (2 * size + 1 + np.arange(nq * 6)).reshape((1,) + hits[1:])])
            sq_id = np.concatenate([ob_id[:n] + size, np.full((1,) + hits[1:], 2 * size)])
            self.h_idx = np.concatenate([ob_id.ravel(), sq_id.ravel()])
            self.hg = e(self.h_idx.size)
            self.obg, self.sqg = self.hg[:self.hg.size // 2].reshape(hits), self.hg[self.hg.size // 2:].reshape(hits)
            self.obg_u = self.obg.view(np.uint64)
            self.hsigns = full(np.array([1.0, -1.0]), hits)
            self.hsigns[-1] = 1.0
        self.pg = e(self.pos_idx.size)  # the gathered pos: the room's gaps, then the pairs' quad j and quad i
        self.gaps = self.pg[:self.q.size].reshape(room)
        if self.r2 is not None:
            size = int(np.prod(pair))
            self.pj, self.pi = (self.pg[self.q.size + i * size:self.q.size + (i + 1) * size].reshape(pair)
                                for i in (0, 1))
        # --- the readings on the rows and their like
        self.a, self.b, self.ab, self.ab2 = e(rs), np.zeros(rs), e(rs), e(rs)
        self.m_ok, self.g = e(rs, bool), e(rs, bool)
        self.bk, self.gk = self.b[:nq * k].reshape(lead + (k,)), self.g[:nq * k].reshape(lead + (k,))
        self.uw = e(lead + (k,))
        kf = k - 1  # the down ray's lane (flow deck)
        if f:
            fl = lead + (1, 3)
            self.flow = self.rows[nq * k:].reshape(fl)
            self.bf2 = self.b[nq * k:].reshape(fl)[..., 0, :2]
            self.gf, self.mf = self.g[nq * k:].reshape(fl), self.m_ok[nq * k:].reshape(fl)
            q = np.arange(nq).reshape(lead)[..., None, None]
            self.d_idx = np.broadcast_to(q * k + kf, fl).copy()  # the down range, thrice per quad
            self.om_idx = (3 * q + np.array([1, 0, 2])).astype(np.intp)  # omega (x, y, z) -> (y, x, z)
            self.om_signs = full(np.array([-1.0, 1.0, 1.0]), fl)  # + (-omega_y, omega_x, .)
            self.dd, self.om = e(fl), e(fl)
            self.perm = np.arange(rs)  # the flow's x and y lanes swapped (max(|x|, |y|) on both)
            self.perm[nq * k:] = (nq * k + 3 * np.arange(nq)[:, None] + np.array([1, 0, 2])).ravel()

        def lanes(rng: float, fx: float, fz: float = 0.0) -> np.ndarray:
            """per lane: ``rng`` on the ranges, ``fx`` on the flow's x and y, ``fz`` on its unused lane"""
            out = np.empty(rs)
            out[:nq * k], out[nq * k:] = rng, np.tile([fx, fx, fz], nq) if f else []
            return out

        self.lim = lanes(s.range_limit, sensors.FLOW_MAX_RATE, -np.inf)  # valid: range <= limit, rate <= max
        self.tof = (lanes(0.0, 0.0), lanes(sensors.TOF_POINT_B, 0.0), lanes(sensors.TOF_POINT_A, 0.0),
                    lanes(sensors.TOF_STD_K, 1.0), lanes(1.0, 0.0), lanes(sensors.TOF_STD_A, sensors.FLOW_STD_PX))
        self.lo, self.hi = lanes(0.0, -sensors.FLOW_LIMIT_PX), lanes(s.range_limit, sensors.FLOW_LIMIT_PX)
        self.dropout, self.scale, self.tiny, self.d_min, self.min_range, self.gain = (np.array(v, float) for v in (
            s.dropout, 1.0 / (1.0 - s.dropout) if s.dropout < 1.0 else 0.0, 2.0 ** -24, 1e-3, sensors.FLOW_MIN_RANGE,
            sensors.FLOW_GAIN))
        self.dark = s.light_lux < sensors.FLOW_MIN_LUX
        self.ndtri = sensors._ndtri()
        # the buffer [values (rows) | flags (rows)] in its invalid state (the limit, flow 0, flags 0) and the
        # deck_layout columns as indices into it
        self.template = np.zeros(2 * rs)
        self.template[:nq * k] = s.range_limit
        self.buf = e(2 * rs)
        self.vals, self.flags = self.buf[:rs], self.buf[rs:]
        q = np.arange(nq)[:, None]
        cols = [q * k + np.arange(5), rs + q * k + np.arange(5)] if s.multiranger else []
        if f:
            fq = nq * k + 3 * q
            cols += [q * k + kf, fq, fq + 1, rs + q * k + kf, rs + fq]
        self.cols = np.concatenate(cols, axis=1).reshape(lead + (-1,))
        assert np.all(sensors.ray_limits(s) == s.range_limit)  # no depth: one limit for every ray
        for x in (self.planes, self.g_lo, self.g_hi, self.signs, self.r_idx, self.pos_idx, self.lim, self.lo,
                  self.hi, self.template, self.cols, *self.tof, self.dropout, self.scale, self.tiny, self.d_min,
                  self.min_range, self.gain, *((self.r2, self.h_idx, self.hsigns) if self.r2 is not None else ()),
                  *((self.d_idx, self.om_idx, self.om_signs, self.perm) if f else ())):
            x.setflags(write=False)


_LAST: dict[tuple[int, tuple[int, ...], int], tuple[Any, _Scratch]] = {}  # (id(cfg), shape, thread) -> (cfg, .)
_LAST_LOCK = threading.Lock()
_LOCAL = threading.local()  # .last: this thread's last (cfg, scratch)


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
    _LOCAL.last = hit
    return hit[1]


def _axis_hits(p: _Scratch, pos: np.ndarray, vel: np.ndarray, R: np.ndarray) -> None:
    """``sensor_rays._axis_hits_numpy`` (the same bits) into ``p.t`` (..., N, 3, 2): the ranges along the
    +-body axes. Call with the divide and invalid errors ignored."""
    if p.vel_row:
        p.pv_pos[...] = pos
        p.pv_vel[...] = vel
        p.pv.take(p.pos_idx, None, p.pg, "wrap")
    else:
        pos.take(p.pos_idx, None, p.pg, "wrap")
    gaps = p.gaps
    _sub(p.planes, gaps, out=gaps)  # high and low planes minus pos
    _clip(gaps, p.g_lo, p.g_hi, out=gaps)  # kept > 0 (high) and < 0 (low)
    inv = R.take(p.r_idx, None, p.inv, "wrap")
    _div(p.signs, inv, out=inv)  # 1 / (+-R[a, c])
    _mul(gaps, inv, out=p.q)
    _max(p.q0, p.q1, out=p.m)  # the plane ahead (the larger quotient, > 0)
    t = p.t
    _min(p.m0, p.m1, out=t)  # the nearest over the 3 world axes
    _min(t, p.m2, out=t)
    if p.r2 is None:
        return
    o = _sub(p.pj, p.pi, out=p.pj)  # (..., N (i), N (j) (+ 1), 3): quad j - quad i (, vel)
    ob = _matmul(o, R, out=p.ob)  # body frame of quad i: ob[i, j, c] = sum_a o[i, j, a] R[i, a, c]
    disc = _mul(ob, ob, out=p.disc)
    c = _add_reduce(disc, axis=-1, out=p.cc)
    _sub(c, p.r2, out=c)  # |offset|^2 - r^2 (a rotation keeps the length); inf on the diagonal
    _sub(disc, p.cc3, out=disc)  # >= 0: the line of ray +-c meets the sphere
    if _fmax_reduce(disc, axis=None) >= 0.0:
        # along +-c the hit is +-ob_c - sqrt(disc); kept where >= 0 (a miss: NaN, behind: < 0; both order
        # above +inf as unsigned integers)
        _sqrt(disc, out=disc)
        p.hb.take(p.h_idx, None, p.hg, "wrap")  # (j, ..., N (i), c, +-): ob, sqrt(disc); the room's t
        obg = _mul(p.obg, p.hsigns, out=p.obg)
        _sub(obg, p.sqg, out=obg)
        _min_reduce(p.obg_u, axis=0, out=p.tu)  # the nearest of the neighbours and the room (t: finite, >= 0)
        if _fmin_reduce(c, axis=None) < 0.0:  # (inside another's hitbox: disc > 0 along every axis)
            inside = np.logical_or.reduce(c < 0.0, axis=-1)
            t[inside] = 0.0


def deck_part(cfg: Any, pos: Any, vel: Any, R: Any, omega: Any, obstacles: Any = None,
              draws: dict[str, Any] | None = None) -> Any:
    """:func:`quadswarm_mj.sensors.deck_part` (same arguments, the same bits) for NumPy arrays with the
    multi-ranger and/or flow deck (float64); the depth camera's part by
    :func:`quadswarm_mj.perf.numpy_depth.deck_part`; otherwise the model's function."""
    s = cfg.sensors
    if s.depth is not None:
        if not (s.multiranger or s.flow):  # the depth camera alone
            return numpy_depth.deck_part(cfg, pos, vel, R, omega, obstacles, draws)
        if type(pos) is np.ndarray and pos.dtype == np.float64 and (draws is None or "range_u" in draws):
            return _with_depth(cfg, pos, vel, R, omega, obstacles, draws)
    if (s.depth is not None or type(pos) is not np.ndarray or pos.dtype != np.float64 or not s.any
            or (draws is not None and "range_u" not in draws)):
        return sensors.deck_part(cfg, pos, vel, R, omega, obstacles, draws)
    last = getattr(_LOCAL, "last", None)
    p = last[1] if last is not None and last[0] is cfg and last[1].shape == pos.shape else _scratch(cfg, pos.shape)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        return _deck_part(p, pos, vel, R, omega, obstacles, draws)


_SPLIT: dict[int, tuple[Any, Any, Any]] = {}  # id(cfg) -> (cfg, its decks without the camera, the camera alone)


def _with_depth(cfg: Any, pos: np.ndarray, vel: np.ndarray, R: np.ndarray, omega: np.ndarray, obstacles: Any,
                draws: dict[str, Any] | None) -> np.ndarray:
    """:func:`deck_part` with the depth camera and the multi-ranger and/or flow deck: the two parts of configs
    with the decks apart (made once per config), joined (the same bits: the model's readings are per ray, its
    deck part the body-axis rays' columns then the depth image's; ``range_u`` splits at the camera's rays)."""
    split = _SPLIT.get(id(cfg))
    if split is None or split[0] is not cfg:
        s = cfg.sensors
        split = (cfg, cfg.replace(sensors=dataclasses.replace(s, depth=None)),
                 cfg.replace(sensors=dataclasses.replace(s, multiranger=False, flow=False)))
        with _LAST_LOCK:
            _SPLIT[id(cfg)] = split
            while len(_SPLIT) > 32:
                _SPLIT.pop(next(iter(_SPLIT)))
    k = split[1].sensors.num_rays  # the body-axis rays first
    d_axis = d_depth = None
    if draws is not None:
        u = draws["range_u"]
        d_axis, d_depth = {**draws, "range_u": u[..., :k]}, {"range_u": u[..., k:]}
    return np.concatenate([deck_part(split[1], pos, vel, R, omega, obstacles, d_axis),
                           numpy_depth.deck_part(split[2], pos, vel, R, omega, obstacles, d_depth)], axis=-1)


def _deck_part(p: _Scratch, pos: np.ndarray, vel: np.ndarray, R: np.ndarray, omega: np.ndarray, obstacles: Any,
               draws: dict[str, Any] | None) -> np.ndarray:
    """:func:`deck_part`'s work (with the divide, invalid and overflow errors ignored): ``p.t`` the true
    ranges, then ``sensors._deck_part_numpy`` (the same bits) from them: the deck part in
    :func:`sensors.deck_layout` order (a fresh array)."""
    _axis_hits(p, pos, vel, R)
    if obstacles is not None:  # the rays' world x and y components: +-R[0, c], +-R[1, c] (as axis_hits)
        dx, dy = (np.stack([R[..., a, :], -R[..., a, :]], axis=-1).reshape(p.t6.shape) for a in range(2))
        _min(p.t6, column_hits_xy(pos, dx, dy, *obstacles), out=p.t6)
    if p.t_rays is not None:
        p.ranges[...] = p.t_rays
    rows, m = p.rows, p.m_ok
    p.buf[...] = p.template  # invalid readings: the limit, flow 0, flags 0
    if p.f:  # the flow lanes: the body velocity over the down range, + (-omega_y, omega_x, .)
        if p.vel_row:  # (..., N, 1, 3) the body velocity (x, y used)
            flow = p.flow
            flow[...] = p.ob_vel
        else:
            flow = _matmul(vel[..., None, :], R, out=p.flow)
        dd = rows.take(p.d_idx, None, p.dd, "wrap")
        _ge(dd, p.min_range, out=p.gf)  # high enough for the flow
        _max(dd, p.d_min, out=dd)
        _div(flow, dd, out=flow)
        om = omega.take(p.om_idx, None, p.om, "wrap")
        _add(flow, _mul(om, p.om_signs, out=om), out=flow)
    ab = _abs(rows, out=p.ab)  # the ranges (>= 0) and the flow's |x|, |y|
    if p.f:
        _max(ab, ab.take(p.perm, None, p.ab2, "wrap"), out=ab)  # max(|x|, |y|) on both flow lanes
    _le(ab, p.lim, out=m)  # valid: range <= limit, flow rate <= its maximum
    if draws is not None:
        u = draws["range_u"]
        _ge(u, p.dropout, out=p.gk)  # not dropped
        _and(m, p.g, out=m)
    elif p.f:
        _and(p.mf, p.gf, out=p.mf)
    if p.f:
        if p.dark:  # too dark: the flow never valid
            p.mf[...] = False
        _mul(p.flow, p.gain, out=p.flow)
    a = p.a
    if draws is not None:  # VL53L1x: t + tof_std(t) tof_normal(u); the flow: + FLOW_STD_PX flow_noise
        lo, hi, a_point, k, one, std = p.tof
        _clip(rows, lo, hi, out=a)  # tof_std(t) (the sign of a zero range is lost next)
        _sub(a, a_point, out=a)
        _mul(a, k, out=a)
        _exp(a, out=a)
        _add(a, one, out=a)
        _mul(a, std, out=a)
        w = _sub(u, p.dropout, out=p.uw)  # tof_normal(u, dropout)
        _mul(w, p.scale, out=w)
        _max(w, p.tiny, out=w)
        p.ndtri(w, out=p.bk)
        if p.f:
            p.bf2[...] = draws["flow_noise"]
        _mul(a, p.b, out=a)
        _add(a, rows, out=a)
        _clip(a, p.lo, p.hi, out=a)  # the ranges to [0, limit], the flow to +-FLOW_LIMIT_PX
    else:
        _clip(rows, p.lo, p.hi, out=a)
    _putmask(p.vals, m, a)  # the valid readings (the invalid keep the template's)
    p.flags[...] = m
    return p.buf.take(p.cols)
