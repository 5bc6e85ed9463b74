"""The CPU engine's sub-step loop for small arrays of several worlds, in NumPy.

:func:`quadswarm_mj.core.substeps.substep_loop` calls, per sub-step, the engine's ops for the wrench
(``perf.numpy_small.substep_wrench``), the paper's floor wrench (``perf.numpy_floor``), the physics step
and the floor landing. On small (B, N, .) arrays NumPy's fixed cost per call dominates, and
part of each sub-step does not change within a control step: the rotor command's square root (motor
lag), the command times the motor noise (thrust) and the quads' weight (floor normal force).
:class:`SmallLoop` computes those once per control step and runs the sub-steps with the same
expressions in the same order (the same bits; ``tests/test_numpy_loop.py`` checks seeded episodes
against the per-sub-step ops). Used for the paper's chain (rotor control, linear thrust map, no
aerodynamics) with the paper's floor, below ``spatial.BIG`` elements, where neither one quad's float loop
(``perf.one_quad_step``) nor one world's (``perf.numpy_swarm``) applies. NumPy only.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from quadswarm_mj.perf import numpy_floor
from quadswarm_mj.spatial import sum_last

#: set to False for the per-sub-step ops (the same-values tests compare the two)
ENABLED = True


class SmallLoop:
    """``fused_loop`` of :func:`quadswarm_mj.core.substeps.substep_loop` for a
    :class:`~quadswarm_mj.envs.cpu_core.CpuSwarm` ``swarm`` with small (B, N) arrays; ``ops`` its
    :class:`~quadswarm_mj.core.ops.NumpyOps` (the floor landing)."""

    def __init__(self, swarm: Any) -> None:
        cfg = swarm.cfg
        self.s = swarm
        self.friction, self.dt, self.max_omega = cfg.collision.floor_friction, cfg.sim_dt, cfg.quad.max_omega

    def __call__(self, cfg: Any, carry: dict[str, Any], inp: dict[str, Any], consts: dict[str, Any],
                 ops: Any) -> dict[str, Any]:
        """``cfg.substeps`` sub-steps from ``carry`` (as ``substep_loop``: ``q``/``v`` the physics' qpos/qvel;
        ``hit_floor`` all False); returns the carry after the last one."""
        s, phys = self.s, self.s.phys
        params, cmd = inp["params"], inp["cmd"]
        q, v, R, u, on_floor, hit_floor = carry["q"], carry["v"], carry["R"], carry["u"], carry["on_floor"], \
            carry["hit_floor"]
        f = carry["f_norm"]
        # constant over the control step: actuation.motor_lag's sqrt(cmd) and alpha, rotor_thrust's cmd * noise,
        # collisions.floor_wrench's mass * gravity
        root, alpha, cn = np.sqrt(cmd), params["alpha"][..., None], cmd * inp["eps"]
        thrust_max, spin, mix = params["thrust_max"], consts["torque_spin"], consts["mix"]
        mass, weight = params["mass"], params["mass"] * params["gravity"]
        rows = np.empty(u.shape[:-1] + (4, 4))
        xfrc = phys.xfrc
        for i in range(cfg.substeps):
            u, f, force, torque = substep_wrench(u, alpha, root, cn, thrust_max, spin, mix, R, rows)
            if s._any_on_floor:  # the floor's normal force and friction (NumpyOps.floor_wrench)
                floor_wrench(on_floor, force, torque, v, mass, params["gravity"], self.friction, self.dt, weight)
            xfrc[..., :3] = force
            xfrc[..., 3:] = torque
            phys.step(self.max_omega)
            q, v, u, on_floor, hit_floor, R = ops.floor_impact(cfg, i, phys.qpos, phys.qvel, u, on_floor, hit_floor)
        return {"q": q, "v": v, "R": R, "u": u, "f_norm": f, "on_floor": on_floor, "hit_floor": hit_floor,
                "aux": carry["aux"], "ctrl": carry["ctrl"]}


def substep_wrench(u: np.ndarray, alpha: np.ndarray, root: np.ndarray, cn: np.ndarray, thrust_max: np.ndarray,
                   spin: np.ndarray, mix: np.ndarray, R: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, ...]:
    """``perf.numpy_small.substep_wrench`` (paper chain) with the step's constants: ``root`` = sqrt(cmd),
    ``alpha`` (..., N, 1), ``cn`` = cmd * noise; ``rows`` a (..., N, 4, 4) scratch array. Returns (u, f_norm,
    world force, world torque)."""
    u = u + alpha * (root - u)  # actuation.motor_lag
    f = np.minimum(np.maximum(u * u + cn, 0.0), 1.0)  # actuation.rotor_thrust
    np.multiply((thrust_max * f)[..., None, :], mix, out=rows[..., :3, :])
    np.multiply(spin, f, out=rows[..., 3, :])
    sm = rows.sum(axis=-1)  # F_z, tau_x, tau_y, tau_z (body)
    return u, f, sm[..., :1] * R[..., :, 2], sum_last(R * sm[..., None, 1:])


def floor_wrench(on_floor: np.ndarray, force: np.ndarray, torque: np.ndarray, v: np.ndarray, mass: Any,
                 gravity: Any, friction: float, dt: float, weight: Any) -> None:
    """``perf.numpy_floor.floor_wrench_inplace`` with the step's ``weight`` = mass * gravity."""
    numpy_floor.floor_wrench_inplace(on_floor, force, torque, v, mass, gravity, friction, dt, weight=weight)
