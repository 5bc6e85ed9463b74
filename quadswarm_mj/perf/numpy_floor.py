"""The paper's floor model in the fewest NumPy calls, for the CPU engine's small arrays.

:func:`quadswarm_mj.collisions.floor_wrench` and :func:`quadswarm_mj.collisions.floor_impact` (the
model, component form in :mod:`quadswarm_mj.components`) change only the grounded quads. On a single
env's (B, N, .) arrays NumPy's per-call overhead dominates, so :class:`quadswarm_mj.core.ops.NumpyOps`
and ``CpuSwarm._floor_impact`` call :func:`floor_wrench_inplace` and :func:`floor_impact_rows`
instead: the model's formulas fused into whole-row expressions with the same rounding (bit-identical,
signs of zero included; ``tests/test_numpy_floor.py``), written in place by masked writes (cheaper
than boolean-index gathers and scatters on these small strided arrays). NumPy only.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from quadswarm_mj.constants import FLOOR_TOL
from quadswarm_mj.perf.numpy_small import yaw_entries_qpos

# thresholds of (|F_h|, |v_h|): the static ratio divides by |F_h| where it is > 0, the kinetic one by
# the speed where the quad moves (> 1e-9 m/s), as the model
_THRESH = np.array([0.0, 1e-9])


def floor_wrench_inplace(on_floor: np.ndarray, force: np.ndarray, torque: np.ndarray, v: np.ndarray,
                         mass: Any, gravity: Any, friction: float, dt: float, weight: Any = None) -> None:
    """:func:`quadswarm_mj.collisions.floor_wrench` written into ``force``/``torque`` (..., N, 3)
    (world, N and N m) at the quads flagged in ``on_floor`` (..., N) bool; ``v`` (..., N, >= 2) the
    world velocity (its first two entries horizontal, m/s), ``mass`` (kg) broadcastable to
    ``on_floor``; ``weight`` = ``mass * gravity`` when the caller has it. The other quads' entries are left
    as they are (the model returns them unchanged)."""
    every = np.count_nonzero(on_floor) == on_floor.size  # all grounded: computed in place
    f = force if every else force.copy()  # (..., 3) the new force where grounded
    h = np.concatenate((f[..., :2], v[..., :2]), axis=-1)  # F_x F_y v_x v_y
    sq = h * h
    mags = np.sqrt(sq[..., 0::2] + sq[..., 1::2])  # |F_h|, speed (sqrt(x x + y y) as norm_last)
    normal = np.maximum(0.0, (mass * gravity if weight is None else weight) - f[..., 2])
    cap = friction * normal
    num = np.empty_like(mags)  # static: max(0, |F_h| - cap); kinetic: min(cap, m speed / dt)
    np.maximum(0.0, mags[..., 0] - cap, out=num[..., 0])
    np.minimum(cap, mass * mags[..., 1] / dt, out=num[..., 1])
    positive = mags > _THRESH  # |F_h| > 0, moving
    ratio = num / np.where(positive, mags, 1.0)
    np.multiply(h[..., :2], ratio[..., :1], out=f[..., :2])  # static friction
    np.subtract(h[..., :2], ratio[..., 1:] * h[..., 2:], out=f[..., :2], where=positive[..., 1:])  # kinetic
    f[..., 2] += normal
    if every:
        torque[..., :2] = 0.0  # no roll/pitch torque (+0.0, as the model's zeros)
    else:  # masked writes (cheaper than a gather and a scatter of the grounded rows at this size)
        mask = on_floor[..., None]
        np.copyto(force, f, where=mask)
        np.copyto(torque[..., :2], 0.0, where=mask)


def floor_impact_rows(q: np.ndarray, v: np.ndarray, on_floor: np.ndarray, floor_z: float, offsets: Any,
                      yaw_draw: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """:func:`quadswarm_mj.collisions.floor_impact` (angle path) written in place into MuJoCo's rows:
    ``q`` (M, N, 7) qpos (positions m, with the world ``offsets`` (M or 1, 1, 3); None: all zero),
    ``v`` (M, N, 6) qvel (world linear, body angular); ``yaw_draw`` (M, N) rad. Positions are
    rewritten as (p - offset) + offset everywhere (the engine's frame round trip). Masked writes
    (``where=``), cheaper than boolean-index writes on these strided views. Returns (hit, grounded,
    any hit); the caller resets the motors of the hit quads."""
    z = q[..., 2] if offsets is None else q[..., 2] - offsets[..., 2]
    hit = (z <= floor_z) > on_floor  # at or below the floor and airborne
    staying = on_floor & (z <= floor_z + FLOOR_TOL)
    grounded = hit | staying
    any_hit = np.count_nonzero(hit) > 0
    e = yaw_entries_qpos(q)  # R10, R00, R22 of the old rotation
    yaw = np.arctan2(e[..., 0], e[..., 1]) + (np.where(hit & (e[..., 2] < 0), yaw_draw, 0.0) if any_hit else 0.0)
    half = 0.5 * yaw  # the yaw-only quaternion (cos h, 0, 0, sin h) where grounded
    np.cos(half, out=q[..., 3], where=grounded)
    np.copyto(q[..., 4:6], 0.0, where=grounded[..., None])
    np.sin(half, out=q[..., 6], where=grounded)
    if offsets is None:  # (p - 0.0) + 0.0 == p + 0.0 bitwise (signs of zero included)
        np.copyto(q[..., 2], floor_z, where=grounded)
        q[..., :3] += 0.0
    else:
        pos = q[..., :3] - offsets
        np.copyto(pos[..., 2], floor_z, where=grounded)
        np.add(pos, offsets, out=q[..., :3])
    if any_hit:  # a hit zeroes vel and omega (0.0 * x: signs kept)
        np.multiply(v, 0.0, out=v, where=hit[..., None])
    np.copyto(v[..., 2:5], 0.0, where=staying[..., None])  # staying: no vertical speed, no roll/pitch rate
    return hit, grounded, any_hit
