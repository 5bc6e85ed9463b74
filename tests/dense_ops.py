"""Engine ops with every draw given dense (for every quad), in NumPy or ``jax.numpy``: the tests' plain
reference beside :class:`~quadswarm_mj.core.ops.NumpyOps` (per-event draws from a ``Generator``) and
:class:`~quadswarm_mj.core.ops.JaxOps` (budgeted slots). Every stage runs on every quad, so the same
inputs give the same step in either namespace (``tests/test_numpy_jax_step.py``)."""

from __future__ import annotations

from typing import Any

from quadswarm_mj import actuation, collisions, pipeline, spatial
from quadswarm_mj.core.ops import AlwaysOn


class DenseOps(AlwaysOn):
    """The ops of :mod:`quadswarm_mj.core.control` with the step's draws ``d`` given dense: ``motor``
    (..., N, 4) normals, ``yaw`` (substeps, ..., N) landing yaw draws (rad), ``wall``, ``quad``, ``obst``,
    ``down`` (the draw specs' dicts at (...,) worlds); for the task step ``scenario`` (..., n) uniforms
    and optionally ``sensor``/``deck`` (the noise specs' dicts; absent: noise-free). ``yaw_cs``: the
    floor impact's trig-free path (cos, sin of the yaw draws; the JAX engine's) instead of the angle path
    (the MuJoCo engine's).
    With obstacles: ``omap`` (:class:`~quadswarm_mj.obstacles.ObstacleMap`) and the last step's column
    contacts ``obst_contact`` (..., N)."""

    wrench = staticmethod(actuation.substep_wrench)
    rotmat = staticmethod(spatial.quat_to_rotmat)

    def __init__(self, cfg: Any, d: dict[str, Any], xp: Any, yaw_cs: bool = False, omap: Any = None,
                 obst_contact: Any = None, dtype: Any = None) -> None:
        self.cfg, self.d, self.xp, self.yaw_cs = cfg, d, xp, yaw_cs
        self.omap, self.obst_contact = omap, obst_contact
        self.dtype = xp.float64 if dtype is None else dtype
        self.room = (xp.asarray(cfg.room_low, dtype=self.dtype), xp.asarray(cfg.room_high, dtype=self.dtype))

    def terms(self, terms: dict[str, Any]) -> dict[str, Any]:
        """The reward terms in ``dtype``."""
        return {k: self.xp.asarray(v, dtype=self.dtype) for k, v in terms.items()}

    @staticmethod
    def floor_wrench(cfg: Any, on_floor: Any, force: Any, torque: Any, v: Any, params: dict[str, Any]) -> tuple:
        return collisions.floor_wrench(on_floor, force, torque, v[..., :3], params["mass"], params["gravity"],
                                       cfg.collision.floor_friction, cfg.sim_dt)

    def _yaw(self, i: int) -> dict[str, Any]:
        yaw = self.d["yaw"][i]
        return {"yaw_draw_cs": (self.xp.cos(yaw), self.xp.sin(yaw))} if self.yaw_cs else {"yaw_draw": yaw}

    def floor_impact(self, cfg: Any, i: int, q: Any, v: Any, u: Any, on_floor: Any, hit_floor: Any) -> tuple:
        xp, y, quat = self.xp, self._yaw(i), q[..., 3:7]
        r = collisions.floor_impact(q[..., :3], v[..., :3], v[..., 3:], quat, spatial.quat_to_rotmat(quat), u, on_floor,
                                    cfg.quad.arm, y.get("yaw_draw"), yaw_draw_cs=y.get("yaw_draw_cs"))
        q = xp.concatenate([r["pos"], r["quat"]], -1)
        v = xp.concatenate([r["vel"], r["omega"]], -1)
        return q, v, r["u"], r["on_floor"], hit_floor | r["hit_floor"], r["R"]

    def zeros_like(self, a: Any) -> Any:
        return self.xp.zeros(a.shape, dtype=bool)

    def draws(self, kind: str, mask_fn: Any, w: Any) -> Any:
        if kind == "yaw":  # the room guard's landings: the last sub-step's draws
            return self._yaw(-1)
        if kind in ("sensor", "deck"):  # None: noise-free
            return self.d.get(kind)
        return self.d[kind]

    def quad_quad(self, pos: Any, vel: Any, omega: Any, prev: Any, contact: Any, new: Any) -> dict[str, Any]:
        return collisions.quad_collisions(pos, vel, omega, prev, self.cfg.hitbox, self.d["quad"])

    def obstacles(self, pos: Any, vel: Any, omega: Any) -> dict[str, Any]:
        cfg = self.cfg
        r = pipeline.obstacle_stage(pos, vel, omega, self.obst_contact, self.omap, cfg.quad.arm, self.d["obst"],
                                    cfg.collision_model == "paper")
        return {"vel": r["vel"], "omega": r["omega"], "obst_new": r["new_contact"], "obst_contact": r["contact"],
                "changed": True}
