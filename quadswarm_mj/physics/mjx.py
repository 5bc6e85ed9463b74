"""The JAX engine's rigid-body integrators on ``mjx.Data``: the exact free-body step
(:func:`quadswarm_mj.freebody.freebody_step`, no contacts) or ``mjx.step`` (MJX's contact solver), one
physics sub-step each, plus reading and writing the quads' free joints and the per-world model fields
(drawn mass and inertia, column radius) that reach ``mjx.step`` through ``model.replace``."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from mujoco import mjx

from quadswarm_mj.physics.freebody import WorldLocal


class MjxPhysics:
    """The quads' rows of an MJX model of one world (``arena``: :func:`quadswarm_mj.arena.build_arena`
    with 1 world; ``model``: its ``mjx.put_model``); ``obstacle_response``: the paper's model resolves
    the columns (else MuJoCo's contacts do, with each world's drawn radius)."""

    def __init__(self, arena: Any, model: mjx.Model, num_quads: int, obstacle_response: bool) -> None:
        n = num_quads
        self.arena, self.model, self.n, self.obstacle_response = arena, model, n, obstacle_response
        self.qs, self.vs, self.fb = arena.qpos_start, arena.qvel_start, arena.first_body
        # the quads' free joints are the whole qpos/qvel: read and write them with reshapes, no scatter
        self.whole = self.qs == 0 and self.vs == 0 and arena.model.nq == 7 * n and arena.model.nv == 6 * n

    def read(self, data: mjx.Data) -> tuple[jax.Array, jax.Array]:
        """The quads' free joints: qpos (N, 7) (pos m world, quat wxyz body->world), qvel (N, 6)
        (linear m/s world, angular rad/s body)."""
        n = self.n
        if self.whole:
            return data.qpos.reshape(n, 7), data.qvel.reshape(n, 6)
        return (data.qpos[self.qs:self.qs + 7 * n].reshape(n, 7), data.qvel[self.vs:self.vs + 6 * n].reshape(n, 6))

    def write(self, data: mjx.Data, q: jax.Array, v: jax.Array) -> mjx.Data:
        """``data`` with the quads' qpos (N, 7) and qvel (N, 6) replaced."""
        n = self.n
        q, v = q.astype(data.qpos.dtype), v.astype(data.qvel.dtype)
        if self.whole:
            return data.replace(qpos=q.reshape(-1), qvel=v.reshape(-1))
        return data.replace(qpos=data.qpos.at[self.qs:self.qs + 7 * n].set(q.ravel()),
                            qvel=data.qvel.at[self.vs:self.vs + 6 * n].set(v.ravel()))

    def model_with(self, params: dict[str, Any], obstacle_radius: Any = None) -> mjx.Model:
        """The MJX model with this world's drawn mass and inertia in the quad rows and, with MuJoCo
        contacts on the columns, this world's column radius (m; drawn per reset with ``size_random``)
        in the column geoms (the pool is built with the largest radius)."""
        m, sl = self.model, slice(self.fb, self.fb + self.n)
        m = m.replace(body_mass=m.body_mass.at[sl].set(params["mass"].astype(m.body_mass.dtype)),
                      body_inertia=m.body_inertia.at[sl].set(params["inertia"].astype(m.body_inertia.dtype)))
        if obstacle_radius is not None and not self.obstacle_response:
            ids = jnp.asarray(self.arena.obstacle_geom_ids[0])
            m = m.replace(geom_size=m.geom_size.at[ids, 0].set(jnp.asarray(obstacle_radius, m.geom_size.dtype)))
        return m

    def integrator(self, physics: str, params: dict[str, Any], obstacle_radius: Any = None) -> Any:
        """The rigid-body stage: ``integrate(q (N, 7), v (N, 6), wrench (N, 6) world force N and torque
        N m at the CoM, aux) -> (q, v, aux)``, one physics sub-step of ``cfg.sim_dt`` (``aux``: the
        ``mjx.Data`` carried through the sub-steps by "mjx", None for "freebody")."""
        n, fb = self.n, self.fb
        if physics == "freebody":
            from quadswarm_mj.freebody import freebody_constants, freebody_step

            c = freebody_constants(self.arena.model, self.arena)  # checks the model's assumptions
            dt = c.dt

            def integrate_fb(q: Any, v: Any, wrench: Any, aux: Any) -> tuple[Any, Any, Any]:
                q2, v2 = freebody_step(q, v, wrench, params["mass"], params["inertia"], c.ipos, c.iquat,
                                       c.gravity, dt)
                return q2, v2, aux

            return integrate_fb
        model = self.model_with(params, obstacle_radius)

        def integrate_mjx(q: Any, v: Any, wrench: Any, data: Any) -> tuple[Any, Any, Any]:
            data = self.write(data, q, v)
            xfrc = data.xfrc_applied.at[fb:fb + n].set(wrench.astype(data.xfrc_applied.dtype))
            data = mjx.step(model, data.replace(xfrc_applied=xfrc))
            q2, v2 = self.read(data)
            return q2.astype(q.dtype), v2.astype(v.dtype), data

        return integrate_mjx

    def substep_physics(self, physics: str, params: dict[str, Any], max_omega: float,
                        obstacle_radius: Any = None) -> Any:
        """The ``physics`` of :func:`quadswarm_mj.core.substeps.substep_loop`: :class:`~quadswarm_mj.physics.
        freebody.FreeBodyPhysics` for "freebody", :class:`JaxSubstep` around ``mjx.step`` for "mjx"."""
        if physics == "freebody":
            from quadswarm_mj.freebody import freebody_constants
            from quadswarm_mj.physics.freebody import FreeBodyPhysics

            c = freebody_constants(self.arena.model, self.arena)
            return FreeBodyPhysics(params["mass"], params["inertia"], c.gravity, c.dt, max_omega, c.ipos, c.iquat)
        return JaxSubstep(self.integrator(physics, params, obstacle_radius), max_omega)


class JaxSubstep(WorldLocal):
    """The sub-step interface of :func:`quadswarm_mj.core.substeps.substep_loop` around an integrator
    ``integrate(q, v, wrench, aux) -> (q, v, aux)`` (:meth:`MjxPhysics.integrator`), with the angular
    velocity clipped to +-``max_omega`` (rad/s) per body axis after it. Positions are world-local."""

    def __init__(self, integrate: Any, max_omega: float) -> None:
        self.integrate, self.max_omega = integrate, max_omega

    def substep(self, q: Any, v: Any, force: Any, torque: Any, aux: Any) -> tuple[Any, Any, Any]:
        q, v, aux = self.integrate(q, v, jnp.concatenate([force, torque], axis=-1), aux)
        w = self.max_omega
        return q, jnp.concatenate([v[..., :3], jnp.clip(v[..., 3:], -w, w)], -1), aux
