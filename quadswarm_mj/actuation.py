"""Per-rotor actuation (SPEC §2): action -> command -> motor lag -> motor noise -> thrusts -> wrench.

Rotor layout (body frame: x forward, y left, z up; X configuration, seen from above)::

          front (+x)
      3 (FL, +1)   0 (FR, -1)
             \\     /
              [COM]          +y <- left
             /     \\
      2 (BL, -1)   1 (BR, +1)

Rotor ``i`` sits at ``ROTOR_SIGNS[i] * (arm/sqrt 2, arm/sqrt 2)`` in xy, ``rotor_z`` below the
COM; ``SPIN[i]`` is the sign of its yaw reaction torque about body z.

All functions are pure, take arrays with any leading batch dims (``(N, 4)``, ``(B, N, 4)``) and
run unchanged on NumPy and ``jax.numpy``. Normalized thrust ``f_norm`` is in [0, 1] of
``thrust_max``; forces are in N, torques in N m.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from quadswarm_mj import components as C
from quadswarm_mj._xp import array_namespace
from quadswarm_mj.config import QuadParams
from quadswarm_mj.random_draws import DrawSpec, Normal
from quadswarm_mj.spatial import sum_last

#: xy signs of rotors 0..3: front-right, back-right, back-left, front-left.
ROTOR_SIGNS = np.array([[1.0, -1.0], [-1.0, -1.0], [-1.0, 1.0], [1.0, 1.0]])
#: yaw reaction torque sign of rotors 0..3.
SPIN = np.array([-1.0, 1.0, -1.0, 1.0])


def rotor_positions(quad: QuadParams) -> np.ndarray:
    """(4, 3) rotor positions relative to the COM in the body frame (m)."""
    xy = quad.arm / np.sqrt(2.0)
    pos = np.zeros((4, 3))
    pos[:, :2] = ROTOR_SIGNS * xy
    pos[:, 2] = quad.rotor_z
    return pos


def motor_alpha(dt: Any, settling_time: Any) -> Any:
    """First-order motor filter gain for a 2 % settling time (4 time constants)."""
    xp = array_namespace(settling_time)
    return xp.minimum(1.0, 4.0 * dt / (settling_time + 1e-6))


def action_to_command(action: Any) -> Any:
    """Raw action in [-1, 1] (clipped) -> normalized thrust command in [0, 1]."""
    xp = array_namespace(action)
    return 0.5 * (xp.minimum(xp.maximum(action, -1.0), 1.0) + 1.0)  # clip as two cheap ufuncs


def motor_noise_draw_spec(num_quads: int) -> DrawSpec:
    """One standard normal per rotor per control step."""
    return {"motor": Normal(0.0, 1.0, (num_quads, 4))}


def motor_noise_step(eps: Any, sigma: Any, theta: float, normal: Any) -> Any:
    """Ornstein-Uhlenbeck update of the per-rotor motor noise (once per control step).

    ``sigma`` is (..., N) (0.2 * noise ratio); ``normal`` is a standard normal draw (..., N, 4).
    """
    return eps + theta * (0.0 - eps) + sigma[..., None] * normal


def motor_lag(u: Any, cmd: Any, alpha: Any) -> Any:
    """One sub-step of the motor lag on the normalized rotor speed ``u`` (..., N, 4)."""
    xp = array_namespace(u, cmd)
    return u + alpha[..., None] * (xp.sqrt(cmd) - u)


def rotor_thrust(u: Any, cmd: Any, noise: Any) -> Any:
    """Normalized rotor thrust f_norm = clip(u^2 + cmd * noise, 0, 1)."""
    xp = array_namespace(u, cmd)
    return xp.minimum(xp.maximum(u * u + cmd * noise, 0.0), 1.0)  # = clip, as two cheap ufuncs


def thrust_map(f: Any, q: float) -> Any:
    """Static thrust curve: thrust / thrust_max = (1 - q) f + q f^2 of the normalized motor output f.

    q = ``QuadParams.thrust_map_quadratic`` in [0, 1]; q = 0 is the paper's linear model (identity).
    Monotone on [0, 1] with map(0) = 0 and map(1) = 1."""
    return f * ((1.0 - q) + q * f)


def inverse_thrust_map(t: Any, q: float) -> Any:
    """The f in [0, 1] with ``thrust_map(f, q) == t`` for t in [0, 1] (stable root of the quadratic)."""
    xp = array_namespace(t)
    if q == 0.0:
        return t
    t = xp.maximum(t, 0.0)
    return 2.0 * t / xp.maximum((1.0 - q) + xp.sqrt((1.0 - q) ** 2 + 4.0 * q * t), 1e-30)


def body_wrench(f_norm: Any, thrust_max: Any, torque_max: Any, rotor_pos: Any) -> tuple[Any, Any]:
    """Rotor thrusts -> (force, torque) in the body frame about the COM.

    ``thrust_max`` and ``torque_max`` are per rotor (..., N, 4) in N and N m; ``rotor_pos`` (4, 3).
    """
    xp = array_namespace(f_norm)
    fz, torque_b = _thrust_torque(xp, f_norm, thrust_max, torque_max * SPIN, wrench_matrix(rotor_pos))
    zero = 0.0 * fz
    return xp.concatenate([zero, zero, fz], axis=-1), torque_b


def wrench_matrix(rotor_pos: Any) -> Any:
    """(3, 4) rows mapping rotor thrusts (N) to [F_z, tau_x, tau_y] in the body frame:
    F_z = sum F_i, tau_x = sum y_i F_i, tau_y = -sum x_i F_i (``rotor_pos`` (4, 3), m)."""
    xp = array_namespace(rotor_pos)
    return xp.stack([xp.ones_like(rotor_pos[:, 0]), rotor_pos[:, 1], -rotor_pos[:, 0]])


def _thrust_torque(xp: Any, f_norm: Any, thrust_max: Any, torque_spin: Any, mix: Any) -> tuple[Any, Any]:
    """Total thrust (..., N, 1) in N along body z and the body torque (..., N, 3) in N m.

    ``torque_spin`` = torque_max * SPIN (..., N, 4), ``mix`` = :func:`wrench_matrix`."""
    thrust = thrust_max * f_norm  # N per rotor
    s = sum_last(thrust[..., None, :] * mix)  # F_z, tau_x, tau_y
    tz = sum_last(torque_spin * f_norm)  # yaw reaction torque
    return s[..., :1], xp.concatenate([s[..., 1:], tz[..., None]], axis=-1)


def hover_motor_state(params: dict[str, Any]) -> Any:
    """Per-rotor normalized speed u (..., N, 4) whose thrust balances gravity."""
    xp = array_namespace(params["thrust_max"])
    total = xp.sum(params["thrust_max"], axis=-1, keepdims=True)
    f = xp.clip(params["mass"][..., None] * params["gravity"] / total, 0.0, 1.0)
    return xp.sqrt(f) * xp.ones_like(params["thrust_max"])


def hover_motor_state_mapped(params: dict[str, Any], thrust_quadratic: float) -> Any:
    """:func:`hover_motor_state` through the static thrust map (``QuadParams.thrust_map_quadratic``);
    equal to it for ``thrust_quadratic == 0``."""
    u = hover_motor_state(params)
    return u if thrust_quadratic == 0.0 else array_namespace(u).sqrt(inverse_thrust_map(u * u, thrust_quadratic))


def substep_wrench(u: Any, cmd: Any, noise: Any, params: dict[str, Any], R: Any, rotor_pos: Any,
                   mix: Any | None = None, torque_spin: Any | None = None, thrust_quadratic: float = 0.0,
                   rotor_gain: Any | None = None) -> tuple[Any, Any, Any, Any]:
    """One physics sub-step of the actuation chain.

    Returns the new motor state ``u``, ``f_norm`` (..., N, 4) and the world-frame force
    and torque (..., N, 3) to write into ``xfrc_applied``. ``mix`` (= ``wrench_matrix(rotor_pos)``)
    and ``torque_spin`` (= ``params["torque_max"] * SPIN``) may be passed in precomputed.
    ``thrust_quadratic`` (a Python float, ``QuadParams.thrust_map_quadratic``) applies
    :func:`thrust_map` to ``f_norm`` before the wrench; ``rotor_gain`` (..., N, 4), e.g. the ground
    effect of :func:`quadswarm_mj.aerodynamics.ground_effect_gain`, multiplies each rotor's thrust
    and reaction torque. With the defaults (0.0, None) neither is evaluated (bit-identical to the
    paper's chain). The returned ``f_norm`` is always the motor output before both. One body:
    :func:`quadswarm_mj.components.rotor_wrench` (``perf.numpy_small`` has the small-NumPy form).
    """
    mix = wrench_matrix(rotor_pos) if mix is None else mix
    torque_spin = params["torque_max"] * SPIN if torque_spin is None else torque_spin
    lead = R.shape[:-2]
    r = C.rotor_wrench(C.split(u), C.split(cmd), C.split(noise), params["alpha"], C.split(params["thrust_max"]),
                       C.split(torque_spin), mix, C.split(R.reshape(lead + (9,))), thrust_quadratic,
                       None if rotor_gain is None else C.split(rotor_gain))
    return tuple(C.stack(x) for x in r)
