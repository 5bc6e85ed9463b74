"""Baseline position controller: flies formations, holds a hover, tracks a moving goal; its
mixer is the inverse of the actuation model; it works on (B, N) batches and respects limits."""

from __future__ import annotations

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, QuadParams, QuadSwarmEnv, list_scenarios
from quadswarm_mj.actuation import body_wrench, rotor_positions
from quadswarm_mj.controllers import ControllerGains, PositionController
from quadswarm_mj.spatial import quat_to_rotmat


def fly(env: QuadSwarmEnv, seconds: float, seed: int, use_params: bool = True):
    """Run the controller; return distances to goal (T, N), z (T, N), the env and the last info."""
    obs, info = env.reset(seed=seed)
    ctrl = PositionController(env.cfg)
    dists, zs = [], []
    for _ in range(int(round(seconds * env.cfg.control_hz))):
        a = ctrl(info["state"], info["goals"], info["goal_vel"], info["params"] if use_params else None)
        obs, _, _, _, info = env.step(a.reshape(env.action_space.shape))
        dists.append(np.linalg.norm(info["state"]["pos"] - info["goals"], axis=-1))
        zs.append(info["state"]["pos"][:, 2])
    return np.array(dists), np.array(zs), env, info


def assert_airborne(env: QuadSwarmEnv, zs: np.ndarray) -> None:
    assert not env.core.on_floor.any(), "a quad ended on the floor"
    assert zs[-1].min() > 0.3


@pytest.mark.parametrize("seed", [0, 1])
def test_formation_static_diff_goal_8_quads(seed):
    env = QuadSwarmEnv(num_quads=8, scenario="static_diff_goal")  # default noise on, motors start at 0
    assert env.cfg.noise.motor_noise_ratio > 0 and env.cfg.motor_start == "zero"
    d, zs, env, info = fly(env, 6.0, seed)
    assert d[-1].mean() <= 0.15, d[-1]
    assert d[0].mean() > 0.5  # it really had to fly there
    assert_airborne(env, zs)
    assert env.core.episode_metrics()["collisions"][0] == 0


def test_single_quad_holds_static_goal():
    env = QuadSwarmEnv(num_quads=1, scenario="static_same_goal")
    d, zs, env, _ = fly(env, 4.0, seed=3)
    assert d[-1, 0] <= 0.1
    assert d[-100:].max() <= 0.1  # holds it over the last second, not just passes through
    assert_airborne(env, zs)


def test_motor_spin_up_sag_is_small():
    """Motors start at zero speed (the default): started at its goal, the quad sags while they
    spin up; the controller saturates thrust so the sag stays a few cm (hover command: ~1 m)."""
    env = QuadSwarmEnv(num_quads=1, scenario="static_same_goal")
    goal = np.array([[0.0, 0.0, 2.0]])
    obs, info = env.reset(seed=5, options={"state": {"pos": goal, "goals": goal}})
    assert np.all(info["state"]["thrust"] == 0)
    ctrl = PositionController(env.cfg)
    zs = []
    for _ in range(200):
        _, _, _, _, info = env.step(ctrl(info["state"], info["goals"]).reshape(4))
        zs.append(info["state"]["pos"][0, 2])
    assert 2.0 - min(zs) < 0.1
    assert abs(zs[-1] - 2.0) < 0.05


def test_tracks_lissajous_goal():
    assert "ep_lissajous3D" in list_scenarios()
    env = QuadSwarmEnv(num_quads=1, scenario="ep_lissajous3D")
    d, zs, env, _ = fly(env, 10.0, seed=0)
    assert d[400:].mean() <= 0.5  # from 4 s to 10 s
    assert_airborne(env, zs)


def test_tracks_lissajous_curve_with_feedforward():
    """SPEC §10's curve fed directly (independent of the scenario): goal and goal velocity."""
    env = QuadSwarmEnv(num_quads=1, scenario="static_same_goal")
    obs, info = env.reset(seed=0)
    ctrl = PositionController(env.cfg)

    def curve(t):
        p = np.array([-2.0, 0.0, 2.0]) + np.array([np.sin(0.4 * t), 0.6 * np.sin(0.8 * t + np.pi / 2),
                                                     0.3 * np.cos(0.8 * t + np.pi / 2)])
        v = np.array([0.4 * np.cos(0.4 * t), 0.48 * np.cos(0.8 * t + np.pi / 2), -0.24 * np.sin(0.8 * t + np.pi / 2)])
        return p[None], v[None]

    d = []
    for k in range(1000):
        g, gv = curve(k * 0.01)
        _, _, _, _, info = env.step(ctrl(info["state"], g, gv, info["params"]).reshape(4))
        d.append(np.linalg.norm(info["state"]["pos"][0] - curve((k + 1) * 0.01)[0][0]))
    assert np.mean(d[400:]) <= 0.15


def test_randomized_airframes_with_their_params():
    env = QuadSwarmEnv(num_quads=8, scenario="static_diff_goal", randomize=True)
    d, zs, env, info = fly(env, 6.0, seed=2)
    assert np.ptp(info["params"]["mass"]) > 0.005  # the airframes really differ
    assert d[-1].mean() <= 0.15
    assert_airborne(env, zs)


def test_optional_avoidance_keeps_a_shared_goal_collision_free():
    """8 quads sent to one point collide without avoidance; with ``avoid_radius`` they cluster."""
    def run(gains):
        env = QuadSwarmEnv(num_quads=8, scenario="static_same_goal", episode_seconds=6.0)
        obs, info = env.reset(seed=0)
        ctrl = PositionController(env.cfg, gains=gains)
        for _ in range(600):
            obs, _, _, _, info = env.step(ctrl(info["state"], info["goals"], info["goal_vel"], info["params"]))
        return info["episode_metrics"], np.linalg.norm(info["state"]["pos"] - info["goals"], axis=-1)

    m_off, _ = run(None)
    m_on, d_on = run(ControllerGains(avoid_radius=0.3))
    assert m_off["collisions"] > 1
    assert m_on["collisions"] == 0 and m_on["floor_hits"] == 0
    assert d_on.max() < 0.5


def test_hover_equilibrium_gives_hover_action():
    q = QuadParams()
    ctrl = PositionController(EnvConfig())
    n = 3
    state = {"pos": np.tile([0.0, 0.0, 2.0], (n, 1)), "vel": np.zeros((n, 3)),
             "rot": np.tile(np.eye(3), (n, 1, 1)), "omega": np.zeros((n, 3))}
    a = ctrl(state, state["pos"].copy())
    np.testing.assert_allclose(a, q.hover_action, atol=1e-9)
    heavy = ctrl(state, state["pos"].copy(), params={"mass": np.full(n, 1.2 * q.mass)})
    np.testing.assert_allclose(heavy, 2 * 1.2 * q.hover_command - 1, atol=1e-9)


def test_mixer_is_the_actuation_model():
    """mixer(f) equals (F_z, torque) of actuation.body_wrench, so its inverse is exact."""
    rng = np.random.default_rng(0)
    q = QuadParams()
    ctrl = PositionController(q)
    tm = q.thrust_max * rng.uniform(0.9, 1.1, (5, 4))
    qm = q.torque_max * rng.uniform(0.8, 1.2, (5, 4))
    f = rng.uniform(0, 1, (5, 4))
    force, torque = body_wrench(f, tm, qm, rotor_positions(q))
    w = np.einsum("nij,nj->ni", ctrl.mixer(tm, qm), f)
    np.testing.assert_allclose(w[:, 0], force[:, 2], rtol=1e-12)
    np.testing.assert_allclose(w[:, 1:], torque, rtol=1e-12, atol=1e-15)


def test_extreme_states_give_actions_in_range():
    rng = np.random.default_rng(1)
    n = 64
    quat = rng.normal(size=(n, 4))
    state = {"pos": rng.uniform(-4, 4, (n, 3)) + [0, 0, 5], "vel": rng.uniform(-8, 8, (n, 3)),
             "rot": quat_to_rotmat(quat / np.linalg.norm(quat, axis=1, keepdims=True)),
             "omega": rng.uniform(-40, 40, (n, 3))}
    a = PositionController(EnvConfig())(state, rng.uniform(-4, 4, (n, 3)) + [0, 0, 5])
    assert a.shape == (n, 4) and np.isfinite(a).all()
    assert (a >= -1).all() and (a <= 1).all()


def test_allocation_exact_when_feasible_attitude_first_when_not():
    q = QuadParams()
    ctrl = PositionController(q)
    rng = np.random.default_rng(4)
    n = 200
    tm = q.thrust_max * rng.uniform(0.9, 1.1, (n, 4))
    qm = q.torque_max * rng.uniform(0.8, 1.2, (n, 4))
    M = ctrl.mixer(tm, qm)
    # feasible wrenches (made from rotor thrusts in [0.1, 0.9]) are reproduced exactly
    w = np.einsum("nij,nj->ni", M, rng.uniform(0.1, 0.9, (n, 4)))
    f = ctrl.allocate(w[:, 0], w[:, 1:], tm, qm)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", M, f), w, rtol=1e-9, atol=1e-12)
    # far too much roll/pitch torque: rotors saturate, the roll/pitch direction is kept
    tau = rng.normal(size=(n, 3)) * [0.05, 0.05, 0.0]
    f = ctrl.allocate(np.full(n, 4 * q.mass * q.gravity), tau, tm, qm)
    assert (f >= 0).all() and (f <= 1).all()
    got = np.einsum("nij,nj->ni", M, f)[:, 1:3]
    cos = np.sum(got * tau[:, :2], 1) / (np.linalg.norm(got, axis=1) * np.linalg.norm(tau[:, :2], axis=1))
    assert cos.min() > 1 - 1e-9
    assert (np.ptp(f, axis=1) > 0.999).all()  # the full differential range is used
    # a collective above the limit is cut, the torque is still exact
    tau = rng.normal(size=(n, 3)) * [1e-3, 1e-3, 1e-4]
    f = ctrl.allocate(np.full(n, 10.0), tau, tm, qm)
    got = np.einsum("nij,nj->ni", M, f)
    np.testing.assert_allclose(got[:, 1:], tau, rtol=1e-9, atol=1e-12)
    assert (got[:, 0] < 4 * q.thrust_max * 1.1).all() and np.isclose(f.max(axis=1), 1).all()


def test_batched_worlds_match_single_calls():
    rng = np.random.default_rng(2)
    B, N = 3, 5
    quat = rng.normal(size=(B, N, 4))
    state = {"pos": rng.uniform(0, 3, (B, N, 3)), "vel": rng.normal(size=(B, N, 3)),
             "rot": quat_to_rotmat(quat / np.linalg.norm(quat, axis=-1, keepdims=True)),
             "omega": rng.normal(size=(B, N, 3))}
    goals = rng.uniform(0, 3, (B, N, 3))
    params = {"mass": rng.uniform(0.025, 0.03, (B, N)), "thrust_max": rng.uniform(0.12, 0.14, (B, N, 4))}
    ctrl = PositionController(EnvConfig())
    a = ctrl(state, goals, params=params)
    assert a.shape == (B, N, 4)
    for b in range(B):
        ab = ctrl({k: v[b] for k, v in state.items()}, goals[b], params={k: v[b] for k, v in params.items()})
        np.testing.assert_allclose(a[b], ab, rtol=0, atol=1e-12)


def test_runs_on_jax_numpy():
    jnp = pytest.importorskip("jax.numpy")
    rng = np.random.default_rng(3)
    n = 4
    quat = rng.normal(size=(n, 4))
    state = {"pos": rng.uniform(0, 3, (n, 3)), "vel": rng.normal(size=(n, 3)),
             "rot": quat_to_rotmat(quat / np.linalg.norm(quat, axis=-1, keepdims=True)),
             "omega": rng.normal(size=(n, 3))}
    goals = rng.uniform(0, 3, (n, 3))
    ctrl = PositionController(EnvConfig())
    a_np = ctrl(state, goals)
    a_jx = ctrl({k: jnp.asarray(v, dtype=jnp.float32) for k, v in state.items()}, jnp.asarray(goals, jnp.float32))
    assert type(a_jx).__module__.startswith("jax")
    np.testing.assert_allclose(np.asarray(a_jx), a_np, atol=2e-3)


def test_bad_input_raises_value_errors():
    ctrl = PositionController(EnvConfig())
    state = {"pos": np.zeros((2, 3)), "vel": np.zeros((2, 3)), "rot": np.tile(np.eye(3), (2, 1, 1)),
             "omega": np.zeros((2, 3))}
    with pytest.raises(ValueError, match="goals"):
        ctrl(state, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="state"):
        ctrl({"pos": np.zeros((2, 3))}, np.zeros((2, 3)))
    with pytest.raises(ValueError, match="kp"):
        ControllerGains(kp=-1.0)
    with pytest.raises(ValueError, match="cfg"):
        PositionController("cf2")


def test_holds_a_goal_on_the_identified_preset():
    """With a nonlinear thrust map (preset "crazyflie21_identified") the controller's actions go
    through the inverse map: it holds a static goal within 0.1 m from a motors-off start."""
    env = QuadSwarmEnv(num_quads=1, scenario="static_same_goal", quad="crazyflie21_identified")
    d, zs, env, _ = fly(env, 4.0, seed=3)
    assert d[-100:].max() <= 0.1
    assert_airborne(env, zs)
