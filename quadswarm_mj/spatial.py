"""Rotation helpers over arrays with leading batch dims (NumPy or jax.numpy).

Quaternions are MuJoCo's (w, x, y, z); rotation matrices map body to world.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from quadswarm_mj._xp import array_namespace

#: Arrays with at least this many elements take the component-wise code paths below: NumPy's
#: per-call overhead dominates small arrays (fewest calls wins), its per-row overhead for
#: reductions over a short last axis dominates large ones (whole-array strided ops win).
BIG = 4096


def sum_last(x: Any) -> Any:
    """Sum over a short last axis (< 8) as ((x0 + x1) + x2) + ...: exactly ``x.sum(axis=-1)``
    (NumPy adds a contiguous axis shorter than 8 left to right), in the faster form for the size."""
    n = x.shape[-1]
    if x.size < BIG or n >= 8:
        return x.sum(axis=-1)
    r = x[..., 0] + x[..., 1]
    for i in range(2, n):
        r = r + x[..., i]
    return r


def sumsq_last(x: Any) -> Any:
    """``(x * x).sum(axis=-1)`` over a short last axis, same rounding (see :func:`sum_last`)."""
    n = x.shape[-1]
    if x.size < BIG or n >= 8:
        return (x * x).sum(axis=-1)
    r = x[..., 0] * x[..., 0] + x[..., 1] * x[..., 1]
    for i in range(2, n):
        r = r + x[..., i] * x[..., i]
    return r


def norm_last(x: Any) -> Any:
    """Euclidean norm over the last axis (same rounding as sqrt(sum(x * x)))."""
    sqrt = np.sqrt if type(x) is np.ndarray else array_namespace(x).sqrt
    return sqrt(sumsq_last(x))


def quat_to_rotmat(q: Any) -> Any:
    """(..., 4) unit quaternion (w, x, y, z) -> (..., 3, 3) body-to-world rotation (the textbook
    formula, :func:`quat_to_rotmat_components`; ``perf.numpy_small.quat_to_rotmat`` is its
    fewest-calls form for small NumPy arrays)."""
    xp = array_namespace(q)
    rows = quat_to_rotmat_components(q[..., 0], q[..., 1], q[..., 2], q[..., 3])
    return xp.stack(rows, axis=-1).reshape(q.shape[:-1] + (3, 3))


def quat_to_rotmat_components(w: Any, x: Any, y: Any, z: Any) -> tuple[Any, ...]:
    """Body-to-world rotation of the unit quaternion (w, x, y, z) given as component arrays: the 9
    entries (R00, R01, R02, R10, ..., R22), row-major, by the textbook formula (:func:`quat_to_rotmat`'s body)."""
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return (1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
            2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
            2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy))


def rotmat_to_quat(R: Any) -> Any:
    """(..., 3, 3) rotation -> (..., 4) unit quaternion (w, x, y, z), w >= 0 (branch-free)."""
    xp = array_namespace(R)
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    # Four candidate solutions; pick the numerically largest pivot.
    tw = 1 + m00 + m11 + m22
    tx = 1 + m00 - m11 - m22
    ty = 1 - m00 + m11 - m22
    tz = 1 - m00 - m11 + m22
    qw = xp.stack([tw, m21 - m12, m02 - m20, m10 - m01], axis=-1)
    qx = xp.stack([m21 - m12, tx, m01 + m10, m02 + m20], axis=-1)
    qy = xp.stack([m02 - m20, m01 + m10, ty, m12 + m21], axis=-1)
    qz = xp.stack([m10 - m01, m02 + m20, m12 + m21, tz], axis=-1)
    t = xp.stack([tw, tx, ty, tz], axis=-1)
    best = xp.argmax(t, axis=-1)[..., None, None]
    cands = xp.stack([qw, qx, qy, qz], axis=-2)  # (..., 4 candidates, 4)
    q = xp.take_along_axis(cands, best, axis=-2)[..., 0, :]
    q = q / xp.sqrt(xp.sum(q * q, axis=-1, keepdims=True))
    return q * xp.where(q[..., :1] < 0, -1.0, 1.0)


def yaw_of(R: Any) -> Any:
    """Heading (rad) of the body x axis projected on the world xy plane."""
    xp = array_namespace(R)
    return xp.arctan2(R[..., 1, 0], R[..., 0, 0])


def yaw_quat(yaw: Any) -> Any:
    """(...,) yaw angle (rad) -> (..., 4) quaternion of a pure rotation about world z."""
    xp = array_namespace(yaw)
    h = (0.5 * yaw)[..., None]
    z = xp.zeros_like(h)
    return xp.concatenate([xp.cos(h), z, z, xp.sin(h)], axis=-1)


def yaw_rotmat(yaw: Any) -> Any:
    """(...,) yaw angle (rad) -> (..., 3, 3) rotation about world z."""
    xp = array_namespace(yaw)
    c, s = xp.cos(yaw), xp.sin(yaw)
    z, o = xp.zeros_like(c), xp.ones_like(c)
    return xp.stack([c, -s, z, s, c, z, z, z, o], axis=-1).reshape(yaw.shape + (3, 3))


def yaw_cos_sin(R: Any) -> tuple[Any, Any]:
    """(cos, sin) of :func:`yaw_of` without trigonometry: the body x axis' xy projection normalized
    ((1, 0) where it vanishes, as ``atan2(0, 0) = 0``). Equal to ``cos/sin(yaw_of(R))`` up to round-off."""
    return yaw_cos_sin_components(R[..., 0, 0], R[..., 1, 0])


def yaw_cos_sin_components(c0: Any, s0: Any) -> tuple[Any, Any]:
    """:func:`yaw_cos_sin` from the rotation's entries R00 (``c0``) and R10 (``s0``)."""
    xp = array_namespace(c0, s0)
    h = xp.sqrt(c0 * c0 + s0 * s0)
    ok = h > 0
    inv = 1.0 / xp.where(ok, h, 1.0)
    return xp.where(ok, c0 * inv, 1.0), xp.where(ok, s0 * inv, 0.0)


def yaw_half_cos_sin(c: Any, s: Any) -> tuple[Any, Any]:
    """(cos, sin) of half the yaw with cosine ``c`` and sine ``s`` (trig-free, the half-angle formulas in
    their well-conditioned branches): the w and z components of :func:`yaw_quat` of that yaw in [-pi, pi]
    (x = y = 0; the representative with w >= 0)."""
    xp = array_namespace(c, s)
    pos_branch = c >= 0
    ch_a = xp.sqrt(xp.maximum(0.5 * (1.0 + c), 0.0))
    sh_b = xp.sqrt(xp.maximum(0.5 * (1.0 - c), 0.0))
    sh_b = xp.where(s < 0, -sh_b, sh_b) if xp is np else xp.copysign(sh_b, s)
    ch = xp.where(pos_branch, ch_a, s / xp.where(pos_branch, 1.0, 2.0 * sh_b))
    sh = xp.where(pos_branch, s / xp.where(pos_branch, 2.0 * ch_a, 1.0), sh_b)
    return ch, sh
