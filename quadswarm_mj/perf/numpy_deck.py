"""The multi-ranger and flow decks' observation part in NumPy with few, cheap array calls (the MuJoCo
engine's (1, 8, .) arrays: NumPy's per-call cost dominates, and a call's cost depends on its form).

:func:`deck_part` gives the same bits as :func:`quadswarm_mj.sensors.deck_part` (its NumPy forms
``sensor_rays._axis_hits_numpy`` and ``sensors._deck_part_numpy``; ``tests/test_sensors_speed.py``):
the same floating-point operations on the same operands. Almost every call is NumPy's cheapest form: its
operands contiguous and of one shape (or 0-d): each input is first gathered by one ``ndarray.take`` into
preallocated work arrays (per config, shape and thread) laid out so that the reductions become calls on
contiguous halves (the room's quotients world axis first, the hitbox hits neighbour first; their minimum
on the unsigned integers of the distances' bits: a hit ahead is a float >= 0, ordered as the floats; a
miss (NaN) or a hit behind (< 0) orders above +inf, as in ``perf/depth_xla.py``). The readings: one row
of the ranges of all quads, then one of their flow lanes (x, y, unused), so that the noise, the clip and
the masked copy are one call each for both decks (per-lane constants: the ToF-noise chain gives the
flow's noise scale on the flow lanes, clip to 0 then exp(0) = 1). The two matrix products (the
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


def _ro(*xs: np.ndarray) -> None:
    for x in xs:
        x.setflags(write=False)


class _Scratch:
    """Preallocated work arrays of :func:`deck_part` for one (sensors, shape, room, hitbox), the gather
    indices that fill them and the views its calls read and write (nothing is allocated or sliced per
    call but the result). Constants are read-only and of their operands' shapes (or 0-d)."""

    def __init__(self, s: Any, shape: tuple[int, ...], room_low: tuple, room_high: tuple,
                 radius: float | None) -> None:
        lead, n = shape[:-1], shape[-2]  # lead = (..., N)
        e, full = np.empty, (lambda x, shp: np.broadcast_to(np.asarray(x, float), shp).copy())
        hit = radius is not None and n > 1
        k, f = s.num_rays, (3 if s.flow else 0)  # range lanes; flow lanes x, y, unused (per quad)
        self.k, self.f, self.hit = k, f, hit
        # --- the cast. The room: (hi/lo, a, ..., N, c, +-) quotients gap_a / (+-R[a, c])
        room = (2, 3) + lead + (3, 2)
        pos_id = np.arange(int(np.prod(shape))).reshape(shape)
        r_id = np.arange(int(np.prod(shape)) * 3).reshape(lead + (3, 3))
        pos_idx = [np.broadcast_to(np.moveaxis(pos_id, -1, 0)[(None, ...) + (None,) * 2], room)]
        planes = np.moveaxis(np.array([room_high, room_low], float), 1, 1)[(..., ) + (None,) * (len(lead) + 2)]
        self.planes = full(planes, room)
        self.g_lo = full(np.array([1e-30, -np.inf])[(...,) + (None,) * (len(room) - 1)], room)  # gaps kept > 0
        self.g_hi = full(np.array([np.inf, -1e-30])[(...,) + (None,) * (len(room) - 1)], room)  # (high), < 0 (low)
        self.signs = full(np.array([1.0, -1.0]), room)  # a body axis' two rays
        self.r_idx = np.broadcast_to(np.moveaxis(r_id, -2, 0)[None, ..., None], room).copy()
        self.rg, self.q = e(room), e(room)
        self.q0, self.q1, self.m = self.q[0], self.q[1], e(room[1:])  # m: the plane ahead per world axis a
        self.m0, self.m1, self.m2 = self.m[0], self.m[1], self.m[2]
        # the ranges row [ranges (..., N, K) | flow (..., N, 1, 3)]: with both decks the K = 6 axis rays
        nq = int(np.prod(lead))
        self.rows = e(nq * (k + f))
        self.ranges = self.rows[:nq * k].reshape(lead + (k,))
        both = s.multiranger and s.flow
        self.t6 = self.ranges if both else e(lead + (6,))
        self.t = self.t6.reshape(lead + (3, 2))
        self.tu = self.t.view(np.uint64)
        self.t_rays = None if both else self.t6[..., slice(0, 5) if s.multiranger else slice(5, 6)]
        self.r2 = None
        if hit:  # the hitboxes: offsets, body frame (matmul), |.|^2 - r^2; gathered neighbour first
            pair = lead + (n, 3)
            size = int(np.prod(pair))
            self.r2 = full(np.where(np.eye(n, dtype=bool), -np.inf, radius * radius), lead + (n,))
            pj = np.broadcast_to(pos_id[..., None, :, :], pair)  # (..., N (i), N (j), 3): quad j, quad i
            pi = np.broadcast_to(pos_id[..., :, None, :], pair)
            pos_idx += [pj, pi]
            self.h = e(2 * size + size // 3)  # [ob | ob2 | c]
            self.ob, self.ob2 = self.h[:size].reshape(pair), self.h[size:2 * size].reshape(pair)
            self.cc = self.h[2 * size:].reshape(lead + (n,))
            hits = (n,) + lead + (3, 2)  # (j, ..., N (i), c, +-)
            ob_id = np.arange(size).reshape(pair)
            c_id = 2 * size + np.arange(size // 3).reshape(lead + (n,))
            self.h_idx = np.concatenate([np.broadcast_to(np.moveaxis(x, src, 0)[..., None] if src == -2 else
                                                         np.moveaxis(x, -1, 0)[..., None, None], hits).ravel()
                                         for x, src in ((ob_id, -2), (ob_id + size, -2), (c_id, -1))])
            self.hg = e(self.h_idx.size)
            hs = int(np.prod(hits))
            self.obg, self.o2g, self.cg = (self.hg[i * hs:(i + 1) * hs].reshape(hits) for i in range(3))
            self.hsigns = full(np.array([1.0, -1.0]), hits)
            self.halving, x, kk = [], self.obg.view(np.uint64), n  # the minimum over j by halving
            while kk > 1:
                hh = kk // 2
                out = e((hh,) + hits[1:], np.uint64)
                self.halving.append((x[:hh], x[hh:2 * hh], out))
                if kk % 2:
                    self.halving.append((out[:1], x[2 * hh:], out[:1]))
                x, kk = out, hh
            self.near = x[0]
        self.pos_idx = np.concatenate([x.ravel() for x in pos_idx])
        self.pg = e(self.pos_idx.size)
        self.gaps = self.pg[:self.planes.size].reshape(room)
        if hit:
            size = int(np.prod(lead + (n, 3)))
            a0 = self.planes.size
            self.pj, self.pi = (self.pg[a0 + i * size:a0 + (i + 1) * size].reshape(lead + (n, 3)) for i in (0, 1))
        # --- the readings, on the rows [ranges | flow] and its like
        rs = self.rows.size
        self.a, self.b, self.ab, self.ab2 = e(rs), np.zeros(rs), e(rs), e(rs)
        self.m_ok, self.g = e(rs, bool), e(rs, bool)
        self.bk, self.gk = self.b[:nq * k].reshape(lead + (k,)), self.g[:nq * k].reshape(lead + (k,))
        self.uw = e(lead + (k,))
        self.kf = k - 1  # the down ray's lane (flow deck)
        if f:
            fl = lead + (1, 3)
            self.flow = self.rows[nq * k:].reshape(fl)
            self.bf2 = self.b[nq * k:].reshape(fl)[..., 0, :2]
            self.gf, self.mf = self.g[nq * k:].reshape(fl), self.m_ok[nq * k:].reshape(fl)
            q = np.arange(nq).reshape(lead)[..., None, None]
            self.d_idx = np.broadcast_to(q * k + self.kf, fl).copy()  # the down range, thrice per quad
            self.om_idx = (3 * q + np.array([1, 0, 2])).astype(np.intp)  # omega (x, y, z) -> (y, x, z)
            self.om_signs = full(np.array([-1.0, 1.0, 1.0]), fl)  # + (-omega_y, omega_x, .)
            self.dd, self.om = e(fl), e(fl)
            perm = np.arange(rs)
            perm[nq * k:] = (nq * k + 3 * np.arange(nq)[:, None] + np.array([1, 0, 2])).ravel()
            self.perm = perm  # the flow's x and y lanes swapped (max(|x|, |y|) on both)
        # per lane constants: the ToF model on the ranges, the flow's on the flow lanes (unused lane: never valid)
        def lanes(rng: float, fx: float, fz: float = 0.0) -> np.ndarray:
            out = np.empty(rs)
            out[:nq * k] = rng
            out[nq * k:] = np.tile([fx, fx, fz], nq) if f else []
            return out
        self.lim = lanes(s.range_limit, sensors.FLOW_MAX_RATE, -np.inf)  # valid: range <= limit, rate <= max
        self.tof = [lanes(0.0, 0.0), lanes(sensors.TOF_POINT_B, 0.0), lanes(sensors.TOF_POINT_A, 0.0),
                    lanes(sensors.TOF_STD_K, 1.0), lanes(1.0, 0.0), lanes(sensors.TOF_STD_A, sensors.FLOW_STD_PX)]
        self.lo, self.hi = lanes(0.0, -sensors.FLOW_LIMIT_PX), lanes(s.range_limit, sensors.FLOW_LIMIT_PX)
        scale = 1.0 / (1.0 - s.dropout) if s.dropout < 1.0 else 0.0
        self.c = {name: np.array(v, float) for name, v in {
            "dropout": s.dropout, "scale": scale, "tiny": 2.0 ** -24, "d_min": 1e-3,
            "min_range": sensors.FLOW_MIN_RANGE, "gain": sensors.FLOW_GAIN}.items()}
        self.dark = s.light_lux < sensors.FLOW_MIN_LUX
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
            cols += [q * k + self.kf, fq, fq + 1, rs + q * k + self.kf, rs + fq]
        self.cols = np.concatenate(cols, axis=1).reshape(lead + (-1,))
        assert np.all(sensors.ray_limits(s) == s.range_limit)  # no depth: one limit for every ray
        _ro(self.planes, self.g_lo, self.g_hi, self.signs, self.r_idx, self.pos_idx, self.lim, self.lo, self.hi,
            self.template, self.cols, *self.tof, *self.c.values())
        if hit:
            _ro(self.r2, self.h_idx, self.hsigns)
        if f:
            _ro(self.d_idx, self.om_idx, self.om_signs, self.perm)


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
    pos.take(p.pos_idx, out=p.pg, mode="wrap")  # the room's pos per quotient, then the pairs' quad j and quad i
    gaps = np.subtract(p.planes, p.gaps, out=p.gaps)  # high and low planes minus pos
    _clip(gaps, p.g_lo, p.g_hi, out=gaps)  # kept > 0 (high) and < 0 (low)
    R.take(p.r_idx, out=p.rg, mode="wrap")
    np.divide(p.signs, p.rg, out=p.rg)  # 1 / (+-R[a, c])
    np.multiply(gaps, p.rg, out=p.q)
    np.maximum(p.q0, p.q1, out=p.m)  # the plane ahead (the larger quotient, > 0)
    np.minimum(p.m0, p.m1, out=p.t)  # the nearest over the 3 world axes
    np.minimum(p.t, p.m2, out=p.t)
    if not p.hit:
        return
    np.subtract(p.pj, p.pi, out=p.ob)  # (..., N (i), N (j), 3): quad j - quad i
    ob = np.matmul(p.ob, R, out=p.ob)  # body frame of quad i: ob[i, j, c] = sum_a o[i, j, a] R[i, a, c]
    ob2 = np.multiply(ob, ob, out=p.ob2)
    c = np.add.reduce(ob2, axis=-1, out=p.cc)
    np.subtract(c, p.r2, out=c)  # |offset|^2 - r^2 (a rotation keeps the length); inf on the diagonal
    p.h.take(p.h_idx, out=p.hg, mode="wrap")  # (j, ..., N (i), c, +-): ob, ob2, c
    disc = np.subtract(p.o2g, p.cg, out=p.o2g)  # >= 0: the line of ray +-c meets the sphere
    if np.fmax.reduce(disc, axis=None) >= 0.0:
        # along +-c the hit is +-ob_c - sqrt(disc); kept where >= 0 (a miss: NaN, behind: < 0; both order
        # above +inf as unsigned integers)
        np.sqrt(disc, out=disc)
        np.multiply(p.obg, p.hsigns, out=p.obg)
        np.subtract(p.obg, disc, out=p.obg)
        for x, y, out in p.halving:  # the nearest over the neighbours
            np.minimum(x, y, out=out)
        np.minimum(p.tu, p.near, out=p.tu)  # the room's t: finite, >= 0
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
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        _axis_hits(p, pos, R)
        if obstacles is not None:  # the rays' world x and y components: +-R[0, c], +-R[1, c] (as axis_hits)
            dx, dy = (np.stack([R[..., a, :], -R[..., a, :]], axis=-1).reshape(p.t6.shape) for a in range(2))
            np.minimum(p.t6, column_hits_xy(pos, dx, dy, *obstacles), out=p.t6)
        if p.t_rays is not None:
            np.copyto(p.ranges, p.t_rays)
        return _readings(p, vel, R, omega, draws)


def _readings(p: _Scratch, vel: np.ndarray, R: np.ndarray, omega: np.ndarray,
              draws: dict[str, Any] | None) -> np.ndarray:
    """``sensors._deck_part_numpy`` (the same bits) from the true ranges in ``p.ranges`` (..., N, K): the
    deck part in :func:`sensors.deck_layout` order (a fresh array)."""
    c, rows, m = p.c, p.rows, p.m_ok
    np.copyto(p.buf, p.template)  # invalid readings: the limit, flow 0, flags 0
    if p.f:  # the flow lanes: the body velocity over the down range, + (-omega_y, omega_x, .)
        flow = np.matmul(vel[..., None, :], R, out=p.flow)  # (..., N, 1, 3) the body velocity (x, y used)
        dd = rows.take(p.d_idx, out=p.dd, mode="wrap")
        np.greater_equal(dd, c["min_range"], out=p.gf)  # high enough for the flow
        np.maximum(dd, c["d_min"], out=dd)
        flow /= dd
        om = omega.take(p.om_idx, out=p.om, mode="wrap")
        om *= p.om_signs
        flow += om
    ab = np.abs(rows, out=p.ab)  # the ranges (>= 0) and the flow's |x|, |y|
    if p.f:
        np.maximum(ab, ab.take(p.perm, out=p.ab2, mode="wrap"), out=ab)  # max(|x|, |y|) on both flow lanes
    np.less_equal(ab, p.lim, out=m)  # valid: range <= limit, flow rate <= its maximum
    if draws is not None:
        u = draws["range_u"]
        np.greater_equal(u, c["dropout"], out=p.gk)  # not dropped
        m &= p.g
    elif p.f:
        p.mf &= p.gf
    if p.f:
        if p.dark:  # too dark: the flow never valid
            p.mf[...] = False
        p.flow *= c["gain"]
    a = p.a
    if draws is not None:  # VL53L1x: t + tof_std(t) tof_normal(u); the flow: + FLOW_STD_PX flow_noise
        lo, hi, a_point, k, one, std = p.tof
        _clip(rows, lo, hi, out=a)  # tof_std(t) (the sign of a zero range is lost next)
        a -= a_point
        a *= k
        np.exp(a, out=a)
        a += one
        a *= std
        w = np.subtract(u, c["dropout"], out=p.uw)  # tof_normal(u, dropout)
        w *= c["scale"]
        np.maximum(w, c["tiny"], out=w)
        sensors._ndtri()(w, out=p.bk)
        if p.f:
            np.copyto(p.bf2, draws["flow_noise"])
        a *= p.b
        a += rows
        _clip(a, p.lo, p.hi, out=a)  # the ranges to [0, limit], the flow to +-FLOW_LIMIT_PX
    else:
        _clip(rows, p.lo, p.hi, out=a)
    np.copyto(p.vals, a, where=m)
    np.copyto(p.flags, m)
    return p.buf.take(p.cols)
