"""freebody_step is MuJoCo's mj_step for contact-free free bodies: float64 vs mj_step, jit vs NumPy, float32 vs mjx.

Random masses and inertias are written into the MjModel and followed by ``mj_setConst``: MuJoCo caches the
mass matrix diagonal of "simple" bodies (COM at the body origin, principal axes = body axes, as the Crazyflie)
in ``dof_M0`` at compile time and uses it in ``mj_step``; without the refresh ``mj_step`` mixes the new bias
force with the old mass matrix (see ``test_mj_step_needs_set_const_after_mass_change``).
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from quadswarm_mj.arena import build_arena
from quadswarm_mj.config import EnvConfig
from quadswarm_mj.freebody import freebody_constants, freebody_step

T = 200  # sub-steps
N = 4
CF_INERTIA = np.array([1.3669e-05, 1.4357e-05, 2.6562e-05])  # kg m^2, the Crazyflie's


def _offset_model(n: int) -> tuple[mujoco.MjModel, np.ndarray]:
    """n free bodies with the COM off the body origin and rotated principal axes (MjSpec)."""
    spec = mujoco.MjSpec()
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_EULER
    spec.option.timestep = 0.005
    spec.option.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    for i in range(n):
        b = spec.worldbody.add_body(name=f"b{i}", pos=(0.3 * i, 0.0, 1.0))
        b.add_freejoint()
        b.explicitinertial = True
        b.ipos = (0.01 * (i + 1), -0.02, 0.015)
        iq = np.array([0.9, 0.3, -0.2, 0.25 + 0.1 * i])
        b.iquat = iq / np.linalg.norm(iq)
        b.mass, b.inertia = 0.03, (1e-5, 2e-5, 3e-5)
        b.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=(0.02, 0, 0), contype=0, conaffinity=0, mass=0)
    m = spec.compile()
    return m, np.array([m.body(f"b{i}").id for i in range(n)])


def _arena_model(n: int) -> tuple[mujoco.MjModel, np.ndarray]:
    a = build_arena(EnvConfig(num_quads=n), 1)
    return a.model, a.body_ids[0]


MODELS = {"arena": _arena_model, "offset": _offset_model}


def _case(model: mujoco.MjModel, ids: np.ndarray, seed: int) -> dict[str, np.ndarray]:
    """Random masses and inertias (written into ``model``), spinning initial state, wrenches per sub-step."""
    rng = np.random.default_rng(seed)
    n = len(ids)
    model.body_mass[ids] = rng.uniform(0.02, 0.04, n)
    model.body_inertia[ids] = CF_INERTIA * rng.uniform(0.7, 1.3, (n, 3))
    mujoco.mj_setConst(model, mujoco.MjData(model))
    quat = rng.normal(size=(n, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    omega = rng.normal(size=(n, 3))
    omega *= rng.uniform(20.0, 40.0, (n, 1)) / np.linalg.norm(omega, axis=1, keepdims=True)
    return {
        "qpos": np.concatenate([rng.uniform(-1.0, 1.0, (n, 3)), quat], 1),
        "qvel": np.concatenate([rng.normal(0.0, 1.0, (n, 3)), omega], 1),
        "xfrc": np.concatenate([rng.normal(0.0, 0.3, (T, n, 3)), rng.normal(0.0, 1e-4, (T, n, 3))], 2),
        "mass": model.body_mass[ids].copy(), "inertia": model.body_inertia[ids].copy(),
    }


def _mj_rollout(model: mujoco.MjModel, ids: np.ndarray, c: dict[str, np.ndarray],
                max_omega: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """mj_step rollout; ``max_omega`` clips the angular velocity after each step (as ``CpuSwarm.step``)."""
    d = mujoco.MjData(model)
    jnt = model.body_jntadr[ids]
    qa = model.jnt_qposadr[jnt][:, None] + np.arange(7)
    va = model.jnt_dofadr[jnt][:, None] + np.arange(6)
    d.qpos[qa], d.qvel[va] = c["qpos"], c["qvel"]
    qs, vs = [], []
    for t in range(T):
        d.xfrc_applied[ids] = c["xfrc"][t]
        mujoco.mj_step(model, d)
        if max_omega is not None:
            d.qvel[va[:, 3:]] = np.clip(d.qvel[va[:, 3:]], -max_omega, max_omega)
        qs.append(d.qpos[qa].copy())
        vs.append(d.qvel[va].copy())
    return np.stack(qs), np.stack(vs)


def _np_rollout(k, c: dict[str, np.ndarray], ipos=False, iquat=False,
                max_omega: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """NumPy rollout; ``ipos`` / ``iquat`` False take the constants' values (override with None to drop)."""
    ipos = k.ipos if ipos is False else ipos
    iquat = k.iquat if iquat is False else iquat
    q, v = c["qpos"], c["qvel"]
    qs, vs = [], []
    for t in range(T):
        q, v = freebody_step(q, v, c["xfrc"][t], c["mass"], c["inertia"], ipos, iquat, k.gravity, k.dt, max_omega)
        qs.append(q)
        vs.append(v)
    return np.stack(qs), np.stack(vs)


def _jax_rollout(k, c: dict[str, np.ndarray], dtype):
    import jax
    import jax.numpy as jnp

    def roll(qpos, qvel, xfrc, mass, inertia):
        def body(carry, x):
            q, v = freebody_step(carry[0], carry[1], x, mass, inertia, k.ipos, k.iquat, k.gravity, k.dt)
            return (q, v), (q, v)
        return jax.lax.scan(body, (qpos, qvel), xfrc)[1]

    args = [jnp.asarray(c[n], dtype) for n in ("qpos", "qvel", "xfrc", "mass", "inertia")]
    q, v = jax.jit(roll)(*args)
    assert q.dtype == dtype and v.dtype == dtype
    return np.asarray(q, np.float64), np.asarray(v, np.float64)


def _err(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
    return float(np.abs(a[0] - b[0]).max()), float(np.abs(a[1] - b[1]).max())


def _check_spin(qvel: np.ndarray, high: float = 60.0) -> None:
    """The bodies keep spinning at 15..high rad/s (MuJoCo's explicit Euler lets the gyroscopic term grow
    the spin of an asymmetric body at |omega| dt ~ 0.2: some seeds reach hundreds of rad/s in 200 sub-steps,
    so the seeds below are fixed ones whose spin stays in range)."""
    w = np.linalg.norm(qvel[..., 3:], axis=-1)
    assert w.min() > 15.0 and np.abs(qvel[..., 3:]).max() < high, (w.min(), np.abs(qvel[..., 3:]).max())


@pytest.mark.parametrize("name", sorted(MODELS))
def test_matches_mj_step_float64(name: str) -> None:
    """200 sub-steps of spinning bodies under random wrenches, random masses and inertias: within 1e-9 of
    mj_step (measured 1.1e-12 arena, 8e-13 offset); the arena's Crazyflie takes the cheap path, the offset
    model the general one."""
    model, ids = MODELS[name](N)
    k = freebody_constants(model, ids)
    assert (k.ipos is None and k.iquat is None) if name == "arena" else (k.ipos is not None and k.iquat is not None)
    assert k.dt == model.opt.timestep and np.array_equal(k.gravity, model.opt.gravity)
    c = _case(model, ids, seed=1)
    ref = _mj_rollout(model, ids, c)
    _check_spin(ref[1])
    err_q, err_v = _err(_np_rollout(k, c), ref)
    assert err_q <= 1e-9 and err_v <= 1e-9, (err_q, err_v)
    if name == "offset":  # the COM offset and the inertial frame matter: dropping either is far off
        assert max(_err(_np_rollout(k, c, ipos=None), ref)) > 1e-3
        assert max(_err(_np_rollout(k, c, iquat=None), ref)) > 1e-3


@pytest.mark.parametrize("name", sorted(MODELS))
def test_matches_mj_step_with_omega_clip(name: str) -> None:
    """With the simulator's clip (|omega_i| <= 40 rad/s after each sub-step) on both sides, a seed whose
    unclipped spin grows to hundreds of rad/s also stays within 1e-9 of mj_step."""
    model, ids = MODELS[name](N)
    k = freebody_constants(model, ids)
    c = _case(model, ids, seed=2)
    ref = _mj_rollout(model, ids, c, max_omega=40.0)
    with np.errstate(all="ignore"):  # unclipped, this seed spins up (to overflow on the arena model)
        assert np.nanmax(np.abs(_np_rollout(k, c)[1][..., 3:])) > 100.0
    _check_spin(ref[1], high=40.0 + 1e-12)
    err_q, err_v = _err(_np_rollout(k, c, max_omega=40.0), ref)
    assert err_q <= 1e-9 and err_v <= 1e-9, (err_q, err_v)


def test_mj_step_needs_set_const_after_mass_change() -> None:
    """Why ``_case`` calls ``mj_setConst``: for the Crazyflie ("simple" body) mj_step takes the mass matrix
    from ``dof_M0``, so a heavier quad written into ``body_mass`` alone falls faster than g."""
    model, ids = _arena_model(1)
    d = mujoco.MjData(model)
    model.body_mass[ids] *= 1.5
    mujoco.mj_step(model, d)
    vz_stale = d.qvel[2]
    mujoco.mj_resetData(model, d)
    mujoco.mj_setConst(model, d)
    mujoco.mj_step(model, d)
    g_dt = model.opt.gravity[2] * model.opt.timestep
    assert d.qvel[2] == pytest.approx(g_dt, rel=1e-12)
    assert vz_stale == pytest.approx(1.5 * g_dt, rel=1e-12)  # MuJoCo 4.0.0's behaviour; if it changes, drop this


def test_batched_shapes_and_broadcast() -> None:
    """(B, N) states with (N,) constants equal the per-world calls; outputs keep the state's dtype."""
    model, ids = _offset_model(N)
    k = freebody_constants(model, ids)
    rng = np.random.default_rng(2)
    B = 3
    quat = rng.normal(size=(B, N, 4))
    quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
    qpos = np.concatenate([rng.normal(size=(B, N, 3)), quat], -1)
    qvel = rng.normal(0.0, 10.0, (B, N, 6))
    xfrc = rng.normal(0.0, 1e-3, (B, N, 6))
    mass, inertia = model.body_mass[ids], model.body_inertia[ids]
    q, v = freebody_step(qpos, qvel, xfrc, mass, inertia, k.ipos, k.iquat, k.gravity, k.dt)
    assert q.shape == (B, N, 7) and v.shape == (B, N, 6) and q.dtype == np.float64
    for b in range(B):
        qb, vb = freebody_step(qpos[b], qvel[b], xfrc[b], mass, inertia, k.ipos, k.iquat, k.gravity, k.dt)
        np.testing.assert_array_equal(q[b], qb)
        np.testing.assert_array_equal(v[b], vb)
    np.testing.assert_allclose(np.linalg.norm(q[..., 3:], axis=-1), 1.0, atol=1e-15)


def test_max_omega_clips_angular_velocity_after_the_step() -> None:
    model, ids = _arena_model(N)
    k = freebody_constants(model, ids)
    c = _case(model, ids, seed=3)
    args = (c["qpos"], c["qvel"], c["xfrc"][0], c["mass"], c["inertia"], k.ipos, k.iquat, k.gravity, k.dt)
    q0, v0 = freebody_step(*args)
    q1, v1 = freebody_step(*args, max_omega=10.0)
    np.testing.assert_array_equal(q1, q0)  # positions use the unclipped velocity
    np.testing.assert_array_equal(v1[:, :3], v0[:, :3])
    np.testing.assert_array_equal(v1[:, 3:], np.clip(v0[:, 3:], -10.0, 10.0))
    assert np.abs(v0[:, 3:]).max() > 10.0


def test_zero_angular_velocity_keeps_the_attitude() -> None:
    """No spin, no torque: the quaternion is unchanged and the body falls freely (exact Euler step)."""
    model, ids = _arena_model(2)
    k = freebody_constants(model, ids)
    qpos = np.array([[0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0], [1.0, 2.0, 3.0, 0.5, 0.5, 0.5, 0.5]])
    q, v = freebody_step(qpos, np.zeros((2, 6)), np.zeros((2, 6)), model.body_mass[ids], model.body_inertia[ids],
                         k.ipos, k.iquat, k.gravity, k.dt)
    np.testing.assert_allclose(q[:, 3:], qpos[:, 3:], atol=1e-16)
    np.testing.assert_allclose(v, [[0, 0, -9.81 * k.dt, 0, 0, 0]] * 2, atol=1e-16)
    np.testing.assert_allclose(q[:, :3], qpos[:, :3] + k.dt * v[:, :3], atol=1e-16)


def test_constants_reject_models_outside_the_assumptions() -> None:
    with pytest.raises(ValueError, match="contacts are enabled"):
        a = build_arena(EnvConfig(num_quads=2, collision_model="mujoco"), 1)
        freebody_constants(a.model, a)
    model, ids = _arena_model(2)
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4
    with pytest.raises(ValueError, match="integrator"):
        freebody_constants(model, ids)
    model, ids = _arena_model(2)
    model.dof_damping[:] = 0.1
    with pytest.raises(ValueError, match="damping"):
        freebody_constants(model, ids)
    with pytest.raises(ValueError, match="world must be in"):
        freebody_constants(model, build_arena(EnvConfig(num_quads=2), 1), world=1)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_jit_float64_equals_numpy(name: str) -> None:
    """With x64 on, ``jit(vmap(freebody_step))`` from each of the 200 states of the NumPy rollout gives
    NumPy's next state to round-off (<= 1e-12; XLA contracts and reorders floating-point ops), and a jitted
    ``lax.scan`` rollout of 200 sub-steps stays within 1e-11 of the NumPy one (measured 6e-14 arena,
    3e-13 offset; a seed that spins up to hundreds of rad/s amplifies round-off to ~1e-10)."""
    jax = pytest.importorskip("jax")
    import jax.numpy as jnp

    model, ids = MODELS[name](N)
    k = freebody_constants(model, ids)
    c = _case(model, ids, seed=1)
    ref = _np_rollout(k, c)
    _check_spin(ref[1])
    q_in = np.concatenate([c["qpos"][None], ref[0][:-1]])
    v_in = np.concatenate([c["qvel"][None], ref[1][:-1]])
    with jax.enable_x64(True):
        one = jax.jit(jax.vmap(lambda q, v, x: freebody_step(q, v, x, jnp.asarray(c["mass"]),
                                                             jnp.asarray(c["inertia"]), k.ipos, k.iquat,
                                                             k.gravity, k.dt)))
        step = one(jnp.asarray(q_in), jnp.asarray(v_in), jnp.asarray(c["xfrc"]))
        assert step[0].dtype == jnp.float64
        step = (np.asarray(step[0]), np.asarray(step[1]))
        roll = _jax_rollout(k, c, jnp.float64)
    err_q, err_v = _err(step, ref)
    assert err_q <= 1e-12 and err_v <= 1e-12, (err_q, err_v)
    err_q, err_v = _err(roll, ref)
    assert err_q <= 1e-11 and err_v <= 1e-11, (err_q, err_v)


@pytest.mark.slow  # compiles mjx.step: 13 s on an idle 2-core machine, 45 s under load
def test_float32_matches_mjx_step() -> None:
    """float32 freebody vs float32 ``mjx.step`` on the arena model (random masses and inertias through
    ``model.replace``, as the MJX env does), 200 sub-steps: they agree within float32 round-off growth
    (measured 1.1e-5 on qpos, 3.6e-4 on qvel with |omega| ~ 30 rad/s; bounds 1e-4 and 3e-3), and the
    freebody step is no farther from the float64 truth than mjx.step is (measured: qpos 5e-6 vs 9e-6,
    qvel 3.4e-5 vs 3.6e-4)."""
    jax = pytest.importorskip("jax")
    import jax.numpy as jnp
    from mujoco import mjx

    a = build_arena(EnvConfig(num_quads=N), 1)
    model, ids = a.model, a.body_ids[0]
    k = freebody_constants(model, a)
    c = _case(model, ids, seed=7)
    truth = _np_rollout(k, c)  # float64, = mj_step to 1e-9 (test_matches_mj_step_float64)
    _check_spin(truth[1])
    fb32 = _jax_rollout(k, c, jnp.float32)

    mm = mjx.put_model(model)
    sl = slice(a.first_body, a.first_body + N)
    qs, vs = slice(a.qpos_start, a.qpos_start + 7 * N), slice(a.qvel_start, a.qvel_start + 6 * N)

    def roll(qpos, qvel, xfrc, mass, inertia):
        m = mm.replace(body_mass=mm.body_mass.at[sl].set(mass), body_inertia=mm.body_inertia.at[sl].set(inertia))
        d = mjx.make_data(m)
        d = d.replace(qpos=d.qpos.at[qs].set(qpos.ravel()), qvel=d.qvel.at[vs].set(qvel.ravel()))

        def body(d, x):
            d = mjx.step(m, d.replace(xfrc_applied=d.xfrc_applied.at[sl].set(x)))
            return d, (d.qpos[qs].reshape(N, 7), d.qvel[vs].reshape(N, 6))
        return jax.lax.scan(body, d, xfrc)[1]

    out = jax.jit(roll)(*(jnp.asarray(c[n], jnp.float32) for n in ("qpos", "qvel", "xfrc", "mass", "inertia")))
    mjx32 = (np.asarray(out[0], np.float64), np.asarray(out[1], np.float64))
    err_q, err_v = _err(fb32, mjx32)
    assert err_q <= 1e-4 and err_v <= 3e-3, (err_q, err_v)
    fb_q, fb_v = _err(fb32, truth)
    mjx_q, mjx_v = _err(mjx32, truth)
    assert fb_q <= 3 * mjx_q and fb_v <= 3 * mjx_v, (fb_q, fb_v, mjx_q, mjx_v)
