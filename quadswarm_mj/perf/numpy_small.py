"""The sub-step model functions in the fewest NumPy calls, for the small arrays of the CPU engine.

The model defines :func:`quadswarm_mj.actuation.substep_wrench`, :func:`quadswarm_mj.collisions.
floor_wrench` and :func:`quadswarm_mj.spatial.quat_to_rotmat` once each (component form,
:mod:`quadswarm_mj.components`). On a single env's (1, N, .) arrays NumPy's per-call overhead dominates,
so the CPU engine calls these instead: whole-array expressions of the same formulas with the same
rounding (bit-identical, signs of zero included where stated; ``tests/test_components.py``). From
``spatial.BIG`` elements on they call the model's body (NumPy's per-row overhead of reductions over
short axes then dominates; the component form wins). NumPy only.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from quadswarm_mj import actuation, collisions, spatial
from quadswarm_mj.actuation import SPIN, motor_lag, rotor_thrust, thrust_map, wrench_matrix
from quadswarm_mj.perf import one_quad
from quadswarm_mj.spatial import BIG, norm_last, sum_last


def substep_wrench(u: Any, cmd: Any, noise: Any, params: dict[str, Any], R: Any, rotor_pos: Any,
                   mix: Any | None = None, torque_spin: Any | None = None, thrust_quadratic: float = 0.0,
                   rotor_gain: Any | None = None) -> tuple[Any, Any, Any, Any]:
    """:func:`quadswarm_mj.actuation.substep_wrench` (same arguments, same bits)."""
    one = u.size == 4 and one_quad.ENABLED and thrust_quadratic == 0.0 and rotor_gain is None
    if one and mix is not None and torque_spin is not None:  # one quad: perf.one_quad's float form
        return one_quad.substep_wrench(u, cmd, noise, params["alpha"], params["thrust_max"], torque_spin, mix, R)
    if u.size >= BIG:
        return actuation.substep_wrench(u, cmd, noise, params, R, rotor_pos, mix, torque_spin, thrust_quadratic,
                                        rotor_gain)
    u = motor_lag(u, cmd, params["alpha"])
    f_norm = rotor_thrust(u, cmd, noise)
    mix = wrench_matrix(rotor_pos) if mix is None else mix
    torque_spin = params["torque_max"] * SPIN if torque_spin is None else torque_spin
    f_eff = f_norm if thrust_quadratic == 0.0 else thrust_map(f_norm, thrust_quadratic)
    if rotor_gain is not None:
        f_eff = f_eff * rotor_gain
    # rows: thrust (N per rotor) times the mix rows (F_z, tau_x, tau_y), and the yaw reaction torque per
    # rotor; one sum over the rotors (each row as sum_last sums it: the same bits)
    rows = np.empty(f_eff.shape[:-1] + (4, 4))
    np.multiply((params["thrust_max"] * f_eff)[..., None, :], mix, out=rows[..., :3, :])
    np.multiply(torque_spin, f_eff, out=rows[..., 3, :])
    s = rows.sum(axis=-1)  # F_z, tau_x, tau_y, tau_z (body)
    return u, f_norm, s[..., :1] * R[..., :, 2], sum_last(R * s[..., None, 1:])


def floor_wrench(on_floor: Any, force_w: Any, torque_w: Any, vel: Any, mass: Any, gravity: float,
                 friction: float, dt: float) -> tuple[Any, Any]:
    """:func:`quadswarm_mj.collisions.floor_wrench` (same arguments, same bits; the two results may be
    views of one (..., 6) array)."""
    if force_w.size == 3 and one_quad.ENABLED:
        return one_quad.floor_wrench(on_floor, force_w, torque_w, vel, mass, gravity, friction, dt)
    if force_w.size >= BIG:
        return collisions.floor_wrench(on_floor, force_w, torque_w, vel, mass, gravity, friction, dt)
    normal = np.maximum(0.0, mass * gravity - force_w[..., 2])
    cap = friction * normal
    f_h = force_w[..., :2]
    f_mag = norm_last(f_h)
    v_h = vel[..., :2]
    speed = norm_last(v_h)
    moving = speed > 1e-9
    new = np.empty(force_w.shape[:-1] + (6,))  # the grounded quads' force and torque (world)
    h = new[..., :2]  # horizontal force: static friction, then kinetic where moving
    np.multiply(f_h, (np.maximum(0.0, f_mag - cap) / np.where(f_mag > 0, f_mag, 1.0))[..., None], out=h)
    kinetic_mag = np.minimum(cap, mass * speed / dt)
    np.subtract(f_h, (kinetic_mag / np.where(moving, speed, 1.0))[..., None] * v_h, out=h, where=moving[..., None])
    np.add(force_w[..., 2], normal, out=new[..., 2])
    new[..., 3:5] = 0.0
    new[..., 5] = torque_w[..., 2]
    if np.count_nonzero(on_floor) < on_floor.size:
        new = np.where(on_floor[..., None], new, np.concatenate([force_w, torque_w], axis=-1))
    return new[..., :3], new[..., 3:]


# quat_to_rotmat as one gather: R_k = base_k + coef_k * (P[ia_k] + sign_k * P[ib_k]) with P the outer
# product of (w, x, y, z) with itself flattened (index 4 a + b): entry by entry the textbook formula
# (R_00 = 1 - 2 (yy + zz), R_01 = 2 (xy - wz), ...). coef = +-2 and sign = +-1 scale exactly, so
# coef * P[ia] + coef * sign * P[ib], summed, rounds as the textbook expression (only the sign of an
# exact zero may differ); 5 array operations instead of 30.
_Q_IAB = np.array([10, 6, 7, 6, 5, 11, 7, 11, 5,  # yy xy xz | xy xx yz | xz yz xx
                   15, 3, 2, 3, 15, 1, 2, 1, 10])  # zz wz wy | wz zz wx | wy wx yy
_Q_SIGN = np.array([1.0, -1.0, 1.0, 1.0, 1.0, -1.0, -1.0, 1.0, 1.0])
_Q_COEF = np.array([-2.0, 2.0, 2.0, 2.0, -2.0, 2.0, 2.0, 2.0, -2.0])
_Q_SCALE = np.concatenate([_Q_COEF, _Q_COEF * _Q_SIGN])
_Q_BASE = np.array([1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])


def quat_to_rotmat(q: Any) -> Any:
    """:func:`quadswarm_mj.spatial.quat_to_rotmat` (the same values; the sign of an exact zero may differ)."""
    if q.size == 4 and one_quad.ENABLED:
        return one_quad.quat_to_rotmat(q)
    if q.size >= BIG:
        return spatial.quat_to_rotmat(q)
    lead = q.shape[:-1]
    P = (q[..., :, None] * q[..., None, :]).reshape(lead + (16,))
    t = P.take(_Q_IAB, axis=-1) * _Q_SCALE
    # a + b (where a sum over the pair would give 0 + a + b): only the sign of an exact-zero t differs,
    # which the base's + 0.0 / + 1.0 erases (the same bits)
    return (_Q_BASE + (t[..., :9] + t[..., 9:])).reshape(lead + (3, 3))


# The entries (R10, R00, R22) of quat_to_rotmat (the floor impact's heading and upside-down test), with
# quat_to_rotmat's rounding: base + (coef * q_a q_b + coef * sign * q_c q_d), signs of zero included.
_YAW_I1 = np.array([1, 2, 1, 0, 3, 2])  # x y x | w z y
_YAW_I2 = np.array([2, 2, 1, 3, 3, 2])  # y y x | z z y  (products xy yy xx | wz zz yy)
_YAW_SCALE = np.array([2.0, -2.0, -2.0, 2.0, -2.0, -2.0])
_YAW_BASE = np.array([0.0, 1.0, 1.0])


# the same products taken straight from qpos rows (..., 7) (position, then the quaternion at 3:7): two
# gathers of a contiguous last axis instead of a strided quaternion view's outer product (same bits)
_QPOS_A, _QPOS_B = _Q_IAB // 4 + 3, _Q_IAB % 4 + 3
_QPOS_YAW_1, _QPOS_YAW_2 = _YAW_I1 + 3, _YAW_I2 + 3


def quat_to_rotmat_qpos(qpos: Any) -> Any:
    """(..., 7) free-body qpos rows -> (..., 3, 3): :func:`quat_to_rotmat` of ``qpos[..., 3:7]``
    below ``spatial.BIG`` elements (bit-identical, signs of zero included)."""
    t = qpos.take(_QPOS_A, axis=-1) * qpos.take(_QPOS_B, axis=-1)  # q_a q_b = P[4 a + b]
    t *= _Q_SCALE
    return (_Q_BASE + (t[..., :9] + t[..., 9:])).reshape(qpos.shape[:-1] + (3, 3))


def yaw_entries_qpos(qpos: Any) -> Any:
    """(..., 7) free-body qpos rows -> (..., 3): the entries R10, R00, R22 of :func:`quat_to_rotmat` of
    ``qpos[..., 3:7]`` (bit-identical, signs of zero included): ``arctan2(R10, R00)`` is the heading
    (:func:`quadswarm_mj.spatial.yaw_of`), R22 < 0 an upside-down body."""
    p = qpos.take(_QPOS_YAW_1, axis=-1) * qpos.take(_QPOS_YAW_2, axis=-1)
    p *= _YAW_SCALE
    return _YAW_BASE + (p[..., :3] + p[..., 3:])
