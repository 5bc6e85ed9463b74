"""The engine differences of the control step (:mod:`quadswarm_mj.core.step`), and nothing else.

* :class:`NumpyOps` (the CPU engine, (B, N) arrays): an event model runs only on the worlds with an
  event (``gate`` returns their index, or None: the stage is skipped), and its random draws are made
  then, per world, from the engine's seeded ``numpy.random.Generator`` in the stages' fixed order
  (seeded runs are bit-identical; with B = 1 the draws happen exactly when the event does).
* :class:`JaxOps` (the JAX engine, (N,) arrays of one world under ``vmap``/``jit``): every stage runs
  always (a model function leaves unaffected quads unchanged), with the step's draws made up front
  in fixed-size budgets of event slots, spread over this step's events in index order
  (:func:`quadswarm_mj.collisions.expand_per_quad`; beyond the budget events reuse slots, new
  quad-quad pairs wait a step: ``collisions.quad_collisions_budgeted``).

Both offer the sub-steps' ops (:mod:`quadswarm_mj.core.substeps`: ``loop``, ``wrench``, ``rotmat``,
``floor_wrench``, ``floor_impact``), the later stages' (:mod:`quadswarm_mj.core.step`: ``room``, ``gate``,
``wall_gate``, ``put``, ``zeros_like``, ``draws(kind, mask_fn, w)``, ``pairwise_contacts``, ``quad_quad``,
``obstacles``; ``mask_fn`` is called only where the engine needs the mask) and the task step's
(:func:`quadswarm_mj.core.control.task_step`: ``dtype``, ``terms``, the draws "scenario", "sensor", "deck",
and the task functions of :class:`ModelForms`). The engines' same-values speed forms of
:mod:`quadswarm_mj.perf` are reached only here.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from quadswarm_mj import actuation, collisions, observations, rewards, spatial
from quadswarm_mj import metrics as metrics_lib
from quadswarm_mj.collisions import expand_per_quad, quad_collisions, quad_collisions_budgeted
from quadswarm_mj.perf import (
    numpy_deck,
    numpy_floor,
    numpy_loop,
    numpy_small,
    numpy_swarm,
    numpy_swarm_task,
    one_quad,
    xla_cpu,
)
from quadswarm_mj.perf.numpy_loop import SmallLoop
from quadswarm_mj.perf.numpy_swarm import SwarmLoop
from quadswarm_mj.perf.one_quad_step import OneQuadLoop, OneQuadTask
from quadswarm_mj.spatial import BIG

ALL = slice(None)
_ZERO = np.zeros(())  # 0.0 as a 0-d array (a NumPy call converts a Python float on every call)


def sub(draws: dict[str, Any], prefix: str) -> dict[str, Any]:
    """The draws named ``prefix/...`` with the prefix removed."""
    p = prefix + "/"
    return {k[len(p):]: v for k, v in draws.items() if k.startswith(p)}


def put(arr: np.ndarray, idx: Any, value: Any) -> np.ndarray:
    """``arr`` with rows ``idx`` replaced (a fresh array; ``value`` itself when idx is every row)."""
    if isinstance(idx, slice):
        if type(value) is np.ndarray and value.shape == arr.shape and value.dtype == arr.dtype:
            return value  # a fresh result of a model function: take it as it is
        out = np.empty_like(arr)
        out[...] = value
        return out
    out = arr.copy()
    out[idx] = value
    return out


class ModelForms:
    """The model's functions of the control step as the model defines them (any namespace, any batch
    dims): ``command``, ``motor_noise``, ``pairwise_contacts``, ``reward_terms``, ``total_reward``,
    ``metrics_update``, ``obs`` (:func:`quadswarm_mj.observations.build_obs`). An engine's ops override
    them with same-values forms."""

    command = staticmethod(actuation.action_to_command)
    motor_noise = staticmethod(actuation.motor_noise_step)
    pairwise_contacts = staticmethod(collisions.pairwise_contacts)
    reward_terms = staticmethod(rewards.reward_terms)
    total_reward = staticmethod(rewards.total_reward)
    metrics_update = staticmethod(metrics_lib.update)
    obs = staticmethod(observations.build_obs)

    @staticmethod
    def loop(body: Any, carry: Any, n: int) -> Any:
        """``n`` sub-steps, eagerly: ``carry = body(carry, i)`` (the JAX engine's ops use ``fori_loop``)."""
        for i in range(n):
            carry = body(carry, i)
        return carry


class NumpyOps(ModelForms):
    """Eager event gating with per-event NumPy draws, for a :class:`~quadswarm_mj.envs.cpu_core.CpuSwarm`
    (its generator, draw specs and world bookkeeping). With one quad in one world (B N = 1) the task
    functions are :mod:`quadswarm_mj.perf.one_quad`'s float forms (the same bits; ``one_quad.ENABLED``
    False: the model's)."""

    wrench = staticmethod(numpy_small.substep_wrench)
    rotmat = staticmethod(numpy_small.quat_to_rotmat)
    dtype = np.float64

    @staticmethod
    def terms(terms: dict[str, Any]) -> dict[str, Any]:
        """The reward terms as they are (float64 already)."""
        return terms

    def __init__(self, swarm: Any) -> None:
        self.s = swarm
        self.room = (swarm.room_low, swarm.room_high)
        cfg = swarm.cfg
        self._one = swarm.B * swarm.N == 1  # one quad in one world: the float forms
        # the observation's float form covers the own-state layouts without neighbours, obstacles, decks
        self._one_obs = (self._one and cfg.neighbors == 0 and cfg.obstacles is None and not cfg.sensors.any
                         and cfg.obs_self != "wall")
        self._obs_floor = cfg.obs_self == "floor"
        self._cfg = cfg
        self._reward_plan = one_quad.reward_plan(rewards._term_factors(cfg.rewards, cfg.sim_dt, cfg.control_dt),
                                                 rewards.ANNEALED, cfg.rewards.vel_limit)
        self._deck_noise = cfg.sensors.any and cfg.sensors.noise
        self._deck_spec = None  # the deck draws' (name, uniform?, a, b, shape), made on first use
        self._sensor_std_full: tuple | None = None  # (the engine's sensor std, it broadcast to the draw's shape)
        lo, hi = swarm._out_lo.tolist(), swarm._out_hi.tolist()
        self._out = (lo[0], lo[1], lo[2], hi[0], hi[1], hi[2])  # the walls' and ceiling's bounds (floats)
        self._sum_keys: dict[tuple, list[str]] = {}
        B, N = swarm.B, swarm.N  # the shapes of the step's draws: motor, scenario, sensor
        self._shapes = ((B, N, 4), (B, swarm._n_scn), (3, B, N, 3))
        # one quad, the paper's chain and floor: the whole sub-step loop on floats (perf.one_quad_step)
        # several quads or worlds, small arrays: the loop with the control step's constants computed once
        # (perf.numpy_loop)
        # one world of several quads: the same loop on work arrays made once (perf.numpy_swarm)
        paper_chain = cfg.collision_model == "paper" and swarm._act is None
        self._loop = (None if not paper_chain else OneQuadLoop(swarm) if self._one
                      else SmallLoop(swarm) if 4 * B * N < BIG else None)
        self._swarm_loop = (SwarmLoop(swarm) if paper_chain and not self._one and B == 1 and swarm._offsets_zero
                            and 4 * N < BIG else None)
        # ... and the task half of the step (scenario, rewards, metrics, observation) on floats
        sensor = (swarm._sensor_keys, swarm._sensor_std) if swarm._sensor_on else (None, None)
        self._task = (OneQuadTask(cfg, swarm.obs_low, swarm.obs_high, swarm.obs_scale, swarm._zero_terms, *sensor)
                      if self._one_obs and cfg.control_mode == "rotor" else None)
        # several quads: the task half in few NumPy calls (perf.numpy_swarm_task)
        self._swarm_task = (numpy_swarm_task.SwarmTask(swarm) if not self._one and 4 * B * N < BIG
                            and numpy_swarm_task.applies(cfg, B, N) else None)

    @property
    def fused_loop(self) -> Any:
        """``core.substeps.substep_loop``'s whole-loop form for this engine, or None (the per-sub-step ops)."""
        if self._one:
            return self._loop if one_quad.ENABLED else None
        if self._swarm_loop is not None and numpy_swarm.ENABLED:
            return self._swarm_loop
        return self._loop if numpy_loop.ENABLED else None

    @property
    def fused_stages(self) -> Any:
        """``core.step.velocity_stages``' event-free form for this engine (``perf.numpy_swarm``), or None."""
        return self._swarm_loop.stages if self._swarm_loop is not None and numpy_swarm.ENABLED else None

    @property
    def fused_task(self) -> Any:
        """``core.control.task_step``'s whole-stage form for this engine (one quad: on floats; several quads:
        ``perf.numpy_swarm_task``), or None."""
        if self._one:
            return self._task if one_quad.ENABLED else None
        return self._swarm_task if numpy_swarm_task.ENABLED else None

    def command(self, action: np.ndarray) -> np.ndarray:
        """:func:`quadswarm_mj.actuation.action_to_command` (one quad: on floats, same bits)."""
        if self._one and one_quad.ENABLED and action.dtype == np.float64:
            return one_quad.action_to_command(action)
        if numpy_swarm.ENABLED and type(action) is np.ndarray and action.dtype == np.float64:
            return numpy_swarm.action_to_command(action)  # (the clip as one call, same bits)
        return actuation.action_to_command(action)

    def motor_noise(self, eps: np.ndarray, sigma: np.ndarray, theta: float, normal: np.ndarray) -> np.ndarray:
        """:func:`quadswarm_mj.actuation.motor_noise_step` (one quad: on floats, same bits)."""
        if self._one and one_quad.ENABLED:
            return one_quad.motor_noise_step(eps, sigma, theta, normal)
        if numpy_swarm.ENABLED and type(eps) is np.ndarray and eps.dtype == np.float64:
            return numpy_swarm.motor_noise_step(eps, sigma, theta, normal)  # (0-d constants, same bits)
        return actuation.motor_noise_step(eps, sigma, theta, normal)

    def reward_terms(self, cfg: Any, pos: Any, vel: Any, R: Any, omega: Any, goals: Any, action: Any, f_norm: Any,
                     prev_f_norm: Any, on_floor: Any, hit_floor: Any, hit_wall: Any, hit_ceiling: Any,
                     new_contact: Any, dist: Any, anneal: Any = 1.0, goal_dist: Any | None = None) -> dict[str, Any]:
        """:func:`quadswarm_mj.rewards.reward_terms` (one quad: ``perf.one_quad.reward_terms``, same bits)."""
        if self._one and one_quad.ENABLED and action.dtype == np.float64:
            plan = self._reward_plan if cfg is self._cfg else one_quad.reward_plan(
                rewards._term_factors(cfg.rewards, cfg.sim_dt, cfg.control_dt), rewards.ANNEALED,
                cfg.rewards.vel_limit)
            return one_quad.reward_terms(plan, pos, vel, R, omega, goals, action, f_norm, prev_f_norm, on_floor,
                                         hit_floor, hit_wall, hit_ceiling, new_contact, anneal, goal_dist)
        return rewards.reward_terms(cfg, pos, vel, R, omega, goals, action, f_norm, prev_f_norm, on_floor, hit_floor,
                                    hit_wall, hit_ceiling, new_contact, dist, anneal, goal_dist)

    def total_reward(self, terms: dict[str, Any], skip: tuple[str, ...] = ()) -> Any:
        """:func:`quadswarm_mj.rewards.total_reward` (one quad: the same sum on floats)."""
        if self._one and one_quad.ENABLED:
            keys = self._sum_keys.get((skip, len(terms)))
            if keys is None:  # the order of rewards.total_reward, made once per (skip, terms present)
                keys = [k for k in rewards.TERMS if k not in skip] + [k for k in rewards.OBSTACLE_TERMS if k in terms]
                self._sum_keys[(skip, len(terms))] = keys
            return one_quad.total_reward(terms, keys)
        return rewards.total_reward(terms, skip)

    def metrics_update(self, m: dict[str, Any], t: Any, dist_to_goal: Any, new_contact: Any, hit_floor: Any,
                       hit_wall: Any, hit_ceiling: Any, goal_jump: Any, grace_s: float) -> dict[str, Any]:
        """:func:`quadswarm_mj.metrics.update` (one quad: ``perf.one_quad.metrics_update``, same values)."""
        if self._one and one_quad.ENABLED:
            return one_quad.metrics_update(m, t, dist_to_goal, new_contact, hit_floor, hit_wall, hit_ceiling, goal_jump,
                                           grace_s, metrics_lib.MIN_SEGMENT_S, metrics_lib.REACH_DISTANCE)
        return metrics_lib.update(m, t, dist_to_goal, new_contact, hit_floor, hit_wall, hit_ceiling, goal_jump, grace_s)

    def obs(self, cfg: Any, pos: Any, vel: Any, R: Any, omega: Any, goals: Any, noise: dict[str, Any] | None,
            low: Any, high: Any, scale: Any | None = None, dist: Any | None = None, obstacles: Any | None = None,
            obstacle_feats: Any | None = None, deck_draws: dict[str, Any] | None = None) -> Any:
        """:func:`quadswarm_mj.observations.build_obs` (one quad without neighbours, obstacles or decks:
        ``perf.one_quad.build_obs``, same values; the decks' part: ``perf.numpy_deck``, same bits)."""
        if self._one_obs and one_quad.ENABLED and pos.shape == (1, 1, 3):
            return one_quad.build_obs(pos, vel, R, omega, goals, noise, low, high, scale, self._obs_floor)
        return observations.build_obs(cfg, pos, vel, R, omega, goals, noise, low, high, scale, dist, obstacles,
                                      obstacle_feats, deck_draws, deck_fn=numpy_deck.deck_part)


    def floor_wrench(self, cfg: Any, on_floor: np.ndarray, force: np.ndarray, torque: np.ndarray, v: np.ndarray,
                     params: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """The floor's normal force and friction on the worlds with a grounded quad (none: unchanged)."""
        s = self.s
        if not s._any_on_floor:
            return force, torque
        if self._one and one_quad.ENABLED:  # ``v`` (1, 1, 6): its first two entries are the horizontal speed
            return one_quad.floor_wrench(on_floor, force, torque, v, params["mass"], params["gravity"],
                                         cfg.collision.floor_friction, cfg.sim_dt)
        if force.size < BIG:  # perf.numpy_floor: the grounded quads' rows, written in place (same bits)
            numpy_floor.floor_wrench_inplace(on_floor, force, torque, v, params["mass"], params["gravity"],
                                             cfg.collision.floor_friction, cfg.sim_dt)
            return force, torque
        w = s._worlds(on_floor)
        fw, tw = numpy_small.floor_wrench(on_floor[w], force[w], torque[w], v[w, :, :3], params["mass"][w],
                                          params["gravity"], cfg.collision.floor_friction, cfg.sim_dt)
        if isinstance(w, slice):
            return fw, tw
        force[w], torque[w] = fw, tw
        return force, torque

    def floor_impact(self, cfg: Any, i: int, q: np.ndarray, v: np.ndarray, u: np.ndarray, on_floor: np.ndarray,
                     hit_floor: np.ndarray) -> tuple[Any, ...]:
        """The paper's floor landing on the worlds with a quad at or below the floor height or grounded
        (``CpuSwarm._floor_impact``: masked writes into the physics' qpos/qvel, yaw drawn per world
        then); returns (q, v, u, on_floor, hit_floor, R of the new q)."""
        s = self.s
        if self._one and one_quad.ENABLED:  # one quad: perf.one_quad's float forms (same draw, same bits)
            if q[0, 0, 2] <= s.floor_z or (s._any_on_floor and on_floor[0, 0]):  # grounded, as below
                u, on_floor = self._floor_impact_one(q, v, u, on_floor, hit_floor)
            return q, v, u, on_floor, hit_floor, one_quad.quat_to_rotmat(q[..., 3:7])
        grounded = q[..., 2] <= s.floor_z
        if s._any_on_floor:
            grounded |= on_floor
        if np.count_nonzero(grounded):  # (faster than .any() on tiny masks)
            u, on_floor = s._floor_rows(s._worlds(grounded), u, on_floor, hit_floor)
        R = (numpy_small.quat_to_rotmat_qpos(q) if 7 < q.size < BIG  # (the same bits, fewer calls)
             else numpy_small.quat_to_rotmat(q[..., 3:7]))
        return q, v, u, on_floor, hit_floor, R

    def _floor_impact_one(self, q: np.ndarray, v: np.ndarray, u: np.ndarray, on_floor: np.ndarray,
                          hit_floor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``CpuSwarm._floor_impact`` of the one quad (its yaw drawn as there): written into the physics'
        qpos/qvel (``q``, ``v``) and ``hit_floor`` in place; returns (u, on_floor)."""
        s = self.s
        d = s._spec_floor["yaw"]
        yaw = s.rng.uniform(d.low, d.high) if s.cfg.noise.stochastic_collisions else float(d.mean)
        grounded, hit, u = one_quad.floor_impact_inplace(s.qpos[0, 0], s.qvel[0, 0], u, bool(on_floor[0, 0]), s.floor_z,
                                                         s.offsets[0, 0], yaw)
        if hit:
            hit_floor[0, 0] = True
        s.phys.touch()
        s._any_on_floor = grounded
        return u, np.array([[grounded]])

    def wall_gate(self, pos: np.ndarray, at_wall: np.ndarray, at_ceiling: np.ndarray) -> Any:
        """The worlds with a quad at or beyond a wall or the ceiling (one compare of all three axes) or
        flagged there at the last step (None: none)."""
        if self._one:  # one quad (B = 1): the same compares on floats
            x, y, z = pos.ravel().tolist()
            lx, ly, lz, hx, hy, hz = self._out
            if (x <= lx or y <= ly or z <= lz or x >= hx or y >= hy or z >= hz or at_wall[0, 0]
                    or at_ceiling[0, 0]):
                return ALL
            return None
        out = (pos <= self.s._out_lo) | (pos >= self.s._out_hi)
        if not (np.count_nonzero(out) or np.count_nonzero(at_wall) or np.count_nonzero(at_ceiling)):  # (= .any())
            return None
        return self.s._worlds(out.any(-1) | at_wall | at_ceiling)

    def gate(self, mask_fn: Any) -> Any:
        mask = mask_fn()
        return self.s._worlds(mask) if mask.any() else None

    @staticmethod
    def zeros_like(a: np.ndarray) -> np.ndarray:
        return np.zeros(a.shape, bool)

    put = staticmethod(put)

    def draws(self, kind: str, mask_fn: Any, w: Any) -> dict[str, Any]:
        s = self.s
        if kind == "motor":  # the step's motor-noise normals (B, N, 4)
            return s.rng.standard_normal(self._shapes[0])
        if kind == "scenario":  # the scenario's uniforms (B, n)
            return s.rng.uniform(size=self._shapes[1])
        if kind == "sensor":  # = NumpySampler(rng).draw(sensor_noise_spec(cfg), (B,)): 0 + std * N(0, 1)
            if not s._sensor_on:
                return None
            z = s.rng.standard_normal(self._shapes[2])
            std = self._sensor_std_full  # std of the full shape (a same-shape product costs less than a broadcast)
            if std is None or std[0] is not s._sensor_std:
                std = self._sensor_std_full = (s._sensor_std, np.broadcast_to(s._sensor_std, z.shape).copy())
            np.multiply(z, std[1], z)
            np.add(z, _ZERO, z)  # = 0.0 + std * z (in place: the same operations, the same bits)
            return dict(zip(s._sensor_keys, z))
        noise = s.cfg.noise
        if kind == "deck":  # deck sensor noise (quadswarm_mj.sensors), None: noise-free
            if not self._deck_noise:
                return None
            if self._deck_spec is None:  # = NumpySampler(rng).draw(deck_draw_spec(cfg), (B,)), its spec made once
                from quadswarm_mj.random_draws import Uniform
                from quadswarm_mj.sensors import deck_draw_spec

                spec = deck_draw_spec(s.cfg)
                if not all((d.low, d.high) == (0.0, 1.0) if isinstance(d, Uniform) else (d.mean, d.std) == (0.0, 1.0)
                           for d in spec.values()):  # random / standard_normal below draw these only
                    raise RuntimeError(f"deck draws must be U(0, 1) or N(0, 1): {spec}")
                self._deck_spec = [(k, isinstance(d, Uniform), (s.B,) + tuple(d.shape)) for k, d in spec.items()]
            # random / standard_normal: the bits of uniform(0, 1) / normal(0, 1) without their argument
            # checks (the spec's bounds are those; tests/test_draw_log.py compares the values' hashes)
            return {k: (s.rng.random if uni else s.rng.standard_normal)(shape) for k, uni, shape in self._deck_spec}
        if kind == "wall":
            return s._sampler(noise.stochastic_collisions).draw(s._spec_wall, (s._count(w),))
        if kind == "yaw":  # = s._sampler(...).draw(s._spec_floor, (M,))["yaw"]
            M, d = s._count(w), s._spec_floor["yaw"]
            yaw = (s.rng.uniform(d.low, d.high, size=(M, s.N)) if noise.stochastic_collisions
                   else np.full((M, s.N), d.mean))
            return {"yaw_draw": yaw}
        if kind == "down":
            return s._sampler(noise.stochastic_downwash).draw(s._spec_down, (s.B,))
        raise ValueError(kind)

    def pairwise_contacts(self, pos: Any, hitbox: float) -> tuple[Any, Any]:
        """:func:`quadswarm_mj.collisions.pairwise_contacts`; with one quad per world no pair: contacts all
        False and the distance ||p - p|| (0.0, NaN for a non-finite position, as the norm gives)."""
        if self._one:  # on floats: p - p is 0.0 (NaN for a non-finite p), as is its norm
            x, y, z = pos.ravel().tolist()
            return np.zeros((1, 1, 1), bool), np.array([[[(x - x) + (y - y) + (z - z)]]])
        if self.s.N == 1:
            d = pos - pos
            return np.zeros(pos.shape[:-1] + (1,), bool), np.add.reduce(d * d, axis=-1, keepdims=True)
        return collisions.pairwise_contacts(pos, hitbox)

    def quad_quad(self, pos: Any, vel: Any, omega: Any, prev: Any, contact: Any, new: Any) -> dict[str, Any] | None:
        """The paper's response on the worlds with a new contact (None: there is none)."""
        if self.s.N == 1 or not np.count_nonzero(new):  # (one quad: no pair; faster than .any() on small masks)
            return None
        s = self.s
        w = s._worlds(new.any(-1))
        draws = s._sampler(s.cfg.noise.stochastic_collisions).draw(s._spec_quad, (s._count(w),))
        q = quad_collisions(pos[w], vel[w], omega[w], prev[w], s.cfg.hitbox, draws)
        return {"vel": put(vel, w, q["vel"]), "omega": put(omega, w, q["omega"]), "contact": contact,
                "new_contact": new}

    def obstacles(self, pos: Any, vel: Any, omega: Any) -> dict[str, Any]:
        vel, omega = vel.copy(), omega.copy()  # the engine's stage writes them in place
        new, changed, contact = self.s._obstacle_stage(pos, vel, omega)
        return {"vel": vel, "omega": omega, "obst_new": new, "obst_contact": contact, "obst_feats": self.s._obst_feats,
                "changed": changed}


class AlwaysOn(ModelForms):
    """The gating of engines that run every stage on every quad (a model function leaves unaffected quads
    unchanged): every world, always; a stage's result replaces the whole array."""

    @staticmethod
    def gate(mask_fn: Any) -> Any:
        return ALL

    @staticmethod
    def wall_gate(pos: Any, at_wall: Any, at_ceiling: Any) -> Any:
        return ALL

    @staticmethod
    def put(arr: Any, w: Any, value: Any) -> Any:
        return value


@functools.cache
def jax_deck_part() -> Any:
    """:func:`quadswarm_mj.sensors.deck_part` with the JAX engine's same-values forms: the float32 erfinv of
    its random numbers (:func:`quadswarm_mj.perf.fused_draws.erf_inv_f32`), the depth camera's hitbox
    test for XLA:CPU (:func:`quadswarm_mj.perf.depth_xla.sphere_pixel_hits`) and, with the depth camera,
    the part computed once for the observation and the info readings
    (:func:`quadswarm_mj.perf.jax_deck.deck_part`);
    ``build_obs``' ``deck_fn``."""
    from quadswarm_mj.perf.jax_deck import deck_part

    return deck_part


class JaxOps(AlwaysOn):
    """Always-on stages with the step's budgeted draws ``rnd`` (one world, ``jax.numpy``)."""

    wrench = staticmethod(actuation.substep_wrench)
    rotmat = staticmethod(spatial.quat_to_rotmat)

    def __init__(self, cfg: Any, rnd: dict[str, Any], dtype: Any, obstacle_stage: Any = None) -> None:
        import jax.numpy as jnp

        self.cfg, self.rnd, self.jnp, self.dtype = cfg, rnd, jnp, dtype
        self.room = (jnp.asarray(cfg.room_low, dtype), jnp.asarray(cfg.room_high, dtype))
        self._obstacle_stage = obstacle_stage
        self._k = xla_cpu.jax_kernels()  # the model's kernels, worlds axis last (same values)

    def pairwise_contacts(self, pos: Any, hitbox: float) -> tuple[Any, Any]:
        return collisions.pairwise_contacts(pos, hitbox, self._k["pair_dist"])

    def obs(self, *args: Any, **kw: Any) -> Any:
        """:func:`quadswarm_mj.observations.build_obs` with the worlds-last neighbour ranks and the engine's
        deck part (:func:`jax_deck_part`)."""
        return observations.build_obs(*args, rank_fn=self._k["rank_fn"], deck_fn=jax_deck_part(), **kw)

    def loop(self, body: Any, carry: Any, n: int) -> Any:
        """``lax.scan`` over the sub-steps, each given its floor-landing yaw slots (cos, sin) (n, slots)."""
        import jax

        yaw = self.rnd["floor/yaw"]
        assert yaw.shape[0] == n, (yaw.shape, n)
        return jax.lax.scan(lambda c, x: (body(c, x), None), carry, (self.jnp.cos(yaw), self.jnp.sin(yaw)))[0]

    @staticmethod
    def floor_wrench(cfg: Any, on_floor: Any, force: Any, torque: Any, v: Any, params: dict[str, Any]) -> tuple:
        return collisions.floor_wrench(on_floor, force, torque, v[..., :3], params["mass"], params["gravity"],
                                       cfg.collision.floor_friction, cfg.sim_dt)

    def floor_impact(self, cfg: Any, yaw_cs: Any, q: Any, v: Any, u: Any, on_floor: Any, hit_floor: Any) -> tuple:
        """The paper's floor landing on every quad, this sub-step's yaw slots spread over its landings
        (trig-free path); returns (q, v, u, on_floor, hit_floor, R)."""
        jnp, floor_z = self.jnp, cfg.quad.arm
        R = spatial.quat_to_rotmat(q[..., 3:7])
        landing = (q[..., 2] <= floor_z) & ~on_floor
        d = expand_per_quad(landing, {"c": yaw_cs[0], "s": yaw_cs[1]})  # trig-free yaw draws
        r = collisions.floor_impact(q[..., :3], v[..., :3], v[..., 3:], q[..., 3:7], R, u, on_floor, floor_z, None,
                                    yaw_draw_cs=(d["c"], d["s"]))
        q = jnp.concatenate([r["pos"], r["quat"]], -1)
        v = jnp.concatenate([r["vel"], r["omega"]], -1)
        return q, v, r["u"], r["on_floor"], hit_floor | r["hit_floor"], r["R"]

    def terms(self, terms: dict[str, Any]) -> dict[str, Any]:
        """The reward terms in the engine's float dtype (a zero-scale term may come back weakly typed, and
        a state whose leaf types change between reset and step would make jit compile step twice)."""
        return {name: v.astype(self.dtype) for name, v in terms.items()}

    def zeros_like(self, a: Any) -> Any:
        return self.jnp.zeros_like(a)

    def draws(self, kind: str, mask_fn: Any, w: Any) -> dict[str, Any]:
        jnp, rnd = self.jnp, self.rnd
        if kind == "motor":
            return rnd["motor/motor"]
        if kind == "scenario":
            return rnd["scenario"]
        if kind in ("sensor", "deck"):  # None: noise-free
            return sub(rnd, kind) or None
        if kind == "wall":
            return expand_per_quad(mask_fn(), sub(rnd, "wall"))
        if kind == "yaw":  # the last sub-step's landing slots (unused without the paper's floor), trig-free
            yaw = rnd["floor/yaw"][-1]
            d = expand_per_quad(mask_fn(), {"c": jnp.cos(yaw), "s": jnp.sin(yaw)})
            return {"yaw_draw_cs": (d["c"], d["s"])}
        if kind == "down":
            from quadswarm_mj.downwash import expand_downwash_draws

            return expand_downwash_draws(mask_fn(), sub(rnd, "down"))
        raise ValueError(kind)

    def quad_quad(self, pos: Any, vel: Any, omega: Any, prev: Any, contact: Any, new: Any) -> dict[str, Any]:
        """The budgeted response: new pairs beyond ``QUAD_PAIR_BUDGET`` wait for the next step."""
        return quad_collisions_budgeted(pos, vel, omega, prev, self.cfg.hitbox, sub(self.rnd, "quad"),
                                        self._k["pair_dist"], self._k["pair_events"])

    def obstacles(self, pos: Any, vel: Any, omega: Any) -> dict[str, Any]:
        return self._obstacle_stage(pos, vel, omega)
