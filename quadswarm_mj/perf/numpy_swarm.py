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

from types import SimpleNamespace
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
        # flat views (MuJoCo's arrays are contiguous): the sources of the flat gathers
        self.qf, self.vf, self.xf = q.reshape(-1), v.reshape(-1), x.reshape(-1)
        self.z2, self.zq, self.qp = q[:, 2:3], q[:, 2:7], q[:, :3]
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
        rows = np.empty((n, 4, 4))  # thrust x mix rows (F_z, tau_x, tau_y) and yaw reaction per rotor
        sm = np.empty((n, 4))  # F_z, tau_x, tau_y, tau_z (body)
        self.R = np.empty((n, 3, 3))
        self.R9 = self.R.reshape(n, 9)
        mix4 = np.ones((4, 4))  # the mix rows (F_z, tau_x, tau_y) and 1.0 for the yaw reaction (set per call)
        self._ts_src: tuple | None = None
        self._wrench_rows = (rows, np.empty((n, 4, 4)), mix4, sm, sm[:, :1], sm[:, None, 1:], np.empty((n, 3, 3)),
                             self.R[:, :, 2], np.empty((n, 4)))
        # the floor wrench's rows, component-major (., N): G = (v_x, v_y, F_x, F_y, F_z, tau_x, tau_y) gathered,
        # W = (F_x, F_y, F_z, tau_x, tau_y) written (tau rows stay 0.0)
        G, W = np.empty((7, n)), np.zeros((5, n))
        sq, mags, num, den, kv = np.empty((4, n)), np.empty((2, n)), np.empty((2, n)), np.empty((2, n)), \
            np.empty((2, n))
        self._floor_rows = (G, G[:2], G[2:], G[:4], G[2:4], G[4], sq, sq[0::2], sq[1::2], mags, mags[0], mags[1],
                            num, num[0], num[1], den, np.empty((2, n), bool), kv, np.empty(n), np.empty(n),
                            np.empty(n), W, W[:2], W[2], np.empty((5, n)))
        # the landing's rows: one flat gather of qpos (z twice, the yaw entries' two factors, entry-major) into g
        g = np.empty(14 * n)
        le16, p, e = np.empty(2 * n, bool), np.empty(6 * n), np.empty(3 * n)
        q5 = np.zeros((n, 5))  # (floor_z, cos h, 0, 0, sin h)
        q5[:, 0] = self.floor_z
        self._landing_rows = (g, g[:2 * n], g[2 * n:8 * n], g[8 * n:], le16, le16[:n], le16[n:], p, p[:3 * n],
                              p[3 * n:], e, e[:n], e[n:2 * n], e[2 * n:], np.empty(n), np.empty(n), q5,
                              q5[:, 1], q5[:, 4], np.empty(n, bool), np.empty(n, bool))
        # rotation rows: the two factors of the 18 products per quad gathered as (2, 2, N, 9), product (2, N, 9)
        self.t36 = np.empty((2, 2, n, 9))
        self.t18 = np.empty((2, n, 9))
        self._k = _constants(n, self.floor_z, self.floor_top, self.friction, self.dt)

    _KEEP = ("s", "friction", "dt", "max_omega", "floor_z", "floor_top", "yaw", "yaw_mean", "n",
             "stages_apply", "out_lo", "out_hi", "hitbox", "offdiag")

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
        """``self.R`` = ``perf.numpy_small.quat_to_rotmat_qpos`` of the physics' qpos (same bits: the same
        products, scales and sums, on rows gathered in one flat take)."""
        t36, t = self.t36, self.t18
        self._v.qf.take(self._k.rot_idx, None, t36, "wrap")  # (valid indices: wrap is raise, without its checks)
        np.multiply(t36[0], t36[1], t)
        np.multiply(t, self._k.rot_scale, t)
        np.add(t[0], t[1], self.R9)
        np.add(self.R9, self._k.rot_base, self.R9)  # base + (a + b): the same sum

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
        R = self.R
        R[...] = carry["R"][0]
        u = carry["u"][0]
        f = np.empty((n, 4))
        ts, mix4 = self._wrench_rows[1:3]
        src = self._ts_src  # ts = (thrust_max x 3 rows, torque_spin) per quad, made again when they change
        if src is None or src[0] is not params["thrust_max"] or src[1] is not consts["torque_spin"] \
                or src[2] is not mix:
            ts[:, :3, :] = thrust_max[:, None, :]
            ts[:, 3, :] = spin
            mix4[:3] = mix
            self._ts_src = (params["thrust_max"], consts["torque_spin"], mix)
        f_row = f[:, None, :]
        force, torque, max_omega = V.force, V.torque, self.max_omega
        wrench = self._wrench
        for i in range(cfg.substeps):
            u = wrench(i, u, f, f_row, root, alpha, cn, force, torque)  # written into xfrc_applied
            if s._any_on_floor:  # the floor's normal force and friction (numpy_floor.floor_wrench_inplace)
                self._floor_wrench(V, on_floor, mass, weight)
            phys.step(max_omega)
            on_floor = self._landing(V, u, on_floor, hit_row)
            self.rotmat()
        return {"q": phys.qpos, "v": phys.qvel, "R": R.copy().reshape(1, n, 3, 3), "u": u.reshape(1, n, 4),
                "f_norm": f.reshape(1, n, 4), "on_floor": on_floor.reshape(1, n), "hit_floor": hit_floor,
                "aux": carry["aux"], "ctrl": carry["ctrl"]}

    def _wrench(self, i: int, u: np.ndarray, f: np.ndarray, f_row: np.ndarray, root: np.ndarray, alpha: np.ndarray,
                cn: np.ndarray, force: np.ndarray, torque: np.ndarray) -> np.ndarray:
        """Sub-step ``i``'s rotor wrench (``numpy_loop.substep_wrench``: motor lag, thrusts ``f`` written in place,
        force and torque written into xfrc_applied's ``force``/``torque`` rows); returns u (fresh at i = 0)."""
        rows, ts, mix4, sm, sm_fz, sm_tau, rt, R_z, d4 = self._wrench_rows
        mul, reduce = np.multiply, np.add.reduce
        np.subtract(root, u, d4)
        d4 *= alpha
        u = u + d4 if i == 0 else np.add(u, d4, u)  # a fresh u for this step, then in place
        mul(u, u, f)
        f += cn
        if _clip is not None:  # = min(max(f, 0), 1): u u + c n is never -0.0, so no sign of zero differs
            _clip(f, 0.0, 1.0, out=f)
        else:
            np.minimum(np.maximum(f, 0.0, out=f), 1.0, out=f)
        mul(ts, f_row, rows)  # (thrust_max f) mix for F_z, tau_x, tau_y; (spin f) 1.0 for tau_z
        rows *= mix4
        reduce(rows, -1, None, sm)
        mul(sm_fz, R_z, force)
        mul(self.R, sm_tau, rt)
        reduce(rt, -1, None, torque)
        return u

    def _floor_wrench(self, V: _Views, on_floor: np.ndarray, mass: np.ndarray, weight: np.ndarray) -> None:
        """``numpy_floor.floor_wrench_inplace`` on xfrc_applied's rows (the same expressions and order) on
        component-major rows gathered from qvel and xfrc_applied and put back in one call (grounded quads
        only); max(0, x) and min(a, x) as the clip ufunc (the same bits: no operand is -0.0 here)."""
        k = self._k
        G, G_v, G_x, h, h_f, f_z, sq, sq_a, sq_b, mags, speed, mag_f, num, num_k, num_s, den, positive, kv, \
            normal, cap, tmp, W, W_h, W_z, W_mixed = self._floor_rows
        V.vf.take(k.v_idx, None, G_v, "wrap")  # (v_x, v_y)
        V.xf.take(k.x_idx, None, G_x, "wrap")  # (F_x, F_y, F_z, tau_x, tau_y)
        np.multiply(h, h, sq)
        np.add(sq_a, sq_b, mags)
        np.sqrt(mags, mags)  # speed, |F_h| (sqrt(x x + y y) as norm_last)
        np.subtract(weight, f_z, normal)
        _clip(normal, k.zero, k.inf, normal)  # max(0, weight - F_z)
        np.multiply(k.friction, normal, cap)
        np.subtract(mag_f, cap, tmp)
        _clip(tmp, k.zero, k.inf, num_s)  # static: max(0, |F_h| - cap)
        np.multiply(mass, speed, tmp)
        np.divide(tmp, k.dt, tmp)
        _clip(cap, k.ninf, tmp, num_k)  # kinetic: min(cap, m speed / dt)
        np.greater(mags, k.thresh, positive)  # moving, |F_h| > 0
        _copyto(den, k.ones2)
        _copyto(den, mags, where=positive)
        np.divide(num, den, num)  # ratio (kinetic, static)
        np.multiply(h_f, num_s, W_h)  # static friction
        np.multiply(num_k, G_v, kv)
        np.subtract(h_f, kv, kv)
        _copyto(W_h, kv, where=positive[0])  # kinetic
        np.add(f_z, normal, W_z)
        if _count_nonzero(on_floor) != self.n:  # the other quads' rows as they are
            _copyto(W_mixed, G_x)
            _copyto(W_mixed, W, where=on_floor)
            W = W_mixed
        V.xf.put(k.x_idx, W)

    def _landing(self, V: _Views, u: np.ndarray, on_floor: np.ndarray, hit_row: np.ndarray) -> np.ndarray:
        """``numpy_loop.SmallLoop.floor_impact`` of the one world (``numpy_floor.floor_impact_rows``, offsets
        zero): written into qpos/qvel, ``u`` and ``hit_row`` in place; returns the new on_floor (N,). The same
        expressions on contiguous rows of one flat gather (``numpy_small.yaw_entries_qpos``' products, scales
        and sums)."""
        s, k = self.s, self._k
        g, z2, f1, f2, le16, le, stay_le, p, p_a, p_b, e, e0, e1, e2, yaw, half, q5, q5_cos, q5_sin, hit, \
            staying = self._landing_rows
        V.qf.take(k.land_idx, None, g, "wrap")
        np.less_equal(z2, k.z_bounds, le16)  # z <= floor_z, z <= floor_z + FLOOR_TOL
        if not s._any_on_floor and not _count_nonzero(le):  # (_any_on_floor mirrors on_floor.any())
            return on_floor
        yaw_draw = s.rng.uniform(*self.yaw, size=(1, self.n))[0] if self.yaw is not None else None
        np.greater(le, on_floor, hit)  # at or below the floor and airborne
        np.logical_and(on_floor, stay_le, staying)
        grounded = np.logical_or(hit, staying)
        any_hit = _count_nonzero(hit) > 0
        np.multiply(f1, f2, p)  # numpy_small.yaw_entries_qpos: R10, R00, R22 of the old rotation
        np.multiply(p, k.yaw_scale, p)
        np.add(p_a, p_b, e)
        np.add(e, k.yaw_base, e)
        np.arctan2(e0, e1, yaw)
        if any_hit:
            if yaw_draw is None:
                yaw_draw = np.full(self.n, self.yaw_mean)
            yaw += np.where(hit & (e2 < 0), yaw_draw, 0.0)
        else:
            np.add(yaw, k.zero, yaw)
        np.multiply(k.half, yaw, half)
        # (z, the yaw-only quaternion) where grounded: (floor_z, cos h, 0, 0, sin h) in one masked write
        np.cos(half, q5_cos)
        np.sin(half, q5_sin)
        _copyto(V.zq, q5, where=grounded[:, None])
        np.add(V.q, k.q_zero, V.q)  # (p - 0.0) + 0.0 of the frame round trip (the quaternion + -0.0: as it is)
        if any_hit:  # a hit zeroes vel and omega, and the motors (0.0 * x: signs kept)
            np.multiply(V.v, 0.0, out=V.v, where=hit[:, None])
            np.multiply(u, 0.0, out=u, where=hit[:, None])
            hit_row |= hit
        _copyto(V.v_stay, k.zero, where=staying[:, None])
        s.phys.touch()
        s._any_on_floor = _count_nonzero(grounded) > 0
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
        if _count_nonzero(out) or _count_nonzero(at_wall) or _count_nonzero(at_ceiling):
            return None
        rel = pos[..., :, None, :] - pos[..., None, :, :]
        dist = np.sqrt((rel * rel).sum(axis=-1))  # spatial.norm_last below spatial.BIG elements
        contact = (dist <= self.hitbox) & self.offdiag
        if _count_nonzero(contact):
            new = contact & ~prev["contact"]
            if _count_nonzero(new):  # a new contact: the paper's response (and its draws)
                return None
        else:  # no contact: none new (contact & ~prev is all False)
            new = contact
        hit = np.zeros(at_wall.shape, bool)
        return {**kin, "at_wall": at_wall, "at_ceiling": at_ceiling, "hit_wall": hit, "hit_ceiling": hit,
                "contact": contact, "new_contact": new, "dist": dist, "changed": False}


def _constants(n: int, floor_z: float, floor_top: float, friction: float, dt: float) -> SimpleNamespace:
    """The sub-step's constant operands as arrays of the full shape of the other operand (a NumPy call on
    same-shape contiguous arrays costs less than one that broadcasts or converts a Python float) and the
    flat gather indices into one world's qpos (N * 7,)."""
    rows = 7 * np.arange(n)
    k = SimpleNamespace(zero=np.zeros(()), half=np.full((), 0.5))
    k.land_idx = np.concatenate([rows + 2, rows + 2, (_QPOS_YAW_1[:, None] + rows).ravel(),
                                 (_QPOS_YAW_2[:, None] + rows).ravel()])
    k.z_bounds = np.repeat([floor_z, floor_top], n)
    k.yaw_scale, k.yaw_base = np.repeat(_YAW_SCALE, n), np.repeat(_YAW_BASE, n)
    k.q_zero = np.tile([0.0, 0.0, 0.0, -0.0, -0.0, -0.0, -0.0], (n, 1))
    k.rot_idx = np.stack([a.reshape(2, 1, 9) + rows[:, None] for a in (_QPOS_A, _QPOS_B)])  # (2, 2, N, 9)
    k.rot_scale = np.broadcast_to(_Q_SCALE.reshape(2, 1, 9), (2, n, 9)).copy()
    k.rot_base = np.tile(_Q_BASE, (n, 1))
    rows6 = 6 * np.arange(n)
    k.v_idx, k.x_idx = (np.stack([rows6 + c for c in cols]) for cols in ((0, 1), (0, 1, 2, 3, 4)))  # (2, N), (5, N)
    k.inf, k.ninf, k.ones2 = np.full((), np.inf), np.full((), -np.inf), np.ones((2, n))
    k.thresh = np.repeat([[1e-9], [0.0]], n, axis=1)  # (speed, |F_h|) thresholds, as numpy_floor's
    k.friction, k.dt = np.full((), friction), np.full((), dt)
    return k


#: ``np.copyto`` without its Python-level wrapper (the same function)
_copyto = getattr(getattr(getattr(np, "_core", None), "_multiarray_umath", None), "copyto", np.copyto)
#: NumPy's clip ufunc (None if absent: the two ufuncs)
_clip = getattr(getattr(getattr(np, "_core", None), "umath", None), "clip", None)


def action_to_command(action: np.ndarray) -> np.ndarray:
    """:func:`quadswarm_mj.actuation.action_to_command` (0.5 (clip(a, -1, 1) + 1)) with the clip as one ufunc: the
    same bits (the bounds are not zero, so no sign of zero can differ; NaN stays NaN)."""
    if _clip is None:
        return 0.5 * (np.minimum(np.maximum(action, -1.0), 1.0) + 1.0)
    c = _clip(action, -1.0, 1.0)
    c += 1.0
    c *= 0.5
    return c


#: ``np.count_nonzero`` without its Python-level wrapper (the same function)
_count_nonzero = getattr(getattr(getattr(np, "_core", None), "_multiarray_umath", None), "count_nonzero",
                         np.count_nonzero)
