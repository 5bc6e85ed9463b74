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
3. once per control step: walls and ceiling -> quad-quad -> :func:`obstacle_stage` (with
   ``cfg.obstacles``) -> downwash.
4. scenario (goals) -> reward terms -> episode metrics -> observations.

The control and aerodynamics extension points below are identities today; the helpers that add
control modes and aerodynamics replace their bodies (keeping the signatures: pure, any leading dims,
``jax.numpy`` or NumPy) and add their draws to the step's spec. :func:`obstacle_stage` is the
obstacle stage of the JAX engine (the CPU engine runs the same functions event-gated).
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


def obstacle_stage(pos: Any, vel: Any, omega: Any, prev_contact: Any, omap: Any, arm: float, draws: Any,
                   respond: bool = True) -> dict[str, Any]:
    """Once per control step after quad-quad: the obstacle stage (SPEC_obstacles A.3) on (pos m
    world, vel m/s world, omega rad/s body) with the map ``omap`` (:class:`~quadswarm_mj.obstacles.
    ObstacleMap`) and the previous step's contacts ``prev_contact`` (..., N) bool. ``respond``
    False (MuJoCo contacts) only detects. Returns :func:`quadswarm_mj.obstacles.obstacle_step`'s
    dict (``vel``, ``omega``, ``contact``, ``new_contact``, ``index``). The engines also append the
    9 features to the observations and add the ``obstacle_collision`` reward term."""
    from quadswarm_mj.obstacles import obstacle_step

    return obstacle_step(pos, vel, omega, prev_contact, omap.centres, omap.valid, omap.radius, arm, draws,
                         respond=respond)


def initial_state(cfg: Any, scenario: Any, rand_draws: dict[str, Any], scenario_u: Any, spawn_u: Any,
                  overrides: dict[str, Any], xp: Any, dtype: Any, obstacles: Any = None) -> dict[str, Any]:
    """The reset math of both engines: dynamics parameters, scenario start, spawn, and the overrides of
    ``options["state"]`` / ``init_state`` (already validated, rows of the reset worlds).

    ``rand_draws`` are the randomization draws (or the nominal ones), ``scenario_u`` and ``spawn_u``
    the scenario's and the spawn's uniforms (leading dims (..., ) of the worlds reset). ``overrides``
    may hold ``pos``, ``vel``, ``rot``, ``omega``, ``goals`` arrays (..., N, ...) and ``motors`` ("zero",
    "hover" or (..., N, 4) normalized thrusts; default ``cfg.motor_start``). Returns ``params``,
    ``scenario`` (ScenarioState), ``pos`` m world, ``vel`` m/s world, ``rot`` body->world, ``omega``
    rad/s body and ``u0`` (normalized rotor speeds). ``obstacles``: the worlds' column map
    (``ObstacleMap``, with ``cfg.obstacles``): scenarios and spawns then avoid the columns
    (:mod:`quadswarm_mj.scenarios.obstacle_scenarios`)."""
    from quadswarm_mj.actuation import hover_motor_state
    from quadswarm_mj.randomization import params_from_draws
    from quadswarm_mj.scenarios.base import spawn_state
    from quadswarm_mj.spatial import yaw_rotmat

    params = params_from_draws(cfg, rand_draws)
    if cfg.obstacles is None:
        sstate = scenario.init(cfg, scenario_u)
    else:
        from quadswarm_mj.scenarios.obstacle_scenarios import scenario_init

        sstate = scenario_init(scenario, cfg, scenario_u, obstacles)
    if overrides.get("goals") is not None:
        sstate = sstate._replace(goals=xp.asarray(overrides["goals"], dtype=dtype).reshape(sstate.goals.shape))
    if cfg.obstacles is None:
        sp = spawn_state(cfg, sstate.goals, spawn_u)
    else:
        from quadswarm_mj.scenarios.obstacle_scenarios import scenario_spawn

        sp = scenario_spawn(cfg, sstate.goals, spawn_u, obstacles)
    pos, R = sp["pos"], yaw_rotmat(sp["yaw"])
    shape = pos.shape

    def pick(key: str, default: Any, tail: tuple[int, ...]) -> Any:
        v = overrides.get(key)
        return default if v is None else xp.asarray(v, dtype=dtype).reshape(shape[:-1] + tail)

    pos = pick("pos", pos, (3,))
    vel = pick("vel", xp.zeros(shape, dtype=dtype), (3,))
    R = pick("rot", R, (3, 3))
    omega = pick("omega", xp.zeros(shape, dtype=dtype), (3,))
    motors = overrides.get("motors", cfg.motor_start)
    if isinstance(motors, str):
        u0 = (xp.asarray(hover_motor_state(params), dtype=dtype) if motors == "hover"
              else xp.zeros(shape[:-1] + (4,), dtype=dtype))
    else:
        u0 = xp.sqrt(xp.clip(xp.asarray(motors, dtype=dtype).reshape(shape[:-1] + (4,)), 0.0, 1.0))
    return {"params": params, "scenario": sstate, "pos": pos, "vel": vel, "rot": R, "omega": omega, "u0": u0}
