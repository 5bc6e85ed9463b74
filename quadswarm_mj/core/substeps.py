"""The actuation sub-steps of a control step, written once for both engines.

Order (docs/engines.md): the motor noise of the step, then per physics sub-step: actuation (the rotor
chain ``substep_wrench``, or the control-mode / thrust-map / aerodynamics chain of
:func:`quadswarm_mj.pipeline.make_substep_actuation`) -> the paper's floor normal and friction -> the
rigid-body integrator ``physics`` (one ``cfg.sim_dt``, angular velocity clipped) -> the paper's floor
landing. ``physics`` is passed in (:mod:`quadswarm_mj.physics`: MuJoCo C on ``MjData``/``mujoco.batch``,
the exact free-body step, ``mjx.step``); ``ops`` (:mod:`quadswarm_mj.core.ops`) holds the engine
differences: the loop (a Python loop or ``lax.scan``), which worlds the floor models run on and where
their draws come from. Vectors: ``q`` (..., N, 7) [position m, quaternion wxyz body->world] and ``v``
(..., N, 6) [m/s world, rad/s body] in the back end's own storage (the physics adapter maps positions to
world-local ones: ``physics.local_pos``), ``R`` (..., N, 3, 3) body->world, ``u``/``f_norm`` (..., N, 4).
"""

from __future__ import annotations

from typing import Any

#: the sub-step carry's fields (``ctrl``: (last rotor command, controller state) with the extended
#: actuation chain, else None; ``aux``: the physics back end's own carry, e.g. ``mjx.Data``, or None)
CARRY = ("q", "v", "R", "u", "f_norm", "on_floor", "hit_floor", "aux", "ctrl")


def step_inputs(cfg: Any, action: Any, eps: Any, params: dict[str, Any], ops: Any) -> dict[str, Any]:
    """What every sub-step of a control step reads: ``action`` (..., N, 4), its rotor command ``cmd``
    (None outside the "rotor" control mode) and the motor noise ``eps`` after this step's
    Ornstein-Uhlenbeck update (its normal draws from ``ops``; ``ops.command``, ``ops.motor_noise``: the
    engine's forms of ``actuation.action_to_command``, ``actuation.motor_noise_step``)."""
    cmd = ops.command(action) if cfg.control_mode == "rotor" else None
    if cfg.noise.motor_noise_ratio > 0:
        eps = ops.motor_noise(eps, params["motor_sigma"], cfg.noise.motor_noise_theta, ops.draws("motor", None, None))
    return {"action": action, "cmd": cmd, "eps": eps, "params": params}


def substep_loop(cfg: Any, carry: dict[str, Any], inp: dict[str, Any], consts: dict[str, Any], physics: Any,
                 ops: Any) -> dict[str, Any]:
    """``cfg.substeps`` physics sub-steps from ``carry`` (fields :data:`CARRY`; ``R`` the rotation of
    ``q``, ``hit_floor`` all False) with :func:`step_inputs`' ``inp`` and the engine's actuation
    constants ``consts`` (``rotor_pos`` (4, 3) m, ``mix`` (3, 4), ``torque_spin`` (..., N, 4), ``act``:
    :func:`~quadswarm_mj.pipeline.make_substep_actuation`'s chain or None). Returns the carry after the
    last sub-step (``R`` the rotation of its ``q``; ``hit_floor``: landings in any sub-step).

    ``physics``: ``substep(q, v, force, torque, aux) -> (q, v, aux)`` (world force N and torque N m at
    the centre of mass), ``local_pos(q)``, ``velocities(v) -> (vel, omega)``; a back end that runs the
    whole loop as one kernel (:mod:`quadswarm_mj.perf`) offers ``fused_loop(cfg, carry, inp, consts,
    ops)`` instead (same values), as may the engine's ``ops`` (the CPU engine's one-quad and small-array loops)."""
    fused = getattr(physics, "fused_loop", None) or getattr(ops, "fused_loop", None)
    if fused is not None:
        return fused(cfg, carry, inp, consts, ops)
    paper_floor = cfg.collision_model == "paper"
    act, params, cmd, eps = consts["act"], inp["params"], inp["cmd"], inp["eps"]
    rotor_pos, mix, spin = consts["rotor_pos"], consts["mix"], consts["torque_spin"]

    def substep(c: dict[str, Any], x: Any) -> dict[str, Any]:
        q, v, R, u, on_floor, ctrl = c["q"], c["v"], c["R"], c["u"], c["on_floor"], c["ctrl"]
        if act is None:
            u, f_norm, force, torque = ops.wrench(u, cmd, eps, params, R, rotor_pos, mix, spin)
        else:  # control mode, thrust map, aerodynamics
            vel, omega = physics.velocities(v)
            u, f_norm, force, torque, cmd_s, cs = act(u, inp["action"], cmd, eps, params, physics.local_pos(q), vel,
                                                      R, omega, ctrl[1], rotor_pos, mix, spin)
            ctrl = (cmd_s, cs)
        if paper_floor:  # normal force and friction on grounded quads
            force, torque = ops.floor_wrench(cfg, on_floor, force, torque, v, params)
        q, v, aux = physics.substep(q, v, force, torque, c["aux"])
        hit_floor = c["hit_floor"]
        if paper_floor:  # landings (else MuJoCo's contacts act on the floor)
            q, v, u, on_floor, hit_floor, R = ops.floor_impact(cfg, x, q, v, u, on_floor, hit_floor)
        else:
            R = ops.rotmat(q[..., 3:7])
        c["q"], c["v"], c["R"], c["u"], c["f_norm"] = q, v, R, u, f_norm
        c["on_floor"], c["hit_floor"], c["aux"], c["ctrl"] = on_floor, hit_floor, aux, ctrl
        return c  # (the loop's own dict, updated)

    return ops.loop(substep, dict(carry), cfg.substeps)
