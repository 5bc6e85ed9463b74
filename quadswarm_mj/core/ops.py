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

Both offer ``room`` (room_low, room_high), ``gate(mask_fn)``, ``wall_gate``, ``put(arr, w, value)``,
``zeros_like``, ``draws(kind, mask_fn, w)`` (kind: "wall", "yaw", "down"), ``quad_quad`` and
``obstacles``; ``mask_fn`` is called only where the engine needs the mask.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from quadswarm_mj.collisions import expand_per_quad, quad_collisions, quad_collisions_budgeted

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

    def __init__(self, swarm: Any) -> None:
        self.s = swarm
        self.room = (swarm.room_low, swarm.room_high)

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


class JaxOps:
    """Always-on stages with the step's budgeted draws ``rnd`` (one world, ``jax.numpy``)."""

    def __init__(self, cfg: Any, rnd: dict[str, Any], dtype: Any, obstacle_stage: Any = None) -> None:
        import jax.numpy as jnp

        self.cfg, self.rnd, self.jnp = cfg, rnd, jnp
        self.room = (jnp.asarray(cfg.room_low, dtype), jnp.asarray(cfg.room_high, dtype))
        self._obstacle_stage = obstacle_stage

    @staticmethod
    def gate(mask_fn: Any) -> Any:
        return ALL

    @staticmethod
    def wall_gate(pos: Any, at_wall: Any, at_ceiling: Any) -> Any:
        return ALL

    def zeros_like(self, a: Any) -> Any:
        return self.jnp.zeros_like(a)

    @staticmethod
    def put(arr: Any, w: Any, value: Any) -> Any:
        return value

    def draws(self, kind: str, mask_fn: Any, w: Any) -> dict[str, Any]:
        jnp, rnd = self.jnp, self.rnd
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
