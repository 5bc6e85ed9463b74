"""MuJoCo's ``mj_step`` specialised to contact-free free bodies, as plain array code (NumPy or jax.numpy).

An exact specialisation (same physics, different round-off): ``tests/test_freebody.py`` checks it against
``mujoco.mj_step`` in float64 to 1e-9 over 200 sub-steps and against ``mjx.step`` in float32. Conventions
(MuJoCo's free joint):

- ``qpos`` (..., N, 7): body origin (m, world), then the quaternion (w, x, y, z) body to world;
- ``qvel`` (..., N, 6): linear velocity (m/s, world), then angular velocity (rad/s, BODY frame);
- ``xfrc`` (..., N, 6): ``xfrc_applied`` rows, force (N, world) at the COM, then torque (N m, world);
- ``mass`` (..., N) kg, ``inertia`` (..., N, 3) kg m^2 (principal moments about the COM), randomisable;
- ``ipos`` (N, 3) m / ``iquat`` (N, 4): the inertial frame in the body frame; ``None`` means zero /
  identity (the Crazyflie's case, the cheap path, a static choice at trace time).

What a step does, how an engine uses it, and the ``mj_setConst`` caveat: docs/model.md ("The free-body step").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from quadswarm_mj._xp import array_namespace

Vec = tuple[Any, Any, Any]
Mat = tuple[Any, Any, Any, Any, Any, Any, Any, Any, Any]  # row-major 3x3

#: Below this norm MuJoCo's ``mju_normalize3`` / ``mju_normalize4`` treat a vector as zero (mjMINVAL).
_MINVAL = 1e-15


# ---------------------------------------------------------------------------------------- 3-vector algebra
def _split(x: Any) -> tuple[Any, ...]:
    return tuple(x[..., i] for i in range(x.shape[-1]))


def _cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _quat2mat(w: Any, x: Any, y: Any, z: Any) -> Mat:
    """Body-to-world rotation of a unit quaternion, term for term as ``mju_quat2Mat``."""
    q00, q01, q02, q03 = w * w, w * x, w * y, w * z
    q11, q12, q13 = x * x, x * y, x * z
    q22, q23, q33 = y * y, y * z, z * z
    return (q00 + q11 - q22 - q33, 2 * (q12 - q03), 2 * (q13 + q02),
            2 * (q12 + q03), q00 - q11 + q22 - q33, 2 * (q23 - q01),
            2 * (q13 - q02), 2 * (q23 + q01), q00 - q11 - q22 + q33)


def _mv(R: Mat, v: Vec) -> Vec:
    """R v."""
    return (R[0] * v[0] + R[1] * v[1] + R[2] * v[2],
            R[3] * v[0] + R[4] * v[1] + R[5] * v[2],
            R[6] * v[0] + R[7] * v[1] + R[8] * v[2])


def _mtv(R: Mat, v: Vec) -> Vec:
    """R^T v."""
    return (R[0] * v[0] + R[3] * v[1] + R[6] * v[2],
            R[1] * v[0] + R[4] * v[1] + R[7] * v[2],
            R[2] * v[0] + R[5] * v[1] + R[8] * v[2])


# ---------------------------------------------------------------------------------------- the step
def freebody_step(qpos: Any, qvel: Any, xfrc: Any, mass: Any, inertia: Any, ipos: Any | None,
                  iquat: Any | None, gravity: Any, dt: float | Any,
                  max_omega: float | None = None) -> tuple[Any, Any]:
    """One ``mj_step`` (Euler, no contacts) of N free bodies; returns ``(qpos_new, qvel_new)``.

    Shapes and frames are in the module docstring: ``qpos`` (..., N, 7) [pos m world, quat wxyz
    body->world], ``qvel`` (..., N, 6) [m/s world, rad/s BODY], ``xfrc`` (..., N, 6) [N world at the COM,
    N m world], ``mass`` (..., N) kg, ``inertia`` (..., N, 3) kg m^2 principal, ``ipos`` (N, 3) m /
    ``iquat`` (N, 4) the inertial frame in the body frame, or ``None`` for zero / identity, ``gravity`` (3,)
    m/s^2 world, ``dt`` s. ``max_omega`` (rad/s, optional) clips the new angular velocity per axis.
    Outputs have the dtype of ``qpos`` (constants are cast to it) and the broadcast leading shape.
    """
    xp = array_namespace(qpos, qvel, xfrc, mass, inertia, gravity)
    dtype = qpos.dtype

    def cast(a: Any) -> Any:
        return xp.asarray(a, dtype=dtype)

    q = _split(qpos)
    pos, quat, v, w = freebody_step_components(
        q[:3], q[3:], _split(qvel[..., :3]), _split(qvel[..., 3:]), _split(cast(xfrc[..., :3])),
        _split(cast(xfrc[..., 3:])), cast(mass), _split(cast(inertia)), ipos, iquat, _split(cast(gravity)), dt,
        max_omega, xp)
    # per-body constants may carry leading dims the state lacks (or the converse): broadcast, then stack
    out = xp.broadcast_arrays(*pos, *quat, *v, *w)
    return xp.stack(out[:7], axis=-1).astype(dtype), xp.stack(out[7:], axis=-1).astype(dtype)


def freebody_step_components(pos: Vec, quat: tuple[Any, Any, Any, Any], vel: Vec, omega: Vec, force: Vec,
                             torque: Vec, mass: Any, inertia: Vec, ipos: Any | None, iquat: Any | None,
                             gravity: Vec, dt: float | Any, max_omega: float | None = None,
                             xp: Any = None) -> tuple[Vec, tuple[Any, Any, Any, Any], Vec, Vec]:
    """:func:`freebody_step` on vectors given as tuples of their components (structure of arrays).

    ``pos`` (m, world), ``quat`` (w, x, y, z; body->world), ``vel`` (m/s, world), ``omega`` (rad/s, BODY),
    ``force`` (N, world, at the COM), ``torque`` (N m, world), ``inertia`` (kg m^2, principal) and
    ``gravity`` (m/s^2, world) are tuples of (..., N) arrays, ``mass`` (..., N) kg; ``ipos``/``iquat`` as
    in :func:`freebody_step`. Returns ``(pos, quat, vel, omega)`` as tuples of components. The formulas
    are those of :func:`freebody_step`, which calls this function (the JAX engine's sub-step loop carries
    components, so XLA runs contiguous loops instead of strided slices of (N, 7) rows).
    """
    xp = array_namespace(*pos, *vel) if xp is None else xp
    dtype = pos[0].dtype
    px, py, pz = pos
    qw, qx, qy, qz = quat
    v, w, F, tau, m, d, g = vel, omega, force, torque, mass, inertia, gravity

    # mj_kinematics: normalise the quaternion, body-to-world rotation
    inv_n = 1 / xp.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    qw, qx, qy, qz = qw * inv_n, qx * inv_n, qy * inv_n, qz * inv_n
    R = _quat2mat(qw, qx, qy, qz)

    # Euler's equations about the COM in the principal (inertial) frame: d * alpha_i + w_i x (d * w_i) = tau_i
    tau_b = _mtv(R, tau)
    if iquat is None:
        w_i, tau_i = w, tau_b
    else:
        Ri = _quat2mat(*_split(xp.asarray(iquat, dtype=dtype)))
        w_i, tau_i = _mtv(Ri, w), _mtv(Ri, tau_b)
    gyro = _cross(w_i, (d[0] * w_i[0], d[1] * w_i[1], d[2] * w_i[2]))
    alpha_i = tuple((tau_i[k] - gyro[k]) / d[k] for k in range(3))
    alpha = alpha_i if iquat is None else _mv(Ri, alpha_i)  # body frame, rad/s^2

    # Newton at the COM: m a_com = F + m g; the body origin's acceleration is a_com minus the rigid
    # motion of the COM offset c about it: a = a_com - R (alpha x c + w x (w x c))
    acc = tuple(g[k] + F[k] / m for k in range(3))
    if ipos is not None:
        c = _split(xp.asarray(ipos, dtype=dtype))
        wc = _cross(w, c)
        rel = _cross(alpha, c)
        cen = _cross(w, wc)
        off = _mv(R, tuple(rel[k] + cen[k] for k in range(3)))
        acc = tuple(acc[k] - off[k] for k in range(3))

    # semi-implicit Euler: velocities first (mj_advance), then mj_integratePos with the new velocity
    v = tuple(v[k] + dt * acc[k] for k in range(3))
    w = tuple(w[k] + dt * alpha[k] for k in range(3))
    px, py, pz = px + dt * v[0], py + dt * v[1], pz + dt * v[2]
    # mju_quatIntegrate: q <- q * (cos(a/2), sin(a/2) axis), a = dt |w|, axis = w / |w|
    # |w| is taken as sqrt(|w|^2 + mjMINVAL^2): a relative change below 1e-16 for |w| > 1e-7 rad/s, and
    # at w = 0 the identity rotation (sin(a/2) / |w| -> dt / 2) with finite values and gradients, where
    # MuJoCo's own zero-vector branch gives the identity to within dt * mjMINVAL
    wn = xp.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2] + _MINVAL * _MINVAL)
    half = 0.5 * dt * wn
    s = xp.sin(half) / wn  # sin(a/2) / |w|
    rw, rx, ry, rz = xp.cos(half), s * w[0], s * w[1], s * w[2]
    nw = qw * rw - qx * rx - qy * ry - qz * rz
    nx = qw * rx + qx * rw + qy * rz - qz * ry
    ny = qw * ry - qx * rz + qy * rw + qz * rx
    nz = qw * rz + qx * ry - qy * rx + qz * rw
    # mj_normalizeQuat
    inv_n = 1 / xp.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
    nw, nx, ny, nz = nw * inv_n, nx * inv_n, ny * inv_n, nz * inv_n

    if max_omega is not None:
        w = tuple(xp.clip(wk, -max_omega, max_omega) for wk in w)
    return (px, py, pz), (nw, nx, ny, nz), v, w


# ---------------------------------------------------------------------------------------- model constants
@dataclass(frozen=True)
class FreeBodyConstants:
    """Per-quad constants of :func:`freebody_step`, read once from a compiled model (NumPy float64).

    ``ipos`` (N, 3) m is ``None`` when every quad's COM is at its body origin, ``iquat`` (N, 4) is
    ``None`` when every quad's principal axes are its body axes (the cheap paths). ``mass`` (N,) kg and
    ``inertia`` (N, 3) kg m^2 are the model's nominal values (the simulator passes its randomised ones
    instead). ``gravity`` (3,) m/s^2 world (zero if the model disables gravity), ``dt`` s the timestep."""

    ipos: np.ndarray | None
    iquat: np.ndarray | None
    mass: np.ndarray
    inertia: np.ndarray
    gravity: np.ndarray
    dt: float


def _require(ok: bool, what: str) -> None:
    if not ok:
        raise ValueError(f"freebody_step does not apply to this model: {what}")


def freebody_constants(model: mujoco.MjModel, body_ids: Any, world: int | None = 0) -> FreeBodyConstants:
    """Constants of :func:`freebody_step` for the quad bodies of ``model``; checks its assumptions.

    ``body_ids`` is an :class:`quadswarm_mj.arena.Arena` (its ``body_ids``, (B, N)) or an int array of
    body ids (..., N). ``world`` picks one row of a (B, N) id array (the (N, ...) constants the one-world
    engine uses); ``None`` keeps all leading dims. Raises ``ValueError`` naming the violated assumption
    (integrator not Euler, contacts possible, damping, armature, fluid forces, gravity compensation,
    actuators, constraints, a body that is not a lone free body child of the world).
    """
    ids = np.asarray(getattr(body_ids, "body_ids", body_ids), dtype=np.int64)
    if world is not None and ids.ndim == 2:
        if not 0 <= world < ids.shape[0]:
            raise ValueError(f"world must be in [0, {ids.shape[0] - 1}], got {world}")
        ids = ids[world]
    flat = ids.ravel()
    opt = model.opt
    _require(opt.integrator == mujoco.mjtIntegrator.mjINT_EULER, f"integrator is {opt.integrator}, not Euler")
    jnt = model.body_jntadr[flat]
    _require(bool(np.all(model.body_jntnum[flat] == 1)), "a quad body has not exactly one joint")
    _require(bool(np.all(model.jnt_type[jnt] == mujoco.mjtJoint.mjJNT_FREE)), "a quad joint is not free")
    _require(bool(np.all(model.body_parentid[flat] == 0)), "a quad body is not a child of the world")
    _require(not np.isin(flat, model.body_parentid[1:]).any(), "a quad body has child bodies")
    dof = (model.jnt_dofadr[jnt][:, None] + np.arange(6)).ravel()
    _require(not np.any(model.dof_damping[dof]) and not np.any(model.dof_armature[dof]),
             "quad joints have damping or armature")
    _require(not np.any(model.dof_frictionloss[dof]), "quad joints have friction loss")
    _require(opt.density == 0 and opt.viscosity == 0, "fluid forces (opt.density / opt.viscosity) are on")
    _require(not np.any(model.body_gravcomp[flat]), "quad bodies have gravity compensation")
    _require(model.nu == 0 and model.neq == 0 and model.ntendon == 0, "the model has actuators, equalities or tendons")
    contact_off = bool(opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT)
    geoms = np.isin(model.geom_bodyid, flat)
    _require(contact_off or not np.any(model.geom_contype[geoms] | model.geom_conaffinity[geoms]),
             "contacts are enabled and quad geoms can collide")
    gravity_off = bool(opt.disableflags & mujoco.mjtDisableBit.mjDSBL_GRAVITY)
    ipos = model.body_ipos[ids].copy()
    iquat = model.body_iquat[ids].copy()
    return FreeBodyConstants(
        ipos=ipos if np.any(ipos) else None,
        iquat=None if np.all(iquat == np.array([1.0, 0.0, 0.0, 0.0])) else iquat,
        mass=model.body_mass[ids].copy(), inertia=model.body_inertia[ids].copy(),
        gravity=np.zeros(3) if gravity_off else np.array(opt.gravity, dtype=np.float64),
        dt=float(opt.timestep))
