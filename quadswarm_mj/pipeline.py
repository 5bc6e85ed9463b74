"""The stages of one control step of the JAX engine, and the extension points between them.

Order of a control step (:meth:`quadswarm_mj.envs.mjx_env.MjxQuadSwarmEnv._physics` and ``step``;
``CpuSwarm._physics``/``step`` run the same order with event gating):

1. draws: one fused draw of everything the step can use (motor and sensor noise per quad, the
   event models' budgeted slots: :mod:`quadswarm_mj.collisions`, :mod:`quadswarm_mj.downwash`).
2. sub-steps (``lax.scan`` over ``cfg.substeps``): :func:`control_stage` (action -> rotor command
   at the physics rate) -> motor lag and noise -> rotor thrusts -> body wrench ->
   :func:`aero_stage` (per-rotor thrust / extra body forces) -> floor normal and friction ->
   rigid-body integrator (passed in: ``freebody_step`` or ``mjx.step``) -> omega clip -> floor
   landing.
3. once per control step: walls and ceiling -> quad-quad -> :func:`obstacle_stage` -> downwash.
4. scenario (goals) -> reward terms -> episode metrics -> observations.

The extension points below are identities today; the helpers that add control modes,
aerodynamics and obstacles replace their bodies (keeping the signatures: pure, any leading dims,
``jax.numpy`` or NumPy) and add their draws to the step's spec.
"""

from __future__ import annotations

from typing import Any


def control_stage(cmd: Any, qpos: Any, qvel: Any, R: Any) -> Any:
    """Extension point, inside the sub-step loop before the motor model: map the control step's
    command (N, 4) (today: normalized rotor speed from the per-rotor action) to the rotor command
    of this sub-step, given the quad state (qpos (N, 7), qvel (N, 6), R (N, 3, 3) body->world).
    Identity (per-rotor control)."""
    return cmd


def aero_stage(force: Any, torque: Any, f_norm: Any, qpos: Any, qvel: Any, R: Any) -> tuple[Any, Any]:
    """Extension point, per sub-step after the rotor thrusts: modify the world-frame body force (N, 3)
    N and torque (N, 3) N m (e.g. drag, ground effect) given the normalized rotor thrusts ``f_norm``
    (N, 4). Identity (no aerodynamics beyond the paper's model)."""
    return force, torque


def obstacle_stage(pos: Any, vel: Any, omega: Any) -> tuple[Any, Any, Any]:
    """Extension point, once per control step after quad-quad: obstacle response on (pos m world,
    vel m/s world, omega rad/s body). The obstacle helper also appends SDF features to the
    observations and an ``obstacle_collision`` reward term. Identity (no obstacles)."""
    return pos, vel, omega
