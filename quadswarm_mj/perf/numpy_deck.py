"""The multi-ranger and flow decks' observation part in NumPy with few, cheap array calls (the MuJoCo
engine's (1, 8, .) arrays: NumPy's per-call cost dominates, and a call's cost depends on its form).

:func:`deck_part` gives the same bits as :func:`quadswarm_mj.sensors.deck_part` (its NumPy forms
``sensor_rays._axis_hits_numpy`` and ``sensors._deck_part_numpy``; ``tests/test_sensors_speed.py``,
``tests/test_numpy_deck_bits.py``): the same floating-point operations on the same operands, nearly every
call on contiguous operands of one shape or 0-d. The inputs (pos m, vel m/s world; omega rad/s body; R
body -> world) are gathered (one ``concatenate`` and one ``take``; R one ``take``) into work arrays (per
config, shape and thread) laid out so that one call serves several of the model's operations (one
subtraction makes the room's gaps and the pairs' offsets, one product the room's quotients and the flow's
rate terms) and reductions are calls on contiguous blocks (a ray's nearest of the neighbours and the
room's 3 world axes: one minimum on the distances' bits as unsigned integers, where a miss (-inf) or a hit
behind (< 0) orders above +inf); "any" tests are a comparison and ``count_nonzero``. The readings: one
row of the ranges, then the flow lanes (x, y, unused), so the noise, the clip and the masked copy are one
call each (per-lane constants make the ToF-noise chain give the flow's noise scale on its lanes). The
body-frame products stay BLAS products as the model's (they round with FMA); with the flow deck the body
velocity is row N of the neighbours' product (offset vel - 0). No floating-point error arises on finite
input, so no ``np.errstate`` is set (it costs ~3 us inside a step; tested under ``all="raise"``). The depth
camera's part: :mod:`quadswarm_mj.perf.numpy_depth`; other inputs (JAX, float32, noise as ``range_z``) go to
the model. ``core.ops.NumpyOps`` passes it on.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from quadswarm_mj import np_calls, sensors
from quadswarm_mj.perf import numpy_depth
from quadswarm_mj.perf.scratch_cache import LOCK, ScratchCache
from quadswarm_mj.sensor_rays import column_hits_xy

_clip = np_calls.clip
_add, _sub, _mul, _div, _abs = np.add, np.subtract, np.multiply, np.divide, np.abs
_max, _min, _le, _ge, _exp, _sqrt, _matmul = np.maximum, np.minimum, np.less_equal, np.greater_equal, np.exp, \
    np.sqrt, np.matmul
_and, _lt = np.logical_and, np.less
_min_reduce = np.minimum.reduce
_count_nonzero, _copyto, _concatenate = np_calls.count_nonzero, np_calls.copyto, np_calls.concatenate


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
        nr = int(np.prod(room))
        src_id = np.arange(nq * 3).reshape(shape)  # pos in the gathers' source (pv: [pos | vel | omega | 0])
        room_idx = np.broadcast_to(np.moveaxis(src_id, -1, 0)[(None, ...) + (None,) * 2], room).ravel()
        r_idx = np.broadcast_to(np.moveaxis(np.arange(nq * 9).reshape(lead + (3, 3)), -2, 0)[None, ..., None], room)
        ex = (...,) + (None,) * (len(lead) + 2)
        planes = full(np.array([room_high, room_low], float)[ex], room)
        self.g_lo = full(np.array([[1e-30] * 3, [-np.inf] * 3])[ex], room)  # the gaps kept > 0 (high), < 0 (low)
        self.g_hi = full(np.array([[np.inf] * 3, [-1e-30] * 3])[ex], room)
        self.m = e(room[1:])
        self.m0, self.m1, self.m2 = self.m[0], self.m[1], self.m[2]
        hit = radius is not None and n > 1
        self.vel_row = hit and f > 0  # the body velocity: the pairs' product's row N (offset vel - 0; never a hit)
        nv = n + self.vel_row
        pair = lead + (nv, 3)
        npair = int(np.prod(pair)) if hit else 0
        nom = nq * 3 if f else 0  # the flow's rate lanes (omega_y, omega_x, omega_z per quad)
        # xs = [planes | quad j | omega (y, x, z) | pos | quad i] (the pairs' parts empty without the hitbox
        # test, omega's without the flow deck): one gather fills all but the planes; one subtraction [planes |
        # quad j] - [pos | quad i] makes [gaps | offsets] in place of [pos | quad i]; one product [omega | gaps]
        # x [(-1, 1, 1) | 1 / (+-R)] (one quotient [(-1, 1, 1) | +-1] / [1 | R]) makes [the flow's rate terms |
        # the room's quotients]
        self.xs = e(2 * (nr + npair) + nom)
        self.xs[:nr] = planes.ravel()
        self.pg = self.xs[nr:]  # the gather's out
        self.xa, self.xb = self.xs[:nr + npair], self.xs[nr + npair + nom:]
        self.gaps = self.xb[:nr].reshape(room)
        self.xq = self.xs[nr + npair:nr + npair + nom + nr]  # [omega | gaps]
        self.rg = np.ones(nom + nr)  # [1 | R gathered]
        self.rg_r = self.rg[nom:]
        self.r_idx = r_idx.ravel().copy()
        signs = np.ones(nom + nr)  # the rates' (-1, 1, 1); a body axis' two rays (+1, -1)
        signs[nom:] = np.broadcast_to(np.array([1.0, -1.0]), room).ravel()
        if f:
            signs[:nom] = np.tile([-1.0, 1.0, 1.0], nq)
        self.signs, self.inv, self.qx = signs, e(nom + nr), e(nom + nr)
        self.q = self.qx[nom:].reshape(room)
        self.q0, self.q1 = self.q[0], self.q[1]
        if f:
            self.om_terms = self.qx[:nom].reshape(lead + (1, 3))  # (-omega_y, omega_x, omega_z)
        pj_idx = pi_idx = np.zeros(0, np.intp)
        om_idx = (2 * nq * 3 + 3 * np.arange(nq)[:, None] + np.array([1, 0, 2])).ravel() if f else pj_idx
        # hb = [ob | sqrt(disc) (the hitboxes) | 0 | m (the room per world axis) | t6 (the ranges along the 6
        # body axes)], with both decks t6 the first 6 lanes of the rows [ranges (..., N, K) | flow (..., N, 1, 3)]
        both = s.multiranger and s.flow
        size, nm = npair, 3 * nq * 6
        self.hb = np.zeros(2 * size + 1 + nm + (rs if both else nq * 6))
        self.m = self.hb[2 * size + 1:2 * size + 1 + nm].reshape(room[1:])
        self.m0, self.m1, self.m2 = self.m[0], self.m[1], self.m[2]
        at = 2 * size + 1 + nm
        self.rows = self.hb[at:] if both else e(rs)
        self.ranges = self.rows[:nq * k].reshape(lead + (k,))
        self.t6 = self.hb[at:at + nq * 6].reshape(lead + (6,))
        self.t = self.t6.reshape(lead + (3, 2))
        self.tu = self.t.view(np.uint64)
        self.t_rays = None if both else self.t6[..., slice(0, 5) if s.multiranger else slice(5, 6)]
        self.r2 = None  # (..., N, N (+ 1)) hitbox radius^2, -inf on the diagonal (None: no hitbox test)
        self.pv = np.zeros(3 * nq * 3 + 1)  # [pos | vel | omega | 0]: the gathers' source with the flow deck
        self.pv3 = self.pv[:3 * nq * 3].reshape((3 * shape[0],) + shape[1:])  # (pos, vel, omega) along axis 0
        if hit:  # offsets, body frame, disc and its root; the hits and the room gathered (j, ..., N, c, +-)
            r2 = np.full((n, nv), radius * radius)
            r2[:, n:] = -np.inf
            np.fill_diagonal(r2, -np.inf)
            self.r2 = full(r2, lead + (nv,))
            pj = np.broadcast_to(src_id[..., None, :, :], lead + (n, 3))  # (..., N (i), N (j), 3): quad j, quad i
            pi = np.broadcast_to(src_id[..., :, None, :], lead + (n, 3))
            if self.vel_row:
                pj = np.concatenate([pj, (nq * 3 + src_id)[..., None, :]], axis=-2)
                pi = np.concatenate([pi, np.full(lead + (1, 3), 3 * nq * 3)], axis=-2)
            pj_idx, pi_idx = pj.ravel(), pi.ravel()
            self.o = self.xb[nr:].reshape(pair)
            self.cc = e(lead + (nv,))
            self.c_neg = e(lead + (nv,), bool)  # |offset|^2 < r^2 (inside another's hitbox)
            # disc component first (c, ..., N (i), N (j) (+ 1)): |ob|^2 and its subtraction on contiguous blocks
            cm = (3,) + lead + (nv,)
            self.ob, self.disc = self.hb[:size].reshape(pair), self.hb[size:2 * size].reshape(cm)
            self.ob_cm = np.moveaxis(self.ob, -1, 0)  # a view of ob, component first
            self.misses = e(cm, bool)  # disc < 0: the line of a ray misses a hitbox
            self.ob_vel = self.ob[..., n:, :]  # (..., N, 1, 3) the body velocity (with the flow deck)
            self.cc1 = self.cc[None]
            self.disc0, self.disc1, self.disc2 = self.disc[0], self.disc[1], self.disc[2]
            hits = (n + 3,) + lead + (3, 2)  # rows N, N + 1, N + 2: the room per world axis (times 1, minus 0)
            ob_id = np.moveaxis(np.arange(size).reshape(pair)[..., :n, :], -2, 0)[..., None]
            ob_id = np.concatenate([np.broadcast_to(ob_id, (n,) + hits[1:]),
                                    (2 * size + 1 + np.arange(nm)).reshape((3,) + hits[1:])])
            disc_id = np.moveaxis(size + np.arange(size).reshape(cm), 0, -1)  # (..., N, N (+ 1), c) -> its place
            sq_id = np.moveaxis(disc_id[..., :n, :], -2, 0)[..., None]
            sq_id = np.concatenate([np.broadcast_to(sq_id, (n,) + hits[1:]), np.full((3,) + hits[1:], 2 * size)])
            self.h_idx = np.concatenate([ob_id.ravel(), sq_id.ravel()])
            self.hg = e(self.h_idx.size)
            self.obg, self.sqg = self.hg[:self.hg.size // 2].reshape(hits), self.hg[self.hg.size // 2:].reshape(hits)
            self.obg_u = self.obg.view(np.uint64)
            self.hsigns = full(np.array([1.0, -1.0]), hits)
            self.hsigns[n:] = 1.0
        self.src_pv = f > 0
        self.pos_idx = np.concatenate([pj_idx, om_idx, room_idx, pi_idx])
        assert self.pos_idx.size == self.pg.size
        self.zero, self.inf = np.array(0.0), np.array(np.inf)
        self.tiny_r = np.full(nr, 1e-300)  # added to the gathered R (no 1 / 0)
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
            self.dd = e(fl)
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
        for x in (self.g_lo, self.g_hi, self.signs, self.r_idx, self.pos_idx, self.lim, self.lo,
                  self.hi, self.template, self.cols, *self.tof, self.dropout, self.scale, self.tiny, self.d_min,
                  self.min_range, self.gain, self.zero, self.inf, self.tiny_r,
                  *((self.r2, self.h_idx, self.hsigns) if self.r2 is not None else ()),
                  *((self.d_idx, self.perm) if f else ())):
            x.setflags(write=False)


_CACHE = ScratchCache(lambda cfg, shape: _Scratch(cfg.sensors, shape, tuple(cfg.room_low), tuple(cfg.room_high),
                                                  cfg.hitbox))
_scratch = _CACHE.get  # the _Scratch of cfg for positions of shape in this thread
_LOCAL = _CACHE.local  # .last: this thread's last (cfg, scratch)


def _axis_hits(p: _Scratch, pos: np.ndarray, vel: np.ndarray, R: np.ndarray, omega: np.ndarray) -> None:
    """``sensor_rays._axis_hits_numpy`` (the same bits) into ``p.t`` (..., N, 3, 2): the ranges along the
    +-body axes; with the flow deck also ``p.om_terms`` = omega (y, x, z) (-1, 1, 1) (the flow's rate terms,
    ``sensors.flow_pixels2``'s product) and, with the hitbox test, the body velocity in ``p.ob_vel``. No
    floating-point error is raised on finite input (no ``np.errstate`` needed): an exact zero of R is made
    1e-300 (its quotients ~1e300 instead of +-inf: never the nearest, a unit ray has a component >= 0.57),
    a line that misses a hitbox gets sqrt(+inf) instead of sqrt(< 0) (its hit -inf instead of NaN: both
    order above +inf as unsigned integers). Outputs are ufuncs' positional ``out`` (cheaper than the keyword)."""
    if p.src_pv:
        _concatenate((pos, vel, omega), 0, p.pv3)
        p.pv.take(p.pos_idx, None, p.pg, "wrap")
    else:
        pos.take(p.pos_idx, None, p.pg, "wrap")
    _sub(p.xa, p.xb, p.xb)  # high and low planes minus pos; quad j - quad i (, vel - 0)
    gaps = p.gaps
    _clip(gaps, p.g_lo, p.g_hi, gaps)  # kept > 0 (high) and < 0 (low)
    rg_r = R.take(p.r_idx, None, p.rg_r, "wrap")
    _add(rg_r, p.tiny_r, rg_r)  # R + 1e-300: the same bits for |R| > 1e-284; an exact zero made 1e-300
    inv = _div(p.signs, p.rg, p.inv)  # (-1, 1, 1); 1 / (+-R[a, c])
    _mul(p.xq, inv, p.qx)  # the rates' terms; the room's quotients
    _max(p.q0, p.q1, out=p.m)  # the plane ahead along each world axis (the larger quotient, > 0)
    t = p.t
    if p.r2 is not None:
        # p.o (..., N (i), N (j) (+ 1), 3): quad j - quad i (, vel); body frame of quad i:
        _matmul(p.o, R, p.ob)  # ob[i, j, c] = sum_a o[i, j, a] R[i, a, c]
        disc = _mul(p.ob_cm, p.ob_cm, p.disc)  # (c, ..., N, N (+ 1))
        c = _add(p.disc0, p.disc1, p.cc)  # (np.add.reduce over the 3 components: the same sums)
        _add(c, p.disc2, c)
        _sub(c, p.r2, c)  # |offset|^2 - r^2 (a rotation keeps the length); inf on the diagonal
        _sub(disc, p.cc1, disc)  # >= 0: the line of ray +-c meets the sphere (never NaN)
        if _count_nonzero(_lt(disc, p.zero, p.misses)) < p.misses.size:  # a line meets a hitbox
            # along +-c the hit is +-ob_c - sqrt(disc); kept where >= 0 (a miss: -inf, behind: < 0; both order
            # above +inf as unsigned integers)
            _copyto(disc, p.inf, where=p.misses)
            _sqrt(disc, disc)
            p.hb.take(p.h_idx, None, p.hg, "wrap")  # (j, ..., N (i), c, +-): ob, sqrt(disc); the room's 3 axes
            obg = _mul(p.obg, p.hsigns, p.obg)
            _sub(obg, p.sqg, obg)
            _min_reduce(p.obg_u, 0, None, p.tu)  # the nearest of the neighbours and the room's planes (> 0)
            if _count_nonzero(_lt(c, p.zero, p.c_neg)):  # (inside another's hitbox: disc > 0 along every axis)
                t[np.logical_or.reduce(p.c_neg, axis=-1)] = 0.0
            return
    _min(p.m0, p.m1, out=t)  # the nearest over the 3 world axes
    _min(t, p.m2, out=t)


def deck_part(cfg: Any, pos: Any, vel: Any, R: Any, omega: Any, obstacles: Any = None,
              draws: dict[str, Any] | None = None, out: np.ndarray | None = None) -> Any:
    """:func:`quadswarm_mj.sensors.deck_part` (same arguments, the same bits) for NumPy arrays with the
    multi-ranger and/or flow deck (float64); the depth camera's part by
    :func:`quadswarm_mj.perf.numpy_depth.deck_part`; otherwise the model's function. ``out``: an array
    of the part's shape to write it into (returned), else a fresh array."""
    last = getattr(_LOCAL, "last", None)
    if (last is not None and last[0] is cfg and type(pos) is np.ndarray and pos.dtype is _F64
            and last[1].shape == pos.shape and (draws is None or "range_u" in draws)):  # as last call's
        return _deck_part(last[1], pos, vel, R, omega, obstacles, draws, out)
    if out is not None:
        out[...] = deck_part(cfg, pos, vel, R, omega, obstacles, draws)
        return out
    s = cfg.sensors
    if s.depth is not None:
        if not (s.multiranger or s.flow):  # the depth camera alone
            return numpy_depth.deck_part(cfg, pos, vel, R, omega, obstacles, draws)
        if type(pos) is np.ndarray and pos.dtype == np.float64 and (draws is None or "range_u" in draws):
            return _with_depth(cfg, pos, vel, R, omega, obstacles, draws)
    if (s.depth is not None or type(pos) is not np.ndarray or pos.dtype != np.float64 or not s.any
            or (draws is not None and "range_u" not in draws)):
        return sensors.deck_part(cfg, pos, vel, R, omega, obstacles, draws)
    p = last[1] if last is not None and last[0] is cfg and last[1].shape == pos.shape else _scratch(cfg, pos.shape)
    return _deck_part(p, pos, vel, R, omega, obstacles, draws)


_F64 = np.dtype(np.float64)


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
        with LOCK:
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
               draws: dict[str, Any] | None, out: np.ndarray | None = None) -> np.ndarray:
    """:func:`deck_part`'s work: ``p.t`` the true ranges, then ``sensors._deck_part_numpy`` (the same bits)
    from them: the deck part in :func:`sensors.deck_layout` order (into ``out``, else a fresh array). No
    floating-point error on finite input (see :func:`_axis_hits`; the columns' cast ignores its own)."""
    _axis_hits(p, pos, vel, R, omega)
    if obstacles is not None:  # the rays' world x and y components: +-R[0, c], +-R[1, c] (as axis_hits)
        dx, dy = (np.stack([R[..., a, :], -R[..., a, :]], axis=-1).reshape(p.t6.shape) for a in range(2))
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # (0 x -inf: a vertical ray)
            _min(p.t6, column_hits_xy(pos, dx, dy, *obstacles), out=p.t6)
    if p.t_rays is not None:
        p.ranges[...] = p.t_rays
    rows, m = p.rows, p.m_ok
    _copyto(p.buf, p.template)  # invalid readings: the limit, flow 0, flags 0
    if p.f:  # the flow lanes: the body velocity over the down range, + (-omega_y, omega_x, .)
        if p.vel_row:  # (..., N, 1, 3) the body velocity (x, y used)
            flow = p.flow
            _copyto(flow, p.ob_vel)
        else:
            flow = _matmul(vel[..., None, :], R, p.flow)
        dd = rows.take(p.d_idx, None, p.dd, "wrap")
        _ge(dd, p.min_range, p.gf)  # high enough for the flow
        _max(dd, p.d_min, out=dd)
        _div(flow, dd, flow)
        _add(flow, p.om_terms, flow)  # + (-omega_y, omega_x, .) (made in the cast)
    ab = _abs(rows, p.ab)  # the ranges (>= 0) and the flow's |x|, |y|
    if p.f:
        _max(ab, ab.take(p.perm, None, p.ab2, "wrap"), out=ab)  # max(|x|, |y|) on both flow lanes
    _le(ab, p.lim, m)  # valid: range <= limit, flow rate <= its maximum
    if draws is not None:
        u = draws["range_u"]
        _ge(u, p.dropout, p.gk)  # not dropped
        _and(m, p.g, m)
    elif p.f:
        _and(p.mf, p.gf, p.mf)
    if p.f:
        if p.dark:  # too dark: the flow never valid
            p.mf[...] = False
        _mul(p.flow, p.gain, p.flow)
    a = p.a
    if draws is not None:  # VL53L1x: t + tof_std(t) tof_normal(u); the flow: + FLOW_STD_PX flow_noise
        lo, hi, a_point, k, one, std = p.tof
        _clip(rows, lo, hi, a)  # tof_std(t) (the sign of a zero range is lost next)
        _sub(a, a_point, a)
        _mul(a, k, a)
        _exp(a, a)
        _add(a, one, a)
        _mul(a, std, a)
        w = _sub(u, p.dropout, p.uw)  # tof_normal(u, dropout)
        _mul(w, p.scale, w)
        _max(w, p.tiny, out=w)
        p.ndtri(w, p.bk)
        if p.f:
            p.bf2[...] = draws["flow_noise"]
        _mul(a, p.b, a)
        _add(a, rows, a)
        _clip(a, p.lo, p.hi, a)  # the ranges to [0, limit], the flow to +-FLOW_LIMIT_PX
    else:
        _clip(rows, p.lo, p.hi, a)
    _copyto(p.vals, a, where=m)  # the valid readings (the invalid keep the template's)
    _copyto(p.flags, m)
    return p.buf.take(p.cols) if out is None else p.buf.take(p.cols, None, out, "wrap")
