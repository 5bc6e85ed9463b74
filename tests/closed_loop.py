"""A small closed-loop driver for tests of the sub-step stages (control modes, aerodynamics, thrust
map) before they are wired into the engines: it integrates one MuJoCo world exactly like the CPU
engine's sub-step loop (stages -> substep_wrench -> xfrc_applied -> mj_step -> omega clip).

Per sub-step, in order (the plug-in points of the engines)::

    cmd, cs   = mode_step(action, {"rot", "omega", "vel"}, params, cs)   # control mode (or the raw command)
    gain      = ground_effect_stage(cfg, params, pos, R, rotor_pos)      # before the motor model's wrench
    u, f, F, T = substep_wrench(u, cmd, eps, params, R, rotor_pos, thrust_quadratic=q, rotor_gain=gain)
    drag      = drag_stage(cfg, params, R, vel, f, gain)                 # after the motor model
    xfrc_applied <- (F + drag, T); mj_step; clip omega
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from quadswarm_mj.actuation import (
    action_to_command,
    hover_motor_state_mapped,
    motor_noise_step,
    rotor_positions,
    substep_wrench,
)
from quadswarm_mj.aerodynamics import (
    aero_draw_spec,
    aero_nominal_draws,
    aero_params_from_draws,
    drag_stage,
    ground_effect_stage,
)
from quadswarm_mj.arena import build_arena
from quadswarm_mj.config import EnvConfig
from quadswarm_mj.control_modes import init_control_state, make_mode_controller
from quadswarm_mj.random_draws import NumpySampler
from quadswarm_mj.randomization import nominal_draws, params_from_draws, randomization_draw_spec
from quadswarm_mj.spatial import quat_to_rotmat


def make_params(cfg: EnvConfig, seed: int | None = None) -> dict[str, Any]:
    """Per-quad dynamics + aerodynamic parameters (N, ...): nominal, or drawn with ``seed``."""
    if seed is None:
        draws = nominal_draws(cfg, np.zeros(1))
        aero = aero_nominal_draws(cfg, np.zeros(1))
    else:
        sampler = NumpySampler(np.random.default_rng(seed))
        draws, aero = sampler.draw(randomization_draw_spec(cfg)), sampler.draw(aero_draw_spec(cfg))
    return params_from_draws(cfg, draws) | aero_params_from_draws(cfg, aero)


def run_closed_loop(cfg: EnvConfig, action: np.ndarray, seconds: float, seed: int | None = None,
                    pos0: np.ndarray | None = None, vel0: np.ndarray | None = None,
                    hover_start: bool = True) -> dict[str, np.ndarray]:
    """Fly ``cfg.num_quads`` quads, level at rest (or at ``vel0``), from ``pos0`` (default: in a
    row at z = 5 m), with a constant ``action`` (N, 4) in ``cfg.control_mode``'s units.

    Returns trajectories after each control step: rot (T, N, 3, 3), omega body, vel world, pos."""
    n = cfg.num_quads
    arena = build_arena(cfg, 1, visual=False)
    model, data = arena.model, None
    params = make_params(cfg, seed)
    model.body_mass[arena.first_body:arena.first_body + n] = params["mass"]  # the airframe reaches MuJoCo
    model.body_inertia[arena.first_body:arena.first_body + n] = params["inertia"]
    data = mujoco.MjData(model)
    q0, v0 = arena.qpos_start, arena.qvel_start
    qpos = data.qpos[q0:q0 + 7 * n].reshape(n, 7)
    qvel = data.qvel[v0:v0 + 6 * n].reshape(n, 6)
    xfrc = data.xfrc_applied[arena.first_body:arena.first_body + n]
    if pos0 is None:
        pos0 = np.stack([np.arange(n) * 1.0 - 0.5 * (n - 1), np.zeros(n), np.full(n, 5.0)], -1)
    qpos[:, :3] = pos0
    qpos[:, 3:] = [1.0, 0.0, 0.0, 0.0]
    qvel[:] = 0.0
    if vel0 is not None:
        qvel[:, :3] = vel0
    mujoco.mj_forward(model, data)
    rotor_pos = rotor_positions(cfg.quad)
    q = cfg.quad.thrust_map_quadratic
    u = hover_motor_state_mapped(params, q) if hover_start else np.zeros((n, 4))
    eps = np.zeros((n, 4))
    rng = np.random.default_rng(0 if seed is None else seed + 1)
    mode_step = make_mode_controller(cfg)
    cs = init_control_state((n,))
    raw_cmd = action_to_command(action) if mode_step is None else None
    out: dict[str, list] = {"rot": [], "omega": [], "vel": [], "pos": []}
    for _ in range(int(round(seconds * cfg.control_hz))):
        eps = motor_noise_step(eps, params["motor_sigma"], cfg.noise.motor_noise_theta, rng.standard_normal((n, 4)))
        for _ in range(cfg.substeps):
            R = quat_to_rotmat(qpos[:, 3:7].copy())
            pos, vel = qpos[:, :3].copy(), qvel[:, :3].copy()
            if mode_step is None:
                cmd = raw_cmd
            else:
                cmd, cs = mode_step(action, {"rot": R, "omega": qvel[:, 3:].copy(), "vel": vel}, params, cs)
            gain = ground_effect_stage(cfg, params, pos, R, rotor_pos)
            u, f_norm, force, torque = substep_wrench(u, cmd, eps, params, R, rotor_pos, thrust_quadratic=q,
                                                      rotor_gain=gain)
            drag = drag_stage(cfg, params, R, vel, f_norm, gain)
            xfrc[:, :3] = force if drag is None else force + drag
            xfrc[:, 3:] = torque
            mujoco.mj_step(model, data)
            np.clip(qvel[:, 3:], -cfg.quad.max_omega, cfg.quad.max_omega, out=qvel[:, 3:])
        out["rot"].append(quat_to_rotmat(qpos[:, 3:7].copy()))
        out["omega"].append(qvel[:, 3:].copy())
        out["vel"].append(qvel[:, :3].copy())
        out["pos"].append(qpos[:, :3].copy())
    return {k: np.array(v) for k, v in out.items()}
