"""The sub-step's model functions on vectors given as tuples of components (structure of arrays).

The JAX engine's sub-step loop (default configuration: rotor control, the paper's floor, free-body
physics) carries every vector as a tuple of (N,) component arrays, (W, N) under ``vmap``, so XLA:CPU runs
contiguous loops over worlds and quads instead of strided slices and concatenations over 3-, 4-, 7- and
9-wide minor axes. Each function here uses, component for component, the formulas of the
array-of-structures function it mirrors (named in its docstring; the CPU engine calls those): on NumPy
both give the same bits, which ``tests/test_components.py`` checks. Under XLA the two forms compile to
different kernels (reductions over the rotor axis vs explicit sums), so the JAX engine's component loop
agrees with its general loop within float32 round-off (a few ulp per step; tested), not bit for bit.

Conventions: ``Vec3`` is (x, y, z), ``Rotors`` the 4 rotors in :data:`quadswarm_mj.actuation.ROTOR_SIGNS`
order, ``Rot`` the 9 entries of a body-to-world rotation (R00, R01, R02, R10, ..., R22), ``Quat``
(w, x, y, z); each entry an array of shape (..., N).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from quadswarm_mj._xp import array_namespace
from quadswarm_mj.constants import FLOOR_TOL
from quadswarm_mj.spatial import yaw_cos_sin_components, yaw_half_cos_sin

Vec3 = tuple[Any, Any, Any]
Quat = tuple[Any, Any, Any, Any]
Rotors = tuple[Any, Any, Any, Any]
Rot = tuple[Any, Any, Any, Any, Any, Any, Any, Any, Any]


def split(x: Any) -> tuple[Any, ...]:
    """The components of ``x`` (..., K) along its last axis: a K-tuple of (...,) arrays."""
    return tuple(x[..., i] for i in range(x.shape[-1]))


def stack(parts: tuple[Any, ...] | list[Any]) -> Any:
    """The inverse of :func:`split`: components stacked along a new last axis."""
    return array_namespace(*parts).stack(parts, axis=-1)


def _sum(terms: list[Any]) -> Any:
    """((t0 + t1) + t2) + ...: the rounding of :func:`quadswarm_mj.spatial.sum_last` on NumPy."""
    r = terms[0] + terms[1]
    for t in terms[2:]:
        r = r + t
    return r


def rotor_wrench(u: Rotors, cmd: Rotors, noise: Rotors, alpha: Any, thrust_max: Rotors, torque_spin: Rotors,
                 mix: Any, R: Rot, thrust_quadratic: float = 0.0,
                 rotor_gain: Rotors | None = None) -> tuple[Rotors, Rotors, Vec3, Vec3]:
    """:func:`quadswarm_mj.actuation.substep_wrench` per component (the model's one body of it).

    ``u`` normalized rotor speeds, ``cmd`` commands in [0, 1], ``noise`` the motor noise, ``alpha`` (..., N)
    the motor filter gain, ``thrust_max`` (N) and ``torque_spin`` (N m, ``torque_max * SPIN``) per rotor,
    ``mix`` the (3, 4) :func:`~quadswarm_mj.actuation.wrench_matrix`, ``R`` body->world;
    ``thrust_quadratic`` (a Python float) the static thrust map, ``rotor_gain`` per-rotor thrust gains
    (e.g. ground effect; None: 1). Returns the new ``u``, ``f_norm`` (normalized motor output, before the
    map and the gain), and the world force (N) and torque (N m) at the COM.
    """
    xp = array_namespace(*u, *cmd)
    u = tuple(u[i] + alpha * (xp.sqrt(cmd[i]) - u[i]) for i in range(4))  # motor_lag
    f = tuple(xp.minimum(xp.maximum(u[i] * u[i] + cmd[i] * noise[i], 0.0), 1.0) for i in range(4))  # rotor_thrust
    f_eff = f if thrust_quadratic == 0.0 else tuple(fi * ((1.0 - thrust_quadratic) + thrust_quadratic * fi)
                                                    for fi in f)  # actuation.thrust_map
    if rotor_gain is not None:
        f_eff = tuple(f_eff[i] * rotor_gain[i] for i in range(4))
    # a NumPy mix enters as Python floats (constants under jit), a JAX one as traced entries
    m = mix.tolist() if isinstance(mix, np.ndarray) else [[mix[r, i] for i in range(4)] for r in range(3)]
    thrust = [thrust_max[i] * f_eff[i] for i in range(4)]
    fz, tbx, tby = (_sum([thrust[i] * m[r][i] for i in range(4)]) for r in range(3))
    tbz = _sum([torque_spin[i] * f_eff[i] for i in range(4)])
    force = (fz * R[2], fz * R[5], fz * R[8])
    torque = tuple(_sum([R[3 * k] * tbx, R[3 * k + 1] * tby, R[3 * k + 2] * tbz]) for k in range(3))
    return u, f, force, torque


def floor_wrench(on_floor: Any, force: Vec3, torque: Vec3, vel: Vec3, mass: Any, gravity: float, friction: float,
                 dt: float) -> tuple[Vec3, Vec3]:
    """:func:`quadswarm_mj.collisions.floor_wrench` per component (world frame, N and N m)."""
    xp = array_namespace(force[0], vel[0])
    fx, fy, fz = force
    vx, vy = vel[0], vel[1]
    normal = xp.maximum(0.0, mass * gravity - fz)
    cap = friction * normal
    f_mag = xp.sqrt(fx * fx + fy * fy)
    speed = xp.sqrt(vx * vx + vy * vy)
    moving = speed > 1e-9
    static = xp.maximum(0.0, f_mag - cap) / xp.where(f_mag > 0, f_mag, 1.0)
    kinetic = xp.minimum(cap, mass * speed / dt) / xp.where(moving, speed, 1.0)
    hx = xp.where(moving, fx - kinetic * vx, fx * static)
    hy = xp.where(moving, fy - kinetic * vy, fy * static)
    zero = xp.zeros_like(torque[0])
    new_force = (xp.where(on_floor, hx, fx), xp.where(on_floor, hy, fy), xp.where(on_floor, fz + normal, fz))
    new_torque = (xp.where(on_floor, zero, torque[0]), xp.where(on_floor, zero, torque[1]), torque[2])
    return new_force, new_torque


def floor_impact(pos: Vec3, vel: Vec3, omega: Vec3, quat: Quat, R: Rot, u: Rotors, on_floor: Any, floor_z: float,
                 yaw_draw_cs: tuple[Any, Any] | None,
                 materialize: Callable[[tuple[Any, ...]], tuple[Any, ...]] | None = None,
                 yaw_draw: Any = None) -> dict[str, Any]:
    """:func:`quadswarm_mj.collisions.floor_impact` per component (the model's one body of it).

    The landing yaw (the heading kept, plus the draw for an upside-down landing) comes either from
    ``yaw_draw_cs`` = (cos, sin) of the draws, trig-free (the JAX engine), or from the angles
    ``yaw_draw`` (rad, when ``yaw_draw_cs`` is None: ``atan2`` of the heading, then ``cos``/``sin``;
    the CPU engine's seeded record); the two agree to round-off. ``materialize``: applied to the
    landing yaw's (cos, sin) (an identity on their values, e.g. ``perf.xla_cpu.kernel_boundary``), so
    that XLA computes them once instead of inside each of the ~20 selects that read them. Returns a
    dict of ``pos, vel, omega, quat, R, u`` (tuples) and ``on_floor, hit_floor`` (..., N) bool."""
    xp = array_namespace(pos[0], vel[0])
    z = pos[2]
    hit = (z <= floor_z) & ~on_floor
    staying = on_floor & (z <= floor_z + FLOOR_TOL)
    grounded = hit | staying
    flip = hit & (R[8] < 0)  # upside down
    if yaw_draw_cs is None:  # the angle path (spatial.yaw_of, yaw_quat, yaw_rotmat)
        yaw = xp.arctan2(R[3], R[0]) + xp.where(flip, yaw_draw, 0.0)
        c, s = xp.cos(yaw), xp.sin(yaw)
        h = 0.5 * yaw
        ch, sh = xp.cos(h), xp.sin(h)
    else:
        c, s = yaw_cos_sin_components(R[0], R[3])
        dc, ds = yaw_draw_cs
        c, s = xp.where(flip, c * dc - s * ds, c), xp.where(flip, s * dc + c * ds, s)
        if materialize is not None:
            c, s = materialize((c, s))
        ch, sh = yaw_half_cos_sin(c, s)
    zero, one = xp.zeros_like(c), xp.ones_like(c)

    def hit_or(a: Any, b: Any) -> Any:
        return xp.where(hit, 0.0 * a, b)

    new_vel = (hit_or(vel[0], vel[0]), hit_or(vel[1], vel[1]), hit_or(vel[2], xp.where(staying, zero, vel[2])))
    new_omega = (hit_or(omega[0], xp.where(staying, zero, omega[0])),
                 hit_or(omega[1], xp.where(staying, zero, omega[1])), hit_or(omega[2], omega[2]))
    yaw_q = (ch, zero, zero, sh)
    yaw_R = (c, -s, zero, s, c, zero, zero, zero, one)
    return {"pos": (pos[0], pos[1], xp.where(grounded, floor_z, z)), "vel": new_vel, "omega": new_omega,
            "quat": tuple(xp.where(grounded, a, b) for a, b in zip(yaw_q, quat)),
            "R": tuple(xp.where(grounded, a, b) for a, b in zip(yaw_R, R)),
            "u": tuple(hit_or(ui, ui) for ui in u), "on_floor": grounded, "hit_floor": hit}
