"""The CPU engine's sub-step loop for one world of several quads, on preallocated work arrays.

:class:`quadswarm_mj.perf.numpy_loop.SmallLoop` runs the paper's sub-step (rotor wrench, floor normal
force and friction, ``mj_step``, floor landing, rotation of the new pose) in whole-array NumPy calls on
(B, N, .) arrays; on one world of a few quads NumPy's fixed cost per call and per view dominates (about
60 calls and as many views a sub-step). :class:`SwarmLoop` runs the same expressions in the same order
(the same bits, signs of zero included; ``tests/test_numpy_swarm.py`` checks seeded episodes against
``SmallLoop`` and the per-sub-step ops) on (N, .) work arrays allocated once per env, with every view
of them and of MuJoCo's ``qpos``/``qvel``/``xfrc_applied`` made once, results written with ``out=``
(the rotor wrench straight into ``xfrc_applied``) and the floor models' scratch rows reused. Used for
one world (B = 1, offsets zero) with the paper's chain and floor. NumPy only.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from quadswarm_mj.collisions import off_diagonal
from quadswarm_mj.constants import FLOOR_TOL
from quadswarm_mj.perf.numpy_small import (
    _Q_BASE,
    _Q_SCALE,
    _QPOS_A,
    _QPOS_B,
    _QPOS_YAW_1,
    _QPOS_YAW_2,
    _YAW_BASE,
    _YAW_SCALE,
)
from quadswarm_mj.spatial import BIG

#: set to False for ``perf.numpy_loop.SmallLoop`` (the same-values tests compare the two)
ENABLED = True


class _Views:
    """Views of the physics' (1, N, .) ``qpos``/``qvel``/``xfrc`` as (N, .) rows, made once per array."""

    def __init__(self, qpos: np.ndarray, qvel: np.ndarray, xfrc: np.ndarray) -> None:
        self.src = (qpos, qvel, xfrc)
        q, v, x = qpos[0], qvel[0], xfrc[0]
        self.q, self.v = q, v
        self.z, self.qw, self.qxy, self.qz, self.qp = q[:, 2], q[:, 3], q[:, 4:6], q[:, 6], q[:, :3]
        self.v_h, self.v_stay = v[:, :2], v[:, 2:5]
        self.force, self.torque, self.f_h, self.f_z, self.t_xy = x[:, :3], x[:, 3:], x[:, :2], x[:, 2], x[:, 3:5]


class SwarmLoop:
    """``fused_loop`` of :func:`quadswarm_mj.core.substeps.substep_loop` for a one-world
    :class:`~quadswarm_mj.envs.cpu_core.CpuSwarm` ``swarm`` of N quads (its physics, generator and floor mirror)."""

    def __init__(self, swarm: Any) -> None:
        cfg, n = swarm.cfg, swarm.N
        self.s = swarm
        self.friction, self.dt, self.max_omega = cfg.collision.floor_friction, cfg.sim_dt, cfg.quad.max_omega
        self.floor_z = swarm.floor_z
        self.floor_top = swarm.floor_z + FLOOR_TOL
        d = swarm._spec_floor["yaw"]
        self.yaw = (d.low, d.high) if cfg.noise.stochastic_collisions else None
        self.yaw_mean = d.mean
        self.n = n
        # the velocity stages' event-free form applies to the paper's walls without obstacles or downwash
        self.stages_apply = cfg.obstacles is None and not cfg.downwash and 3 * n * n < BIG
        self.out_lo, self.out_hi, self.hitbox = swarm._out_lo, swarm._out_hi, cfg.hitbox
        self.offdiag = off_diagonal(n)
        self._alloc()

    def _alloc(self) -> None:
        """The work rows and their views (made again in a copy: a deep copy does not keep views)."""
        n = self.n
        self._v: _Views | None = None
        # work rows (N, .), reused every sub-step (nothing in them outlives a control step)
        self.rows = np.empty((n, 4, 4))  # thrust x mix rows (F_z, tau_x, tau_y) and yaw reaction per rotor
        self.rows3, self.rows_spin = self.rows[:, :3, :], self.rows[:, 3, :]
        self.tf = np.empty((n, 4))  # thrust_max * f
        self.tf_row = self.tf[:, None, :]
        self.sm = np.empty((n, 4))  # F_z, tau_x, tau_y, tau_z (body)
        self.sm_fz, self.sm_tau = self.sm[:, :1], self.sm[:, None, 1:]
        self.rt = np.empty((n, 3, 3))  # R * tau
        self.R = np.empty((n, 3, 3))
        self.R9 = self.R.reshape(n, 9)
        self.R_z = self.R[:, :, 2]
        self.d4 = np.empty((n, 4))  # motor lag step
        # the floor wrench's rows: h = (F_x, F_y, v_x, v_y), their squares, (|F_h|, speed), ...
        self.h = np.empty((n, 4))
        self.h_f, self.h_v = self.h[:, :2], self.h[:, 2:]
        self.sq = np.empty((n, 4))
        self.sq_a, self.sq_b = self.sq[:, 0::2], self.sq[:, 1::2]
        self.mags = np.empty((n, 2))
        self.mag_f, self.mag_v = self.mags[:, 0], self.mags[:, 1]
        self.num = np.empty((n, 2))
        self.num_s, self.num_k = self.num[:, 0], self.num[:, 1]
        self.ratio = np.empty((n, 2))
        self.ratio_s, self.ratio_k = self.ratio[:, :1], self.ratio[:, 1:]
        self.den = np.empty((n, 2))
        self.pos_ = np.empty((n, 2), bool)
        self.pos_k = self.pos_[:, 1:]
        self.normal, self.cap, self.tmp = np.empty(n), np.empty(n), np.empty(n)
        self.fh2, self.kv = np.empty((n, 2)), np.empty((n, 2))
        self.fcopy = np.empty((n, 3))
        self.fcopy_h, self.fcopy_z = self.fcopy[:, :2], self.fcopy[:, 2]
        # the landing's rows
        self.le, self.stay_le = np.empty(n, bool), np.empty(n, bool)
        self.p6 = np.empty((n, 6))
        self.p6_a, self.p6_b = self.p6[:, :3], self.p6[:, 3:]
        self.e = np.empty((n, 3))
        self.e0, self.e1, self.e2 = self.e[:, 0], self.e[:, 1], self.e[:, 2]
        self.t18 = np.empty((n, 18))
        self.t18_a, self.t18_b = self.t18[:, :9], self.t18[:, 9:]

    _KEEP = ("s", "friction", "dt", "max_omega", "floor_z", "floor_top", "yaw", "yaw_mean", "n", "stages_apply",
             "out_lo", "out_hi", "hitbox", "offdiag")

    def __getstate__(self) -> dict[str, Any]:
        """For copy/pickle: the settings only (the work rows and views are made again)."""
        return {k: self.__dict__[k] for k in self._KEEP}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._alloc()

    def _views(self) -> _Views:
        p, v = self.s.phys, self._v
        if v is None or v.src[0] is not p.qpos or v.src[1] is not p.qvel or v.src[2] is not p.xfrc:
            v = self._v = _Views(p.qpos, p.qvel, p.xfrc)
        return v

    def rotmat(self) -> None:
        """``self.R`` = ``perf.numpy_small.quat_to_rotmat_qpos`` of the physics' qpos (same bits)."""
        q, t = self._v.q, self.t18
        np.multiply(q.take(_QPOS_A, axis=-1), q.take(_QPOS_B, axis=-1), out=t)
        t *= _Q_SCALE
        np.add(self.t18_a, self.t18_b, out=self.R9)
        self.R9 += _Q_BASE  # base + (a + b): the same sum

    def __call__(self, cfg: Any, carry: dict[str, Any], inp: dict[str, Any], consts: dict[str, Any],
                 ops: Any) -> dict[str, Any]:
        """``cfg.substeps`` sub-steps from ``carry`` (as ``substep_loop``: ``q``/``v`` the physics' qpos/qvel;
        ``hit_floor`` all False); returns the carry after the last one."""
        s, phys, V = self.s, self.s.phys, self._views()
        n = self.n
        params, cmd = inp["params"], inp["cmd"][0]
        # constant over the control step (as SmallLoop): sqrt(cmd), alpha, cmd * noise, mass * gravity
        root, alpha, cn = np.sqrt(cmd), params["alpha"][0][:, None], cmd * inp["eps"][0]
        thrust_max, spin, mix = params["thrust_max"][0], consts["torque_spin"][0], consts["mix"]
        gravity = params["gravity"]
        mass = params["mass"][0]
        weight = params["mass"][0] * gravity
        on_floor = carry["on_floor"][0]
        hit_floor = carry["hit_floor"]
        hit_row = hit_floor[0]
        self.R[...] = carry["R"][0]
        u = carry["u"][0]
        f = np.empty((n, 4))
        R, rows, tf, sm, rt, d4 = self.R, self.rows, self.tf, self.sm, self.rt, self.d4
        fric, dt = self.friction, self.dt
        for i in range(cfg.substeps):
            # the rotor wrench (numpy_loop.substep_wrench), written into xfrc_applied
            np.subtract(root, u, out=d4)
            d4 *= alpha
            u = u + d4 if i == 0 else np.add(u, d4, out=u)  # a fresh u for this step, then in place
            np.multiply(u, u, out=f)
            f += cn
            np.maximum(f, 0.0, out=f)
            np.minimum(f, 1.0, out=f)
            np.multiply(thrust_max, f, out=tf)
            np.multiply(self.tf_row, mix, out=self.rows3)
            np.multiply(spin, f, out=self.rows_spin)
            np.add.reduce(rows, axis=-1, out=sm)
            np.multiply(self.sm_fz, self.R_z, out=V.force)
            np.multiply(R, self.sm_tau, out=rt)
            np.add.reduce(rt, axis=-1, out=V.torque)
            if s._any_on_floor:  # the floor's normal force and friction (numpy_floor.floor_wrench_inplace)
                self._floor_wrench(V, on_floor, mass, weight, fric, dt)
            phys.step(self.max_omega)
            on_floor = self._landing(V, u, on_floor, hit_row)
            self.rotmat()
        return {"q": phys.qpos, "v": phys.qvel, "R": R.copy().reshape(1, n, 3, 3), "u": u.reshape(1, n, 4),
                "f_norm": f.reshape(1, n, 4), "on_floor": on_floor.reshape(1, n), "hit_floor": hit_floor,
                "aux": carry["aux"], "ctrl": carry["ctrl"]}

    def _floor_wrench(self, V: _Views, on_floor: np.ndarray, mass: np.ndarray, weight: np.ndarray, friction: float,
                      dt: float) -> None:
        """``numpy_floor.floor_wrench_inplace`` on xfrc_applied's rows (the same expressions and order)."""
        every = np.count_nonzero(on_floor) == self.n
        if every:
            f_h, f_z = V.f_h, V.f_z
        else:
            np.copyto(self.fcopy, V.force)
            f_h, f_z = self.fcopy_h, self.fcopy_z
        h, sq, mags, num, normal, cap = self.h, self.sq, self.mags, self.num, self.normal, self.cap
        self.h_f[...] = f_h
        self.h_v[...] = V.v_h
        np.multiply(h, h, out=sq)
        np.add(self.sq_a, self.sq_b, out=mags)
        np.sqrt(mags, out=mags)
        np.subtract(weight, f_z, out=normal)
        np.maximum(0.0, normal, out=normal)
        np.multiply(friction, normal, out=cap)
        np.subtract(self.mag_f, cap, out=self.tmp)
        np.maximum(0.0, self.tmp, out=self.num_s)
        np.multiply(mass, self.mag_v, out=self.tmp)
        self.tmp /= dt
        np.minimum(cap, self.tmp, out=self.num_k)
        positive = self.pos_
        np.greater(mags, _THRESH, out=positive)
        np.copyto(self.den, 1.0)
        np.copyto(self.den, mags, where=positive)
        np.divide(num, self.den, out=self.ratio)
        np.multiply(self.h_f, self.ratio_s, out=f_h)  # static friction
        np.multiply(self.ratio_k, self.h_v, out=self.kv)
        np.subtract(self.h_f, self.kv, out=f_h, where=self.pos_k)  # kinetic
        f_z += normal
        if every:
            V.t_xy[...] = 0.0
        else:
            mask = on_floor[:, None]
            np.copyto(V.force, self.fcopy, where=mask)
            np.copyto(V.t_xy, 0.0, where=mask)

    def _landing(self, V: _Views, u: np.ndarray, on_floor: np.ndarray, hit_row: np.ndarray) -> np.ndarray:
        """``numpy_loop.SmallLoop.floor_impact`` of the one world (``numpy_floor.floor_impact_rows``, offsets
        zero): written into qpos/qvel, ``u`` and ``hit_row`` in place; returns the new on_floor (N,)."""
        s = self.s
        le = self.le
        np.less_equal(V.z, self.floor_z, out=le)
        grounded = le | on_floor if s._any_on_floor else le
        if not np.count_nonzero(grounded):
            return on_floor
        n = self.n
        yaw_draw = s.rng.uniform(*self.yaw, size=(1, n))[0] if self.yaw is not None else np.full(n, self.yaw_mean)
        hit = le > on_floor  # at or below the floor and airborne
        np.less_equal(V.z, self.floor_top, out=self.stay_le)
        staying = on_floor & self.stay_le
        grounded = hit | staying
        any_hit = np.count_nonzero(hit) > 0
        q, v = V.q, V.v
        p = self.p6  # numpy_small.yaw_entries_qpos: R10, R00, R22 of the old rotation
        np.multiply(q.take(_QPOS_YAW_1, axis=-1), q.take(_QPOS_YAW_2, axis=-1), out=p)
        p *= _YAW_SCALE
        e = self.e
        np.add(self.p6_a, self.p6_b, out=e)
        e += _YAW_BASE
        yaw = np.arctan2(self.e0, self.e1)
        yaw += np.where(hit & (self.e2 < 0), yaw_draw, 0.0) if any_hit else 0.0
        half = 0.5 * yaw
        np.cos(half, out=V.qw, where=grounded)
        np.copyto(V.qxy, 0.0, where=grounded[:, None])
        np.sin(half, out=V.qz, where=grounded)
        np.copyto(V.z, self.floor_z, where=grounded)
        V.qp += 0.0  # (p - 0.0) + 0.0 of the frame round trip
        if any_hit:  # a hit zeroes vel and omega, and the motors (0.0 * x: signs kept)
            np.multiply(v, 0.0, out=v, where=hit[:, None])
            np.multiply(u, 0.0, out=u, where=hit[:, None])
            hit_row |= hit
        np.copyto(V.v_stay, 0.0, where=staying[:, None])
        s.phys.touch()
        s._any_on_floor = np.count_nonzero(grounded) > 0
        return grounded


    def stages(self, cfg: Any, kin: dict[str, Any], prev: dict[str, Any]) -> dict[str, Any] | None:
        """:func:`quadswarm_mj.core.step.velocity_stages` (paper model, no obstacles, no downwash) when no quad is
        at or beyond a wall or the ceiling (now or at the last step) and no contact starts: the same flags and
        pair distances (``NumpyOps.wall_gate``'s compares, ``collisions.pairwise_contacts``' expressions); None
        otherwise (the caller runs ``velocity_stages``, which makes the events' draws)."""
        if not self.stages_apply or cfg is not self.s.cfg:
            return None
        pos, at_wall, at_ceiling = kin["pos"], prev["at_wall"], prev["at_ceiling"]
        out = (pos <= self.out_lo) | (pos >= self.out_hi)
        if np.count_nonzero(out) or np.count_nonzero(at_wall) or np.count_nonzero(at_ceiling):
            return None
        rel = pos[..., :, None, :] - pos[..., None, :, :]
        dist = np.sqrt((rel * rel).sum(axis=-1))  # spatial.norm_last below spatial.BIG elements
        contact = (dist <= self.hitbox) & self.offdiag
        new = contact & ~prev["contact"]
        if np.count_nonzero(new):  # a new contact: the paper's response (and its draws)
            return None
        hit = np.zeros(at_wall.shape, bool)
        return {**kin, "at_wall": at_wall, "at_ceiling": at_ceiling, "hit_wall": hit, "hit_ceiling": hit,
                "contact": contact, "new_contact": new, "dist": dist, "changed": False}


# thresholds of (|F_h|, |v_h|) (numpy_floor): the static ratio divides by |F_h| where > 0, the kinetic by the speed
_THRESH = np.array([0.0, 1e-9])
