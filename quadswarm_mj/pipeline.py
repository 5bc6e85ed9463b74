"""The stages of one control step, and the extension points between them.

:func:`quadswarm_mj.core.control.control_step` spells the order once for both engines: draws -> sub-steps
(:func:`make_substep_actuation` -> floor -> the rigid-body integrator of :mod:`quadswarm_mj.physics` ->
omega clip -> floor landing) -> :func:`quadswarm_mj.core.step.velocity_stages` (walls and ceiling ->
quad-quad -> :func:`obstacle_stage` -> downwash) -> :func:`task_stage` (scenario -> reward terms -> episode
metrics) -> observations. The reset math is :func:`initial_state` and :func:`initial_flags`. The stages are
pure (any leading dims, NumPy or ``jax.numpy``); their draws are in the step's and the reset's specs.
Design: docs/engines.md ("One control step").
"""

from __future__ import annotations

from typing import Any

import numpy as np

from quadswarm_mj import metrics as metrics_lib
from quadswarm_mj.rewards import reward_terms
from quadswarm_mj.spatial import norm_last

_NO_JUMPS: dict[tuple[int, ...], np.ndarray] = {}


def _no_jump(shape: tuple[int, ...]) -> np.ndarray:
    """A read-only all-False (shape) bool array, made once per shape (task_stage's 'no goal jumped')."""
    a = _NO_JUMPS.get(shape)
    if a is None:
        a = _NO_JUMPS[shape] = np.zeros(shape, bool)
        a.flags.writeable = False
    return a


def make_substep_actuation(cfg: Any, wrench: Any = None) -> Any:
    """The sub-step actuation chain beyond the paper for ``cfg``, or None when there is nothing beyond
    it (``control_mode == "rotor"``, linear thrust map, aerodynamics off: the engines then call
    ``substep_wrench``, no extra work). Static Python switches, decided once.

    Returns ``act(u, action, cmd, eps, params, pos, vel, R, omega, cs, rotor_pos, mix, torque_spin)
    -> (u, f_norm, force, torque, cmd_s, cs)``, one physics sub-step (any leading dims, NumPy or
    ``jax.numpy``), in the order of docs/model.md ("Beyond the paper"):

    1. control stage: ``cmd_s`` = the mode controller's rotor command (``control_modes.mode_command``
       on the current state, updating the controller state ``cs`` (..., N, 6)), or ``cmd`` (the raw
       per-rotor command ``action_to_command(action)``) in "rotor" mode;
    2. ground-effect gain (``aerodynamics.ground_effect_stage``, ``pos`` world-local m);
    3. motor model and wrench (``substep_wrench`` with the thrust map and the gain);
    4. rotor drag added to the world force (``aerodynamics.drag_stage``, ``vel`` m/s world).
    ``omega`` rad/s body, ``R`` body->world. ``wrench``: the ``substep_wrench`` to call (None:
    :func:`quadswarm_mj.actuation.substep_wrench`; the CPU engine passes its small-NumPy form)."""
    from quadswarm_mj.actuation import substep_wrench

    substep_wrench = substep_wrench if wrench is None else wrench
    from quadswarm_mj.aerodynamics import drag_stage, ground_effect_stage
    from quadswarm_mj.control_modes import make_mode_controller

    mode_step = make_mode_controller(cfg)
    q = cfg.quad.thrust_map_quadratic
    if mode_step is None and q == 0.0 and not cfg.aero.any:
        return None

    def act(u: Any, action: Any, cmd: Any, eps: Any, params: dict[str, Any], pos: Any, vel: Any, R: Any,
            omega: Any, cs: Any, rotor_pos: Any, mix: Any, torque_spin: Any) -> tuple:
        if mode_step is not None:
            cmd, cs = mode_step(action, {"rot": R, "omega": omega, "vel": vel}, params, cs)
        gain = ground_effect_stage(cfg, params, pos, R, rotor_pos)
        u, f_norm, force, torque = substep_wrench(u, cmd, eps, params, R, rotor_pos, mix, torque_spin,
                                                  thrust_quadratic=q, rotor_gain=gain)
        drag = drag_stage(cfg, params, R, vel, f_norm, gain)
        return u, f_norm, force if drag is None else force + drag, torque, cmd, cs

    return act


def effort_action(cfg: Any, action: Any, cmd_s: Any) -> Any:
    """The action the reward's ``effort`` term sees: the raw action in "rotor" mode; in the
    physical-unit modes the equivalent raw per-rotor action ``2 cmd_s - 1`` of the rotor command of
    the step's last sub-step (so the term's scale is the same in every mode)."""
    return action if cfg.control_mode == "rotor" else 2.0 * cmd_s - 1.0


def dynamics_params(cfg: Any, rand_draws: dict[str, Any], aero_draws: dict[str, Any] | None = None) -> dict[str, Any]:
    """Per-quad dynamics parameters (``randomization.params_from_draws``), with the aerodynamic ones
    (``rotor_radius``, ``drag_coeff``: ``aerodynamics.aero_params_from_draws``, nominal when
    ``aero_draws`` is None) merged in when ``cfg.aero`` has an effect on."""
    from quadswarm_mj.randomization import params_from_draws

    params = params_from_draws(cfg, rand_draws)
    if not cfg.aero.any:
        return params
    from quadswarm_mj.aerodynamics import aero_nominal_draws, aero_params_from_draws

    if aero_draws is None:
        like = params["mass"]
        aero_draws = aero_nominal_draws(cfg, like, tuple(like.shape[:-1]))
    return {**params, **aero_params_from_draws(cfg, aero_draws)}


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
                  overrides: dict[str, Any], xp: Any, dtype: Any, aero_draws: dict[str, Any] | None = None,
                  obstacles: Any = None) -> dict[str, Any]:
    """The reset math of both engines: dynamics parameters, scenario start, spawn, and the overrides of
    ``options["state"]`` / ``init_state`` (already validated, rows of the reset worlds).

    ``rand_draws`` are the randomization draws (or the nominal ones), ``scenario_u`` and ``spawn_u``
    the scenario's and the spawn's uniforms (leading dims (..., ) of the worlds reset), ``aero_draws``
    the aerodynamic multipliers (:func:`dynamics_params`; None: nominal). ``overrides``
    may hold ``pos``, ``vel``, ``rot``, ``omega``, ``goals`` arrays (..., N, ...) and ``motors`` ("zero",
    "hover" or (..., N, 4) normalized thrusts; default ``cfg.motor_start``). Returns ``params``,
    ``scenario`` (ScenarioState), ``pos`` m world, ``vel`` m/s world, ``rot`` body->world, ``omega``
    rad/s body and ``u0`` (normalized rotor speeds). ``obstacles``: the worlds' column map
    (``ObstacleMap``, with ``cfg.obstacles``): scenarios and spawns then avoid the columns
    (:mod:`quadswarm_mj.scenarios.obstacle_scenarios`)."""
    from quadswarm_mj.actuation import hover_motor_state_mapped
    from quadswarm_mj.scenarios.base import spawn_state
    from quadswarm_mj.spatial import yaw_rotmat

    params = dynamics_params(cfg, rand_draws, aero_draws)
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
        hover = motors == "hover"
        u0 = (xp.asarray(hover_motor_state_mapped(params, cfg.quad.thrust_map_quadratic), dtype=dtype) if hover
              else xp.zeros(shape[:-1] + (4,), dtype=dtype))
    else:
        u0 = xp.sqrt(xp.clip(xp.asarray(motors, dtype=dtype).reshape(shape[:-1] + (4,)), 0.0, 1.0))
    return {"params": params, "scenario": sstate, "pos": pos, "vel": vel, "rot": R, "omega": omega, "u0": u0}


def initial_flags(cfg: Any, pos: Any, xp: Any) -> tuple[Any, Any, Any]:
    """(on_floor, at_wall, at_ceiling) (..., N) bool of quads starting at ``pos`` (m, world-local): the
    flags the collision functions keep for a quad resting there (``floor_impact`` keeps a grounded
    quad grounded while z <= arm + ``FLOOR_TOL``; ``wall_collisions`` reports a quad at or beyond a
    wall or the ceiling). Reset math of both engines."""
    from quadswarm_mj.constants import FLOOR_TOL

    lo, hi = xp.asarray(cfg.room_low, dtype=pos.dtype), xp.asarray(cfg.room_high, dtype=pos.dtype)
    at_wall = xp.any((pos[..., :2] <= lo[:2]) | (pos[..., :2] >= hi[:2]), axis=-1)
    return pos[..., 2] <= cfg.quad.arm + FLOOR_TOL, at_wall, pos[..., 2] >= hi[2]


def task_stage(cfg: Any, scenario: Any, sstate: Any, t: Any, kin: dict[str, Any], effort: Any, f_norm: Any,
               prev_f_norm: Any, on_floor: Any, anneal: Any, scenario_u: Any, metrics_acc: dict[str, Any],
               omap: Any = None, obst_metrics: dict[str, Any] | None = None,
               obst_threshold: Any = None, ops: Any = None) -> dict[str, Any]:
    """Stage 4 of a control step, after the physics (both engines call this one function).

    ``t`` (...,) s after the step (worlds' batch shape: (B,) on the CPU engine, () per world on the
    JAX engine); ``kin``: the physics stage's ``pos``, ``vel`` (m, m/s world, world-local), ``R``
    (body->world), ``omega`` (rad/s body), ``dist`` (pair distances, m), ``new_contact``,
    ``hit_floor``, ``hit_wall``, ``hit_ceiling`` and, with obstacles, ``obst_new``; ``effort`` the
    action the effort term sees (:func:`effort_action`); ``f_norm``/``prev_f_norm`` normalized rotor
    thrusts (..., N, 4) of this and the last step; ``on_floor`` (..., N) bool; ``anneal`` the
    collision-penalty factor; ``scenario_u`` the scenario's uniforms. With ``omap`` (columns):
    obstacle-aware scenario step, the ``obstacle_collision`` (and ``obstacle_proximity``) term and the obstacle
    metrics (``obst_metrics`` updated with the scenario's approach distance ``obst_threshold``, m; None:
    computed from the new scenario state). ``ops``: the engine's forms of ``reward_terms`` and
    ``metrics_update`` (:class:`quadswarm_mj.core.ops.ModelForms`; None: the model's own).

    Returns ``sstate``, ``goals``, ``goal_vel``, ``dist_goal`` (..., N) m, ``terms`` (reward terms,
    per quad), ``metrics_acc`` and ``obst_metrics`` (None without obstacles)."""
    prev_goals = sstate.goals
    if omap is None:
        sstate = scenario.step(cfg, sstate, t, kin["pos"], scenario_u)
    else:
        from quadswarm_mj.scenarios.obstacle_scenarios import scenario_step

        sstate = scenario_step(scenario, cfg, sstate, t, kin["pos"], scenario_u, omap)
    goals, goal_vel = sstate.goals, sstate.goal_vel
    if goals is prev_goals:  # the scenario kept its goals (NumPy): no jump, as goal_jump would say
        jump = _no_jump(goals.shape[:-1])
    else:
        jump = metrics_lib.goal_jump(prev_goals, goals, goal_vel, cfg.control_dt)
    dist_goal = norm_last(goals - kin["pos"])
    reward_dist = dist_goal  # the pos cost's distance: straight, or around the nearest column (ObstacleConfig)
    if omap is not None and cfg.obstacles.pos_around_columns:
        from quadswarm_mj.obstacles import around_distance

        reward_dist = around_distance(kin["pos"], goals, *omap)
    reward_fn = reward_terms if ops is None else ops.reward_terms
    terms = reward_fn(cfg, kin["pos"], kin["vel"], kin["R"], kin["omega"], goals, effort, f_norm, prev_f_norm, on_floor,
                      kin["hit_floor"], kin["hit_wall"], kin["hit_ceiling"], kin["new_contact"], kin["dist"], anneal,
                      goal_dist=reward_dist)
    if omap is not None:
        from quadswarm_mj.obstacles import obstacle_penalty

        terms["obstacle_collision"] = obstacle_penalty(kin["obst_new"], cfg.obstacles.collision_reward, anneal)
        o = cfg.obstacles
        if o.proximity_reward > 0 or o.approach_reward > 0:
            from quadswarm_mj.obstacles import CENTRE_FEATURE, obstacle_approach, obstacle_features, obstacle_proximity

            feats = kin.get("obst_feats")  # the engine's features of these positions, if made
            if feats is None:
                feats = obstacle_features(kin["pos"], *omap)
            if o.proximity_reward > 0:
                terms["obstacle_proximity"] = obstacle_proximity(feats[..., CENTRE_FEATURE], o.proximity_reward,
                                                                 o.proximity_falloff, cfg.control_dt)
            if o.approach_reward > 0:
                terms["obstacle_approach"] = obstacle_approach(feats, kin["vel"], o.approach_reward,
                                                               o.proximity_falloff, cfg.control_dt)
    t_q = t[..., None]  # per-quad broadcast of the worlds' time
    metrics_acc = (metrics_lib.update if ops is None else ops.metrics_update)(
        metrics_acc, t_q, dist_goal, kin["new_contact"], kin["hit_floor"], kin["hit_wall"], kin["hit_ceiling"], jump,
        cfg.grace_period_s)
    if omap is not None:
        from quadswarm_mj.obstacles import metrics_update
        from quadswarm_mj.scenarios.obstacle_scenarios import approach_threshold

        thr = obst_threshold if obst_threshold is not None else approach_threshold(scenario, cfg, sstate)
        obst_metrics = metrics_update(obst_metrics, t_q, kin["obst_new"], metrics_acc["last_dist"],
                                      metrics_acc["steps"], thr, cfg.grace_period_s)
    return {"sstate": sstate, "goals": goals, "goal_vel": goal_vel, "dist_goal": dist_goal, "terms": terms,
            "metrics_acc": metrics_acc, "obst_metrics": obst_metrics if omap is not None else None}
