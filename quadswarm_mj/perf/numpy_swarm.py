"""The CPU engine's sub-step loop for one world of several quads, on preallocated component-major rows.

:class:`quadswarm_mj.perf.numpy_loop.SmallLoop` runs the paper's sub-step (rotor wrench, floor normal
force and friction, ``mj_step``, floor landing, rotation of the new pose) in whole-array NumPy calls on
(B, N, .) arrays; on one world of a few quads NumPy's fixed cost per call dominates, and a call that
broadcasts, reads a strided view, converts a Python float or makes a view costs two to four times a call on
same-shape contiguous arrays. :class:`SwarmLoop` runs the same expressions in the same order (the same bits,
signs of zero included; ``tests/test_numpy_swarm.py`` checks seeded episodes against ``SmallLoop`` and the
per-sub-step ops) on component-major (., N) rows allocated once per env with every view made once: the
motor state replicated over the rotor sums' rows, the rotation stored by column, constants as same-shape or
0-d arrays, MuJoCo's ``qpos``/``qvel`` read by one flat ``take`` per stage and the world wrench written into
``xfrc_applied`` by one ``put``. Used for one world (B = 1, offsets zero) with the paper's chain and floor.
NumPy only.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np

from quadswarm_mj import np_calls
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
        self.z2, self.zq = q[:, 2:3], q[:, 2:7]
        self.v_h, self.v_stay = v[:, :2], v[:, 2:5]
        self.force, self.torque, self.f_h, self.f_z = x[:, :3], x[:, 3:], x[:, :2], x[:, 2]


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
        # work rows, component-major (., N) (contiguous rows: cheaper NumPy calls than strided (N, .) columns),
        # reused every sub-step (nothing in them outlives a control step)
        self.Rj = np.empty((3, 3, n))  # the rotation R[n, i, j] at Rj[j, i, n]: its column j is the row block Rj[j]
        self.R9 = self.Rj.reshape(9, n)
        # motor state and per-step operands (rotor k, row jj, N): u, f, sqrt(cmd), cmd * noise, alpha, lag step,
        # each replicated over the 12 rows jj of the rotor sums (a NumPy call on same-shape arrays costs a third of
        # one that broadcasts): F_z x 3 (for the force's rows), tau_x x 3, tau_y x 3, tau_z x 3 (for the torque's)
        self._motor = tuple(np.empty((4, 12, n)) for _ in range(6))
        self._ts_src: tuple | None = None
        self._out: tuple = (None, None)  # the last (u, R) returned
        # ts (thrust_max or spin), mix (mix rows, 1.0 for tau_z), rows, sums, R tau products
        self._rotor = (np.empty((4, 12, n)), np.empty((4, 12, n)), np.empty((4, 12, n)), np.empty((12, n)),
                       np.empty((3, 3, n)))
        # the velocity stages' rows: out-of-room flags, pair positions, squared offsets, squared distance
        self._stage_rows = (np.empty((2, 1, n, 3), bool), np.empty((2, 3, n, n)), np.empty((3, n, n)),
                            np.empty((1, n, n)))
        self.W6 = np.empty((6, n))  # the world wrench (F_x, F_y, F_z, tau_x, tau_y, tau_z), put into xfrc_applied
        ts, mix, rows, sm, rt = self._rotor  # (every view made once: a view costs as much as a small NumPy call)
        W6, Rj = self.W6, self.Rj
        self._wrench_args = (*self._motor, ts, mix, rows, *rows, sm, sm[:3], sm[3:].reshape(3, 3, n), rt, *rt, Rj,
                             Rj[2], W6[:3], W6[3:])
        # the floor wrench's rows: H = (v_x, v_y, F_x, F_y, v_y, v_x, F_y, F_x), new = (F_x, F_y, F_z, tau_x, tau_y)
        # (tau rows stay 0.0), the ratios' rows (kinetic, kinetic, static, static)
        H, new, sq, m4 = np.empty((8, n)), np.zeros((5, n)), np.empty((8, n)), np.empty((4, n))
        num2, num4, positive = np.empty((2, n)), np.empty((4, n)), np.empty((4, n), bool)
        self._floor_rows = (H, H[:2], H[2:4], H[4:6], H[6:8], sq, sq[:4], sq[4:], m4, m4[0], m4[2], num2, num2[0],
                            num2[1], num4, num4[:2], num4[2:], np.empty((4, n)), positive, positive[:2],
                            np.empty((2, n)), np.empty(n), np.empty(n), np.empty(n), new, new[:2], new[2],
                            np.empty((5, n), bool), self.W6[:2], self.W6[1::-1], self.W6[2], self.W6[:5])
        # the landing's rows: one flat gather of qpos (z twice, the yaw entries' two factors, entry-major) into g
        g = np.empty(14 * n)
        le16, p, e = np.empty(2 * n, bool), np.empty(6 * n), np.empty(3 * n)
        q5 = np.zeros((n, 5))  # (floor_z, cos h, 0, 0, sin h)
        q5[:, 0] = self.floor_z
        self._landing_rows = (g, g[:2 * n], g[2 * n:8 * n], g[8 * n:], le16, le16[:n], le16[n:], p, p[:3 * n],
                              p[3 * n:], e, e[:n], e[n:2 * n], e[2 * n:], np.empty(n), np.empty(n), q5,
                              q5[:, 1], q5[:, 4], np.empty(n, bool), np.empty(n, bool))
        # rotation rows: the two factors of the 18 products per quad gathered as (2, 2, 9, N), product (2, 9, N)
        t36, t18 = np.empty((2, 2, 9, n)), np.empty((2, 9, n))
        self._rot_rows = (t36, t36[0], t36[1], t18, t18[0], t18[1], self.R9)
        self._k = _constants(n, self.floor_z, self.floor_top, self.friction, self.dt)
        k = self._k
        k.wall_lo, k.wall_hi = (np.broadcast_to(b, (1, n, 3)).copy() for b in (self.out_lo, self.out_hi))
        k.hitbox = np.full((), self.hitbox)

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
        """``self.Rj`` = ``perf.numpy_small.quat_to_rotmat_qpos`` of the physics' qpos, component-major (same bits:
        the same products, scales and sums, on rows gathered in one flat take)."""
        t36, a, b, t, t_a, t_b, R9 = self._rot_rows
        k = self._k
        self._v.qf.take(k.rot_idx, None, t36, "wrap")  # (valid indices: wrap is raise, without its checks)
        np.multiply(a, b, t)
        np.multiply(t, k.rot_scale, t)
        np.add(t_a, t_b, R9)
        np.add(R9, k.rot_base, R9)  # base + (a + b): the same sum

    def __call__(self, cfg: Any, carry: dict[str, Any], inp: dict[str, Any], consts: dict[str, Any],
                 ops: Any) -> dict[str, Any]:
        """``cfg.substeps`` sub-steps from ``carry`` (as ``substep_loop``: ``q``/``v`` the physics' qpos/qvel;
        ``hit_floor`` all False); returns the carry after the last one."""
        s, phys, V, k = self.s, self.s.phys, self._views(), self._k
        n = self.n
        params, cmd = inp["params"], inp["cmd"][0]
        u, f, root, cn, alpha, _ = self._motor
        # constant over the control step (as SmallLoop): sqrt(cmd), alpha, cmd * noise, mass * gravity
        rep = k.motor_idx  # (4, 12, N) flat indices of an (N, 4) array: its entry [n, k] at [k, jj, n]
        np.sqrt(cmd).take(rep, None, root, "wrap")
        np.multiply(cmd, inp["eps"][0]).take(rep, None, cn, "wrap")
        if carry["u"] is not self._out[0]:  # (else u holds it: the carry is this loop's last output)
            np.ravel(carry["u"][0]).take(rep, None, u, "wrap")
        mass = params["mass"][0]
        weight = mass * params["gravity"]
        src = self._ts_src  # per-quad constants, made again when they change (at a reset)
        if src is None or src[0] is not params["thrust_max"] or src[1] is not consts["torque_spin"] \
                or src[2] is not consts["mix"] or src[3] is not params["alpha"]:
            ts, mix = self._rotor[:2]
            ts[:, :9, :] = params["thrust_max"][0].T[:, None, :]
            ts[:, 9:, :] = consts["torque_spin"][0].T[:, None, :]
            mix[:, :9, :] = np.repeat(consts["mix"].T, 3, axis=1)[:, :, None]
            mix[:, 9:, :] = 1.0
            alpha[...] = params["alpha"][0]
            self._ts_src = (params["thrust_max"], consts["torque_spin"], consts["mix"], params["alpha"])
        on_floor = carry["on_floor"][0]
        hit_floor = carry["hit_floor"]
        hit_row = hit_floor[0]
        if carry["R"] is not self._out[1]:  # (as u)
            _copyto(self.Rj, carry["R"][0].transpose(2, 1, 0))
        max_omega, xf, x_idx = self.max_omega, V.xf, k.x_idx
        for _ in range(cfg.substeps):
            self._wrench()  # into self.W6
            if s._any_on_floor:  # the floor's normal force and friction (numpy_floor.floor_wrench_inplace)
                self._floor_wrench(V, on_floor, mass, weight)
            xf.put(x_idx, self.W6)  # xfrc_applied's rows
            phys.step(max_omega)
            on_floor = self._landing(V, u, on_floor, hit_row)
            self.rotmat()
        out = self._out = (u.take(k.motor_out), self.R9.take(k.rot_out))  # fresh (1, N, 4), (1, N, 3, 3)
        return {"q": phys.qpos, "v": phys.qvel, "R": out[1], "u": out[0], "f_norm": f.take(k.motor_out),
                "on_floor": on_floor.reshape(1, n), "hit_floor": hit_floor, "aux": carry["aux"], "ctrl": carry["ctrl"]}

    def _wrench(self) -> None:
        """A sub-step's rotor wrench (``numpy_loop.substep_wrench``: motor lag, thrusts, the body force and torque
        rotated to the world) on the component-major rows (the same products and left-to-right sums), written
        into ``self.W6``; u and f updated in place."""
        u, f, root, cn, alpha, d, ts, mix, rows, r0, r1, r2, r3, sm, sm_f, sm_t, rt, rt0, rt1, rt2, Rj, R_z, W_f, W_t \
            = self._wrench_args
        k = self._k
        np.subtract(root, u, d)
        np.multiply(d, alpha, d)
        np.add(u, d, u)
        np.multiply(u, u, f)
        np.add(f, cn, f)
        _clip(f, k.zero, k.one, f)  # = min(max(f, 0), 1): u u + c n is never -0.0, so no sign of zero differs
        np.multiply(ts, f, rows)  # (thrust_max f) mix; (spin f) 1.0
        np.multiply(rows, mix, rows)
        np.add(r0, r1, sm)  # the sum over the rotors, left to right (as np.add.reduce over 4)
        np.add(sm, r2, sm)
        np.add(sm, r3, sm)
        np.multiply(sm_f, R_z, W_f)  # F_z R[:, 2]
        np.multiply(Rj, sm_t, rt)  # R[i, j] tau_j at rt[j, i]
        np.add(rt0, rt1, W_t)
        np.add(W_t, rt2, W_t)

    def _floor_wrench(self, V: _Views, on_floor: np.ndarray, mass: np.ndarray, weight: np.ndarray) -> None:
        """``numpy_floor.floor_wrench_inplace`` on ``self.W6`` (the same expressions and order) on component-major
        rows, pairs duplicated where a row meets a pair (x, y) (grounded quads only); max(0, x) and min(a, x) as the
        clip ufunc (the same bits: no operand is -0.0 here)."""
        k = self._k
        H, H_v, h_f, H_vs, H_fs, sq, sq_a, sq_b, m4, speed, mag_f, num2, num_k, num_s, num4, r_k, r_s, den, positive, \
            moving, kv, normal, cap, tmp, new, new_h, new_z, mask5, W_h, W_hs, f_z, W5 = self._floor_rows
        V.vf.take(k.v_idx, None, H_v, "wrap")  # (v_x, v_y)
        _copyto(h_f, W_h)  # (F_x, F_y)
        V.vf.take(k.vs_idx, None, H_vs, "wrap")  # (v_y, v_x)
        _copyto(H_fs, W_hs)  # (F_y, F_x)
        np.multiply(H, H, sq)
        np.add(sq_a, sq_b, m4)  # (x x + y y) twice (y y + x x: the same sum) for the speed and |F_h|
        np.sqrt(m4, m4)  # speed, speed, |F_h|, |F_h| (sqrt(x x + y y) as norm_last)
        np.subtract(weight, f_z, normal)
        _clip(normal, k.zero, k.inf, normal)  # max(0, weight - F_z)
        np.multiply(k.friction, normal, cap)
        np.multiply(mass, speed, tmp)
        np.divide(tmp, k.dt, tmp)
        _clip(cap, k.ninf, tmp, num_k)  # kinetic: min(cap, m speed / dt)
        np.subtract(mag_f, cap, tmp)
        _clip(tmp, k.zero, k.inf, num_s)  # static: max(0, |F_h| - cap)
        num2.take(k.pair_idx, None, num4, "wrap")  # (kinetic, kinetic, static, static)
        np.greater(m4, k.thresh, positive)  # moving, moving, |F_h| > 0 (twice)
        _copyto(den, k.ones4)
        _copyto(den, m4, where=positive)
        np.divide(num4, den, num4)  # the ratios
        np.multiply(h_f, r_s, new_h)  # static friction
        np.multiply(r_k, H_v, kv)
        np.subtract(h_f, kv, kv)
        _copyto(new_h, kv, where=moving)  # kinetic
        np.add(f_z, normal, new_z)
        if _count_nonzero(on_floor) == self.n:
            _copyto(W5, new)
        else:  # the other quads' rows as they are
            on_floor.take(k.mask_idx, None, mask5, "wrap")
            _copyto(W5, new, where=mask5)

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
        # (else yaw + 0.0 is yaw: e0 = (a + b) + 0.0 is never -0.0, so neither is arctan2(e0, e1))
        np.multiply(k.half, yaw, half)
        # (z, the yaw-only quaternion) where grounded: (floor_z, cos h, 0, 0, sin h) in one masked write
        np.cos(half, q5_cos)
        np.sin(half, q5_sin)
        _copyto(V.zq, q5, where=grounded[:, None])
        np.add(V.q, k.q_zero, V.q)  # (p - 0.0) + 0.0 of the frame round trip (the quaternion + -0.0: as it is)
        if any_hit:  # a hit zeroes vel and omega, and the motors (0.0 * x: signs kept)
            np.multiply(V.v, 0.0, out=V.v, where=hit[:, None])
            np.multiply(u, 0.0, out=u, where=hit)  # (u: (4, N))
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
        k, out, rel = self._k, self._stage_rows[0], self._stage_rows[1]
        if pos.shape != k.wall_lo.shape:
            return None
        np.less_equal(pos, k.wall_lo, out[0])
        np.greater_equal(pos, k.wall_hi, out[1])
        if _count_nonzero(out) or _count_nonzero(at_wall) or _count_nonzero(at_ceiling):
            return None
        np.ravel(pos).take(k.pair_rows, None, rel, "wrap")  # pos[i, c] and pos[j, c] at [0 / 1, c, i, j]
        sq, dist = self._stage_rows[2:]
        np.subtract(rel[0], rel[1], sq)  # pos_i - pos_j
        np.multiply(sq, sq, sq)
        np.add(sq[0], sq[1], dist[0])  # spatial.norm_last: sqrt of the left-to-right sum of the squares
        np.add(dist[0], sq[2], dist[0])
        dist = np.sqrt(dist)
        contact = np.less_equal(dist, k.hitbox)
        np.logical_and(contact, self.offdiag, contact)
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
    # the rotation's entries in the order (column j, row i): entry e = 3 i + j at position 3 j + i
    order = np.array([3 * i + j for j in range(3) for i in range(3)])
    halves = np.concatenate([order, order + 9])
    k.rot_idx = np.stack([a[halves].reshape(2, 9, 1) + rows for a in (_QPOS_A, _QPOS_B)])  # (2, 2, 9, N)
    k.rot_scale = np.repeat(_Q_SCALE[halves].reshape(2, 9, 1), n, axis=2)
    k.rot_base = np.repeat(_Q_BASE[order].reshape(9, 1), n, axis=1)
    rows6 = 6 * np.arange(n)
    k.v_idx, k.x_idx = (np.stack([rows6 + c for c in cols]) for cols in ((0, 1), range(6)))  # (2, N), (6, N)
    k.vs_idx = np.stack([rows6 + 1, rows6])
    k.one, k.inf, k.ninf, k.ones4 = np.ones(()), np.full((), np.inf), np.full((), -np.inf), np.ones((4, n))
    k.thresh = np.repeat([[1e-9], [1e-9], [0.0], [0.0]], n, axis=1)  # (speed, |F_h|) thresholds, as numpy_floor's
    k.pair_idx = np.stack([np.arange(n)] * 2 + [np.arange(n, 2 * n)] * 2)  # rows (0, 0, 1, 1) of a (2, N) array
    k.mask_idx = np.stack([np.arange(n)] * 5)  # an (N,) row five times
    i3 = (3 * np.arange(n)[:, None] + np.arange(3)[:, None, None])  # (3, N, 1): pos[i, c] of an (N, 3) array
    k.pair_rows = np.stack([np.broadcast_to(i3, (3, n, n)), np.broadcast_to(i3.transpose(0, 2, 1), (3, n, n))])
    k.motor_out = (12 * n * np.arange(4) + np.arange(n)[:, None]).reshape(1, n, 4)  # [k, 0, n] of (4, 12, N)
    k.rot_out = (n * (np.arange(3)[:, None] + 3 * np.arange(3)) + np.arange(n)[:, None, None])[None]  # row 3 j + i
    k.motor_idx = np.broadcast_to((4 * np.arange(n) + np.arange(4)[:, None])[:, None, :], (4, 12, n)).copy()
    k.friction, k.dt = np.full((), friction), np.full((), dt)
    return k


_copyto, _clip = np_calls.copyto, np_calls.clip  # without np's Python wrappers (the same functions)


def action_to_command(action: np.ndarray) -> np.ndarray:
    """:func:`quadswarm_mj.actuation.action_to_command` (0.5 (clip(a, -1, 1) + 1)) with the clip as one ufunc: the
    same bits (the bounds are not zero, so no sign of zero can differ; NaN stays NaN)."""
    c = _clip(action, _C["-1"], _C["1"])
    np.add(c, _C["1"], c)
    np.multiply(c, _C["0.5"], c)
    return c


def motor_noise_step(eps: np.ndarray, sigma: np.ndarray, theta: float, normal: np.ndarray) -> np.ndarray:
    """:func:`quadswarm_mj.actuation.motor_noise_step` (eps + theta (0.0 - eps) + sigma[..., None] normal, in
    that order) with 0-d operands for the constants: the same bits, a fresh array."""
    th = _C.get(theta)
    if th is None:
        th = _C[theta] = np.full((), theta)
    a = np.subtract(_C["0"], eps)
    np.multiply(th, a, a)
    np.add(eps, a, a)
    np.add(a, np.multiply(sigma[..., None], normal), a)
    return a


#: 0-d float64 constants (a NumPy call converts a Python float operand on every call)
_C: dict = {"-1": np.full((), -1.0), "1": np.ones(()), "0.5": np.full((), 0.5), "0": np.zeros(())}


_count_nonzero = np_calls.count_nonzero  # without np's Python wrapper
