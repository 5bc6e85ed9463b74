"""Physics of the model (SPEC §1-6), checked through the public env and the pure functions."""

from __future__ import annotations

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, QuadParams, QuadSwarmEnv
from quadswarm_mj.actuation import SPIN, rotor_positions
from quadswarm_mj.collisions import floor_wrench, quad_collision_draw_spec, quad_collisions
from quadswarm_mj.downwash import apply_downwash, downwash_draw_spec
from quadswarm_mj.random_draws import MeanSampler, NumpySampler

Q = QuadParams()
HOVER = Q.hover_action
ARM = Q.arm


def make_env(n=1, **kw) -> QuadSwarmEnv:
    return QuadSwarmEnv(EnvConfig(num_quads=n, **kw).without_noise())


def start(env, pos, vel=None, motors="hover", omega=None):
    n = len(pos)
    state = {"pos": np.asarray(pos, float), "vel": np.zeros((n, 3)) if vel is None else np.asarray(vel, float),
             "rot": np.tile(np.eye(3), (n, 1, 1)), "omega": np.zeros((n, 3)) if omega is None else omega,
             "motors": motors}
    return env.reset(seed=0, options={"state": state})[1]


def act(env, a):
    return env.step(a[0] if env.cfg.num_quads == 1 else a)[4]


def test_hover_thrust_balances_gravity():
    assert 4 * Q.thrust_max * Q.hover_command == pytest.approx(Q.mass * Q.gravity, rel=1e-12)
    assert Q.thrust_max == pytest.approx(0.130473, abs=1e-6) and Q.torque_max == pytest.approx(7.82838e-4, rel=1e-5)
    assert Q.hover_action == pytest.approx(0.0526316, abs=1e-7)


def test_hover_holds_altitude():
    env = make_env()
    start(env, [[0.0, 0.0, 2.0]])
    for _ in range(300):
        info = act(env, np.full((1, 4), HOVER))
    np.testing.assert_allclose(info["state"]["pos"], [[0.0, 0.0, 2.0]], atol=1e-9)
    np.testing.assert_allclose(info["state"]["vel"], 0.0, atol=1e-9)


def test_free_fall():
    env = make_env()
    start(env, [[0.0, 0.0, 8.0]], motors="zero")
    for k in range(1, 101):
        info = act(env, np.full((1, 4), -1.0))
        t = k * 0.01
        assert info["state"]["vel"][0, 2] == pytest.approx(-9.81 * t, rel=1e-9)
    # semi-implicit Euler: z = z0 - g dt^2 k(k+1)/2 with k sub-steps; continuous: z0 - g t^2 / 2
    assert info["state"]["pos"][0, 2] == pytest.approx(8.0 - 0.5 * 9.81 * 1.0**2, abs=0.03)
    np.testing.assert_allclose(info["state"]["pos"][0, :2], 0.0, atol=1e-12)


def test_motor_settling_time():
    env = make_env()
    start(env, [[0.0, 0.0, 5.0]], motors="zero")
    thrust = []
    for _ in range(20):  # 0.2 s full command
        thrust.append(act(env, np.ones((1, 4)))["state"]["thrust"][0, 0])
    speed = np.sqrt(thrust)  # normalized rotor speed u
    assert speed[14] >= 0.98  # within 2 % after the 0.15 s settling time (15 control steps)
    assert speed[9] < 0.98  # but not after 0.1 s
    assert speed[0] > 0  # the lag is a first-order filter, not a delay


@pytest.mark.parametrize("rotor", [0, 1, 2, 3])
def test_each_rotor_rolls_pitches_and_yaws_the_right_way(rotor):
    env = make_env()
    start(env, [[0.0, 0.0, 5.0]])
    a = np.full((1, 4), HOVER)
    a[0, rotor] += 0.1
    for _ in range(10):
        info = act(env, a)
    R = info["state"]["rot"][0]
    r = rotor_positions(Q)
    z_world = (R @ r.T)[2]  # world height of each rotor relative to the COM
    opposite = (rotor + 2) % 4
    assert z_world[rotor] > z_world[opposite] + 1e-3  # the side with more thrust rises
    assert np.sign(info["state"]["omega"][0, 2]) == SPIN[rotor]  # yaw reaction torque sign


def test_headon_collision_conserves_momentum_with_unit_decay():
    env = QuadSwarmEnv(EnvConfig(num_quads=2, collision_decay=(1.0, 1.0)).without_noise())
    info = start(env, [[-0.3, 0.1, 2.0], [0.3, 0.0, 2.0]], vel=[[1.5, 0, 0], [-1.0, 0.2, 0]])
    p0 = info["state"]["vel"].sum(0)
    seen = False
    for _ in range(40):
        prev = info["state"]["vel"].copy()
        info = act(env, np.full((2, 4), HOVER))
        if info["new_collisions"].any():
            seen = True
            np.testing.assert_allclose(info["state"]["vel"].sum(0), prev.sum(0), atol=1e-9)
            n = info["state"]["pos"][0] - info["state"]["pos"][1]
            assert info["state"]["vel"][0] @ n > 0 > info["state"]["vel"][1] @ n  # they separate
            break
    assert seen
    assert np.abs(p0).sum() > 0


def test_collision_response_is_pure_and_conserves_momentum_batched():
    pos = np.array([[0.0, 0, 2], [0.05, 0.02, 2.0], [3.0, 0, 2], [3.0, 0.07, 2.0]])[None]
    vel = np.zeros((1, 4, 3))
    for i, j in ((0, 1), (2, 3)):  # approaching along the normal, sharing a tangential velocity
        n = (pos[0, i] - pos[0, j]) / np.linalg.norm(pos[0, i] - pos[0, j])
        t = np.cross(n, [0.0, 0.0, 1.0]) * 0.3
        vel[0, i], vel[0, j] = -1.0 * n + t, 0.5 * n + t
    draws = MeanSampler().draw(quad_collision_draw_spec(4, 3, 0.8, 0.15, (1.0, 1.0), (1.0, 2.0)), (1,))
    out = quad_collisions(pos, vel, np.zeros((1, 4, 3)), np.zeros((1, 4, 4), bool), 2 * ARM, draws)
    assert out["new_contact"][0, 0, 1] and out["new_contact"][0, 2, 3] and not out["new_contact"][0, 0, 2]
    np.testing.assert_allclose(out["vel"].sum(1), vel.sum(1), atol=1e-12)
    # already-colliding pairs get no new response
    again = quad_collisions(pos, out["vel"], out["omega"], out["contact"], 2 * ARM, draws)
    np.testing.assert_array_equal(again["vel"], out["vel"])


def test_collision_noise_separates_pairs():
    rng = np.random.default_rng(1)
    sampler = NumpySampler(rng)
    spec = quad_collision_draw_spec(2, 3, 0.8, 0.15, (0.2, 0.8), (10 * np.pi, 20 * np.pi))
    ok = 0
    for _ in range(200):
        pos = np.array([[[-0.04, 0, 2], [0.04, 0, 2]]])
        vel = np.array([[[1.0, 0, 0], [-1.0, 0, 0]]]) + rng.normal(0, 0.1, (1, 2, 3))
        out = quad_collisions(pos, vel, np.zeros((1, 2, 3)), np.zeros((1, 2, 2), bool), 2 * ARM,
                              sampler.draw(spec, (1,)))
        n = pos[0, 0] - pos[0, 1]
        ok += out["vel"][0, 0] @ n > 0 > out["vel"][0, 1] @ n
        assert np.linalg.norm(out["vel"][0], axis=-1).max() <= np.linalg.norm(vel[0], axis=-1).max() + 1e-12
        assert np.abs(out["omega"]).max() > 10  # angular kick
    assert ok >= 195


def test_downwash_only_inside_the_cylinder_below():
    # quad 0 at 2 m; quad 1 0.3 m straight below it (inside); quad 2 0.3 m below but 0.3 m aside
    # (outside the 0.1 m radius); quad 4 0.8 m below quad 3 (deeper than 0.7 m); quad 5 alone.
    pos = np.array([[0.0, 0, 2.0], [0.0, 0, 1.7], [0.3, 0, 1.7], [2.0, 0, 2.0], [2.0, 0, 1.2], [-3.0, 3, 2]])
    R = np.tile(np.eye(3), (6, 1, 1))
    vel = np.zeros((6, 3))
    draws = MeanSampler().draw(downwash_draw_spec(6))
    v, w = apply_downwash(pos, vel, np.zeros((6, 3)), R, 0.01, draws)
    assert v[1, 2] < 0 and v[1, 2] == pytest.approx(-(6 / 17) * (7 - 3.0) * 0.01, rel=1e-3)
    np.testing.assert_array_equal(v[[0, 2, 3, 4, 5]], 0.0)
    np.testing.assert_array_equal(w, 0.0)  # noise off: no angular term
    # through the env, with downwash on: the lower quad is pushed down relative to a lone quad
    def run(downwash: bool) -> float:
        env = QuadSwarmEnv(EnvConfig(num_quads=2, downwash=downwash).without_noise())
        start(env, [[0.0, 0.0, 2.0], [0.0, 0.0, 1.6]])
        for _ in range(20):
            info = act(env, np.full((2, 4), HOVER))
        return info["state"]["pos"]
    on, off = run(True), run(False)
    assert on[1, 2] < off[1, 2] - 1e-3 and on[0, 2] == pytest.approx(off[0, 2], abs=1e-12)


def test_grounded_quad_below_friction_does_not_slide():
    env = make_env()
    info = start(env, [[1.0, -1.0, ARM]], motors="zero")
    a = np.array([[0.3, 0.3, -0.5, -0.5]])  # uneven, total thrust below weight
    for _ in range(100):
        info = act(env, a)
    np.testing.assert_allclose(info["state"]["pos"][0], [1.0, -1.0, ARM], atol=1e-12)
    assert info["on_floor"][0]
    # pure function: a horizontal force below mu N at rest is cancelled; above it, reduced by mu N
    f = np.array([[0.05, 0.0, 0.1]])
    weight = Q.mass * Q.gravity
    new_f, _ = floor_wrench(np.array([True]), f, np.zeros((1, 3)), np.zeros((1, 3)), np.array([Q.mass]), Q.gravity,
                            0.6, 0.005)
    assert 0.05 < 0.6 * (weight - 0.1)
    np.testing.assert_allclose(new_f[0], [0.0, 0.0, weight], atol=1e-15)
    big = np.array([[0.5, 0.0, 0.1]])
    new_f, _ = floor_wrench(np.array([True]), big, np.zeros((1, 3)), np.zeros((1, 3)), np.array([Q.mass]), Q.gravity,
                            0.6, 0.005)
    assert new_f[0, 0] == pytest.approx(0.5 - 0.6 * (weight - 0.1))


def test_kinetic_friction_stops_a_sliding_quad():
    env = make_env()
    start(env, [[0.0, 0.0, ARM]], vel=[[1.0, 0.0, 0.0]], motors="zero")
    for _ in range(50):
        info = act(env, np.full((1, 4), -1.0))
    stop = 1.0**2 / (2 * 0.6 * 9.81)  # v^2 / (2 mu g)
    assert abs(info["state"]["vel"][0, 0]) < 1e-12
    assert info["state"]["pos"][0, 0] == pytest.approx(stop, abs=0.01)


def test_wall_bounce_noise_free():
    env = QuadSwarmEnv(EnvConfig(num_quads=1, room_size=(4, 4, 4)).without_noise())
    start(env, [[1.9, 0.0, 2.0]], vel=[[2.0, 0.0, 0.0]])
    for _ in range(10):
        info = act(env, np.full((1, 4), HOVER))
        if info["state"]["vel"][0, 0] < 0:
            break
    v = info["state"]["vel"][0]
    assert info["state"]["pos"][0, 0] <= 2.0
    assert v[0] < 0 and v[2] < 0 and abs(v[1]) < 1e-9  # straight back, with a downward component
    assert np.linalg.norm(v) == pytest.approx(0.5 * 2.0, rel=0.02)  # decay mean 0.5


def test_randomization_reaches_the_physics():
    env = QuadSwarmEnv(EnvConfig(num_quads=8, randomize=True))
    _, info = env.reset(seed=0)
    m = info["params"]["mass"]
    assert m.shape == (8,) and np.ptp(m) > 0 and np.all((m >= 0.8 * Q.mass) & (m <= 1.2 * Q.mass))
    ids = env.core.arena.body_ids[0]
    np.testing.assert_allclose(env.core.model.body_mass[ids], m)
    np.testing.assert_allclose(env.core.model.body_inertia[ids], info["params"]["inertia"])
    tm = info["params"]["thrust_max"]
    assert tm.shape == (8, 4) and np.ptp(tm) > 0
    _, info2 = env.reset()
    assert not np.array_equal(info2["params"]["mass"], m)  # redrawn every reset
    # the nominal hover command no longer balances each quad: heavier quads sink
    env = QuadSwarmEnv(EnvConfig(num_quads=8, randomize=True, noise={"motor_noise_ratio": 0.0}))
    _, info = env.reset(seed=1, options={"state": {"pos": np.c_[np.arange(8.0) - 4, np.zeros(8), np.full(8, 5.0)],
                                                   "rot": np.tile(np.eye(3), (8, 1, 1)), "motors": "hover"}})
    for _ in range(30):
        _, _, _, _, info = env.step(np.full((8, 4), HOVER))
    ratio = info["params"]["thrust_max"].sum(-1) / 4 / Q.thrust_max / (info["params"]["mass"] / Q.mass)
    dz = info["state"]["pos"][:, 2] - 5.0
    heavy, light = np.argmin(ratio), np.argmax(ratio)
    assert dz[heavy] < dz[light]


@pytest.mark.parametrize("backend", ["mjdata", "batch"])
def test_randomized_mass_and_inertia_reach_the_dynamics(backend):
    """Drawn masses and inertias act in MuJoCo's mass matrix, not only in gravity: free fall is g for
    every mass, a constant thrust F accelerates by F / m - g, and a torque by tau / I."""
    from quadswarm_mj.envs.cpu_core import CpuSwarm

    cfg = EnvConfig(num_quads=3, randomize=True, motor_start="hover").without_noise().replace(randomize=True)
    core = CpuSwarm(cfg, 4, backend=backend, chunk_worlds=2)
    core.seed(1)
    core.reset()
    m, inertia = core.params["mass"], core.params["inertia"]
    assert np.ptp(m) > 1e-3  # the draws differ
    core.qpos[..., 2] = 5.0
    core.qvel[...] = 0.0
    core.state_changed()
    dt = cfg.sim_dt
    F, tau = 0.2, 1e-5
    core.xfrc[...] = 0.0
    core.xfrc[..., 2] = F
    core.xfrc[..., 5] = tau  # world z torque = body z torque (the spawn rotation is a yaw)
    core.phys.step(cfg.quad.max_omega)
    acc_z = core.qvel[..., 2] / dt
    np.testing.assert_allclose(acc_z, F / m - cfg.quad.gravity, rtol=1e-9)
    np.testing.assert_allclose(core.qvel[..., 5] / dt, tau / inertia[..., 2], rtol=1e-9)
