"""Aerodynamic effects beyond the paper: ground effect and rotor (blade) drag (``EnvConfig.aero``).

Pure functions of arrays with leading batch dims (..., N), NumPy or ``jax.numpy``, run at the physics rate
inside the sub-step loop; off by default (static switches: the stages return None).

* Ground effect (Cheeseman & Bennett 1955): T_IGE / T_OGE = 1 / (1 - (r / 4h)^2) per rotor at height h (m),
  clipped at ``AeroConfig.ground_effect_max_gain``; :func:`ground_effect_stage` gives the per-rotor gain,
  applied by ``substep_wrench(..., rotor_gain=gain)``.
* Rotor drag: F_body = -diag(c) (sum_i w_i) v_body (N), w_i rotor speeds (rad/s) from F_i = k_f w_i^2;
  :func:`drag_stage` gives the world force added to ``xfrc_applied``.

Per-quad parameters (:func:`aero_params_from_draws`): ``rotor_radius`` (..., N) m and ``drag_coeff``
(..., N, 3), nominal or scaled by per-reset draws (:func:`aero_draw_spec`). Constants, sources and the
order inside a sub-step: docs/model.md ("Beyond the paper").
"""

from __future__ import annotations

from typing import Any

from quadswarm_mj._xp import array_namespace
from quadswarm_mj.config import AeroConfig, EnvConfig
from quadswarm_mj.random_draws import DrawSpec, Uniform
from quadswarm_mj.spatial import sum_last


def aero_draw_spec(cfg: EnvConfig) -> DrawSpec:
    """Per-quad multipliers of the aerodynamic constants for one world (drawn when ``randomize``)."""
    a, n = cfg.aero, cfg.num_quads
    return {"rotor_radius_scale": Uniform(*a.rotor_radius_scale, (n,)),
            "drag_scale": Uniform(*a.drag_scale, (n,))}


def aero_nominal_draws(cfg: EnvConfig, like: Any, batch_shape: tuple[int, ...] = ()) -> dict[str, Any]:
    """Draws that reproduce the nominal constants (all multipliers 1)."""
    xp = array_namespace(like)
    shp = tuple(batch_shape) + (cfg.num_quads,)
    return {k: xp.ones(shp, dtype=like.dtype) for k in ("rotor_radius_scale", "drag_scale")}


def aero_params_from_draws(cfg: EnvConfig, draws: dict[str, Any]) -> dict[str, Any]:
    """``rotor_radius`` (..., N) m and ``drag_coeff`` (..., N, 3) N/(m/s)/(rad/s); merge these into
    the dynamics parameter dict of :func:`quadswarm_mj.randomization.params_from_draws`."""
    a: AeroConfig = cfg.aero
    xp = array_namespace(draws["drag_scale"])
    c = xp.asarray(a.drag_coeff, dtype=draws["drag_scale"].dtype)
    return {"rotor_radius": a.rotor_radius * draws["rotor_radius_scale"],
            "drag_coeff": draws["drag_scale"][..., None] * c}


def rotor_heights(pos: Any, R: Any, rotor_pos: Any) -> Any:
    """Height above the floor z = 0 (m) of each rotor (..., N, 4): ``pos`` (..., N, 3) world-local
    COM position, ``R`` (..., N, 3, 3) body->world, ``rotor_pos`` (4, 3) body frame."""
    return pos[..., 2:3] + sum_last(R[..., 2:3, :] * rotor_pos)


def ground_effect_gain(height: Any, rotor_radius: Any, max_gain: float) -> Any:
    """Cheeseman-Bennett thrust gain 1 / (1 - (r / 4h)^2) (..., N, 4), clipped at ``max_gain``.

    ``height`` (..., N, 4) m (rotor height above the floor, any value: below the clip height the gain
    is ``max_gain``), ``rotor_radius`` (..., N) m."""
    xp = array_namespace(height, rotor_radius)
    ratio_sq_max = 1.0 - 1.0 / max_gain  # (r / 4h)^2 at the clip
    ratio = rotor_radius[..., None] / (4.0 * xp.maximum(height, 1e-9))
    ratio_sq = xp.minimum(ratio * ratio, ratio_sq_max)
    return 1.0 / (1.0 - ratio_sq)


def rotor_speeds(rotor_thrust_n: Any, thrust_coeff: float) -> Any:
    """Rotor speeds (rad/s) from rotor thrusts (N) by F = k_f w^2 (thrusts below 0 count as 0)."""
    xp = array_namespace(rotor_thrust_n)
    return xp.sqrt(xp.maximum(rotor_thrust_n, 0.0) / thrust_coeff)


def rotor_drag_force(R: Any, vel: Any, rotor_thrust_n: Any, drag_coeff: Any, thrust_coeff: float) -> Any:
    """World-frame rotor drag force (..., N, 3) in N.

    F_body = -drag_coeff * sum_i w_i * v_body, v_body = R^T ``vel`` (``vel`` (..., N, 3) m/s world),
    w_i = :func:`rotor_speeds` of ``rotor_thrust_n`` (..., N, 4) N (the thrust each rotor gives
    this sub-step), ``drag_coeff`` (..., N, 3) N/(m/s)/(rad/s) per body axis."""
    w_sum = sum_last(rotor_speeds(rotor_thrust_n, thrust_coeff))[..., None]
    v_body = sum_last(_transpose(R) * vel[..., None, :])  # R^T v
    f_body = -drag_coeff * w_sum * v_body
    return sum_last(R * f_body[..., None, :])


def _transpose(R: Any) -> Any:
    return array_namespace(R).swapaxes(R, -1, -2)


def ground_effect_stage(cfg: EnvConfig, params: dict[str, Any], pos: Any, R: Any, rotor_pos: Any) -> Any | None:
    """Sub-step stage BEFORE the wrench: the per-rotor ground-effect gain (..., N, 4) to pass as
    ``substep_wrench(..., rotor_gain=...)``, or None when ``cfg.aero.ground_effect`` is off (a
    static switch). ``pos`` (..., N, 3) world-local COM position (floor at z = 0), ``R`` body->world;
    ``params`` must hold ``rotor_radius`` (:func:`aero_params_from_draws`)."""
    a = cfg.aero
    if not a.ground_effect:
        return None
    return ground_effect_gain(rotor_heights(pos, R, rotor_pos), params["rotor_radius"], a.ground_effect_max_gain)


def drag_stage(cfg: EnvConfig, params: dict[str, Any], R: Any, vel: Any, f_norm: Any,
               rotor_gain: Any | None = None) -> Any | None:
    """Sub-step stage AFTER the motor model: the world rotor-drag force (..., N, 3) to add to the
    force written to ``xfrc_applied``, or None when ``cfg.aero.drag`` is off (a static switch).

    ``f_norm`` (..., N, 4) is this sub-step's motor output (returned by ``substep_wrench``); the
    rotor thrusts are ``thrust_max * thrust_map(f_norm) * rotor_gain`` as in the wrench; ``vel``
    (..., N, 3) m/s world; ``params`` must hold ``thrust_max`` and ``drag_coeff``."""
    from quadswarm_mj.actuation import thrust_map  # late import: actuation imports nothing from here

    a = cfg.aero
    if not a.drag:
        return None
    q = cfg.quad.thrust_map_quadratic
    thrust = params["thrust_max"] * (f_norm if q == 0.0 else thrust_map(f_norm, q))
    if rotor_gain is not None:
        thrust = thrust * rotor_gain
    return rotor_drag_force(R, vel, thrust, params["drag_coeff"], a.thrust_coeff)
