"""The CPU engine shared by every CPU front end: B worlds x N quads in one MjModel/MjData.

All model math is batched over (B, N) with the pure functions of the package; MuJoCo's C
engine integrates the rigid bodies. ``QuadSwarmEnv`` is this engine with B = 1,
``QuadSwarmVectorEnv`` uses B worlds, ``QuadSwarmParallelEnv`` wraps ``QuadSwarmEnv``.

Random numbers come from one seeded ``numpy.random.Generator``; draws are taken in a fixed
order, so seeded runs are bit-identical. Draws whose only use is an event that did not happen
this step (a new contact, a wall hit) are skipped: the stream stays deterministic.
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from quadswarm_mj import metrics as metrics_lib
from quadswarm_mj.actuation import (action_to_command, hover_motor_state, motor_noise_step, rotor_positions,
                                    substep_wrench)
from quadswarm_mj.arena import build_arena
from quadswarm_mj.collisions import (FLOOR_TOL, floor_draw_spec, floor_impact, floor_wrench, pairwise_contacts,
                                     quad_collision_draw_spec, quad_collisions, wall_collisions, wall_draw_spec)
from quadswarm_mj.config import EnvConfig
from quadswarm_mj.downwash import apply_downwash, downwash_draw_spec
from quadswarm_mj.observations import build_obs, obs_bounds, obs_scale, sensor_noise_spec
from quadswarm_mj.random_draws import MeanSampler, NumpySampler
from quadswarm_mj.randomization import nominal_draws, params_from_draws, randomization_draw_spec
from quadswarm_mj.rewards import anneal_factor, reward_terms, total_reward
from quadswarm_mj.scenarios import ScenarioState, get_scenario
from quadswarm_mj.scenarios.base import spawn_num_uniforms, spawn_state
from quadswarm_mj.spatial import quat_to_rotmat, rotmat_to_quat, yaw_rotmat

STATE_KEYS = ("pos", "vel", "rot", "omega", "motors", "goals")


def _merge(mask: np.ndarray, new: Any, old: Any) -> Any:
    """Select ``new`` for worlds in ``mask`` (B,), else ``old`` (arrays with leading B)."""
    m = mask.reshape(mask.shape + (1,) * (np.ndim(new) - 1))
    return np.where(m, new, old)


class CpuSwarm:
    """B worlds of N quads on CPU MuJoCo. State arrays are (B, N, ...), world-local frames."""

    def __init__(self, cfg: EnvConfig, num_worlds: int = 1):
        self.cfg = cfg
        self.B, self.N = num_worlds, cfg.num_quads
        self.arena = build_arena(cfg, num_worlds)
        self.model = self.arena.model
        self.data = mujoco.MjData(self.model)
        B, N = self.B, self.N
        qs, vs, fb = self.arena.qpos_start, self.arena.qvel_start, self.arena.first_body
        self.qpos = self.data.qpos[qs:qs + 7 * B * N].reshape(B, N, 7)  # views into MjData
        self.qvel = self.data.qvel[vs:vs + 6 * B * N].reshape(B, N, 6)
        self.xfrc = self.data.xfrc_applied[fb:fb + B * N].reshape(B, N, 6)
        assert np.shares_memory(self.qpos, self.data.qpos) and np.shares_memory(self.xfrc, self.data.xfrc_applied)
        self.offsets = self.arena.world_offsets[:, None, :]
        self.body_slice = slice(fb, fb + B * N)
        self.rotor_pos = rotor_positions(cfg.quad)
        self.scenario = get_scenario(cfg.scenario)
        self.paper_floor = cfg.collision_model == "paper"
        self.paper_quads = cfg.collision_model in ("paper", "blend")
        self.floor_z = cfg.quad.arm
        low, high = obs_bounds(cfg)
        self.obs_low, self.obs_high = low.astype(np.float64), high.astype(np.float64)
        self.obs_scale = obs_scale(cfg) if cfg.normalize_obs else None
        self.room_low = np.asarray(cfg.room_low)
        self.room_high = np.asarray(cfg.room_high)
        self.rng = np.random.default_rng()
        self.total_steps = 0  # across episodes, for reward annealing
        # draw specs, built once
        c = cfg.collision
        self._spec_quad = quad_collision_draw_spec(N, c.tries, c.shared_noise_std, c.own_noise_std,
                                                   cfg.collision_decay, c.kick_omega)
        self._spec_wall = wall_draw_spec(N, cfg.collision_decay, c.kick_omega)
        self._spec_floor = floor_draw_spec(N)
        self._spec_down = downwash_draw_spec(N)
        self._spec_sensor = sensor_noise_spec(cfg)
        self._sensor_on = any(d.std > 0 for d in self._spec_sensor.values())
        self._n_scn = self.scenario.num_uniforms(N)
        zeros = np.zeros((B, N))
        self.params = params_from_draws(cfg, nominal_draws(cfg, zeros, (B,)))
        self.u = np.zeros((B, N, 4))
        self.motor_eps = np.zeros((B, N, 4))
        self.f_norm = np.zeros((B, N, 4))
        self.prev_f_norm = np.zeros((B, N, 4))
        self.on_floor = np.zeros((B, N), bool)
        self.at_wall = np.zeros((B, N), bool)
        self.at_ceiling = np.zeros((B, N), bool)
        self.contact = np.zeros((B, N, N), bool)
        self.steps = np.zeros(B, np.int64)
        self.sstate: ScenarioState | None = None
        self.metrics = metrics_lib.init(zeros, (B,), N)
        self.last_action = np.zeros((B, N, 4))

    # ------------------------------------------------------------------ samplers
    def _sampler(self, stochastic: bool) -> Any:
        return NumpySampler(self.rng) if stochastic else MeanSampler()

    def seed(self, seed: int | None) -> None:
        self.rng = np.random.default_rng(seed)

    # ------------------------------------------------------------------ state access
    def kinematics(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(pos, vel, R, omega) copies in world-local frames: pos m, vel m/s world, R body->world,
        omega rad/s body."""
        pos = self.qpos[..., :3] - self.offsets
        return pos, self.qvel[..., :3].copy(), quat_to_rotmat(self.qpos[..., 3:7]), self.qvel[..., 3:].copy()

    def _write_params(self, mask: np.ndarray) -> None:
        ids = self.arena.body_ids[mask].ravel()
        self.model.body_mass[ids] = self.params["mass"][mask].ravel()
        self.model.body_inertia[ids] = self.params["inertia"][mask].reshape(-1, 3)

    # ------------------------------------------------------------------ reset
    def reset(self, mask: np.ndarray | None = None, state: dict[str, Any] | None = None) -> None:
        """Reset the worlds in ``mask`` (B,) bool (all if None); ``state`` holds (B, N, ...) arrays."""
        cfg, B, N = self.cfg, self.B, self.N
        mask = np.ones(B, bool) if mask is None else np.asarray(mask, bool)
        # 1. dynamics parameters
        if cfg.randomize:
            draws = NumpySampler(self.rng).draw(randomization_draw_spec(cfg), (B,))
        else:
            draws = nominal_draws(cfg, np.zeros((B, N)), (B,))
        new_params = params_from_draws(cfg, draws)
        self.params = {k: (v if k == "gravity" else _merge(mask, v, self.params[k])) for k, v in new_params.items()}
        self._write_params(mask)
        # 2. scenario
        u = self.rng.uniform(size=(B, self._n_scn))
        s_new = self.scenario.init(cfg, u)
        if state is not None and state.get("goals") is not None:
            s_new = s_new._replace(goals=np.asarray(state["goals"], dtype=np.float64).reshape(B, N, 3))
        self.sstate = s_new if self.sstate is None else ScenarioState(
            *(_merge(mask, a, b) for a, b in zip(s_new, self.sstate)))
        goals = self.sstate.goals
        # 3. start state
        sp = spawn_state(cfg, goals, self.rng.uniform(size=(B, spawn_num_uniforms(N))))
        pos, R = sp["pos"], yaw_rotmat(sp["yaw"])
        vel, omega = np.zeros((B, N, 3)), np.zeros((B, N, 3))
        motors: Any = cfg.motor_start
        if state is not None:
            pos = np.asarray(state.get("pos", pos), dtype=np.float64).reshape(B, N, 3)
            vel = np.asarray(state.get("vel", vel), dtype=np.float64).reshape(B, N, 3)
            R = np.asarray(state.get("rot", R), dtype=np.float64).reshape(B, N, 3, 3)
            omega = np.asarray(state.get("omega", omega), dtype=np.float64).reshape(B, N, 3)
            motors = state.get("motors", motors)
        if isinstance(motors, str):
            u0 = hover_motor_state(self.params) if motors == "hover" else np.zeros((B, N, 4))
        else:
            u0 = np.sqrt(np.clip(np.asarray(motors, dtype=np.float64).reshape(B, N, 4), 0.0, 1.0))
        m3 = mask[:, None, None]
        self.qpos[..., :3] = np.where(m3, pos + self.offsets, self.qpos[..., :3])
        self.qpos[..., 3:7] = np.where(m3, rotmat_to_quat(R), self.qpos[..., 3:7])
        self.qvel[..., :3] = np.where(m3, vel, self.qvel[..., :3])
        self.qvel[..., 3:] = np.where(m3, omega, self.qvel[..., 3:])
        self.u = np.where(m3, u0, self.u)
        self.motor_eps = np.where(m3, 0.0, self.motor_eps)
        self.f_norm = np.where(m3, self.u**2, self.f_norm)
        self.prev_f_norm = self.f_norm.copy()
        self.last_action = np.where(m3, 0.0, self.last_action)
        m2 = mask[:, None]
        cur_pos = self.qpos[..., :3] - self.offsets
        self.on_floor = np.where(m2, cur_pos[..., 2] <= self.floor_z + FLOOR_TOL, self.on_floor)
        self.at_wall = np.where(m2, np.any((cur_pos[..., :2] <= self.room_low[:2]) |
                                           (cur_pos[..., :2] >= self.room_high[:2]), -1), self.at_wall)
        self.at_ceiling = np.where(m2, cur_pos[..., 2] >= self.room_high[2], self.at_ceiling)
        contact, _ = pairwise_contacts(cur_pos, self.cfg.hitbox)
        self.contact = np.where(mask[:, None, None], contact, self.contact)
        self.steps = np.where(mask, 0, self.steps)
        fresh = metrics_lib.init(np.zeros((B, N)), (B,), N)
        self.metrics = {k: _merge(mask, fresh[k], v) for k, v in self.metrics.items()}
        self.xfrc[...] = 0.0
        self.data.time = 0.0
        mujoco.mj_forward(self.model, self.data)

    # ------------------------------------------------------------------ physics
    def _physics(self, action: np.ndarray) -> dict[str, np.ndarray]:
        cfg, B, N = self.cfg, self.B, self.N
        cmd = action_to_command(action)
        if cfg.noise.motor_noise_ratio > 0:
            self.motor_eps = motor_noise_step(self.motor_eps, self.params["motor_sigma"],
                                              cfg.noise.motor_noise_theta, self.rng.standard_normal((B, N, 4)))
        hit_floor = np.zeros((B, N), bool)
        max_w = cfg.quad.max_omega
        for _ in range(cfg.substeps):
            R = quat_to_rotmat(self.qpos[..., 3:7])
            self.u, self.f_norm, force, torque = substep_wrench(self.u, cmd, self.motor_eps, self.params, R,
                                                                self.rotor_pos)
            if self.paper_floor and self.on_floor.any():
                force, torque = floor_wrench(self.on_floor, force, torque, self.qvel[..., :3], self.params["mass"],
                                             self.params["gravity"], cfg.collision.floor_friction, cfg.sim_dt)
            self.xfrc[..., :3] = force
            self.xfrc[..., 3:] = torque
            mujoco.mj_step(self.model, self.data)
            np.clip(self.qvel[..., 3:], -max_w, max_w, out=self.qvel[..., 3:])
            if self.paper_floor and (self.on_floor.any() or (self.qpos[..., 2] <= self.floor_z).any()):
                pos = self.qpos[..., :3] - self.offsets
                R = quat_to_rotmat(self.qpos[..., 3:7])
                yaw = self._sampler(cfg.noise.stochastic_collisions).draw(self._spec_floor, (B,))["yaw"]
                r = floor_impact(pos, self.qvel[..., :3], self.qvel[..., 3:], self.qpos[..., 3:7], R, self.u,
                                 self.on_floor, self.floor_z, yaw)
                self.qpos[..., :3] = r["pos"] + self.offsets
                self.qpos[..., 3:7] = r["quat"]
                self.qvel[..., :3] = r["vel"]
                self.qvel[..., 3:] = r["omega"]
                self.u = r["u"]
                self.on_floor = r["on_floor"]
                hit_floor |= r["hit_floor"]
        # once per control step: walls, ceiling, quad-quad, downwash (velocity-level models)
        pos, vel, R, omega = self.kinematics()
        if self.paper_floor:
            outside = ((pos[..., :2] <= self.room_low[:2]) | (pos[..., :2] >= self.room_high[:2])).any(-1) | (
                pos[..., 2] >= self.room_high[2])
            if outside.any() or self.at_wall.any() or self.at_ceiling.any():
                draws = self._sampler(cfg.noise.stochastic_collisions).draw(self._spec_wall, (B,))
                w = wall_collisions(pos, vel, omega, self.at_wall, self.at_ceiling, self.room_low, self.room_high,
                                    draws, cfg.collision.wall_speed_limits)
                pos, vel, omega = w["pos"], w["vel"], w["omega"]
                self.at_wall, self.at_ceiling = w["at_wall"], w["at_ceiling"]
                hit_wall, hit_ceiling = w["hit_wall"], w["hit_ceiling"]
            else:
                hit_wall = hit_ceiling = np.zeros((B, N), bool)
        else:  # MuJoCo resolves floor/walls/ceiling; flags from proximity to the surfaces
            margin = cfg.quad.arm + 0.005
            on_floor = pos[..., 2] <= margin
            at_wall = ((pos[..., :2] <= self.room_low[:2] + margin) | (pos[..., :2] >= self.room_high[:2] - margin)).any(-1)
            at_ceiling = pos[..., 2] >= self.room_high[2] - margin
            hit_floor = on_floor & ~self.on_floor
            hit_wall, hit_ceiling = at_wall & ~self.at_wall, at_ceiling & ~self.at_ceiling
            self.on_floor, self.at_wall, self.at_ceiling = on_floor, at_wall, at_ceiling
        contact, dist = pairwise_contacts(pos, cfg.hitbox)
        new_contact = contact & ~self.contact
        if self.paper_quads and new_contact.any():
            draws = self._sampler(cfg.noise.stochastic_collisions).draw(self._spec_quad, (B,))
            q = quad_collisions(pos, vel, omega, self.contact, cfg.hitbox, draws)
            vel, omega = q["vel"], q["omega"]
        self.contact = contact
        if cfg.downwash:
            draws = self._sampler(cfg.noise.stochastic_downwash).draw(self._spec_down, (B,))
            vel, omega = apply_downwash(pos, vel, omega, R, cfg.control_dt, draws)
        self.qpos[..., :3] = pos + self.offsets
        self.qvel[..., :3] = vel
        self.qvel[..., 3:] = omega
        return {"pos": pos, "vel": vel, "R": R, "omega": omega, "dist": dist, "new_contact": new_contact,
                "hit_floor": hit_floor, "hit_wall": hit_wall, "hit_ceiling": hit_ceiling}

    # ------------------------------------------------------------------ step
    def step(self, action: np.ndarray) -> dict[str, Any]:
        """Advance all worlds one control step with validated actions (B, N, 4)."""
        cfg = self.cfg
        self.prev_f_norm = self.f_norm
        k = self._physics(action)
        self.steps = self.steps + 1
        self.total_steps += 1
        t = self.steps * cfg.control_dt  # (B,)
        prev_goals = self.sstate.goals
        u = self.rng.uniform(size=(self.B, self._n_scn))
        self.sstate = self.scenario.step(cfg, self.sstate, t, k["pos"], u)
        goals, goal_vel = self.sstate.goals, self.sstate.goal_vel
        jump = np.linalg.norm(goals - prev_goals, axis=-1) > 1e-3 + 2.0 * np.linalg.norm(goal_vel, axis=-1) * cfg.control_dt
        terms = reward_terms(cfg, k["pos"], k["vel"], k["R"], k["omega"], goals, action, self.f_norm,
                             self.prev_f_norm, self.on_floor, k["hit_floor"], k["hit_wall"], k["hit_ceiling"],
                             k["new_contact"], k["dist"], anneal_factor(cfg, self.total_steps))
        rewards = total_reward(terms)
        dist_goal = np.linalg.norm(goals - k["pos"], axis=-1)
        self.metrics = metrics_lib.update(self.metrics, t[:, None], dist_goal, k["new_contact"], k["hit_floor"],
                                          k["hit_wall"], k["hit_ceiling"], jump, cfg.grace_period_s)
        self.last_action = action
        truncated = self.steps >= cfg.episode_steps
        return {"obs": self.observe(k), "rewards": rewards, "terms": terms, "truncated": truncated,
                "kin": k, "t": t}

    def observe(self, kin: dict[str, Any] | None = None) -> np.ndarray:
        """Observations (B, N, obs_dim) float64 (sensor noise drawn now)."""
        if kin is None:
            pos, vel, R, omega = self.kinematics()
        else:
            pos, vel, R, omega = kin["pos"], kin["vel"], kin["R"], kin["omega"]
        noise = NumpySampler(self.rng).draw(self._spec_sensor, (self.B,)) if self._sensor_on else None
        return build_obs(self.cfg, pos, vel, R, omega, self.sstate.goals, noise, self.obs_low, self.obs_high,
                         self.obs_scale)

    def episode_metrics(self) -> dict[str, np.ndarray]:
        """Per-world episode metrics (B,) so far."""
        t_end = self.steps * self.cfg.control_dt
        return metrics_lib.finalize(self.metrics, t_end[:, None])

    def state_dict(self, kin: dict[str, Any] | None = None) -> dict[str, np.ndarray]:
        """Fresh copies: pos, vel (world), rot (body->world), omega (body), thrust (normalized, (B, N, 4))."""
        pos, vel, R, omega = self.kinematics()
        return {"pos": pos, "vel": vel, "rot": R, "omega": omega, "thrust": self.f_norm.copy()}

    def params_dict(self) -> dict[str, np.ndarray]:
        """Copies of the per-quad dynamics parameters in force (B, N, ...)."""
        return {k: np.array(v, copy=True) for k, v in self.params.items() if k != "gravity"}
