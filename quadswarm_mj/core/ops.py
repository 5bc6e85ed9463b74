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

Both offer, for the sub-steps (:mod:`quadswarm_mj.core.substeps`): ``loop(body, carry, n)``,
``wrench`` (``substep_wrench``), ``rotmat`` (``quat_to_rotmat``), ``floor_wrench`` and ``floor_impact``
(the paper's floor, event-gated on the CPU engine); for the stages after them (:mod:`quadswarm_mj.core.
step`): ``room`` (room_low, room_high), ``gate(mask_fn)``, ``wall_gate``, ``put(arr, w, value)``,
``zeros_like``, ``draws(kind, mask_fn, w)`` (kind: "motor", "wall", "yaw", "down"), ``quad_quad`` and
``obstacles``; ``mask_fn`` is called only where the engine needs the mask; for the task step
(:func:`quadswarm_mj.core.control.task_step`): ``dtype`` (the float dtype), ``terms`` and the draws
"scenario", "sensor", "deck".
"""

from __future__ import annotations

from typing import Any

import numpy as np

from quadswarm_mj import actuation, collisions, spatial
from quadswarm_mj.collisions import expand_per_quad, quad_collisions, quad_collisions_budgeted
from quadswarm_mj.perf import numpy_small

ALL = slice(None)


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


class NumpyOps:
    """Eager event gating with per-event NumPy draws, for a :class:`~quadswarm_mj.envs.cpu_core.CpuSwarm`
    (its generator, draw specs and world bookkeeping)."""

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

    @staticmethod
    def loop(body: Any, carry: Any, n: int) -> Any:
        """``n`` sub-steps: ``carry = body(carry, i)``."""
        for i in range(n):
            carry = body(carry, i)
        return carry

    def floor_wrench(self, cfg: Any, on_floor: np.ndarray, force: np.ndarray, torque: np.ndarray, v: np.ndarray,
                     params: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """The floor's normal force and friction on the worlds with a grounded quad (none: unchanged)."""
        s = self.s
        if not s._any_on_floor:
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
        grounded = q[..., 2] <= s.floor_z
        if s._any_on_floor:
            grounded |= on_floor
        if np.count_nonzero(grounded):  # (faster than .any() on tiny masks)
            s.u, s.on_floor = u, on_floor
            s._floor_impact(s._worlds(grounded), hit_floor)
            u, on_floor = s.u, s.on_floor
        return q, v, u, on_floor, hit_floor, numpy_small.quat_to_rotmat(q[..., 3:7])

    def wall_gate(self, pos: np.ndarray, at_wall: np.ndarray, at_ceiling: np.ndarray) -> Any:
        """The worlds with a quad at or beyond a wall or the ceiling (one compare of all three axes) or
        flagged there at the last step (None: none)."""
        out = (pos <= self.s._out_lo) | (pos >= self.s._out_hi)
        if not (out.any() or at_wall.any() or at_ceiling.any()):
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
        s, noise = self.s, self.s.cfg.noise
        if kind == "motor":  # the step's motor-noise normals (B, N, 4)
            return s.rng.standard_normal((s.B, s.N, 4))
        if kind == "scenario":  # the scenario's uniforms (B, n)
            return s.rng.uniform(size=(s.B, s._n_scn))
        if kind == "sensor":  # = NumpySampler(rng).draw(sensor_noise_spec(cfg), (B,)): 0 + std * N(0, 1)
            if not s._sensor_on:
                return None
            return dict(zip(s._sensor_keys, 0.0 + s._sensor_std * s.rng.standard_normal((3, s.B, s.N, 3))))
        if kind == "deck":  # deck sensor noise (quadswarm_mj.sensors), None: noise-free
            if not (s.cfg.sensors.any and s.cfg.sensors.noise):
                return None
            from quadswarm_mj.random_draws import NumpySampler
            from quadswarm_mj.sensors import deck_draw_spec

            return NumpySampler(s.rng).draw(deck_draw_spec(s.cfg), (s.B,))
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

    def quad_quad(self, pos: Any, vel: Any, omega: Any, prev: Any, contact: Any, new: Any) -> dict[str, Any] | None:
        """The paper's response on the worlds with a new contact (None: there is none)."""
        if not new.any():
            return None
        s = self.s
        w = s._worlds(new.any(-1))
        draws = s._sampler(s.cfg.noise.stochastic_collisions).draw(s._spec_quad, (s._count(w),))
        q = quad_collisions(pos[w], vel[w], omega[w], prev[w], s.cfg.hitbox, draws)
        return {"vel": put(vel, w, q["vel"]), "omega": put(omega, w, q["omega"]), "contact": contact,
                "new_contact": new}

    def obstacles(self, pos: Any, vel: Any, omega: Any) -> dict[str, Any]:
        vel, omega = vel.copy(), omega.copy()  # the engine's stage writes them in place
        new, changed = self.s._obstacle_stage(pos, vel, omega)
        return {"vel": vel, "omega": omega, "obst_new": new, "obst_feats": self.s._obst_feats, "changed": changed}


class AlwaysOn:
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


class JaxOps(AlwaysOn):
    """Always-on stages with the step's budgeted draws ``rnd`` (one world, ``jax.numpy``)."""

    wrench = staticmethod(actuation.substep_wrench)
    rotmat = staticmethod(spatial.quat_to_rotmat)

    def __init__(self, cfg: Any, rnd: dict[str, Any], dtype: Any, obstacle_stage: Any = None) -> None:
        import jax.numpy as jnp

        self.cfg, self.rnd, self.jnp, self.dtype = cfg, rnd, jnp, dtype
        self.room = (jnp.asarray(cfg.room_low, dtype), jnp.asarray(cfg.room_high, dtype))
        self._obstacle_stage = obstacle_stage

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
        return quad_collisions_budgeted(pos, vel, omega, prev, self.cfg.hitbox, sub(self.rnd, "quad"))

    def obstacles(self, pos: Any, vel: Any, omega: Any) -> dict[str, Any]:
        return self._obstacle_stage(pos, vel, omega)
