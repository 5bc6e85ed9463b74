"""The exact free-body step (:func:`quadswarm_mj.freebody.freebody_step`, MuJoCo's Euler step of
contact-free free bodies) as the ``physics`` of :func:`quadswarm_mj.core.substeps.substep_loop`, for
NumPy or ``jax.numpy`` arrays (the JAX engine's ``physics="freebody"``)."""

from __future__ import annotations

from typing import Any

from quadswarm_mj._xp import array_namespace
from quadswarm_mj.freebody import freebody_step


class WorldLocal:
    """Kinematics of a back end whose state has no world offsets (one world, or world-local storage)."""

    @staticmethod
    def local_pos(q: Any) -> Any:
        """Positions (m, world-local) of ``q`` (..., N, 7)."""
        return q[..., :3]

    @staticmethod
    def velocities(v: Any) -> tuple[Any, Any]:
        """(vel m/s world, omega rad/s body) of ``v`` (..., N, 6)."""
        return v[..., :3], v[..., 3:]


class FreeBodyPhysics(WorldLocal):
    """Free bodies of ``mass`` (..., N) kg and principal ``inertia`` (..., N, 3) kg m^2 under ``gravity``
    (3,) m/s^2 world, one step of ``dt`` s, angular velocity clipped to +-``max_omega`` rad/s per body
    axis; ``ipos``/``iquat``: the inertial frame in the body frame (None: the body frame, the Crazyflie).
    Positions are world-local (no offsets); the state is functional (new arrays)."""

    def __init__(self, mass: Any, inertia: Any, gravity: Any, dt: float, max_omega: float, ipos: Any = None,
                 iquat: Any = None) -> None:
        self.mass, self.inertia, self.gravity, self.dt = mass, inertia, gravity, dt
        self.max_omega, self.ipos, self.iquat = max_omega, ipos, iquat

    def substep(self, q: Any, v: Any, force: Any, torque: Any, aux: Any) -> tuple[Any, Any, Any]:
        xp = array_namespace(q, force)
        q, v = freebody_step(q, v, xp.concatenate([force, torque], -1), self.mass, self.inertia, self.ipos,
                             self.iquat, self.gravity, self.dt, max_omega=self.max_omega)
        return q, v, aux
