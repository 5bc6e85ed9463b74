"""Ray casting of the deck sensors (:mod:`quadswarm_mj.sensors`): the room's planes, the obstacle columns
and the other quads' hitbox spheres, analytically, over NumPy or ``jax.numpy``.

Two forms, the same values (to float round-off; ``tests/test_sensors_speed.py``):

* the reference: :func:`cast_rays` of world-frame unit rays (:func:`world_rays`), any ray set;
* the speed forms the observation uses, in the quad's body frame where the rays are fixed:
  :func:`axis_hits` (the 6 body axes: the multi-ranger's 5 rays and the flow deck's) and
  :func:`depth_hits` (the depth camera's H x W pixel rays). A body-axis ray's world direction is a
  column of R, so its quotients against the room's planes are ``gap / R[a, c]`` (9 per quad for all 6
  rays) and its dot product with a neighbour's offset is a component of that offset in the body frame
  (3 per neighbour for all 6 rays). A pixel ray ``(1, -u_w, v_h)`` (not normalized) has dot products
  that are sums of a column term and a row term (``x - u_w y`` + ``v_h z``): one add per ray instead
  of five; the length ``|(1, -u, v)|`` is divided out once per ray at the end.

Geometry (world frame, SI): a ray from ``p`` along the unit vector ``d`` ends at the first of the room's
planes (floor z = 0 .. ceiling, walls; seen from inside), the valid columns (vertical infinite cylinders)
and the other quads' hitbox spheres (the quad's own skipped). A ray that starts inside a column or
another quad's hitbox has length 0. R is body -> world (columns: the body axes in the world frame).
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from quadswarm_mj import np_calls
from quadswarm_mj._xp import array_namespace

_clip = np_calls.clip  # the clip ufunc (np.clip's Python wrapper costs more on small arrays)

#: the body-axis rays of :func:`axis_hits`, in order: +x, -x, +y, -y, +z, -z (the multi-ranger's front,
#: back, left, right, up, then the flow deck's down)
AXIS_DIRS = ((1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, 1.0),
             (0.0, 0.0, -1.0))


def depth_tangents(shape: tuple[int, int], fov_deg: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(u (W,), v (H,)): the pixel centres' tangents of a pinhole with field of view ``fov_deg``
    (horizontal, vertical; deg) around body +x; pixel (h, w) looks along (1, -u_w, v_h) (body frame)."""
    h, w = shape
    tu, tv = (math.tan(math.radians(f) / 2.0) for f in fov_deg)
    u = tu * (2.0 * (np.arange(w) + 0.5) / w - 1.0)  # to the right (body -y)
    v = tv * (1.0 - 2.0 * (np.arange(h) + 0.5) / h)  # up (body +z)
    return u, v


def depth_directions(shape: tuple[int, int], fov_deg: tuple[float, float]) -> np.ndarray:
    """(H, W, 3) unit body-frame rays of the depth camera's pixel centres (pinhole around +x); row 0
    is the top (+z side), column 0 the left (+y side)."""
    h, w = shape
    u, v = depth_tangents(shape, fov_deg)
    d = np.stack(np.broadcast_arrays(np.ones((h, w)), -u[None, :], v[:, None]), axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


# ------------------------------------------------------------------------------ reference form


# The casters work axis by axis (x, y, z arrays of shape (..., N, K)), and the ray-versus-object arrays
# are laid out (..., N, objects, K) with the minimum over the objects' axis: both keep XLA:CPU's vector
# loops along the rays instead of along the 3 components or the 8 quads.


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
    return column_hits_xy(pos, dirs[..., 0], dirs[..., 1], centres, valid, radius)


def column_hits_xy(pos: Any, dx: Any, dy: Any, centres: Any, valid: Any, radius: Any) -> Any:
    """:func:`column_hits` of the rays' horizontal components ``dx``, ``dy`` (..., N, K) (of unit rays)."""
    xp = array_namespace(pos, dx, centres)
    r = xp.asarray(radius, dtype=pos.dtype)[..., None, None]
    ox = pos[..., :, None, 0] - centres[..., None, :, 0]  # (..., N, M) quad - centre
    oy = pos[..., :, None, 1] - centres[..., None, :, 1]
    c = ox * ox + oy * oy - r * r
    ok = valid[..., None, :]
    inside = xp.any((c < 0.0) & ok, axis=-1)  # (..., N)
    neg_s = xp.where(ok, -xp.sqrt(xp.maximum(c, 0.0)), -xp.inf)[..., None]  # invalid slots: never hit
    dx, dy = dx[..., :, None, :], dy[..., :, None, :]  # (..., N, 1, K)
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


# ------------------------------------------------------------------------------ body-frame speed forms


@functools.lru_cache(maxsize=64)
def _room_arrays(room_low: tuple, room_high: tuple) -> tuple[np.ndarray, np.ndarray]:
    """The room's corners as read-only float64 arrays (made once per room)."""
    out = (np.asarray(room_low, float), np.asarray(room_high, float))
    for x in out:
        x.setflags(write=False)
    return out


def _room_gaps(xp: Any, pos: Any, room_low: Any, room_high: Any) -> tuple[Any, Any]:
    """(gap_hi, gap_lo) (..., N, 3): the room's high and low planes minus ``pos``, kept > 0 and < 0."""
    if xp is np:
        lo, hi = _room_arrays(tuple(room_low), tuple(room_high))
        return np.maximum(hi - pos, 1e-30), np.minimum(lo - pos, -1e-30)
    hi = xp.asarray(np.asarray(room_high, float), dtype=pos.dtype)
    lo = xp.asarray(np.asarray(room_low, float), dtype=pos.dtype)
    return xp.maximum(hi - pos, 1e-30), xp.minimum(lo - pos, -1e-30)


def _offsets(xp: Any, pos: Any, R: Any, radius: float) -> tuple[list[Any], Any, Any]:
    """The other quads seen from each quad: ``ob`` = 3 arrays (..., N, N), the body-frame components of
    quad j's centre minus quad i's (m), ``c`` (..., N, N) = |offset|^2 - radius^2 (inf on the diagonal:
    the own sphere never counts) and ``inside`` (..., N): quad i's centre is inside another hitbox."""
    n = pos.shape[-2]
    if xp is np:  # one batched matmul: ob[i, j, c] = sum_a o[i, j, a] R[i, a, c]
        o = pos[..., None, :, :] - pos[..., :, None, :]  # (..., N (i), N (j), 3) world: quad j - quad i
        obm = o @ R
        ob = [obm[..., c] for c in range(3)]
        d2 = np.add.reduce(o * o, axis=-1)
    else:  # XLA:CPU: one (..., N, N) array per component (no minor axis of 3), elementwise sums
        o = [pos[..., None, :, a] - pos[..., :, None, a] for a in range(3)]
        ob = [o[0] * R[..., :, None, 0, c] + o[1] * R[..., :, None, 1, c] + o[2] * R[..., :, None, 2, c]
              for c in range(3)]
        d2 = o[0] * o[0] + o[1] * o[1] + o[2] * o[2]
    c = xp.where(_diagonal(n), xp.inf, d2 - radius * radius)
    return ob, c, xp.any(c < 0.0, axis=-1)


@functools.lru_cache(maxsize=16)
def _diagonal(n: int) -> np.ndarray:
    """(N, N) read-only: True on the diagonal (a quad's own hitbox)."""
    eye = np.eye(n, dtype=bool)
    eye.setflags(write=False)
    return eye


_SIGNS = np.array([1.0, -1.0])


@functools.lru_cache(maxsize=64)
def _axis_constants(room_low: tuple, room_high: tuple, n: int, radius: float | None) -> tuple[np.ndarray, ...]:
    """Read-only constants of :func:`_axis_hits_numpy`: the room's planes (2, 3) = (high, low) and the
    bounds (2, 3) that keep their gaps > 0 and < 0, the ray signs (2,) and (N, N) radius^2 with
    -inf on the diagonal (``|offset|^2 - it`` is inf there: the own sphere never counts)."""
    planes = np.array([room_high, room_low], float)
    lo = np.array([[1e-30] * 3, [-np.inf] * 3])
    hi = np.array([[np.inf] * 3, [-1e-30] * 3])
    r2 = np.full((n, n), 0.0 if radius is None else radius * radius)
    np.fill_diagonal(r2, -np.inf)
    out = (planes, lo, hi, _SIGNS.copy(), r2)
    for x in out:
        x.setflags(write=False)
    return out


def _axis_hits_numpy(pos: np.ndarray, R: np.ndarray, room_low: Any, room_high: Any,
                     radius: float | None) -> np.ndarray:
    """:func:`axis_hits` in NumPy with few calls (the CPU engine's arrays are small: call overhead
    dominates): the room's quotients of the 6 rays in one (..., N, hi/lo, a, c, +-) array, the
    hitboxes' on (..., N, N, c, +-) and skipped when no ray line of any quad meets another's hitbox (the
    same values as the plain form). Call inside ``np.errstate(divide="ignore", invalid="ignore")``."""
    n = pos.shape[-2]
    planes, g_lo, g_hi, signs, r2 = _axis_constants(tuple(room_low), tuple(room_high), n, radius)
    gaps = np.subtract(planes, pos[..., None, :])  # (..., N, 2, 3): high and low planes minus pos
    _clip(gaps, g_lo, g_hi, out=gaps)  # kept > 0 (high) and < 0 (low)
    inv = np.divide(signs, R[..., None])  # (..., N, a, c, +-): 1 / (+-R[a, c])
    q = np.multiply(gaps[..., :, :, None, None], inv[..., None, :, :, :])  # (..., N, hi/lo, a, c, +-)
    t = np.minimum.reduce(np.maximum.reduce(q, axis=-4), axis=-3)  # (..., N, c, +-): the plane ahead
    # (the larger quotient), the nearest over the 3 axes; ufunc reductions (no Python wrappers)
    if radius is not None:
        o = pos[..., None, :, :] - pos[..., :, None, :]  # (..., N (i), N (j), 3) world: quad j - quad i
        ob = o @ R  # body frame of quad i: ob[i, j, c] = sum_a o[i, j, a] R[i, a, c]
        ob2 = ob * ob
        c = np.add.reduce(ob2, axis=-1)
        np.subtract(c, r2, out=c)  # |offset|^2 - r^2 (a rotation keeps the length); inf on the diagonal
        disc = np.subtract(ob2, c[..., None], out=ob2)  # >= 0: the line of ray +-c meets the sphere
        if np.fmax.reduce(disc, axis=None) >= 0.0:
            # along +c (-c) the dot product with the offset is b = ob_c (-ob_c): a hit needs disc >= 0
            # and b >= 0, at b - sqrt(disc) >= 0 (c >= 0 outside); a line that misses gives NaN, a ray
            # away from the sphere b - sqrt(disc) < 0 (both: inf); a quad inside: 0 below
            ts = np.subtract(ob[..., None] * signs, np.sqrt(disc)[..., None])  # (..., N, N, 3, 2)
            ts = np.where(ts >= 0.0, ts, np.inf)
            np.minimum(t, np.minimum.reduce(ts, axis=-3), out=t)
        if np.fmin.reduce(c, axis=None) < 0.0:
            inside = np.logical_or.reduce(c < 0.0, axis=-1)
            t[inside] = 0.0
    return t.reshape(t.shape[:-2] + (6,))


def axis_hits(pos: Any, R: Any, room_low: Any, room_high: Any, columns: Any = None,
              quad_radius: float | None = None, share: Any = None) -> Any:
    """(..., N, 6) range (m) along the body axes +x, -x, +y, -y, +z, -z (:data:`AXIS_DIRS`) from the
    quads' centres ``pos`` (..., N, 3), R (..., N, 3, 3) body -> world; otherwise as :func:`cast_rays`
    (the same values to round-off).

    The world component a of body axis c is R[a, c], so the room's quotients are ``gap_a / R[a, c]``
    (along -c they change sign), and the dot product of ray +-c with a neighbour's offset is +-ob_c.
    NumPy works on (..., N, 3, 3) and (..., N, N, 3) arrays (few calls); XLA:CPU on one array per axis.
    ``share``: an engine's identity on the hitbox test's pair arrays (the same values), applied before
    they are read (``perf.jax_deck`` passes one that makes XLA compute them once)."""
    xp = array_namespace(pos, R)
    spheres = quad_radius is not None and pos.shape[-2] > 1
    with np.errstate(divide="ignore", invalid="ignore"):
        if xp is np:
            t = _axis_hits_numpy(pos, R, room_low, room_high, quad_radius if spheres else None)
        else:
            gap_hi, gap_lo = _room_gaps(xp, pos, room_low, room_high)
            if spheres:
                ob, c, inside = _offsets(xp, pos, R, quad_radius)
                if share is not None:
                    c, *ob = (share(x) for x in (c, *ob))
                sc = xp.sqrt(xp.maximum(c, 0.0))
            outs = []
            for k in range(3):  # body axis k: rays +k, -k
                t_pos = t_neg = None
                for a in range(3):
                    inv = 1.0 / R[..., a, k]
                    q_hi, q_lo = gap_hi[..., a] * inv, gap_lo[..., a] * inv
                    p_a, n_a = xp.maximum(q_hi, q_lo), -xp.minimum(q_hi, q_lo)
                    t_pos = p_a if t_pos is None else xp.minimum(t_pos, p_a)
                    t_neg = n_a if t_neg is None else xp.minimum(t_neg, n_a)
                if spheres:
                    b = ob[k]
                    sq = xp.sqrt(xp.maximum(b * b - c, 0.0))
                    t_pos = xp.minimum(t_pos, xp.min(xp.where(b >= sc, b - sq, xp.inf), axis=-1))
                    t_neg = xp.minimum(t_neg, xp.min(xp.where(-b >= sc, -b - sq, xp.inf), axis=-1))
                outs += [t_pos, t_neg]
            t = xp.stack(outs, axis=-1)
            if spheres:
                t = xp.where(inside[..., None], 0.0, t)
        if columns is not None:  # the rays' world x and y components: +-R[0, c], +-R[1, c]
            dx, dy = (xp.stack([R[..., a, :], -R[..., a, :]], axis=-1).reshape(t.shape) for a in range(2))
            t = xp.minimum(t, column_hits_xy(pos, dx, dy, *columns))
    return t


@functools.lru_cache(maxsize=32)
def _pixel_constants(shape: tuple[int, int], fov_deg: tuple[float, float]) -> tuple[np.ndarray, ...]:
    """(u (W,), v (H,), -u per pixel (H W,), v per pixel (H W,), |e| per pixel (H W,)) of
    :func:`depth_tangents` (row-major pixels). Read-only."""
    h, w = shape
    u, v = depth_tangents(shape, fov_deg)
    u_k, v_k = np.tile(-u, h), np.repeat(v, w)
    out = (u, v, u_k, v_k, np.sqrt(1.0 + u_k * u_k + v_k * v_k))
    for x in out:
        x.setflags(write=False)
    return out


_ZERO_INDEX = np.zeros(1, np.intp)


@functools.lru_cache(maxsize=32)
def _pyramid_bounds(shape: tuple[int, int], fov_deg: tuple[float, float], radius: float) -> tuple[float, ...]:
    """(u_max, v_max, r sqrt(1 + u_max^2), r sqrt(1 + v_max^2)) of the depth camera's pixel tangents."""
    u, v = _pixel_constants(shape, fov_deg)[:2]
    u_max, v_max = float(np.abs(u).max()), float(np.abs(v).max())
    return u_max, v_max, radius * math.sqrt(1.0 + u_max * u_max), radius * math.sqrt(1.0 + v_max * v_max)


def _depth_spheres_numpy(pos: np.ndarray, R: np.ndarray, t: np.ndarray, bounds: tuple[float, ...],
                         uk: np.ndarray, vk: np.ndarray, norm: np.ndarray, radius: float) -> np.ndarray:
    """``t`` (..., N, H W) with the other quads' hitboxes of :func:`depth_hits` (NumPy; the same values).

    Only the pairs whose sphere can meet the camera's pyramid of pixel-centre rays are cast: sphere
    centre (X, Y, Z) in the body frame with X >= -r, |Y| - u_max X <= r sqrt(1 + u_max^2) and
    |Z| - v_max X <= r sqrt(1 + v_max^2) (the sphere reaches into each of the pyramid's half-spaces; a
    necessary condition). Usually few pairs pass: the arrays shrink from N N H W numbers."""
    ob, c, inside = _offsets(np, pos, R, radius)
    u_max, v_max, y_lim, z_lim = bounds  # _pyramid_bounds
    x, y, z = ob
    cand = ((x >= -radius) & (np.abs(y) - u_max * x <= y_lim) & (np.abs(z) - v_max * x <= z_lim) & (c < np.inf))
    idx = np.nonzero(cand)  # (..., i, j) of the pairs cast, in C order: each quad i's pairs are one run
    if idx[0].size:
        beta = x[idx][:, None] + uk * y[idx][:, None] + vk * z[idx][:, None]  # (P, H W)
        disc = beta * beta - (norm * norm) * c[idx][:, None]
        ts = np.where((beta > 0.0) & (disc >= 0.0), beta - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        quad = np.ravel_multi_index(idx[:-1], t.shape[:-1]) if len(idx) > 2 else idx[0]
        first = np.flatnonzero(quad[1:] != quad[:-1]) + 1
        starts = np.concatenate((_ZERO_INDEX, first))
        nearest = np.full(t.shape, np.inf)  # the nearest per quad i (a minimum: exact in any order)
        nearest.reshape(-1, t.shape[-1])[quad[starts]] = np.minimum.reduceat(ts, starts, axis=0)
        t = np.minimum(t, nearest * (1.0 / norm))
    if inside.any():
        t = np.where(inside[..., None], 0.0, t)
    return t


def sphere_pixel_hits(ob: list[Any], c: Any, uk: Any, vk: Any, norm2: Any) -> Any:
    """(..., N, H W) the nearest of the other quads' hitboxes along each pixel ray of :func:`depth_hits`
    (``jax.numpy``), as the parameter ``beta - sqrt(disc)`` along e = (1, -u_w, v_h) times |e| (divide by
    |e| for metres; +inf: no hit), of the body-frame offsets ``ob`` = 3 arrays (..., N (i), N (j)), ``c``
    (..., N, N) = |offset|^2 - r^2 (inf on the diagonal) and the pixels' ``uk``, ``vk``, ``norm2`` = |e|^2
    (H W,). A hit ahead from outside: beta = |e| (d . offset) > 0 and disc = beta^2 - |e|^2 c >= 0; a
    pair with c < 0 (inside) is the caller's to override. The engines may pass a same-values form."""
    xp = array_namespace(c)
    beta = ob[0][..., None] + uk * ob[1][..., None] + vk * ob[2][..., None]  # (..., N, N, H W)
    disc = beta * beta - norm2 * c[..., None]
    ts = xp.where((beta > 0.0) & (disc >= 0.0), beta - xp.sqrt(xp.maximum(disc, 0.0)), xp.inf)
    return xp.min(ts, axis=-2)


def depth_hits(pos: Any, R: Any, shape: tuple[int, int], fov_deg: tuple[float, float], room_low: Any,
               room_high: Any, columns: Any = None, quad_radius: float | None = None,
               pixel_spheres: Any = None) -> Any:
    """(..., N, H W) range (m) along the depth camera's pixel rays (:func:`depth_directions`, row-major)
    from the quads' centres ``pos`` (..., N, 3), R (..., N, 3, 3) body -> world; otherwise as
    :func:`cast_rays` (the same values to round-off). ``pixel_spheres``: the hitbox test under JAX
    (:func:`sphere_pixel_hits`' signature and values; None: that function).

    The pixel rays are cast along e = (1, -u_w, v_h) (not normalized; |e| divided out per ray at the
    end): a component of e in another frame is ``x - u_w y + v_h z`` (two multiply-adds per ray instead
    of the unit rays' 3 x 3 rotation), and so is its dot product with a neighbour's body-frame offset.
    The pixels stay on one flat axis (..., H W): XLA:CPU's loops over a split (H, W) pair are far slower."""
    xp = array_namespace(pos, R)
    u, v, u_k, v_k, norm = _pixel_constants(tuple(shape), tuple(fov_deg))
    f = pos.dtype
    uk, vk = xp.asarray(u_k, dtype=f), xp.asarray(v_k, dtype=f)

    def along(x: Any, y: Any, z: Any) -> Any:
        """(..., H W): x - u_w y + v_h z over the pixels for the components x, y, z (...)."""
        return x[..., None] + uk * y[..., None] + vk * z[..., None]

    with np.errstate(divide="ignore", invalid="ignore"):
        gap_hi, gap_lo = _room_gaps(xp, pos, room_low, room_high)
        t, e = None, []
        for a in range(3):  # world component a of e
            e.append(along(R[..., a, 0], R[..., a, 1], R[..., a, 2]))  # (..., N, H W)
            inv = 1.0 / e[a]
            ta = xp.maximum(gap_hi[..., a, None] * inv, gap_lo[..., a, None] * inv)
            t = ta if t is None else xp.minimum(t, ta)
        t = t * xp.asarray(norm, dtype=f)  # parameter along e -> range (m)
        if quad_radius is not None and pos.shape[-2] > 1 and xp is np:
            bounds = _pyramid_bounds(tuple(shape), tuple(fov_deg), float(quad_radius))
            t = _depth_spheres_numpy(pos, R, t, bounds, uk, vk, norm, quad_radius)
        elif quad_radius is not None and pos.shape[-2] > 1:  # range (beta - sqrt(disc)) / |e| of the nearest
            ob, c, inside = _offsets(xp, pos, R, quad_radius)
            ts = (pixel_spheres or sphere_pixel_hits)(ob, c, uk, vk, xp.asarray(norm * norm, dtype=f))
            t = xp.minimum(t, ts * xp.asarray(1.0 / norm, dtype=f))
            t = xp.where(inside[..., None], 0.0, t)
        if columns is not None:
            inv_n = xp.asarray(1.0 / norm, dtype=f)
            t = xp.minimum(t, column_hits_xy(pos, e[0] * inv_n, e[1] * inv_n, *columns))
    return t
