"""quadswarm_mj.perf.one_quad (the one-quad float forms of the sub-step model) gives the bits of the array
forms: function by function on random inputs (signs of zero included) and over whole seeded episodes of
the single env with random actions (floor hits, staying on the floor, lift-off)."""

from __future__ import annotations

import numpy as np
import pytest
from episode_record import record_random_run

from quadswarm_mj import actuation, collisions
from quadswarm_mj.config import EnvConfig
from quadswarm_mj.core.ops import NumpyOps
from quadswarm_mj.envs.cpu_core import CpuSwarm
from quadswarm_mj.envs.gym_env import QuadSwarmEnv
from quadswarm_mj.perf import numpy_small as small
from quadswarm_mj.perf import one_quad


def _same(a, b):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape and a.dtype == b.dtype
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(np.signbit(a), np.signbit(b))


def _rotations(rng, n):
    q = rng.normal(size=(n, 1, 1, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q[0, 0, 0] = [1.0, 0.0, 0.0, 0.0]
    q[1, 0, 0] = [0.0, 1.0, 0.0, -0.0]
    return q, small.quat_to_rotmat(q)


def test_quat_to_rotmat_is_the_array_form_bitwise():
    rng = np.random.default_rng(4)
    q, _ = _rotations(rng, 500)
    q[2, 0, 0] = [-0.0, 0.0, -1.0, 0.0]
    for i in range(500):
        got = one_quad.quat_to_rotmat(q[i])
        one_quad.ENABLED = False
        try:
            ref = small.quat_to_rotmat(q[i])
        finally:
            one_quad.ENABLED = True
        _same(got, ref)
        _same(small.quat_to_rotmat(q[i, 0, 0]), ref[0, 0])


def test_substep_wrench_is_the_array_forms_bitwise():
    rng = np.random.default_rng(0)
    cfg = EnvConfig(num_quads=1)
    core = CpuSwarm(cfg, visual=False)
    params = {k: v for k, v in core.params.items()}
    _, Rs = _rotations(rng, 200)
    for i in range(200):
        u = rng.uniform(0, 1, (1, 1, 4))
        cmd = rng.choice([0.0, 1.0, 0.3, rng.uniform()], size=(1, 1, 4))
        noise = rng.normal(0, 0.5, (1, 1, 4))
        noise[..., i % 4] = -u[..., i % 4] ** 2  # a thrust of exactly 0 (and of -0.0 rounded)
        got = one_quad.substep_wrench(u, cmd, noise, params["alpha"], params["thrust_max"], core._torque_spin,
                                      core._mix, Rs[i])
        one_quad.ENABLED = False
        try:
            ref = small.substep_wrench(u, cmd, noise, params, Rs[i], core.rotor_pos, core._mix, core._torque_spin)
        finally:
            one_quad.ENABLED = True
        body = actuation.substep_wrench(u, cmd, noise, params, Rs[i], core.rotor_pos, core._mix, core._torque_spin)
        for a, b, c in zip(got, ref, body):
            _same(a, b)
            np.testing.assert_array_equal(a, c)


def test_floor_wrench_is_the_array_forms_bitwise():
    rng = np.random.default_rng(1)
    for i in range(300):
        force = rng.normal(0, 0.3, (1, 1, 3))
        torque = rng.normal(0, 1e-3, (1, 1, 3))
        vel = rng.normal(0, 1, (1, 1, 3))
        if i % 3 == 0:
            vel[..., :2] = 0.0  # at rest: static friction
        if i % 5 == 0:
            force[..., :2] = 0.0
        if i % 7 == 0:
            force[..., 2] = 5.0  # lifting: no normal force
        mass = np.full((1, 1), 0.028 + 0.01 * rng.uniform())
        on = np.array([[i % 11 != 0]])
        args = (on, force, torque, vel, mass, 9.81, 0.3, 0.005)
        got = one_quad.floor_wrench(*args)
        one_quad.ENABLED = False
        try:
            ref = small.floor_wrench(*args)
        finally:
            one_quad.ENABLED = True
        body = collisions.floor_wrench(*args)
        for a, b, c in zip(got, ref, body):
            _same(a, b)
            np.testing.assert_array_equal(a, c)


@pytest.mark.parametrize("stochastic", [True, False])
def test_engine_floor_impact_is_the_array_form_bitwise(stochastic):
    """``CpuSwarm._floor_impact`` with one quad (the float form) = perf.numpy_small's array form."""
    import copy
    import dataclasses

    cfg = EnvConfig(num_quads=1)
    cfg = cfg.replace(noise=dataclasses.replace(cfg.noise, stochastic_collisions=stochastic))
    rng = np.random.default_rng(2)
    quats, Rs = _rotations(rng, 300)
    seen = set()
    core = CpuSwarm(cfg, visual=False)
    core.seed(2)
    core.reset()
    fz = core.floor_z
    for i in range(300):
        core.qpos[0, 0, 2] = rng.choice([fz - 0.01, fz, fz + 5e-7, fz + 0.01, 1.0])
        core.qpos[0, 0, 3:7] = quats[i, 0, 0]
        core.qvel[...] = rng.normal(size=(1, 1, 6))
        if i % 4 == 0:
            core.qvel[...] = -0.0
        core.on_floor = np.array([[bool(rng.uniform() < 0.5)]])
        core.u = rng.uniform(size=(1, 1, 4))
        core.state_changed()
        q, v, u, on = core.qpos.copy(), core.qvel.copy(), core.u.copy(), core.on_floor.copy()
        d = core._spec_floor["yaw"]
        yaw = (copy.deepcopy(core.rng).uniform(d.low, d.high, size=(1, 1)) if stochastic
               else np.full((1, 1), d.mean))
        ref = collisions.floor_impact(q[..., :3], v[..., :3], v[..., 3:], q[..., 3:7],
                                      small.quat_to_rotmat(q[..., 3:7]), u, on, fz, yaw)
        hit_floor = np.zeros((1, 1), bool)
        core._floor_impact(slice(None), hit_floor)
        _same(core.qpos[..., :3], ref["pos"])
        _same(core.qpos[..., 3:7], ref["quat"])
        _same(core.qvel[..., :3], ref["vel"])
        _same(core.qvel[..., 3:], ref["omega"])
        _same(core.u, ref["u"])
        _same(core.on_floor, ref["on_floor"])
        _same(hit_floor, ref["hit_floor"])
        assert core._any_on_floor == bool(core.on_floor.any())
        seen.add((bool(ref["hit_floor"][0, 0]), bool(ref["on_floor"][0, 0]),
                  bool(ref["hit_floor"][0, 0] and Rs[i, 0, 0, 2, 2] < 0)))
    assert {(True, True, True), (True, True, False), (False, True, False), (False, False, False)} <= seen


def _episode(seed: int, enabled: bool, **kw) -> list[np.ndarray]:
    one_quad.ENABLED = enabled
    try:
        env = QuadSwarmEnv(EnvConfig(num_quads=1, episode_seconds=3.0, **kw))
        return record_random_run(env, seed, 700, lambda obs, r, info: [
            obs, r, info["state"]["pos"], info["state"]["vel"], info["state"]["rot"], info["state"]["omega"],
            info["state"]["thrust"], info["on_floor"], info["rewards"], *info["reward_terms"].values()])
    finally:
        one_quad.ENABLED = True


@pytest.mark.parametrize("kw", [{}, {"randomize": True},
                                {"scenario": "dynamic_same_goal", "obs_self": "floor", "normalize_obs": True},
                                {"scenario": "ep_lissajous3D", "rewards": {"anneal_steps": 500}, "sim_hz": 300},
                                {"noise": {"stochastic_collisions": False, "sensor_pos_std": 0.0, "sensor_vel_std": 0.0,
                                           "sensor_omega_std": 0.0, "motor_noise_ratio": 0.0}}])
def test_single_env_episodes_are_the_array_forms_bitwise(kw):
    got, ref = _episode(3, True, **kw), _episode(3, False, **kw)
    assert len(got) == len(ref)
    on_floor = [bool(x) for x in got if np.shape(x) == (1,) and np.asarray(x).dtype == bool]
    assert any(on_floor) and not all(on_floor)  # on the floor and in the air
    for a, b in zip(got, ref):
        _same(a, b)


def _rewards_and_metrics(enabled: bool, scales, seed: int) -> list:
    """reward_terms, total_reward and metrics.update on random one-quad inputs (events, goal jumps), as the
    CPU engine's ops give them (``NumpyOps``: perf.one_quad's forms when enabled)."""
    from quadswarm_mj import metrics as metrics_lib
    from quadswarm_mj import rewards

    cfg = EnvConfig(num_quads=1, rewards=scales)
    ops = NumpyOps(CpuSwarm(cfg, visual=False))
    rng = np.random.default_rng(seed)
    _, Rs = _rotations(rng, 100)
    m = metrics_lib.init(np.zeros((1, 1)), (1,), 1)
    out = []
    one_quad.ENABLED = enabled
    try:
        for i in range(100):
            pos, vel, omega, goals = (rng.normal(size=(1, 1, 3)) for _ in range(4))
            action = rng.normal(0, 1.5, (1, 1, 4))
            f, pf = rng.uniform(size=(1, 1, 4)), rng.uniform(size=(1, 1, 4))
            flags = [rng.uniform(size=(1, 1)) < 0.3 for _ in range(4)]
            contact = rng.uniform(size=(1, 1, 1)) < 0.3
            dist = np.zeros((1, 1, 1))
            gd = None if i % 2 else np.sqrt(((goals - pos) ** 2).sum(-1))
            anneal = min(1.0, i / 50) if i % 3 else np.minimum(1.0, i / 70)
            terms = ops.reward_terms(cfg, pos, vel, Rs[i], omega, goals, action, f, pf, flags[0], *flags[1:],
                                     contact, dist, anneal, goal_dist=gd)
            out += [*terms.values(), ops.total_reward(terms, rewards.zero_terms(cfg))]
            t = np.full((1, 1), 0.01 * i + (3.0 if i > 50 else 0.0))
            d = np.abs(rng.normal(0, 0.4, (1, 1)))
            m = ops.metrics_update(m, t, d, contact, *flags[1:], rng.uniform(size=(1, 1)) < 0.2, 0.3)
            out += list(m.values())
        out += list(metrics_lib.finalize(m, np.array([[2.0]])).values())
    finally:
        one_quad.ENABLED = True
    return out


@pytest.mark.parametrize("which", ["default", "all"])
def test_reward_terms_and_metrics_are_the_array_forms_bitwise(which):
    from quadswarm_mj.config import RewardScales

    scales = RewardScales() if which == "default" else RewardScales(
        **{k: 0.5 + i for i, k in enumerate(RewardScales.TERMS)})
    got, ref = _rewards_and_metrics(True, scales, 7), _rewards_and_metrics(False, scales, 7)
    assert len(got) == len(ref)
    for a, b in zip(got, ref):
        _same(a, b)


@pytest.mark.parametrize("obs_self", ["base", "floor"])
@pytest.mark.parametrize("normalize", [False, True])
def test_build_obs_is_the_array_form_bitwise(obs_self, normalize):
    from quadswarm_mj.observations import obs_bounds, obs_scale

    cfg = EnvConfig(num_quads=1, obs_self=obs_self, normalize_obs=normalize)
    build_obs = NumpyOps(CpuSwarm(cfg, visual=False)).obs  # perf.one_quad's form when enabled
    low, high = obs_bounds(cfg)
    low, high = low.astype(np.float64), high.astype(np.float64)
    scale = obs_scale(cfg) if normalize else None
    rng = np.random.default_rng(5)
    _, Rs = _rotations(rng, 200)
    for i in range(200):
        pos, vel, omega, goals = (rng.normal(0, 20, (1, 1, 3)) for _ in range(4))  # beyond the bounds too
        noise = None if i % 3 == 0 else {k: rng.normal(0, 0.1, (1, 1, 3)) for k in ("pos", "vel", "omega")}
        args = (cfg, pos, vel, Rs[i], omega, goals, noise, low, high, scale)
        got = build_obs(*args)
        one_quad.ENABLED = False
        try:
            ref = build_obs(*args)
        finally:
            one_quad.ENABLED = True
        _same(got, ref)


def test_numpy_ops_route_one_quad_only_to_the_float_forms(monkeypatch):
    """The CPU engine's ops run perf.one_quad_step's whole-stage float forms (on perf.one_quad's bodies) for one
    quad in one world, the model's own functions otherwise (the model modules themselves know nothing of perf)."""
    from quadswarm_mj.perf import one_quad_step

    calls = []
    for name in ("reward_values", "metrics_floats", "obs_values", "wrench_floats", "rotmat_floats"):
        real = getattr(one_quad_step, name)
        monkeypatch.setattr(one_quad_step, name, lambda *a, _n=name, _r=real, **k: calls.append(_n) or _r(*a, **k))
    for n, want in ((1, {"reward_values", "metrics_floats", "obs_values", "wrench_floats", "rotmat_floats"}),
                    (2, set())):
        calls.clear()
        env = QuadSwarmEnv(EnvConfig(num_quads=n, num_neighbors=0))
        env.reset(seed=0)
        env.step(env.action_space.sample())
        assert set(calls) == want, (n, calls)
        ops = env.core._ops
        assert (isinstance(ops.fused_loop, one_quad_step.OneQuadLoop),
                isinstance(ops.fused_task, one_quad_step.OneQuadTask)) == (n == 1,) * 2
        one_quad.ENABLED = False
        try:
            assert not isinstance(ops.fused_loop, one_quad_step.OneQuadLoop)
            assert not isinstance(ops.fused_task, one_quad_step.OneQuadTask)
        finally:
            one_quad.ENABLED = True


def test_numpy_ops_one_quad_wall_gate_and_contacts_are_the_array_forms():
    """NumpyOps' float forms for one quad in one world (the wall/ceiling gate, the pair contacts and
    distances) give the array forms' results, at the bounds and for non-finite positions too."""
    cfg = EnvConfig(num_quads=1)
    ops = NumpyOps(CpuSwarm(cfg, visual=False))
    ref = NumpyOps(CpuSwarm(cfg, visual=False))
    ref._one = False  # the array forms
    lo, hi = np.asarray(cfg.room_low), np.asarray(cfg.room_high)
    rng = np.random.default_rng(11)
    cases = [lo, hi, np.array([lo[0], 0.0, 1.0]), np.array([0.0, hi[1], 1.0]), np.array([0.0, 0.0, hi[2]]),
             np.array([np.nan, 0.0, 1.0]), np.array([np.inf, 0.0, 1.0]), np.array([0.0, 0.0, -np.inf])]
    cases += list(rng.uniform(lo - 0.5, hi + 0.5, (200, 3)))
    for i, p in enumerate(cases):
        pos = np.asarray(p, float).reshape(1, 1, 3)
        flags = [np.array([[bool(i % 3 == 0)]]), np.array([[bool(i % 5 == 0)]])]
        assert ops.wall_gate(pos, *flags) == ref.wall_gate(pos, *flags)
        with np.errstate(invalid="ignore"):  # inf - inf
            got, want = ops.pairwise_contacts(pos, cfg.hitbox), collisions.pairwise_contacts(pos, cfg.hitbox)
        for a, b in zip(got, want):
            _same(a, b)


def test_one_body_omega_clip_is_the_array_clip():
    """MjDataPhysics.step's angular-velocity clip on floats (one body) writes the bits of np.clip."""
    cfg = EnvConfig(num_quads=1)
    m = cfg.quad.max_omega
    for w in ([m + 1.0, -m - 1.0, 0.5], [m, -m, -0.0], [3 * m, 2 * m, -2 * m], [0.0, -0.0, m * 0.999]):
        out = []
        for one in (True, False):
            core = CpuSwarm(cfg, visual=False)
            core.seed(0)
            core.reset()
            core.qvel[0, 0, 3:] = w
            core.phys._one = one
            core.phys.step(m)
            out.append(core.qvel.copy())
        _same(*out)


def test_command_and_motor_noise_are_the_array_forms_bitwise():
    rng = np.random.default_rng(4)
    for i in range(300):
        a = rng.normal(0, 1.5, (1, 1, 4))
        a[0, 0, i % 4] = (-0.0, 1.0, -1.0, 0.0)[i % 4]
        _same(one_quad.action_to_command(a), actuation.action_to_command(a))
        eps, normal, sigma = rng.normal(0, 0.2, (1, 1, 4)), rng.normal(size=(1, 1, 4)), rng.uniform(0, 0.2, (1, 1))
        _same(one_quad.motor_noise_step(eps, sigma, 0.15, normal), actuation.motor_noise_step(eps, sigma, 0.15, normal))


def test_numpy_ops_contacts_of_single_quad_worlds_are_the_array_forms():
    """B worlds of one quad each (a vector env): no pair; distances ||p - p|| as the norm gives them."""
    cfg = EnvConfig(num_quads=1)
    ops = NumpyOps(CpuSwarm(cfg, num_worlds=4, visual=False))
    pos = np.random.default_rng(2).normal(size=(4, 1, 3))
    pos[1, 0, 2], pos[2, 0, 0] = np.nan, -np.inf
    with np.errstate(invalid="ignore"):
        got, want = ops.pairwise_contacts(pos, cfg.hitbox), collisions.pairwise_contacts(pos, cfg.hitbox)
    for a, b in zip(got, want):
        _same(a, b)


@pytest.mark.parametrize("backend", ["mjdata", "batch"])
def test_engine_one_quad_runs_are_the_array_forms_bitwise(backend):
    """The one-quad engine (perf.one_quad_step's loop and task) on both physics back ends: a seeded run with
    falls and lift-offs gives the array forms' bits."""
    out = []
    for enabled in (True, False):
        one_quad.ENABLED = enabled
        try:
            core = CpuSwarm(EnvConfig(num_quads=1), 1, backend=backend, visual=False)
            core.seed(3)
            core.reset()
            rng = np.random.default_rng(4)
            run = []
            for _ in range(400):
                o = core.step(np.clip(-0.3 + rng.standard_normal((1, 1, 4)), -1, 1))
                run += [o["obs"], o["rewards"], *o["terms"].values(), core.qpos.copy(), core.qvel.copy(),
                        core.on_floor.copy(), *core.metrics.values()]
            out.append(run)
        finally:
            one_quad.ENABLED = True
    for a, b in zip(*out):
        _same(a, b)
