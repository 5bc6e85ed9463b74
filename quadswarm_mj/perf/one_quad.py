"""The sub-step model functions for exactly one quad (one world), on Python floats.

For a single env with one quad the arrays of :mod:`quadswarm_mj.perf.numpy_small` hold 1 to 9 values,
and NumPy's fixed cost per call (about 1 us) is the whole cost. These forms read the few values out as
Python floats, apply the model's formulas (:mod:`quadswarm_mj.components`, the one body of each) term
by term with the same rounding (IEEE double arithmetic and ``math.sqrt`` round exactly as NumPy's; the
transcendental functions stay NumPy's ufuncs, whose SIMD forms may differ from ``math``'s in the last
bit), and return fresh NumPy arrays of the usual shapes. ``perf.numpy_small`` calls them for
one-element batches; ``tests/test_perf_one_quad.py`` checks the same bits (signs of zero included)
against the array forms. NumPy only.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from quadswarm_mj.constants import FLOOR_TOL

#: set to False for the array forms everywhere (the same-values tests compare the two)
ENABLED = True

_arctan2, _cos, _sin = np.arctan2, np.cos, np.sin


def _max(a: float, b: float) -> float:
    """``np.maximum(a, b)`` on floats: ``b`` when they are equal (signs of zero), NaN from either."""
    return a if (a > b or a != a) else b


def _min(a: float, b: float) -> float:
    """``np.minimum(a, b)`` on floats: ``b`` when they are equal (signs of zero), NaN from either."""
    return a if (a < b or a != a) else b


def substep_wrench(u: Any, cmd: Any, noise: Any, alpha: Any, thrust_max: Any, torque_spin: Any, mix: Any,
                   R: Any) -> tuple[Any, Any, Any, Any]:
    """:func:`quadswarm_mj.actuation.substep_wrench` for one quad in the paper's chain (linear thrust map,
    no rotor gain): ``u``, ``cmd``, ``noise``, ``thrust_max``, ``torque_spin`` (1, 1, 4), ``alpha`` (1, 1),
    ``mix`` (3, 4), ``R`` (1, 1, 3, 3). Returns fresh (u, f_norm) (1, 1, 4) and world (force, torque)
    (1, 1, 3), the bits of ``perf.numpy_small.substep_wrench``."""
    u0, u1, u2, u3 = u.ravel().tolist()
    c0, c1, c2, c3 = cmd.ravel().tolist()
    n0, n1, n2, n3 = noise.ravel().tolist()
    a = alpha.item()
    sqrt = math.sqrt  # correctly rounded, as np.sqrt
    s0, s1, s2, s3 = sqrt(c0), sqrt(c1), sqrt(c2), sqrt(c3)
    u0, u1, u2, u3 = u0 + a * (s0 - u0), u1 + a * (s1 - u1), u2 + a * (s2 - u2), u3 + a * (s3 - u3)
    f0 = _min(_max(u0 * u0 + c0 * n0, 0.0), 1.0)
    f1 = _min(_max(u1 * u1 + c1 * n1, 0.0), 1.0)
    f2 = _min(_max(u2 * u2 + c2 * n2, 0.0), 1.0)
    f3 = _min(_max(u3 * u3 + c3 * n3, 0.0), 1.0)
    m0, m1, m2 = mix.tolist()
    t0, t1, t2, t3 = thrust_max.ravel().tolist()
    t0, t1, t2, t3 = t0 * f0, t1 * f1, t2 * f2, t3 * f3
    fz = ((t0 * m0[0] + t1 * m0[1]) + t2 * m0[2]) + t3 * m0[3]
    tx = ((t0 * m1[0] + t1 * m1[1]) + t2 * m1[2]) + t3 * m1[3]
    ty = ((t0 * m2[0] + t1 * m2[1]) + t2 * m2[2]) + t3 * m2[3]
    q0, q1, q2, q3 = torque_spin.ravel().tolist()
    tz = ((q0 * f0 + q1 * f1) + q2 * f2) + q3 * f3
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R.ravel().tolist()
    force = np.array([[[fz * r02, fz * r12, fz * r22]]])
    torque = np.array([[[(r00 * tx + r01 * ty) + r02 * tz, (r10 * tx + r11 * ty) + r12 * tz,
                         (r20 * tx + r21 * ty) + r22 * tz]]])
    return np.array([[[u0, u1, u2, u3]]]), np.array([[[f0, f1, f2, f3]]]), force, torque


def floor_wrench(on_floor: Any, force_w: Any, torque_w: Any, vel: Any, mass: Any, gravity: float,
                 friction: float, dt: float) -> tuple[Any, Any]:
    """:func:`quadswarm_mj.collisions.floor_wrench` for one quad: ``on_floor`` (1, 1) bool, ``force_w``,
    ``torque_w``, ``vel`` (1, 1, 3), ``mass`` (1, 1). Returns fresh (force, torque) (1, 1, 3)."""
    fx, fy, fz = force_w.ravel().tolist()
    if not on_floor.item():
        return np.array([[[fx, fy, fz]]]), torque_w.reshape(1, 1, 3).copy()
    vx, vy = vel.ravel().tolist()[:2]
    m = mass.item()
    normal = _max(0.0, m * gravity - fz)
    cap = friction * normal
    f_mag = math.sqrt(fx * fx + fy * fy)
    speed = math.sqrt(vx * vx + vy * vy)
    if speed > 1e-9:  # kinetic friction opposes the velocity
        kinetic = _min(cap, m * speed / dt) / speed
        hx, hy = fx - kinetic * vx, fy - kinetic * vy
    else:  # static friction cancels the horizontal force up to the cap
        static = _max(0.0, f_mag - cap) / (f_mag if f_mag > 0 else 1.0)
        hx, hy = fx * static, fy * static
    tz = torque_w.ravel()[2].item()
    return np.array([[[hx, hy, fz + normal]]]), np.array([[[0.0, 0.0, tz]]])


def floor_impact_inplace(q: Any, v: Any, u: Any, on_floor: bool, floor_z: float, offset: Any,
                         yaw_draw: float) -> tuple[bool, bool, Any]:
    """The paper's floor model after a sub-step for one quad, written into ``q`` (7,) = qpos (position
    with the world ``offset`` (3,) added, quaternion) and ``v`` (6,) = qvel (vel, omega) in place: the
    values of ``perf.numpy_small.floor_impact`` (``CpuSwarm._floor_impact``'s masked writes). ``u`` (1, 1, 4)
    motor state; ``yaw_draw`` (rad) the upside-down landing's draw. Returns (grounded, hit, u) with ``u``
    a fresh array zeroed (0.0 * u) on a hit, else ``u`` itself."""
    ox, oy, oz = offset.tolist()
    x, y, zq, w, qx, qy, qz = q.tolist()
    z = zq - oz
    hit = z <= floor_z and not on_floor
    staying = on_floor and z <= floor_z + FLOOR_TOL
    if not (hit or staying):
        q[0], q[1], q[2] = (x - ox) + ox, (y - oy) + oy, z + oz
        return False, False, u
    # R10, R00 (the heading) and R22 (upside down) of quat_to_rotmat, with its rounding
    r10 = 0.0 + (qx * qy * 2.0 + w * qz * 2.0)
    r00 = 1.0 + (qy * qy * -2.0 + qz * qz * -2.0)
    yaw = float(_arctan2(r10, r00))
    if hit:
        r22 = 1.0 + (qx * qx * -2.0 + qy * qy * -2.0)
        yaw = yaw + (yaw_draw if r22 < 0 else 0.0)
    else:
        yaw = yaw + 0.0
    half = 0.5 * yaw
    q[0], q[1], q[2] = (x - ox) + ox, (y - oy) + oy, floor_z + oz
    q[3], q[4], q[5], q[6] = float(_cos(half)), 0.0, 0.0, float(_sin(half))
    if hit:  # vel, omega and the motors zeroed (0.0 * x: signs kept)
        v *= 0.0
        u = 0.0 * u
    else:  # staying: no vertical speed, no roll/pitch rate
        v[2], v[3], v[4] = 0.0, 0.0, 0.0
    return True, hit, u
