"""The MuJoCo C back ends of the CPU engine: B worlds of N free-body quads stepped by MuJoCo.

Both expose the same small interface to :class:`quadswarm_mj.envs.cpu_core.CpuSwarm`: ``qpos`` (B, N, 7),
``qvel`` (B, N, 6), ``xfrc`` (B, N, 6) arrays the engine reads and writes, ``offsets`` (B, 1, 3) the
worlds' origins in the model, ``step(max_omega)`` one physics sub-step (then the body rates clipped),
``touch()`` after the engine wrote ``qpos``/``qvel``, ``write_params``, ``after_reset``,
``set_obstacles``; ``model``/``data``/``arena`` for rendering and inspection.

* :class:`MjDataPhysics` (``backend="mjdata"``): one ``MjModel``/``MjData`` with all worlds side by
  side; the arrays are views into ``MjData``, one ``mj_step`` steps every world. ``visual=True`` keeps
  the Crazyflie's visual geoms (rendering); ``visual=False`` drops them, which halves MuJoCo's
  kinematics cost per body.
* :class:`BatchPhysics` (``backend="batch"``): ``mujoco.batch.Batch`` of ceil(B / C) simulations of a
  C-world model without visual geoms (``chunk_worlds`` = C, 64 by default), one call steps them all;
  the arrays are copied into the simulations' state rows when the engine changed them. Building one
  MjSpec model grows quadratically with its bodies (a 1024-world model takes minutes), a 64-world
  model builds in 0.2 s and steps as fast per body. ``data`` is None.

MuJoCo's automatic reset on instability is off: :class:`PhysicsInstabilityError` names the quad.
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from quadswarm_mj import np_calls
from quadswarm_mj.arena import build_arena
from quadswarm_mj.config import EnvConfig

BACKENDS = ("mjdata", "batch")
#: min(max(x, lo), hi) elementwise in one call, and count_nonzero, without np's Python wrappers
_clip, _count_nonzero = np_calls.clip, np_calls.count_nonzero
#: qvel entries up to which MjDataPhysics.step clips all of qvel (small arrays: fewer, cheaper calls)
_WHOLE_CLIP = 6 * 256
#: MuJoCo's mjMAXVAL: a qpos, qvel or qacc entry beyond it (or NaN) is what MuJoCo calls unstable
_MJ_MAXVAL = 1e10
#: MuJoCo's instability warnings (mjWARN_BADQPOS, mjWARN_BADQVEL, mjWARN_BADQACC), contiguous
_BAD_WARNINGS = slice(int(mujoco.mjtWarning.mjWARN_BADQPOS), int(mujoco.mjtWarning.mjWARN_BADQACC) + 1)


class PhysicsInstabilityError(RuntimeError):
    """MuJoCo found the physics of a quad unstable (NaN, inf or a value beyond 1e10 in its position,
    velocity or acceleration). MuJoCo's automatic reset, which would move every world of the shared
    data back to the model's default pose without a word, is turned off: the step stops with this
    error naming the world and quad, and the env needs ``reset()``. Validated inputs (the bounds of
    ``quadswarm_mj.config``) do not get here; this is the backstop."""


def _no_autoreset(model: mujoco.MjModel) -> None:
    """Turn MuJoCo's automatic reset on instability off (see :class:`PhysicsInstabilityError`); a
    stable simulation steps exactly as before."""
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_AUTORESET)


def _raise_unstable(qpos: np.ndarray, qvel: np.ndarray, qacc: np.ndarray, first_world: int) -> None:
    """Raise :class:`PhysicsInstabilityError` naming the quads whose (B, N, .) state or acceleration
    is NaN, inf or beyond 1e10 (the one with the largest |qacc| if none is)."""
    with np.errstate(invalid="ignore"):
        bad = np.zeros(qacc.shape[:2], bool)
        for a in (qpos, qvel, qacc):
            bad |= ~(np.abs(a) <= _MJ_MAXVAL).all(-1)
        if not bad.any():
            bad.flat[int(np.nanargmax(np.abs(qacc).max(-1)))] = True
    where = np.argwhere(bad)
    w, q = (int(i) for i in where[0])
    more = f" (and {len(where) - 1} more quads)" if len(where) > 1 else ""
    raise PhysicsInstabilityError(
        f"the physics became unstable at world {w + first_world}, quad {q}{more}: NaN, inf or a value beyond 1e10 "
        f"in its position, velocity or acceleration (MuJoCo's automatic reset, which would have moved every world "
        f"to the default pose, is off); the env needs reset(). Inputs within the bounds of quadswarm_mj.config "
        f"should not get here: please report the configuration")


def _check_simple_bodies(model: mujoco.MjModel, arena: Any) -> None:
    """The quads' free-joint mass-matrix diagonal ``dof_M0`` must be (m, m, m, Ixx, Iyy, Izz) so that
    writing it with the body mass and inertia is exact (the Crazyflie's inertial frame is its body
    frame). MuJoCo 4 builds the mass matrix of such "simple" bodies from ``dof_M0``, which
    ``mj_setConst`` computes at compile time: writing ``body_mass``/``body_inertia`` alone would
    change gravity (m g) but not the inertia the solver divides by."""
    fb, vs, n = arena.first_body, arena.qvel_start, arena.body_ids.size
    m0 = model.dof_M0[vs:vs + 6 * n].reshape(n, 6)
    expect = np.concatenate([np.repeat(model.body_mass[fb:fb + n, None], 3, 1), model.body_inertia[fb:fb + n]], 1)
    if not np.allclose(m0, expect, rtol=1e-12, atol=0.0):
        raise RuntimeError("quad bodies are not simple free bodies (dof_M0 != mass, inertia): the inertial frame "
                           "must coincide with the body frame")


class _SubstepAdapter:
    """The sub-step interface of :func:`quadswarm_mj.core.substeps.substep_loop` on the (B, N, .) views
    ``qpos``/``qvel``/``xfrc`` (MuJoCo's frame: positions include the world offsets)."""

    qpos: np.ndarray
    qvel: np.ndarray
    xfrc: np.ndarray
    offsets: np.ndarray
    max_omega: float
    _any_offset: bool

    def substep(self, q: np.ndarray, v: np.ndarray, force: np.ndarray, torque: np.ndarray, aux: Any) -> tuple:
        """Write the world wrench into ``xfrc_applied``, step once (angular velocity clipped); the state
        arrays are MuJoCo's own (returned as they are: ``q``/``v`` are ``qpos``/``qvel``)."""
        self.xfrc[..., :3] = force
        self.xfrc[..., 3:] = torque
        self.step(self.max_omega)
        return self.qpos, self.qvel, aux

    def local_pos(self, q: np.ndarray) -> np.ndarray:
        """World-local positions (m) of ``q`` (B, N, 7) (a fresh array; x - 0.0 is x, signed zeros included,
        so with all offsets zero a copy gives the same bits)."""
        return q[..., :3] - self.offsets if self._any_offset else q[..., :3].copy()

    @staticmethod
    def velocities(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(vel m/s world, omega rad/s body) copies (``v`` is MuJoCo's, overwritten by the next sub-step)."""
        return v[..., :3].copy(), v[..., 3:].copy()


class MjDataPhysics(_SubstepAdapter):
    """All B worlds in one MjModel/MjData; qpos/qvel/xfrc are views into it (no copies)."""

    def __init__(self, cfg: EnvConfig, num_worlds: int, visual: bool = True):
        B, N = num_worlds, cfg.num_quads
        self.max_omega = cfg.quad.max_omega
        self.arena = build_arena(cfg, num_worlds) if visual else build_arena(cfg, num_worlds, visual=False)
        self.model = self.arena.model
        _no_autoreset(self.model)
        self.data = mujoco.MjData(self.model)
        qs, vs, fb = self.arena.qpos_start, self.arena.qvel_start, self.arena.first_body
        self.qpos = self.data.qpos[qs:qs + 7 * B * N].reshape(B, N, 7)  # views into MjData
        self.qvel = self.data.qvel[vs:vs + 6 * B * N].reshape(B, N, 6)
        self._qacc = self.data.qacc[vs:vs + 6 * B * N].reshape(B, N, 6)
        self._bad_counts = self.data.warning.number[_BAD_WARNINGS]  # a view of MuJoCo's instability warnings
        self.first_world = 0  # index of world 0 in error messages (a vector env's shard sets it)
        self.xfrc = self.data.xfrc_applied[fb:fb + B * N].reshape(B, N, 6)
        assert np.shares_memory(self.qpos, self.data.qpos) and np.shares_memory(self.xfrc, self.data.xfrc_applied)
        self.offsets = self.arena.world_offsets[:, None, :]
        self._any_offset = bool(np.any(self.offsets))
        _check_simple_bodies(self.model, self.arena)
        self._M0 = self.model.dof_M0[vs:vs + 6 * B * N].reshape(B * N, 6)  # a view
        self._one = B * N == 1  # one body: the angular-velocity clip on floats

    def __getstate__(self) -> dict[str, Any]:
        """For copy/pickle: without the views into MjData/MjModel (:meth:`__setstate__` makes them again)."""
        return {k: v for k, v in self.__dict__.items()
                if k not in ("qpos", "qvel", "xfrc", "_M0", "_qacc", "_bad_counts")}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        B, N = self.offsets.shape[0], self.arena.num_quads
        qs, vs, fb = self.arena.qpos_start, self.arena.qvel_start, self.arena.first_body
        self.qpos = self.data.qpos[qs:qs + 7 * B * N].reshape(B, N, 7)
        self.qvel = self.data.qvel[vs:vs + 6 * B * N].reshape(B, N, 6)
        self._qacc = self.data.qacc[vs:vs + 6 * B * N].reshape(B, N, 6)
        self._bad_counts = self.data.warning.number[_BAD_WARNINGS]
        self.xfrc = self.data.xfrc_applied[fb:fb + B * N].reshape(B, N, 6)
        self._M0 = self.model.dof_M0[vs:vs + 6 * B * N].reshape(B * N, 6)

    def touch(self) -> None:
        """The engine wrote qpos/qvel: nothing to do, they are MjData itself."""

    def step(self, max_omega: float) -> None:
        """One physics sub-step, then angular velocity clipped to +-max_omega per body axis; raises
        :class:`PhysicsInstabilityError` if MuJoCo warned of an instability."""
        mujoco.mj_step(self.model, self.data)
        if _count_nonzero(self._bad_counts):  # (BADQPOS, BADQVEL, BADQACC) warnings
            self._bad_counts[...] = 0
            _raise_unstable(self.qpos, self.qvel, self._qacc, self.first_world)
        if self._one:  # clip written only where a component is beyond the bound (as clip: NaN stays)
            v = self.qvel[0, 0]
            for i, w in enumerate(v[3:].tolist(), 3):
                if w > max_omega:
                    v[i] = max_omega
                elif w < -max_omega:
                    v[i] = -max_omega
            return
        qvel = self.qvel
        if qvel.size <= _WHOLE_CLIP:  # all of qvel against same-shape bounds (+-inf for the
            b = self.__dict__.get("_vbounds")  # linear rows: x as it is), which costs a quarter of the call below
            if b is None or b[0] != max_omega:
                lo = np.broadcast_to(np.array([-np.inf] * 3 + [-max_omega] * 3), qvel.shape).copy()
                b = self._vbounds = (max_omega, lo, -lo)
            _clip(qvel, b[1], b[2], qvel)
            return
        w = qvel[..., 3:]
        _clip(w, -max_omega, max_omega, out=w)  # min(max(w, -m), m) in one call (NaN stays NaN)

    def write_params(self, idx: Any, mass: np.ndarray, inertia: np.ndarray) -> None:
        ids = self.arena.body_ids[idx].ravel()
        self.model.body_mass[ids] = mass.ravel()
        self.model.body_inertia[ids] = inertia.reshape(-1, 3)
        rows = ids - self.arena.first_body  # the mass matrix of the free joints (see _check_simple_bodies)
        self._M0[rows, :3] = mass.reshape(-1, 1)
        self._M0[rows, 3:] = inertia.reshape(-1, 3)

    def after_reset(self, idx: Any) -> None:
        self.data.time = 0.0
        mujoco.mj_forward(self.model, self.data)

    def set_obstacles(self, cfg: EnvConfig, idx: Any, omap: Any) -> None:
        """Move the column pool of worlds ``idx`` onto their maps (and set the radius under size randomization)."""
        from quadswarm_mj.arena import place_obstacles, set_obstacle_radius

        if self.arena.obstacle_mocap_ids is None:  # a lean paper-model arena has no column geoms
            return

        place_obstacles(self.arena, self.data.mocap_pos, omap.centres, omap.valid, cfg.room_size[2], worlds=idx)
        if cfg.obstacles.size_random:
            set_obstacle_radius(self.model, self.arena, omap.radius, worlds=idx)


_CHUNK_MODELS: dict[Any, Any] = {}  # (cfg, worlds) -> lean arena, compiled once per process


class BatchPhysics(_SubstepAdapter):
    """B worlds as K = ceil(B / C) simulations of a C-world model (no visual geoms) in one
    ``mujoco.batch.Batch``: one call steps them all. The engine's qpos/qvel/xfrc are (B, N, .)
    arrays copied into the simulations' state rows before each step and back after it.

    Why chunks: ``MjSpec`` assembly grows quadratically with the bodies in one model (a 1024-world
    model takes minutes to build), while a C = 64-world model builds in a fraction of a second and
    steps as fast per body as any larger one; one-world simulations (C = 1) pay MuJoCo's per-call
    overhead for every 8 bodies and step about half as fast (measured in BENCHMARKS.md).
    """

    def __init__(self, cfg: EnvConfig, num_worlds: int, chunk_worlds: int = 64, nthread: int = 1):
        import mujoco.batch

        B, N = num_worlds, cfg.num_quads
        self.max_omega = cfg.quad.max_omega
        C = max(1, min(int(chunk_worlds), B))
        K = -(-B // C)
        key = (cfg, C)
        if key not in _CHUNK_MODELS:
            _CHUNK_MODELS[key] = build_arena(cfg, C, visual=False)
        self.arena = _CHUNK_MODELS[key]
        self.model = self.arena.model
        _no_autoreset(self.model)
        self.data = None
        self.batch = mujoco.batch.Batch(self.model, nsim=K, nthread=nthread)
        self.B, self.C, self.K = B, C, K
        qs, vs, fb = self.arena.qpos_start, self.arena.qvel_start, self.arena.first_body
        self._rq = self.batch.bind("qpos")[:, qs:qs + 7 * C * N]  # (K, 7 C N) live views of the state rows
        self._rv = self.batch.bind("qvel")[:, vs:vs + 6 * C * N]
        self._rx = self.batch.bind("xfrc_applied")[:, fb:fb + C * N]
        self._rw = self._rv.reshape(K, C * N, 6)[..., 3:]  # angular velocities in the rows (a view)
        self._ra = self.batch.bind("qacc")[:, vs:vs + 6 * C * N]  # accelerations of the last sub-step
        self.first_world = 0  # index of world 0 in error messages (a vector env's shard sets it)
        self.dirty = True  # the engine's qpos/qvel differ from the rows
        self._time = self.batch.bind("time")
        self._rmass = self.batch.expand("body_mass")[:, fb:fb + C * N]  # per-simulation model fields
        self._rinertia = self.batch.expand("body_inertia")[:, fb:fb + C * N]
        _check_simple_bodies(self.model, self.arena)
        self._rM0 = self.batch.expand("dof_M0")[:, vs:vs + 6 * C * N].reshape(K, C * N, 6)  # see _check_simple_bodies
        self._qpos = self._rq.reshape(K * C, N, 7).copy()  # padded to K * C worlds
        self._qvel = np.zeros((K * C, N, 6))
        self._xfrc = np.zeros((K * C, N, 6))
        self._mass = self._rmass.reshape(K * C, N).copy()
        self._inertia = self._rinertia.reshape(K * C, N, 3).copy()
        self._pad = K * C - B  # padding worlds stay at the model's rest pose
        self._pad_qpos = self._qpos[B:].copy()
        self.qpos, self.qvel, self.xfrc = self._qpos[:B], self._qvel[:B], self._xfrc[:B]
        self.offsets = np.tile(self.arena.world_offsets, (K, 1))[:B, None, :]
        self._any_offset = bool(np.any(self.offsets))

    def __getstate__(self) -> dict[str, Any]:
        raise TypeError("a CpuSwarm on the 'batch' back end (mujoco.batch) cannot be copied or pickled; use "
                        "backend='mjdata' (QuadSwarmVectorEnv(..., backend='mjdata')) for an env to copy")

    def touch(self) -> None:
        """The engine wrote qpos/qvel: copy them into the state rows before the next step."""
        self.dirty = True

    def step(self, max_omega: float) -> None:
        """One physics sub-step, angular velocity clipped to +-max_omega (in the state rows, so the
        copy back brings it); qpos/qvel are copied in only when the engine changed them."""
        K = self.K
        if self.dirty:
            self._rq[...] = self._qpos.reshape(K, -1)
            self._rv[...] = self._qvel.reshape(K, -1)
            self.dirty = False
        self._rx[...] = self._xfrc.reshape(self._rx.shape)
        self.batch.step()
        ra = self._ra
        if not (ra.max() <= _MJ_MAXVAL and ra.min() >= -_MJ_MAXVAL):  # (NaN fails both) MuJoCo's instability test
            B, N = self.B, self._qpos.shape[1]
            _raise_unstable(self._rq.reshape(-1, N, 7)[:B], self._rv.reshape(-1, N, 6)[:B],
                            ra.reshape(-1, N, 6)[:B], self.first_world)
        w = self._rw
        np.minimum(np.maximum(w, -max_omega, out=w), max_omega, out=w)  # = clip
        self._qpos.reshape(K, -1)[...] = self._rq
        self._qvel.reshape(K, -1)[...] = self._rv
        if self._pad:  # padding worlds restart from rest at every sub-step
            self._qpos[self.B:] = self._pad_qpos
            self._qvel[self.B:] = 0.0
            self.dirty = True

    def write_params(self, idx: Any, mass: np.ndarray, inertia: np.ndarray) -> None:
        self._mass[:self.B][idx] = mass
        self._inertia[:self.B][idx] = inertia
        self._rmass[...] = self._mass.reshape(self.K, -1)
        self._rinertia[...] = self._inertia.reshape(self._rinertia.shape)
        self._rM0[..., :3] = self._mass.reshape(self.K, -1, 1)
        self._rM0[..., 3:] = self._inertia.reshape(self.K, -1, 3)

    def after_reset(self, idx: Any) -> None:
        sims = np.arange(self.B)[idx] // self.C
        self._time[np.unique(sims)] = 0.0

    def set_obstacles(self, cfg: EnvConfig, idx: Any, omap: Any) -> None:
        """Move the column pool of worlds ``idx`` onto their maps, in their simulations' rows."""
        from quadswarm_mj.arena import obstacle_positions

        if self.arena.obstacle_mocap_ids is None:  # a lean paper-model arena has no column geoms
            return

        wid = np.arange(self.B)[idx]
        sims, loc = wid // self.C, wid % self.C
        a = self.arena
        p = obstacle_positions(a, omap.centres, omap.valid, cfg.room_size[2], worlds=loc)
        self.batch.bind("mocap_pos")[sims[:, None], a.obstacle_mocap_ids[loc]] = p
        if cfg.obstacles.size_random:
            r = np.broadcast_to(np.asarray(omap.radius, np.float64).reshape(-1), (len(wid),))
            self.batch.expand("geom_size")[sims[:, None], a.obstacle_geom_ids[loc], 0] = r[:, None]
