"""The depth camera's observation part (alone) in NumPy with few, cheap array calls, the counterpart of
:mod:`quadswarm_mj.perf.numpy_deck` (the MuJoCo engine's (1, 8, .) arrays: NumPy's per-call cost dominates).

:func:`deck_part` gives the same bits as :func:`quadswarm_mj.sensors.deck_part` (``sensor_rays.depth_hits``,
``sensor_rays._depth_spheres_numpy``, ``sensors._deck_part_numpy``; ``tests/test_sensors_speed.py``): the same
floating-point operations on the same operands, in work arrays made once per (config, shape, thread).
R is gathered once so that the pixel rays' world components ``e_a = R[a, 0] + u_k R[a, 1] + v_k R[a, 2]``
of the 3 world axes are 4 calls on one (a, ..., N, H W) array; the hitbox test's camera-pyramid check is
one (..., N, N, 3) array; the candidate pairs are cast as the model casts them, each hit kept as the
unsigned integer of its bits (a hit ahead is a float >= 0, ordered as the floats; a miss (NaN) or a hit
behind (< 0) orders above +inf), and each quad's nearest of the room and its pairs is one minimum over a
(..., N, N, H W) block holding the room's range on its diagonal. A pair with ``|offset|^2 - r^2`` exactly
0 (``beta = +0`` would pass as a hit at 0) sends the call to the model; so do other configurations.
Reached through :func:`quadswarm_mj.perf.numpy_deck.deck_part`; docs/sensors.md gives the figures.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from quadswarm_mj import np_calls, sensor_rays, sensors
from quadswarm_mj.perf.scratch_cache import ScratchCache

_clip = np_calls.clip
_add, _sub, _mul, _div, _abs, _where = np.add, np.subtract, np.multiply, np.divide, np.abs, np.where
_max, _min, _le, _ge, _exp, _sqrt, _matmul = np.maximum, np.minimum, np.less_equal, np.greater_equal, np.exp, \
    np.sqrt, np.matmul
_and, _and_reduce, _or_reduce, _add_reduce, _min_reduce, _fmin_reduce = np.logical_and, np.logical_and.reduce, \
    np.logical_or.reduce, np.add.reduce, np.minimum.reduce, np.fmin.reduce
_count_nonzero, _copyto = np_calls.count_nonzero, np_calls.copyto


def applies(s: Any) -> bool:
    """Whether :func:`deck_part` has a fast form for the sensors ``s``: the depth camera alone."""
    return s.depth is not None and not (s.multiranger or s.flow)


class _Scratch:
    """Preallocated work arrays of :func:`deck_part` for one (sensors, shape, room, hitbox): the gather
    indices, the constants (read-only, of their operands' shapes or 0-d) and the views its calls use."""

    def __init__(self, s: Any, shape: tuple[int, ...], room_low: tuple, room_high: tuple,
                 radius: float | None) -> None:
        lead, n = shape[:-1], shape[-2]  # lead = (..., N)
        nq = int(np.prod(lead))
        hw = s.depth[0] * s.depth[1]
        e, full = np.empty, (lambda x, shp: np.broadcast_to(np.asarray(x, float), shp).copy())
        c0 = np.array
        u, v, uk, vk, norm = sensor_rays._pixel_constants(tuple(s.depth), tuple(s.depth_fov))
        self.shape = shape
        self.uk, self.vk = uk, vk  # (H W,) read-only
        # --- the room: R (..., N, a, c) gathered to (c, a, ..., N, 1); pos to (hi/lo, a, ..., N, 1)
        r_id = np.arange(nq * 9).reshape(lead + (3, 3))
        self.r_idx = np.ascontiguousarray(np.moveaxis(r_id, (-1, -2), (0, 1))[..., None])
        self.rg = e(self.r_idx.shape)
        self.rg0, self.rg1, self.rg2 = self.rg[0], self.rg[1], self.rg[2]
        rays = (3,) + lead + (hw,)  # two work arrays: e_a then 1 / e_a in place; v_k e_a2 then the quotients
        self.E, self.tmp = e(rays), e(rays)
        self.E0, self.E1 = self.E[0], self.E[1]
        self.M0, self.M1, self.M2 = self.tmp[0], self.tmp[1], self.tmp[2]
        gshape = (2, 3) + lead + (1,)
        pos_id = np.arange(nq * 3).reshape(shape)
        self.p_idx = np.broadcast_to(np.moveaxis(pos_id, -1, 0)[None, ..., None], gshape).copy()
        self.gaps = e(gshape)
        self.gap_hi, self.gap_lo = self.gaps[0], self.gaps[1]
        ex = (...,) + (None,) * (len(lead) + 1)
        self.planes = full(np.array([room_high, room_low], float)[ex], gshape)
        self.g_lo = full(np.array([[1e-30] * 3, [-np.inf] * 3])[ex], gshape)  # gaps kept > 0 (high), < 0 (low)
        self.g_hi = full(np.array([[np.inf] * 3, [-1e-30] * 3])[ex], gshape)
        self.one = c0(1.0)
        self.t = e(lead + (hw,))
        self.norm = norm  # (H W,) read-only
        self.inv_n1 = 1.0 / norm  # (H W,)
        self.inv_n1.setflags(write=False)
        # --- the hitboxes (radius None or one quad: none)
        self.hit = radius is not None and n > 1
        if self.hit:
            pair = lead + (n, 3)
            pj = np.broadcast_to(pos_id[..., None, :, :], pair)  # (..., N (i), N (j), 3): quad j, quad i
            pi = np.broadcast_to(pos_id[..., :, None, :], pair)
            self.pair_idx = np.stack([pj, pi])
            self.pp = e((2,) + pair)
            self.pj, self.pi = self.pp[0], self.pp[1]
            self.ob, self.o2, self.A, self.X3 = e(pair), e(pair), e(pair), e(pair)
            self.ob_flat = self.ob.reshape(-1, 3)
            self.x1 = self.ob[..., 0:1]
            self.cand3 = e(pair, bool)
            self.cand = e(lead + (n,), bool)
            self.cand_flat = self.cand.reshape(-1)
            self.cc = e(lead + (n,))
            self.cc_flat = self.cc.reshape(-1)
            r2 = np.full((n, n), radius * radius)
            np.fill_diagonal(r2, -np.inf)  # |offset|^2 - (-inf) = inf: the own sphere never counts
            self.r2 = full(r2, lead + (n,))
            u_max, v_max, y_lim, z_lim = sensor_rays._pyramid_bounds(tuple(s.depth), tuple(s.depth_fov), float(radius))
            self.mask = c0([0.0, 1.0, 1.0])  # [0 |x|, |y|, |z|]
            self.coef = c0([1.0, u_max, v_max])  # [x, u_max x, v_max x]
            lim = np.broadcast_to(np.array([radius, y_lim, z_lim]), (n, n, 3)).copy()
            lim[np.arange(n), np.arange(n), 0] = -np.inf  # the diagonal: never a candidate
            self.lim = full(lim, pair)
            self.n2 = norm * norm  # (H W,) |e|^2
            self.n2.setflags(write=False)
            # the room's range on the diagonal of a (..., N (i), N (j), H W) block, the pairs' hits off it
            # (their slots held at the largest unsigned integer between calls)
            self.D = np.full(lead + (n, hw), np.uint64(0xFFFFFFFFFFFFFFFF))
            self.D_rows = self.D.reshape(-1, hw)  # (..., i, j) rows
            self.D_f = self.D.view(np.float64)
            dview = self.D_f.reshape(lead[:-1] + (n * n, hw))
            self.D_diag = dview[..., ::n + 1, :]  # (..., N, H W) the diagonal's rows
            self.big = np.uint64(0xFFFFFFFFFFFFFFFF)
            self.tu = self.t.view(np.uint64)
        # --- the readings
        self.limit = c0(s.depth_max_range)
        self.zero, self.four, self.point_a, self.k, self.std_a = (c0(x) for x in (
            0.0, sensors.TOF_POINT_B, sensors.TOF_POINT_A, sensors.TOF_STD_K, sensors.TOF_STD_A))
        self.dropout = c0(s.dropout)
        self.scale = c0(1.0 / (1.0 - s.dropout) if s.dropout < 1.0 else 0.0)
        self.tiny = c0(2.0 ** -24)
        self.a, self.w = e(lead + (hw,)), e(lead + (hw,))
        self.valid, self.kept = e(lead + (hw,), bool), e(lead + (hw,), bool)
        self.ndtri = sensors._ndtri()
        assert np.all(sensors.ray_limits(s) == s.depth_max_range)
        for x in (self.r_idx, self.p_idx, self.planes, self.g_lo, self.g_hi, self.one,
                  self.limit, self.zero, self.four, self.point_a, self.k, self.std_a, self.dropout, self.scale,
                  self.tiny, *((self.pair_idx, self.r2, self.mask, self.coef, self.lim) if self.hit else ())):
            x.setflags(write=False)


_CACHE = ScratchCache(lambda cfg, shape: _Scratch(cfg.sensors, shape, tuple(cfg.room_low), tuple(cfg.room_high),
                                                  cfg.hitbox))
_scratch = _CACHE.get  # the _Scratch of cfg for positions of shape in this thread
_LOCAL = _CACHE.local  # .last: this thread's last (cfg, scratch)


def deck_part(cfg: Any, pos: Any, vel: Any, R: Any, omega: Any, obstacles: Any = None,
              draws: dict[str, Any] | None = None) -> Any:
    """:func:`quadswarm_mj.sensors.deck_part` (same arguments, the same bits) for NumPy float64 arrays with
    the depth camera alone (:func:`applies`); otherwise the model's function."""
    s = cfg.sensors
    if (not applies(s) or type(pos) is not np.ndarray or pos.dtype != np.float64
            or (draws is not None and "range_u" not in draws)):
        return sensors.deck_part(cfg, pos, vel, R, omega, obstacles, draws)
    last = getattr(_LOCAL, "last", None)
    p = last[1] if last is not None and last[0] is cfg and last[1].shape == pos.shape else _scratch(cfg, pos.shape)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = _ranges(p, pos, R, obstacles)
        if t is None:  # a quad exactly on another's hitbox sphere: the model's function
            return sensors.deck_part(cfg, pos, vel, R, omega, obstacles, draws)
        return _readings(p, t, draws)


def _ranges(p: _Scratch, pos: np.ndarray, R: np.ndarray, obstacles: Any) -> np.ndarray | None:
    """``sensor_rays.depth_hits`` (the same bits) into ``p.t`` (..., N, H W) m; None where the call must go
    to the model (a candidate pair with ``|offset|^2 = r^2`` exactly)."""
    rg = R.take(p.r_idx, None, p.rg, "wrap")  # (c, a, ..., N, 1)
    E = _mul(p.rg1, p.uk, out=p.E)  # e_a = R[a, 0] + u_k R[a, 1] + v_k R[a, 2] (a, ..., N, H W)
    _add(p.rg0, E, out=E)
    _add(E, _mul(p.rg2, p.vk, out=p.tmp), out=E)
    if obstacles is not None:  # the rays' world x and y components, for the columns below
        ex, ey = p.E0 * p.inv_n1, p.E1 * p.inv_n1
    inv = _div(p.one, E, out=E)  # (in place: the work arrays stay few, the cache warm)
    gaps = pos.take(p.p_idx, None, p.gaps, "wrap")
    _sub(p.planes, gaps, out=gaps)  # high and low planes minus pos
    _clip(gaps, p.g_lo, p.g_hi, out=gaps)  # kept > 0 (high) and < 0 (low)
    q_hi = _mul(p.gap_hi, inv, out=p.tmp)  # (a, ..., N, H W)
    _max(q_hi, _mul(p.gap_lo, inv, out=inv), out=q_hi)  # the plane ahead along each world axis
    t = _min(p.M0, p.M1, out=p.t)
    _min(t, p.M2, out=t)
    _mul(t, p.norm, out=t)  # parameter along e -> range (m)
    del rg
    if p.hit:
        pp = pos.take(p.pair_idx, None, p.pp, "wrap")
        o = _sub(pp[0], pp[1], out=p.pj)  # (..., N (i), N (j), 3) world: quad j - quad i
        ob = _matmul(o, R, out=p.ob)  # body frame of quad i (the model's product)
        _add_reduce(_mul(o, o, out=p.o2), axis=-1, out=p.cc)
        c = _sub(p.cc, p.r2, out=p.cc)  # |offset|^2 - r^2, inf on the diagonal
        A = _mul(_abs(ob, out=p.A), p.mask, out=p.A)
        _sub(A, _mul(p.x1, p.coef, out=p.X3), out=A)  # [-x, |y| - u_max x, |z| - v_max x]
        _and_reduce(_le(A, p.lim, out=p.cand3), axis=-1, out=p.cand)
        if _count_nonzero(p.cand):
            fi = p.cand_flat.nonzero()[0]  # the candidate pairs (..., i, j), flat
            g = p.ob_flat.take(fi, 0)  # (P, 3)
            cs = p.cc_flat.take(fi)[:, None]  # (P, 1)
            if _count_nonzero(cs) < cs.size:
                return None
            beta = _mul(p.uk, g[:, 1:2])  # x + u_k y + v_k z (the model's order)
            _add(g[:, 0:1], beta, out=beta)
            _add(beta, _mul(p.vk, g[:, 2:3]), out=beta)
            disc = _sub(_mul(beta, beta), _mul(p.n2, cs))
            _sub(beta, _sqrt(disc, out=disc), out=beta)  # a hit ahead: >= 0; a miss NaN, behind < 0
            _mul(beta, p.inv_n1, out=beta)  # (to metres: monotone, so the nearest is the model's)
            _copyto(p.D_diag, t)
            rows = p.D_rows
            rows[fi] = beta.view(np.uint64)
            _min_reduce(p.D, axis=-2, out=p.tu)  # the nearest of the room and the quad's pairs
            rows[fi] = p.big
        if _fmin_reduce(c, axis=None) < 0.0:  # a quad inside another's hitbox: 0
            inside = _or_reduce(c < 0.0, axis=-1)
            t[inside] = 0.0
    if obstacles is not None:
        _min(t, sensor_rays.column_hits_xy(pos, ex, ey, *obstacles), out=t)
    return t


def _readings(p: _Scratch, t: np.ndarray, draws: dict[str, Any] | None) -> np.ndarray:
    """``sensors._deck_part_numpy`` (the same bits) of the depth ranges ``t``: a fresh (..., N, H W)."""
    valid = _le(t, p.limit, out=p.valid)
    if draws is None:
        return _where(valid, _min(_max(t, p.zero, out=p.a), p.limit, out=p.a), p.limit)
    u = draws["range_u"]
    _and(valid, _ge(u, p.dropout, out=p.kept), out=valid)
    a = _clip(t, p.zero, p.four, out=p.a)  # tof_std(t)
    _sub(a, p.point_a, out=a)
    _mul(a, p.k, out=a)
    _exp(a, out=a)
    _add(a, p.one, out=a)
    _mul(a, p.std_a, out=a)
    w = _sub(u, p.dropout, out=p.w)  # tof_normal(u, dropout)
    _mul(w, p.scale, out=w)
    _max(w, p.tiny, out=w)
    _mul(a, p.ndtri(w, out=w), out=a)
    _add(a, t, out=a)
    return _where(valid, _min(_max(a, p.zero, out=a), p.limit, out=a), p.limit)  # (not the clip ufunc: -0.0)
