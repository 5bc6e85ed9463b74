"""Control modes above the rotors: physical-unit commands -> per-rotor normalized motor commands.

``EnvConfig.control_mode`` selects what an action means (per quad, 4 numbers, in this order):

============ ===================================================================================
mode         action (units, frame)
============ ===================================================================================
"rotor"      the paper's raw per-rotor actions in [-1, 1] (``actuation.action_to_command``)
"ctbr"       collective thrust N in [0, 4 thrust_max], roll rate, pitch rate, yaw rate rad/s
             (body frame: x forward, y left, z up)
"attitude"   collective thrust N in [0, 4 thrust_max], roll rad, pitch rad (ZYX Euler angles
             relative to the current heading), yaw rate rad/s (body z)
"velocity"   vx, vy, vz m/s (world frame), yaw rate rad/s (body z)
============ ===================================================================================

Roll > 0 lowers the right side, pitch > 0 the nose, yaw > 0 is counter-clockwise from above; actions are
clipped into :func:`control_action_bounds`. Each mode is a cascade run every physics sub-step
(:func:`mode_command`, NumPy or ``jax.numpy``, any batch dims) ending in the motor command in [0, 1];
``ctrl_state`` (..., N, 6) holds the rate and velocity integrals (:func:`init_control_state`). The
cascade and the sources of the bounds: docs/model.md ("Beyond the paper").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from quadswarm_mj._xp import array_namespace
from quadswarm_mj.actuation import inverse_thrust_map
from quadswarm_mj.config import CONTROL_MODES, EnvConfig, QuadParams
from quadswarm_mj.controllers import PositionController, _cross, _normalize

#: m/s, per axis velocity bound of the "velocity" mode (30 km/h, gym-pybullet-drones cf2x).
MAX_SPEED = 30.0 / 3.6
CTRL_STATE_DIM = 6


@dataclass(frozen=True)
class ModeGains:
    """Gains of the mode cascade (SI). Rate gains are angular accelerations per rad/s of error
    (scaled by the inertia inside), so they do not depend on the airframe."""

    k_rate: tuple[float, float, float] = (20.0, 20.0, 12.0)  # 1/s, body rate P
    ki_rate: tuple[float, float, float] = (0.0, 0.0, 0.0)  # 1/s^2, body rate I (off: exact model)
    rate_integral_max: float = 1.0  # rad, clip of each rate-error integral
    k_att: tuple[float, float] = (8.0, 8.0)  # 1/s, attitude error -> roll/pitch rate
    k_vel: tuple[float, float, float] = (3.0, 3.0, 4.0)  # 1/s, velocity error -> acceleration
    ki_vel: tuple[float, float, float] = (0.5, 0.5, 1.0)  # 1/s^2
    vel_integral_max: float = 2.0  # m/s * s, clip of each velocity-error integral
    max_tilt_deg: float = 35.0  # deg, tilt limit of the velocity mode
    max_acc: float = 8.0  # m/s^2, norm limit of the commanded acceleration (before gravity)


DEFAULT_GAINS = ModeGains()


def control_action_bounds(cfg: EnvConfig) -> tuple[np.ndarray, np.ndarray]:
    """(low (4,), high (4,)) physical bounds of one quad's action in ``cfg.control_mode``
    (module docstring); "rotor" gives [-1, 1]."""
    q, mode = cfg.quad, cfg.control_mode
    w, t = q.max_omega, 4.0 * q.thrust_max
    if mode == "rotor":
        return -np.ones(4), np.ones(4)
    if mode == "ctbr":
        return np.array([0.0, -w, -w, -w]), np.array([t, w, w, w])
    if mode == "attitude":
        h = math.pi / 2
        return np.array([0.0, -h, -h, -w]), np.array([t, h, h, w])
    if mode == "velocity":
        v = MAX_SPEED
        return np.array([-v, -v, -v, -w]), np.array([v, v, v, w])
    raise ValueError(f"control_mode must be one of {CONTROL_MODES}, got {mode!r}")


def init_control_state(batch_shape: tuple[int, ...], like: Any = None) -> Any:
    """Zero controller state (..., N, 6) (``batch_shape`` = (..., N)) in the namespace of ``like``."""
    xp = array_namespace(like) if like is not None else np
    dtype = like.dtype if like is not None else np.float64
    return xp.zeros(tuple(batch_shape) + (CTRL_STATE_DIM,), dtype=dtype)


@lru_cache(maxsize=16)
def _allocator(quad: QuadParams) -> PositionController:
    return PositionController(quad)


def _vec(xp: Any, v: Any, like: Any) -> Any:
    return xp.asarray(v, dtype=like.dtype)


def _yaw(xp: Any, R: Any) -> Any:
    return xp.arctan2(R[..., 1, 0], R[..., 0, 0])


def _rot_zyx(xp: Any, roll: Any, pitch: Any, yaw: Any) -> Any:
    cr, sr, cp, sp, cy, sy = xp.cos(roll), xp.sin(roll), xp.cos(pitch), xp.sin(pitch), xp.cos(yaw), xp.sin(yaw)
    return xp.stack([xp.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
                     xp.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
                     xp.stack([-sp, cp * sr, cp * cr], -1)], -2)


def _attitude_rates(xp: Any, R: Any, R_d: Any, yaw_rate: Any, gains: ModeGains) -> Any:
    """Body-rate command (..., N, 3): -k_att e_R on roll/pitch (geometric error), yaw rate given."""
    E = xp.einsum("...ki,...kj->...ij", R_d, R) - xp.einsum("...ki,...kj->...ij", R, R_d)
    e_R = 0.5 * xp.stack([E[..., 2, 1], E[..., 0, 2]], axis=-1)
    rp = -_vec(xp, gains.k_att, R) * e_R
    return xp.concatenate([rp, yaw_rate[..., None]], axis=-1)


def _rate_loop(xp: Any, rate_d: Any, omega: Any, inertia: Any, integ: Any, dt: float,
               gains: ModeGains) -> tuple[Any, Any]:
    """Body torque tau = J (k (w_d - w) + ki I) + w x J w and the new integral I (..., N, 3)."""
    err = rate_d - omega
    m = gains.rate_integral_max
    integ = xp.clip(integ + err * dt, -m, m)
    acc = _vec(xp, gains.k_rate, omega) * err + _vec(xp, gains.ki_rate, omega) * integ
    return inertia * acc + _cross(xp, omega, inertia * omega), integ


def _velocity_to_thrust_attitude(xp: Any, v_d: Any, vel: Any, R: Any, mass: Any, g: float, integ: Any,
                                 dt: float, gains: ModeGains) -> tuple[Any, Any, Any]:
    """Velocity loop: (collective thrust (..., N) N, desired R_d (..., N, 3, 3), new integral)."""
    err = v_d - vel
    m = gains.vel_integral_max
    integ = xp.clip(integ + err * dt, -m, m)
    acc = _vec(xp, gains.k_vel, vel) * err + _vec(xp, gains.ki_vel, vel) * integ
    n_acc = xp.sqrt(xp.sum(acc * acc, axis=-1, keepdims=True))
    acc = acc * xp.minimum(1.0, gains.max_acc / xp.maximum(n_acc, 1e-9))
    az = xp.maximum(acc[..., 2] + g, 0.1 * g)  # keep the thrust pointing up
    h = acc[..., :2]
    h_max = az * math.tan(math.radians(gains.max_tilt_deg))
    n_h = xp.sqrt(xp.sum(h * h, axis=-1))
    h = h * xp.minimum(1.0, h_max / xp.maximum(n_h, 1e-9))[..., None]
    a = xp.concatenate([h, az[..., None]], axis=-1)
    ez = xp.zeros_like(a) + xp.asarray([0.0, 0.0, 1.0], dtype=a.dtype)
    b3_d = _normalize(xp, a, ez)
    yaw = _yaw(xp, R)
    heading = xp.stack([xp.cos(yaw), xp.sin(yaw), xp.zeros_like(yaw)], axis=-1)
    b2_d = _normalize(xp, _cross(xp, b3_d, heading), R[..., :, 1])
    R_d = xp.stack([_cross(xp, b2_d, b3_d), b2_d, b3_d], axis=-1)
    thrust = mass * xp.sum(a * R[..., :, 2], axis=-1)
    return thrust, R_d, integ


def mode_command(mode: str, action: Any, state: dict[str, Any], params: dict[str, Any], ctrl_state: Any,
                 dt: float, quad: QuadParams | None = None, gains: ModeGains = DEFAULT_GAINS,
                 bounds: tuple[Any, Any] | None = None) -> tuple[Any, Any]:
    """One physics-rate step of the ``mode`` controller (not "rotor").

    ``action`` (..., N, 4) in the mode's physical units (module docstring; clipped into
    ``bounds`` = :func:`control_action_bounds` if given); ``state``: ``rot`` (..., N, 3, 3)
    body->world, ``omega`` (..., N, 3) rad/s body, ``vel`` (..., N, 3) m/s world (velocity mode);
    ``params``: the per-quad dynamics parameters (``randomization.params_from_draws``: ``mass``,
    ``inertia``, ``thrust_max``, ``torque_max``, ``gravity``); ``ctrl_state`` (..., N, 6);
    ``dt`` the physics step (s); ``quad`` the nominal airframe (rotor geometry and the static
    thrust map, default ``QuadParams()``). Returns (``cmd`` (..., N, 4) in [0, 1], the motor
    command that replaces ``action_to_command(action)``; the new ``ctrl_state``).
    """
    quad = QuadParams() if quad is None else quad
    R, omega = state["rot"], state["omega"]
    xp = array_namespace(R, omega, action)
    action = xp.asarray(action, dtype=omega.dtype)
    if bounds is not None:
        action = xp.clip(action, _vec(xp, bounds[0], omega), _vec(xp, bounds[1], omega))
    mass, inertia = params["mass"], params["inertia"]
    thrust_max, torque_max = params["thrust_max"], params["torque_max"]
    g = params["gravity"]
    i_rate, i_vel = ctrl_state[..., :3], ctrl_state[..., 3:]
    if mode == "ctbr":
        thrust, rate_d = action[..., 0], action[..., 1:]
    elif mode == "attitude":
        R_d = _rot_zyx(xp, action[..., 1], action[..., 2], _yaw(xp, R))
        thrust, rate_d = action[..., 0], _attitude_rates(xp, R, R_d, action[..., 3], gains)
    elif mode == "velocity":
        thrust, R_d, i_vel = _velocity_to_thrust_attitude(xp, action[..., :3], state["vel"], R, mass, g, i_vel,
                                                          dt, gains)
        rate_d = _attitude_rates(xp, R, R_d, action[..., 3], gains)
    else:
        raise ValueError(f"mode_command: mode must be one of {CONTROL_MODES[1:]}, got {mode!r}")
    torque, i_rate = _rate_loop(xp, rate_d, omega, inertia, i_rate, dt, gains)
    f = _allocator(quad).allocate(xp.maximum(thrust, 0.0), torque, thrust_max, torque_max)
    cmd = xp.clip(inverse_thrust_map(f, quad.thrust_map_quadratic), 0.0, 1.0)
    return cmd, xp.concatenate([i_rate, i_vel], axis=-1)


def make_mode_controller(cfg: EnvConfig, gains: ModeGains = DEFAULT_GAINS) -> Any:
    """``step(action, state, params, ctrl_state) -> (cmd, ctrl_state)`` for ``cfg.control_mode``
    at ``cfg.sim_dt``, with ``cfg``'s bounds and airframe bound in (None for "rotor")."""
    if cfg.control_mode == "rotor":
        return None
    mode, quad, dt, bounds = cfg.control_mode, cfg.quad, cfg.sim_dt, control_action_bounds(cfg)

    def step(action: Any, state: dict[str, Any], params: dict[str, Any], ctrl_state: Any) -> tuple[Any, Any]:
        return mode_command(mode, action, state, params, ctrl_state, dt, quad=quad, gains=gains, bounds=bounds)

    return step


def action_box_bounds(cfg: EnvConfig, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) float32 arrays of ``shape`` (..., 4) for a Gymnasium ``Box``: the physical bounds
    of :func:`control_action_bounds` per quad ([-1, 1] in "rotor" mode)."""
    lo, hi = control_action_bounds(cfg)
    return (np.broadcast_to(lo, shape).astype(np.float32), np.broadcast_to(hi, shape).astype(np.float32))
