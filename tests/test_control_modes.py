"""Control modes (quadswarm_mj.control_modes): constant commands reach the commanded rate,
attitude or velocity in closed loop on MuJoCo, NumPy and jax.jit agree, bounds are physical.

The closed-loop driver (tests/closed_loop.py) integrates one world the way the CPU engine's
sub-step loop does: mode_command -> substep_wrench (motor lag, noise, thrust map) ->
xfrc_applied -> mj_step -> omega clip, at the physics rate."""

from __future__ import annotations

import math

import numpy as np
import pytest
from closed_loop import make_params, run_closed_loop

from quadswarm_mj.config import EnvConfig, QuadParams
from quadswarm_mj.control_modes import (
    MAX_SPEED,
    control_action_bounds,
    init_control_state,
    make_mode_controller,
    mode_command,
)
from quadswarm_mj.spatial import quat_to_rotmat


def euler_zyx(R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(roll, pitch, yaw) rad of body->world ``R`` = Rz(yaw) Ry(pitch) Rx(roll)."""
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    pitch = -np.arcsin(np.clip(R[..., 2, 0], -1.0, 1.0))
    return roll, pitch, np.arctan2(R[..., 1, 0], R[..., 0, 0])


def _params(cfg: EnvConfig, seed: int | None = None) -> dict:
    return make_params(cfg, seed)


CFG = EnvConfig(num_quads=2)


def _hover_thrust(cfg: EnvConfig) -> float:
    return cfg.quad.mass * cfg.quad.gravity


#: the airframes the closed-loop tests fly: nominal and noise-free; randomized airframe (seed 3,
#: noise-free); nominal with the paper's motor noise on (tolerances x ``NOISY_FACTOR``, on means)
CASES = ["nominal", "randomized", "noisy"]
NOISY_FACTOR = 5.0


def _case(mode: str, case: str) -> tuple[EnvConfig, int | None, float]:
    cfg = CFG.replace(control_mode=mode)
    if case == "noisy":
        return cfg, None, NOISY_FACTOR
    cfg = cfg.without_noise()
    if case == "randomized":
        return cfg.replace(randomize=True), 3, 1.0
    return cfg, None, 1.0


@pytest.mark.parametrize("case", CASES)
def test_ctbr_constant_rates(case: str) -> None:
    """Constant body rates: from 0.6 s to 1 s every body rate is within 0.02 rad/s of the
    command. With the paper's motor noise the body rates wander by up to ~0.7 rad/s (a P rate
    loop against a 1 % thrust noise per rotor); their mean over the window is within 0.25 rad/s."""
    cfg, seed, tol = _case("ctbr", case)
    rates = np.array([[0.5, -0.3, 1.0], [-0.4, 0.2, -2.0]])
    action = np.concatenate([np.full((2, 1), _hover_thrust(cfg)), rates], -1)
    tr = run_closed_loop(cfg, action, 1.0, seed=seed)
    w = tr["omega"][60:]
    if case == "noisy":
        np.testing.assert_allclose(w.mean(0), rates, atol=0.25)
    else:
        np.testing.assert_allclose(w, np.broadcast_to(rates, w.shape), atol=0.02)


@pytest.mark.parametrize("case", CASES)
def test_attitude_constant_angles(case: str) -> None:
    """Constant roll/pitch (and a yaw rate): ZYX roll and pitch within 0.02 rad from 0.6 s to 1 s,
    the body yaw rate (mean) within 0.05 rad/s (tolerances x5 with motor noise)."""
    cfg, seed, tol = _case("attitude", case)
    att = np.array([[0.2, -0.1, 0.5], [-0.15, 0.25, 0.0]])
    action = np.concatenate([np.full((2, 1), _hover_thrust(cfg)), att], -1)
    tr = run_closed_loop(cfg, action, 1.0, seed=seed)
    roll, pitch, _ = euler_zyx(tr["rot"][60:])
    np.testing.assert_allclose(roll, np.broadcast_to(att[:, 0], roll.shape), atol=0.02 * tol)
    np.testing.assert_allclose(pitch, np.broadcast_to(att[:, 1], pitch.shape), atol=0.02 * tol)
    np.testing.assert_allclose(tr["omega"][60:, :, 2].mean(0), att[:, 2], atol=0.05 * tol)


@pytest.mark.parametrize("case", CASES)
def test_velocity_constant_velocity(case: str) -> None:
    """Constant world velocity: every axis within 0.05 m/s from 3 s to 3.5 s (mean within 0.25
    m/s with motor noise), the yaw rate (mean) within 0.05 rad/s (x5 with noise)."""
    cfg, seed, tol = _case("velocity", case)
    action = np.array([[1.0, -0.5, 0.3, 0.0], [-0.6, 0.4, -0.2, 1.0]])
    tr = run_closed_loop(cfg, action, 3.5, seed=seed)
    v = tr["vel"][300:]
    if case == "noisy":
        np.testing.assert_allclose(v.mean(0), action[:, :3], atol=0.05 * tol)
    else:
        np.testing.assert_allclose(v, np.broadcast_to(action[:, :3], v.shape), atol=0.05)
    np.testing.assert_allclose(tr["omega"][300:, 1, 2].mean(0), 1.0, atol=0.05 * tol)


def test_hover_commands_hold_still_on_the_identified_preset() -> None:
    """Through the nonlinear thrust map: ctbr with m g and zero rates keeps the quad level and
    its vertical speed below 0.05 m/s (the inverse map is applied)."""
    cfg = EnvConfig(num_quads=1, quad="crazyflie21_identified", control_mode="ctbr").without_noise()
    tr = run_closed_loop(cfg, np.array([[_hover_thrust(cfg), 0.0, 0.0, 0.0]]), 1.0)
    assert np.abs(tr["vel"]).max() < 0.05
    assert np.abs(tr["omega"]).max() < 1e-6


def test_bounds_are_physical() -> None:
    q = QuadParams()
    lo, hi = control_action_bounds(EnvConfig(control_mode="ctbr"))
    np.testing.assert_allclose(hi, [4 * q.thrust_max, q.max_omega, q.max_omega, q.max_omega])
    np.testing.assert_allclose(lo, [0.0, -q.max_omega, -q.max_omega, -q.max_omega])
    lo, hi = control_action_bounds(EnvConfig(control_mode="attitude"))
    np.testing.assert_allclose(hi[1:3], [math.pi / 2] * 2)
    lo, hi = control_action_bounds(EnvConfig(control_mode="velocity"))
    np.testing.assert_allclose(hi, [MAX_SPEED] * 3 + [q.max_omega])
    lo, hi = control_action_bounds(EnvConfig())
    np.testing.assert_array_equal(lo, -np.ones(4))
    assert make_mode_controller(EnvConfig()) is None
    with pytest.raises(ValueError, match="control_mode must be one of"):
        EnvConfig(control_mode="position")


def test_commands_stay_in_unit_interval_when_saturated() -> None:
    """Out-of-bounds actions are clipped; the command is always in [0, 1]."""
    cfg = EnvConfig(num_quads=3, control_mode="ctbr")
    p = _params(cfg)
    rng = np.random.default_rng(1)
    R = quat_to_rotmat(rng.normal(size=(3, 4)) / 2.0 + np.array([1.0, 0, 0, 0]))
    omega = rng.normal(size=(3, 3)) * 10
    omega[1] = 0.0
    state = {"rot": R, "omega": omega, "vel": np.zeros((3, 3))}
    action = np.array([[100.0, 500.0, -500.0, 50.0], [-5.0, 0.0, 0.0, 0.0], [0.3, 40.0, 40.0, 40.0]])
    cmd, cs = make_mode_controller(cfg)(action, state, p, init_control_state((3,)))
    assert cmd.shape == (3, 4) and cs.shape == (3, 6)
    assert np.all((cmd >= 0.0) & (cmd <= 1.0))
    np.testing.assert_array_equal(cmd[1], 0.0)  # thrust clipped from -5 N to 0, no rate error: rotors off
    assert cmd[0].max() == 1.0  # thrust clipped to 4 thrust_max, saturated


@pytest.fixture
def x64():
    """jax with float64 enabled for one test (restored after it: later tests run in float32)."""
    jax = pytest.importorskip("jax")
    jax.config.update("jax_enable_x64", True)
    yield jax
    jax.config.update("jax_enable_x64", False)


@pytest.mark.parametrize("mode", ["ctbr", "attitude", "velocity"])
def test_numpy_jax_jit_equivalence(mode: str, x64) -> None:
    jax = x64
    import jax.numpy as jnp

    cfg = EnvConfig(num_quads=3, control_mode=mode, randomize=True, quad="crazyflie21_identified")
    p = _params(cfg, seed=5)
    rng = np.random.default_rng(2)
    qt = rng.normal(size=(2, 3, 4)) * 0.3 + np.array([1.0, 0, 0, 0])
    R = quat_to_rotmat(qt / np.linalg.norm(qt, axis=-1, keepdims=True))
    state = {"rot": R, "omega": rng.normal(size=(2, 3, 3)), "vel": rng.normal(size=(2, 3, 3))}
    lo, hi = control_action_bounds(cfg)
    action = lo + (hi - lo) * rng.uniform(0.3, 0.7, size=(2, 3, 4))
    cs = rng.normal(size=(2, 3, 6)) * 0.01
    pb = {k: (np.broadcast_to(v, (2,) + np.shape(v)) if np.ndim(v) else v) for k, v in p.items()}
    ref = mode_command(mode, action, state, pb, cs, cfg.sim_dt, quad=cfg.quad, bounds=(lo, hi))

    @jax.jit
    def f(a, s, prm, c):
        return mode_command(mode, a, s, prm, c, cfg.sim_dt, quad=cfg.quad, bounds=(lo, hi))

    to_j = lambda t: jax.tree_util.tree_map(jnp.asarray, t)  # noqa: E731
    out = f(to_j(action), to_j(state), to_j({k: v for k, v in pb.items() if k != "gravity"} | {"gravity": 9.81}),
            to_j(cs))
    np.testing.assert_allclose(np.asarray(out[0]), ref[0], atol=1e-10)
    np.testing.assert_allclose(np.asarray(out[1]), ref[1], atol=1e-12)
    assert 0.05 < ref[0].mean() < 0.95  # a real (non-saturated) command was compared


def _env_constant_command(engine: str, mode: str, action: np.ndarray, seconds: float) -> dict[str, np.ndarray]:
    """Run one env (engine "mujoco" = QuadSwarmEnv, "mjx" = MjxQuadSwarmEnv) with a constant
    physical-unit action from a hover start; returns the state trajectory (T, N, ...)."""
    cfg = EnvConfig(num_quads=2, control_mode=mode, motor_start="hover").without_noise()
    n = cfg.num_quads
    start = {"pos": np.array([[-0.5, 0.0, 5.0], [0.5, 0.0, 5.0]]), "vel": np.zeros((n, 3)),
             "rot": np.broadcast_to(np.eye(3), (n, 3, 3)).copy(), "omega": np.zeros((n, 3)), "motors": "hover"}
    steps = int(round(seconds * cfg.control_hz))
    traj: dict[str, list] = {"rot": [], "omega": [], "vel": []}
    if engine == "mujoco":
        from quadswarm_mj.envs.gym_env import QuadSwarmEnv

        env = QuadSwarmEnv(cfg)
        lo, hi = control_action_bounds(cfg)
        np.testing.assert_allclose(env.action_space.low.reshape(n, 4), np.broadcast_to(lo, (n, 4)))
        np.testing.assert_allclose(env.action_space.high.reshape(n, 4), np.broadcast_to(hi, (n, 4)))
        env.reset(seed=0, options={"state": start})
        for _ in range(steps):
            _, _, _, _, info = env.step(action.reshape(env.action_space.shape))
            for k in traj:
                traj[k].append(np.asarray(info["state"][k]))
    else:
        import jax
        import jax.numpy as jnp

        from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv

        env = MjxQuadSwarmEnv(cfg)
        st = env.reset(jax.random.PRNGKey(0), {k: (v if isinstance(v, str) else jnp.asarray(v))
                                               for k, v in start.items()})
        step = jax.jit(env.step)
        a = jnp.asarray(action)
        for _ in range(steps):
            st = step(st, a)
            for k in traj:
                traj[k].append(np.asarray(st.info["state"][k]))
    return {k: np.array(v) for k, v in traj.items()}


@pytest.mark.parametrize("engine", ["mujoco", pytest.param("mjx", marks=pytest.mark.slow)])
def test_env_ctbr_rates(engine: str) -> None:
    g = _hover_thrust(CFG)
    rates = np.array([[0.5, -0.3, 1.0], [-0.4, 0.2, -2.0]])
    tr = _env_constant_command(engine, "ctbr", np.concatenate([np.full((2, 1), g), rates], -1), 0.5)
    np.testing.assert_allclose(tr["omega"][30:].mean(0), rates, atol=0.05)


@pytest.mark.parametrize("engine", ["mujoco", pytest.param("mjx", marks=pytest.mark.slow)])
def test_env_attitude_angles(engine: str) -> None:
    att = np.array([[0.2, -0.1, 0.5], [-0.15, 0.25, 0.0]])
    tr = _env_constant_command(engine, "attitude", np.concatenate([np.full((2, 1), _hover_thrust(CFG)), att], -1),
                               1.0)
    roll, pitch, _ = euler_zyx(tr["rot"][60:])
    np.testing.assert_allclose(roll, np.broadcast_to(att[:, 0], roll.shape), atol=0.02)
    np.testing.assert_allclose(pitch, np.broadcast_to(att[:, 1], pitch.shape), atol=0.02)


@pytest.mark.parametrize("engine", ["mujoco", pytest.param("mjx", marks=pytest.mark.slow)])
def test_env_velocity(engine: str) -> None:
    action = np.array([[1.0, -0.5, 0.3, 0.0], [-0.6, 0.4, -0.2, 1.0]])
    tr = _env_constant_command(engine, "velocity", action, 3.5)
    np.testing.assert_allclose(tr["vel"][300:].mean(0), action[:, :3], atol=0.05)


@pytest.mark.parametrize("mode", ["ctbr", "attitude", "velocity"])
def test_wrappers_expose_physical_action_bounds(mode: str) -> None:
    """Gymnasium, PettingZoo and the vector env take physical-unit actions within the mode's bounds;
    a hover command (ctbr/attitude: m g and zero rates/angles; velocity: zero) keeps a hover start
    level and nearly still for 0.2 s."""
    from quadswarm_mj.envs.gym_env import QuadSwarmEnv
    from quadswarm_mj.envs.parallel_env import QuadSwarmParallelEnv
    from quadswarm_mj.envs.vector_env import QuadSwarmVectorEnv

    cfg = EnvConfig(num_quads=2, control_mode=mode, motor_start="hover").without_noise()
    lo, hi = control_action_bounds(cfg)
    hover = np.zeros(4) if mode == "velocity" else np.array([_hover_thrust(cfg), 0.0, 0.0, 0.0])
    env = QuadSwarmEnv(cfg)
    np.testing.assert_allclose(env.action_space.low.reshape(2, 4), np.broadcast_to(lo, (2, 4)))
    env.reset(seed=0)
    for _ in range(20):
        _, _, _, _, info = env.step(np.broadcast_to(hover, (2, 4)).reshape(env.action_space.shape))
    assert np.abs(info["state"]["omega"]).max() < 0.1
    penv = QuadSwarmParallelEnv(cfg)
    np.testing.assert_allclose(penv.action_space(penv.possible_agents[0]).high, hi)
    penv.reset(seed=0)
    penv.step({a: hover for a in penv.agents})
    venv = QuadSwarmVectorEnv(cfg, num_envs=2)
    np.testing.assert_allclose(venv.single_action_space.high, np.broadcast_to(hi, (2, 4)))
    venv.reset(seed=0)
    venv.step(np.broadcast_to(hover, (2, 2, 4)).copy())
    venv.close()


@pytest.mark.parametrize("mode", ["ctbr", "attitude", "velocity"])
def test_modes_pass_gymnasium_and_pettingzoo_checkers(mode: str) -> None:
    """Gymnasium's check_env and PettingZoo's parallel_api_test accept every mode (CPU engine), with
    the default noise and random actions from the physical action spaces."""
    import warnings

    from gymnasium.utils.env_checker import check_env
    from pettingzoo.test import parallel_api_test

    from quadswarm_mj.envs.gym_env import QuadSwarmEnv
    from quadswarm_mj.envs.parallel_env import QuadSwarmParallelEnv

    cfg = EnvConfig(num_quads=2, control_mode=mode, episode_seconds=0.3)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(QuadSwarmEnv(cfg), skip_render_check=True)
    assert not caught, [str(w.message) for w in caught]
    parallel_api_test(QuadSwarmParallelEnv(cfg), num_cycles=40)


def test_physical_actions_are_clipped_and_effort_uses_the_rotor_command() -> None:
    """An action far beyond the bounds gives the same step as the bound itself; the reward's effort
    term is the norm of the equivalent raw rotor action 2 cmd - 1 (in [-1, 1], so <= 2)."""
    from quadswarm_mj.envs.gym_env import QuadSwarmEnv

    cfg = EnvConfig(num_quads=2, control_mode="ctbr").without_noise()
    lo, hi = control_action_bounds(cfg)
    outs = []
    for a in (np.broadcast_to(hi * 10.0, (2, 4)), np.broadcast_to(hi, (2, 4))):
        env = QuadSwarmEnv(cfg)
        env.reset(seed=0)
        outs.append(env.step(np.array(a))[4])
    np.testing.assert_array_equal(outs[0]["state"]["pos"], outs[1]["state"]["pos"])
    from quadswarm_mj.rewards import term_dt

    assert cfg.rewards.effort > 0
    effort = outs[1]["reward_terms"]["effort"] / (-term_dt(cfg, "effort") * cfg.rewards.effort)
    cmd = env.core.cmd_s[0]
    np.testing.assert_allclose(effort, np.linalg.norm(2.0 * cmd - 1.0, axis=-1), rtol=1e-12)
    assert np.all(np.abs(2.0 * cmd - 1.0) <= 1.0) and effort.max() > 0.5


def test_position_controller_is_rotor_mode_only() -> None:
    from quadswarm_mj.controllers import PositionController

    with pytest.raises(ValueError, match="control_mode='rotor'"):
        PositionController(EnvConfig(control_mode="ctbr"))


@pytest.mark.slow
def test_modes_on_the_jax_front_ends() -> None:
    """QuadSwarmEnv(engine="jax") passes check_env in the ctbr mode and holds a hover command like
    the CPU engine (positions within 1e-4 m after 0.2 s, float32); QuadSwarmVectorEnv(engine="jax")
    exposes the velocity mode's physical bounds and a zero-velocity command keeps a hover start
    within 1 cm over 0.2 s."""
    import warnings

    from gymnasium.utils.env_checker import check_env

    from quadswarm_mj.envs.gym_env import QuadSwarmEnv
    from quadswarm_mj.envs.vector_env import QuadSwarmVectorEnv

    cfg = EnvConfig(num_quads=2, control_mode="ctbr", motor_start="hover", episode_seconds=0.3).without_noise()
    env = QuadSwarmEnv(cfg, engine="jax")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=True)
    assert not caught, [str(w.message) for w in caught]
    hover = np.array([[_hover_thrust(cfg), 0.1, -0.1, 0.2]] * 2)
    pos = []
    start = {"pos": np.array([[-0.5, 0.0, 2.0], [0.5, 0.0, 2.0]]), "rot": np.stack([np.eye(3)] * 2), "motors": "hover"}
    for e in (env, QuadSwarmEnv(cfg)):
        e.reset(seed=3, options={"state": start})
        for _ in range(20):
            info = e.step(hover)[4]
        pos.append(np.asarray(info["state"]["pos"]))
    np.testing.assert_allclose(pos[0], pos[1], atol=1e-4)
    vcfg = cfg.replace(control_mode="velocity")
    venv = QuadSwarmVectorEnv(vcfg, num_envs=2, engine="jax")
    lo, hi = control_action_bounds(vcfg)
    np.testing.assert_allclose(venv.single_action_space.low, np.broadcast_to(lo, (2, 4)), rtol=1e-6)
    obs, info = venv.reset(seed=0)
    p0 = np.asarray(info["state"]["pos"]).copy()
    for _ in range(20):
        obs, _, _, _, info = venv.step(np.zeros((2, 2, 4), np.float32))
    assert np.abs(np.asarray(info["state"]["pos"]) - p0).max() < 0.01
    venv.close()


def test_identified_preset_through_the_engine() -> None:
    """The thrust map reaches the CPU engine: on "crazyflie21_identified" (nonlinear map), a hover
    start with the preset's hover action (the inverse map of m g) holds still (|v| < 1e-6 m/s over
    0.5 s); the linear map's hover action (m g / 4 thrust_max) sinks."""
    from quadswarm_mj.envs.gym_env import QuadSwarmEnv

    cfg = EnvConfig(num_quads=1, quad="crazyflie21_identified", motor_start="hover").without_noise()
    start = {"pos": np.array([[0.0, 0.0, 2.0]]), "rot": np.eye(3)[None], "motors": "hover"}
    linear = 2.0 / cfg.quad.thrust_to_weight - 1.0
    assert cfg.quad.hover_action > linear  # the map gives less thrust than linear below full command
    vz = []
    for a in (cfg.quad.hover_action, linear):
        env = QuadSwarmEnv(cfg)
        env.reset(seed=0, options={"state": start})
        for _ in range(50):
            info = env.step(np.full(4, a))[4]
        vz.append(info["state"]["vel"][0, 2])
    assert abs(vz[0]) < 1e-6 and vz[1] < -0.1


@pytest.mark.slow
def test_ctbr_on_mjx_physics_matches_cpu() -> None:
    """MjxQuadSwarmEnv(physics="mjx") (mjx.step) in ctbr mode, with the identified preset's thrust
    map and both aero effects, matches the CPU engine: positions within 1e-4 m, body rates within
    1e-3 rad/s after 0.2 s (float32 vs float64)."""
    import jax
    import jax.numpy as jnp

    from quadswarm_mj.config import AeroConfig
    from quadswarm_mj.envs.gym_env import QuadSwarmEnv
    from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv

    cfg = EnvConfig(num_quads=2, control_mode="ctbr", quad="crazyflie21_identified", motor_start="hover",
                    aero=AeroConfig(ground_effect=True, drag=True)).without_noise()
    start = {"pos": np.array([[-0.5, 0.0, 0.1], [0.5, 0.0, 2.0]]), "vel": np.array([[0.0, 0.0, 0.0], [1.0, 0, 0]]),
             "rot": np.stack([np.eye(3)] * 2), "omega": np.zeros((2, 3)), "motors": "hover"}
    action = np.array([[_hover_thrust(cfg), 0.3, -0.2, 0.5], [_hover_thrust(cfg), -0.1, 0.2, -0.4]])
    env = QuadSwarmEnv(cfg)
    env.reset(seed=0, options={"state": start})
    for _ in range(20):
        info = env.step(action)[4]
    menv = MjxQuadSwarmEnv(cfg, physics="mjx")
    st = menv.reset(jax.random.PRNGKey(0), {k: (v if isinstance(v, str) else jnp.asarray(v)) for k, v in start.items()})
    step = jax.jit(menv.step)
    for _ in range(20):
        st = step(st, jnp.asarray(action))
    np.testing.assert_allclose(np.asarray(st.info["state"]["pos"]), info["state"]["pos"], atol=1e-4)
    np.testing.assert_allclose(np.asarray(st.info["state"]["omega"]), info["state"]["omega"], atol=1e-3)
    assert np.abs(info["state"]["omega"]).max() > 0.1  # the commanded rates were flown
