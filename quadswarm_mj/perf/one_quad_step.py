"""The CPU engine's control step for exactly one quad in one world on Python floats: sub-step loop and task stage.

:func:`quadswarm_mj.core.substeps.substep_loop` calls, per sub-step, the engine's ops for the wrench, the
paper's floor wrench, the physics step and the floor landing, each of which (for one quad, through
:mod:`quadswarm_mj.perf.one_quad`) reads its few values out of (1, 1, .) arrays and builds fresh arrays
again. :class:`OneQuadLoop` runs the same sequence with the motor state, the rotation and the flags kept
as floats across the sub-steps (the bodies of :mod:`quadswarm_mj.perf.one_quad`: ``wrench_floats``,
``floor_wrench_floats``, ``floor_impact_qv``, ``rotmat_floats``), the same draws in the same order, and
builds the carry's arrays once at the end. Used for the paper's chain (rotor control, linear thrust map,
no aerodynamics) with the paper's floor.

:class:`OneQuadTask` is :func:`quadswarm_mj.core.control.task_step` for one quad without neighbours,
obstacles or deck sensors: the scenario step, reward terms, metrics, observation and reward sum of
:mod:`quadswarm_mj.perf.one_quad` (``reward_values``, ``metrics_floats``, ``obs_values``) on the
kinematics read out once, the step's draws in the same order, and the terms, reward and observation as
rows of one fresh array. ``tests/test_perf_one_quad.py`` checks whole seeded episodes of both against
the array forms bit for bit. NumPy only.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from quadswarm_mj import metrics as metrics_lib
from quadswarm_mj import rewards
from quadswarm_mj.perf.one_quad import (
    _norm,
    floor_impact_qv,
    floor_wrench_floats,
    metrics_floats,
    obs_values,
    reward_plan,
    reward_values,
    rotmat_floats,
    wrench_floats,
)


class OneQuadLoop:
    """``fused_loop`` of :func:`quadswarm_mj.core.substeps.substep_loop` for a one-quad, one-world
    :class:`~quadswarm_mj.envs.cpu_core.CpuSwarm` ``swarm`` (its physics, generator and floor mirror)."""

    def __init__(self, swarm: Any) -> None:
        cfg = swarm.cfg
        self.s = swarm
        self.floor_z = float(swarm.floor_z)
        self.friction, self.dt = cfg.collision.floor_friction, cfg.sim_dt
        self.max_omega = cfg.quad.max_omega
        d = swarm._spec_floor["yaw"]
        self.yaw = (d.low, d.high) if cfg.noise.stochastic_collisions else None
        self.yaw_mean = float(d.mean)

    def __call__(self, cfg: Any, carry: dict[str, Any], inp: dict[str, Any], consts: dict[str, Any],
                 ops: Any) -> dict[str, Any]:
        """``cfg.substeps`` sub-steps from ``carry`` (as ``substep_loop``: ``q``/``v`` MuJoCo's qpos/qvel,
        written there; ``hit_floor`` all False); returns the carry after the last one."""
        s = self.s
        phys = s.phys
        q, v = phys.qpos[0, 0], phys.qvel[0, 0]  # (7,), (6,) views of MuJoCo's state
        xfrc = phys.xfrc[0, 0]
        params = inp["params"]
        u = carry["u"].ravel().tolist()
        cmd, eps = inp["cmd"].ravel().tolist(), inp["eps"].ravel().tolist()
        a, t = params["alpha"].item(), params["thrust_max"].ravel().tolist()
        spin, mix = consts["torque_spin"].ravel().tolist(), consts["mix"].tolist()
        r = carry["R"].ravel().tolist()
        on_floor = bool(carry["on_floor"][0, 0])
        mass, gravity = params["mass"].item(), params["gravity"]
        offset = s.offsets[0, 0].tolist()
        floor_z, hit_any, f = self.floor_z, False, u
        for _ in range(cfg.substeps):
            u, f, force, torque = wrench_floats(u, cmd, eps, a, t, spin, mix, r)
            if s._any_on_floor and on_floor:  # normal force and friction (ops.floor_wrench)
                vx, vy = v[0].item(), v[1].item()
                force, torque = floor_wrench_floats(force, torque, vx, vy, mass, gravity, self.friction, self.dt)
            xfrc[:3] = force
            xfrc[3:] = torque
            phys.step(self.max_omega)
            if q[2] <= floor_z or (s._any_on_floor and on_floor):  # a landing or grounded (ops.floor_impact)
                yaw = s.rng.uniform(*self.yaw) if self.yaw is not None else self.yaw_mean
                on_floor, hit = floor_impact_qv(q, v, on_floor, floor_z, offset, yaw)
                if hit:  # the motors zeroed (0.0 * u: signs kept)
                    u = [0.0 * x for x in u]
                    hit_any = True
                phys.touch()
                s._any_on_floor = on_floor
            r = rotmat_floats(*q[3:7].tolist())
        hit_floor = carry["hit_floor"]
        if hit_any:
            hit_floor[0, 0] = True
        out = np.array(u + f + r)
        return {"q": phys.qpos, "v": phys.qvel, "R": out[8:].reshape(1, 1, 3, 3), "u": out[:4].reshape(1, 1, 4),
                "f_norm": out[4:8].reshape(1, 1, 4), "on_floor": np.array([[on_floor]]), "hit_floor": hit_floor,
                "aux": carry["aux"], "ctrl": carry["ctrl"]}


class OneQuadTask:
    """:func:`quadswarm_mj.core.control.task_step` for a one-quad, one-world CPU engine in "rotor" control
    without neighbours, obstacles or deck sensors (``obs_self`` "base" or "floor"); ``ops`` its
    :class:`~quadswarm_mj.core.ops.NumpyOps` (the draws). ``sensor_keys``/``sensor_std``: the engine's
    sensor-noise draw (its three keys in draw order, their std (3, ...)), None when the noise is off."""

    def __init__(self, cfg: Any, low: np.ndarray, high: np.ndarray, scale: np.ndarray | None,
                 zero_terms: tuple[str, ...], sensor_keys: tuple[str, ...] | None = None,
                 sensor_std: np.ndarray | None = None) -> None:
        self.cfg = cfg
        self.plan = reward_plan(rewards._term_factors(cfg.rewards, cfg.sim_dt, cfg.control_dt), rewards.ANNEALED,
                                 cfg.rewards.vel_limit)
        rows = dict(self.plan[3])
        self.sum_rows = [rows[k] for k in rewards.TERMS if k not in zero_terms]  # rewards.total_reward's order
        self.zero_terms = zero_terms
        self.low, self.high = low.tolist(), high.tolist()
        self.scale = None if scale is None else scale.tolist()
        self.floor = cfg.obs_self == "floor"
        self.dt, self.episode_steps, self.grace = cfg.control_dt, cfg.episode_steps, cfg.grace_period_s
        self.sensor: list[tuple[int, float]] | None = None  # (row of the draw, std) of pos, vel, omega; None: off
        if sensor_keys is not None:
            std = np.ravel(sensor_std).tolist()
            self.sensor = [(sensor_keys.index(key), std[sensor_keys.index(key)]) for key in ("pos", "vel", "omega")]

    def __call__(self, cfg: Any, scenario: Any, s: dict[str, Any], k: dict[str, Any], action: Any,
                 consts: dict[str, Any], ops: Any) -> dict[str, Any] | None:
        """``task_step``'s result (the same values), or None where this form does not apply (a float32
        action, other constants than this engine's: the caller runs ``task_step``)."""
        if (cfg is not self.cfg or action.dtype != np.float64 or consts["zero_terms"] != self.zero_terms
                or not self.sum_rows):
            return None
        steps, total_steps = s["steps"] + 1, s["total_steps"] + 1
        t = steps.astype(np.float64) * self.dt
        anneal = rewards.anneal_factor(cfg, total_steps)
        prev = s["sstate"]
        sstate = scenario.step(cfg, prev, t, k["pos"], ops.draws("scenario", None, None))
        goals, goal_vel = sstate.goals, sstate.goal_vel
        jump = goals is not prev.goals and bool(metrics_lib.goal_jump(prev.goals, goals, goal_vel, self.dt).item())
        p, v, r, w = k["pos"].ravel().tolist(), k["vel"].ravel().tolist(), k["R"].ravel().tolist(), \
            k["omega"].ravel().tolist()
        g = goals.ravel().tolist()
        d = _norm([g[0] - p[0], g[1] - p[1], g[2] - p[2]])  # spatial.norm_last(goals - pos)
        n_new = int(np.count_nonzero(k["new_contact"]))
        hf, hw, hc = bool(k["hit_floor"].item()), bool(k["hit_wall"].item()), bool(k["hit_ceiling"].item())
        vals = reward_values(self.plan, p, v, r, w, g, action.ravel().tolist(), k["f_norm"].ravel().tolist(),
                             s["f_norm"].ravel().tolist(), bool(k["on_floor"].item()), n_new, hf, hw, hc, anneal, d)
        m = metrics_floats(s["metrics_acc"], t.item(), d, n_new, hf, hw, hc, jump, self.grace,
                           metrics_lib.MIN_SEGMENT_S, metrics_lib.REACH_DISTANCE)
        noise = None
        sensor = self.sensor
        if sensor is not None:  # = ops.draws("sensor", ...): 0.0 + std * N(0, 1), the same draw on floats
            z = ops.s.rng.standard_normal((3, 1, 1, 3)).ravel().tolist()
            (i, a), (j, b), (k_, c) = sensor
            i, j, k_ = 3 * i, 3 * j, 3 * k_
            noise = [[0.0 + a * z[i], 0.0 + a * z[i + 1], 0.0 + a * z[i + 2]],
                     [0.0 + b * z[j], 0.0 + b * z[j + 1], 0.0 + b * z[j + 2]],
                     [0.0 + c * z[k_], 0.0 + c * z[k_ + 1], 0.0 + c * z[k_ + 2]]]
        obs = obs_values(p, v, r, w, g, noise, self.low, self.high, self.scale, self.floor)
        rows = self.sum_rows
        total = vals[rows[0]]
        for i in rows[1:]:
            total = total + vals[i]
        n = len(vals)
        buf = np.array(vals + [total] + obs)  # terms, reward, observation: rows of one fresh array
        terms = buf[:n].reshape(n, 1, 1)
        return {"steps": steps, "total_steps": total_steps, "t": t, "sstate": sstate, "goals": goals,
                "goal_vel": goal_vel, "terms": {key: terms[i] for key, i in self.plan[3]},
                "reward": buf[n:n + 1].reshape(1, 1), "metrics_acc": m, "obst_metrics": None,
                "obs": buf[n + 1:].reshape(1, 1, len(obs)), "done": steps >= self.episode_steps}
