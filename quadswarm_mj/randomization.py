"""Per-reset dynamics parameters, nominal or randomized (SPEC §11).

A parameter set is a dict of arrays with leading batch dims (..., N):

=============== ============ ===============================================
key             shape        meaning
=============== ============ ===============================================
mass            (..., N)     kg (MuJoCo body mass)
inertia         (..., N, 3)  kg m^2, principal (MuJoCo body inertia)
thrust_max      (..., N, 4)  N per rotor (nominal mass x drawn thrust-to-weight)
torque_max      (..., N, 4)  N m per rotor
alpha           (..., N)     motor filter gain per sub-step
motor_sigma     (..., N)     OU motor-noise sigma (0.2 x noise ratio)
gravity         ()           m/s^2 (a scalar, not randomized)
=============== ============ ===============================================

``thrust_max`` comes from the *nominal* mass and the drawn thrust-to-weight, never from the
drawn mass: a heavier quad needs more command to hover.
"""

from __future__ import annotations

from typing import Any

from quadswarm_mj._xp import array_namespace
from quadswarm_mj.actuation import motor_alpha
from quadswarm_mj.config import EnvConfig
from quadswarm_mj.random_draws import DrawSpec, Uniform


def randomization_draw_spec(cfg: EnvConfig) -> DrawSpec:
    """Draws for one world of ``cfg.num_quads`` quads."""
    r, n = cfg.randomization, cfg.num_quads
    return {
        "mass_scale": Uniform(*r.mass_scale, (n,)),
        "inertia_scale": Uniform(*r.inertia_scale, (n, 3)),
        "thrust_to_weight": Uniform(*r.thrust_to_weight, (n,)),
        "torque_to_thrust_scale": Uniform(*r.torque_to_thrust_scale, (n,)),
        "motor_settling_time": Uniform(*r.motor_settling_time, (n,)),
        "rotor_thrust_scale": Uniform(*r.rotor_thrust_scale, (n, 4)),
        "motor_noise_ratio": Uniform(*r.motor_noise_ratio, (n,)),
    }


def nominal_draws(cfg: EnvConfig, like: Any, batch_shape: tuple[int, ...] = ()) -> dict[str, Any]:
    """The draws that reproduce the nominal airframe (used when ``randomize=False``)."""
    xp = array_namespace(like)
    n, q = cfg.num_quads, cfg.quad
    shp = tuple(batch_shape) + (n,)

    def full(shape: tuple[int, ...], v: float) -> Any:
        return xp.full(shape, v, dtype=like.dtype)

    return {
        "mass_scale": full(shp, 1.0),
        "inertia_scale": full(shp + (3,), 1.0),
        "thrust_to_weight": full(shp, q.thrust_to_weight),
        "torque_to_thrust_scale": full(shp, 1.0),
        "motor_settling_time": full(shp, q.motor_settling_time),
        "rotor_thrust_scale": full(shp + (4,), 1.0),
        "motor_noise_ratio": full(shp, cfg.noise.motor_noise_ratio),
    }


def params_from_draws(cfg: EnvConfig, draws: dict[str, Any]) -> dict[str, Any]:
    """Dynamics parameters from (nominal or random) draws; pure, any batch dims."""
    xp = array_namespace(draws["mass_scale"])
    q = cfg.quad
    inertia_nominal = xp.asarray(q.inertia, dtype=draws["inertia_scale"].dtype)
    thrust_max = (q.gravity * q.mass * draws["thrust_to_weight"] / 4.0)[..., None] * draws["rotor_thrust_scale"]
    torque_max = (q.torque_to_thrust * draws["torque_to_thrust_scale"])[..., None] * thrust_max
    noise_ratio = draws["motor_noise_ratio"] if cfg.noise.motor_noise_ratio > 0 else 0.0 * draws["motor_noise_ratio"]
    return {
        "mass": q.mass * draws["mass_scale"],
        "inertia": inertia_nominal * draws["inertia_scale"],
        "thrust_max": thrust_max,
        "torque_max": torque_max,
        "alpha": motor_alpha(cfg.sim_dt, draws["motor_settling_time"]),
        "motor_sigma": 0.2 * noise_ratio,
        "gravity": q.gravity,
    }
