"""Aerodynamics (quadswarm_mj.aerodynamics): ground-effect gain and rotor drag, direction and
magnitude, config switches, randomization draws, NumPy vs jax.jit."""

from __future__ import annotations

import numpy as np
import pytest

from quadswarm_mj.actuation import rotor_positions, substep_wrench
from quadswarm_mj.aerodynamics import (
    aero_draw_spec,
    aero_nominal_draws,
    aero_params_from_draws,
    drag_stage,
    ground_effect_gain,
    ground_effect_stage,
    rotor_drag_force,
    rotor_heights,
    rotor_speeds,
)
from quadswarm_mj.config import AeroConfig, EnvConfig
from quadswarm_mj.random_draws import NumpySampler
from quadswarm_mj.randomization import nominal_draws, params_from_draws
from quadswarm_mj.spatial import quat_to_rotmat

R_CF = 0.0231  # m, Crazyflie rotor radius (46.2 mm props)


def test_defaults_off_and_validation() -> None:
    a = EnvConfig().aero
    assert not a.ground_effect and not a.drag and not a.any
    assert a.rotor_radius == R_CF
    with pytest.raises(ValueError, match="aero.ground_effect_max_gain must be .*> 1"):
        AeroConfig(ground_effect_max_gain=1.0)
    with pytest.raises(ValueError, match=r"aero.drag_coeff\[2\] must be .*>= 0"):
        AeroConfig(drag_coeff=(1e-7, 1e-7, -1.0))
    cfg = EnvConfig(aero={"ground_effect": True})
    assert cfg.aero.ground_effect and not cfg.aero.drag


def test_ground_effect_gain_form_and_clip() -> None:
    h = np.array([[0.5 * R_CF, R_CF, 0.043, 2 * R_CF, 0.2]])
    r = np.array([R_CF])
    g = ground_effect_gain(h, r, 4.0 / 3.0)
    expect = 1.0 / (1.0 - (R_CF / (4 * h)) ** 2)
    np.testing.assert_allclose(g[0, 1:], expect[0, 1:], rtol=1e-12)  # the Cheeseman-Bennett form
    np.testing.assert_allclose(g[0, 0], 4.0 / 3.0)  # at h = r / 2 the form equals the clip
    assert np.all(np.diff(g[0]) < 0) and g[0, -1] < 1.001  # decays with height, ~1 far from the floor
    below = ground_effect_gain(np.array([[0.001, 0.0, -0.1, 0.25 * R_CF]]), r, 4.0 / 3.0)
    np.testing.assert_allclose(below, 4.0 / 3.0)  # clipped, no divergence at h = r / 4 or below
    assert 1.015 < g[0, 2] < 1.025  # rotors of a Crazyflie resting on the floor: ~2 % gain


def test_rotor_heights_follow_attitude() -> None:
    rp = rotor_positions(EnvConfig().quad)
    pos = np.array([[0.0, 0.0, 0.1]])
    h = rotor_heights(pos, np.eye(3)[None], rp)
    np.testing.assert_allclose(h, 0.1 + rp[None, :, 2])
    # pitched nose down (about body y by +0.3 rad): front rotors (0, 3) lower than the back ones
    c, s = np.cos(0.3), np.sin(0.3)
    Ry = np.array([[[c, 0, s], [0, 1, 0], [-s, 0, c]]])
    h = rotor_heights(pos, Ry, rp)[0]
    assert h[0] < h[1] and h[3] < h[2]


def test_ground_effect_raises_thrust_in_the_wrench() -> None:
    """Through substep_wrench: the thrust near the floor is the OGE thrust times the gain."""
    cfg = EnvConfig(num_quads=1, aero=AeroConfig(ground_effect=True)).without_noise()
    p = params_from_draws(cfg, nominal_draws(cfg, np.zeros(1))) | aero_params_from_draws(
        cfg, aero_nominal_draws(cfg, np.zeros(1)))
    rp = rotor_positions(cfg.quad)
    u, cmd, R = np.full((1, 4), 0.7), np.full((1, 4), 0.49), np.eye(3)[None]
    pos = np.array([[0.0, 0.0, 0.05]])
    gain = ground_effect_stage(cfg, p, pos, R, rp)
    assert drag_stage(cfg, p, R, np.ones((1, 3)), u * u, gain) is None  # drag off
    assert ground_effect_stage(EnvConfig(num_quads=1), p, pos, R, rp) is None  # default: off
    _, _, f0, t0 = substep_wrench(u, cmd, np.zeros((1, 4)), p, R, rp)
    _, _, f1, t1 = substep_wrench(u, cmd, np.zeros((1, 4)), p, R, rp, rotor_gain=gain)
    np.testing.assert_allclose(f1[0, 2] / f0[0, 2], gain[0, 0], rtol=1e-12)
    assert f1[0, 2] / f0[0, 2] > 1.01
    np.testing.assert_allclose(t1, t0, atol=1e-15)  # level: equal gains, no torque


def _drag_params(cfg: EnvConfig) -> dict:
    return aero_params_from_draws(cfg, aero_nominal_draws(cfg, np.zeros(1)))


def test_rotor_drag_direction_and_magnitude() -> None:
    cfg = EnvConfig(num_quads=3, aero=AeroConfig(drag=True))
    a, p = cfg.aero, _drag_params(cfg)
    hover = cfg.quad.mass * cfg.quad.gravity / 4
    thrust = np.full((3, 4), hover)
    w_sum = 4 * np.sqrt(hover / a.thrust_coeff)
    rng = np.random.default_rng(0)
    qt = rng.normal(size=(3, 4))
    R = quat_to_rotmat(qt / np.linalg.norm(qt, axis=-1, keepdims=True))
    vel = rng.normal(size=(3, 3))
    f = rotor_drag_force(R, vel, thrust, p["drag_coeff"], a.thrust_coeff)
    assert np.all(np.sum(f * vel, -1) < 0)  # opposes the motion
    f_body = np.einsum("nji,nj->ni", R, f)
    v_body = np.einsum("nji,nj->ni", R, vel)
    np.testing.assert_allclose(f_body, -np.asarray(a.drag_coeff) * w_sum * v_body, rtol=1e-12)
    # level quad at 1 m/s forward: ~5.5 mN (2 % of the weight) from the gym-pybullet-drones coefficient
    f1 = rotor_drag_force(np.eye(3)[None], np.array([[1.0, 0, 0]]), thrust[:1], p["drag_coeff"][:1], a.thrust_coeff)
    np.testing.assert_allclose(f1[0], [-a.drag_coeff[0] * w_sum, 0, 0], rtol=1e-12)
    assert 4e-3 < -f1[0, 0] < 7e-3
    assert 1400 < w_sum / 4 < 1700  # hover rotor speed (rad/s), ~15k rpm
    # no rotor speed, no drag; double speed (4x thrust), double drag
    z = rotor_drag_force(R, vel, np.zeros((3, 4)), p["drag_coeff"], a.thrust_coeff)
    np.testing.assert_array_equal(z, 0.0)
    f4 = rotor_drag_force(R, vel, 4 * thrust, p["drag_coeff"], a.thrust_coeff)
    np.testing.assert_allclose(f4, 2 * f, rtol=1e-12)
    np.testing.assert_allclose(rotor_speeds(np.array([a.thrust_coeff * 100.0**2]), a.thrust_coeff), [100.0])


def test_randomization_draws_scale_per_quad() -> None:
    cfg = EnvConfig(num_quads=4, randomize=True, aero=AeroConfig(drag=True, ground_effect=True))
    d = NumpySampler(np.random.default_rng(1)).draw(aero_draw_spec(cfg))
    p = aero_params_from_draws(cfg, d)
    assert p["rotor_radius"].shape == (4,) and p["drag_coeff"].shape == (4, 3)
    lo, hi = cfg.aero.rotor_radius_scale
    assert np.all((p["rotor_radius"] >= lo * R_CF) & (p["rotor_radius"] <= hi * R_CF))
    assert len(np.unique(p["drag_coeff"][:, 0])) == 4  # per quad
    np.testing.assert_allclose(p["drag_coeff"] / np.asarray(cfg.aero.drag_coeff), d["drag_scale"][:, None] * np.ones(3))


@pytest.fixture
def x64():
    """jax with float64 enabled for one test (restored after it: later tests run in float32)."""
    jax = pytest.importorskip("jax")
    jax.config.update("jax_enable_x64", True)
    yield jax
    jax.config.update("jax_enable_x64", False)


def test_numpy_jax_jit_equivalence(x64) -> None:
    jax = x64
    import jax.numpy as jnp

    cfg = EnvConfig(num_quads=3, randomize=True, aero=AeroConfig(drag=True, ground_effect=True),
                    quad="crazyflie21_identified")
    p = params_from_draws(cfg, nominal_draws(cfg, np.zeros(1))) | aero_params_from_draws(
        cfg, NumpySampler(np.random.default_rng(2)).draw(aero_draw_spec(cfg)))
    rng = np.random.default_rng(3)
    qt = rng.normal(size=(3, 4)) * 0.2 + np.array([1.0, 0, 0, 0])
    R = quat_to_rotmat(qt / np.linalg.norm(qt, axis=-1, keepdims=True))
    pos = np.column_stack([rng.normal(size=(3, 2)), [0.02, 0.05, 0.3]])
    vel, f = rng.normal(size=(3, 3)), rng.uniform(0.2, 0.8, size=(3, 4))
    rp = rotor_positions(cfg.quad)

    def both(prm, pos, vel, R, f):
        gain = ground_effect_stage(cfg, prm, pos, R, rp)
        return gain, drag_stage(cfg, prm, R, vel, f, gain)

    g_ref, d_ref = both(p, pos, vel, R, f)
    pj = {k: (jnp.asarray(v) if k != "gravity" else v) for k, v in p.items()}
    g, d = jax.jit(both)(pj, jnp.asarray(pos), jnp.asarray(vel), jnp.asarray(R), jnp.asarray(f))
    np.testing.assert_allclose(np.asarray(g), g_ref, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(d), d_ref, rtol=1e-12, atol=1e-18)
    assert g_ref.max() > 1.01 and np.abs(d_ref).max() > 1e-4  # both effects active in the compared case


def test_closed_loop_ground_effect_lifts_a_hovering_quad() -> None:
    """MuJoCo closed loop (tests/closed_loop.py): a level quad at 6 cm with the hover command
    accelerates upward at (gain - 1) g; with the ground effect off it holds its height."""
    from closed_loop import run_closed_loop

    cfg = EnvConfig(num_quads=1, aero=AeroConfig(ground_effect=True)).without_noise()
    hover = np.full((1, 4), cfg.quad.hover_action)
    pos0 = np.array([[0.0, 0.0, 0.06]])
    tr = run_closed_loop(cfg, hover, 0.05, pos0=pos0)
    h = 0.06 + cfg.quad.rotor_z
    gain = 1.0 / (1.0 - (R_CF / (4 * h)) ** 2)
    expected = (gain - 1.0) * cfg.quad.gravity * 0.05
    np.testing.assert_allclose(tr["vel"][-1, 0, 2], expected, rtol=0.05)
    assert expected > 4e-3
    off = run_closed_loop(cfg.replace(aero=AeroConfig()), hover, 0.05, pos0=pos0)
    assert abs(off["vel"][-1, 0, 2]) < 1e-9


def test_closed_loop_drag_decays_a_gliding_quad() -> None:
    """A level quad at hover thrust moving at 1 m/s along x slows as exp(-k t), k = c_x w_sum / m
    (w_sum the hover rotor speeds), within 1 % after 1 s; its y velocity stays 0."""
    from closed_loop import run_closed_loop

    cfg = EnvConfig(num_quads=1, aero=AeroConfig(drag=True)).without_noise()
    a, q = cfg.aero, cfg.quad
    tr = run_closed_loop(cfg, np.full((1, 4), q.hover_action), 1.0, vel0=np.array([[1.0, 0.0, 0.0]]))
    w_sum = 4 * np.sqrt(q.mass * q.gravity / 4 / a.thrust_coeff)
    k = a.drag_coeff[0] * w_sum / q.mass
    np.testing.assert_allclose(tr["vel"][-1, 0, 0], np.exp(-k * 1.0), rtol=0.01)
    assert np.exp(-k) < 0.85  # a visible effect: > 15 % speed lost in 1 s
    assert abs(tr["vel"][-1, 0, 1]) < 1e-9


# ----------------------------------------------------------------------------- env level, both engines
#: quad 0 rests in the air 6 cm above the floor (ground effect), quad 1 glides at 1 m/s along x at 3 m
#: (drag); hover action, no noise, 0.3 s (30 control steps)
_START = {"pos": np.array([[0.0, 0.0, 0.06], [0.0, 1.0, 3.0]]), "vel": np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]),
          "rot": np.stack([np.eye(3)] * 2), "omega": np.zeros((2, 3)), "motors": "hover"}
_AERO_T = 0.3


def _aero_cfg(on: bool) -> EnvConfig:
    aero = AeroConfig(ground_effect=True, drag=True) if on else AeroConfig()
    return EnvConfig(num_quads=2, aero=aero, scenario="static_same_goal").without_noise()


def _env_run(engine: str, cfg: EnvConfig) -> dict[str, np.ndarray]:
    """Final info state of QuadSwarmEnv ("mujoco") or the jitted MjxQuadSwarmEnv ("mjx")."""
    hover = np.full((2, 4), cfg.quad.hover_action)
    steps = int(round(_AERO_T * cfg.control_hz))
    if engine == "mujoco":
        from quadswarm_mj.envs.gym_env import QuadSwarmEnv

        env = QuadSwarmEnv(cfg)
        env.reset(seed=0, options={"state": _START})
        for _ in range(steps):
            _, _, _, _, info = env.step(hover)
        return {k: np.asarray(v) for k, v in info["state"].items()}
    import jax
    import jax.numpy as jnp

    from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv

    env = MjxQuadSwarmEnv(cfg)
    st = env.reset(jax.random.PRNGKey(0), {k: (v if isinstance(v, str) else jnp.asarray(v)) for k, v in _START.items()})
    step = jax.jit(env.step)
    for _ in range(steps):
        st = step(st, jnp.asarray(hover))
    return {k: np.asarray(v) for k, v in st.info["state"].items()}


@pytest.mark.slow
@pytest.mark.parametrize("engine", ["mujoco", "mjx"])
def test_env_ground_effect_lifts_and_drag_slows(engine: str) -> None:
    """Through the env (both engines): with aero on, the quad hovering 6 cm above the floor climbs
    (its vertical speed after 0.3 s is within 25 % of (gain - 1) g t, the gain at the start height;
    the gain falls as it climbs, hence the tolerance) while with aero off it holds (< 1e-3 m/s);
    the gliding quad's x speed decays as exp(-k t) (within 2 %) and stays 1 m/s with aero off
    (1e-3: float32 on MJX)."""
    cfg_on, cfg_off = _aero_cfg(True), _aero_cfg(False)
    on, off = _env_run(engine, cfg_on), _env_run(engine, cfg_off)
    q, a = cfg_on.quad, cfg_on.aero
    h = 0.06 + q.rotor_z
    gain = 1.0 / (1.0 - (R_CF / (4 * h)) ** 2)
    vz_expected = (gain - 1.0) * q.gravity * _AERO_T
    assert 0.75 * vz_expected < on["vel"][0, 2] < 1.02 * vz_expected
    assert abs(off["vel"][0, 2]) < 1e-3
    assert on["pos"][0, 2] > off["pos"][0, 2] + 1e-3
    w_sum = 4 * np.sqrt(q.mass * q.gravity / 4 / a.thrust_coeff)
    k = a.drag_coeff[0] * w_sum / q.mass
    np.testing.assert_allclose(on["vel"][1, 0], np.exp(-k * _AERO_T), rtol=0.02)
    np.testing.assert_allclose(off["vel"][1, 0], 1.0, atol=1e-3)


def test_env_aero_params_randomized_per_quad() -> None:
    """Aero parameters are in the env's params (info["params"]), nominal without randomization, drawn
    per quad (within the configured ranges) with it; the default config has none (no extra work)."""
    from quadswarm_mj.envs.gym_env import QuadSwarmEnv

    assert "drag_coeff" not in QuadSwarmEnv(EnvConfig(num_quads=2)).reset(seed=0)[1]["params"]
    _, info = QuadSwarmEnv(_aero_cfg(True)).reset(seed=0)
    np.testing.assert_allclose(info["params"]["rotor_radius"], [R_CF] * 2)
    cfg = _aero_cfg(True).replace(randomize=True)
    _, info = QuadSwarmEnv(cfg).reset(seed=1)
    r, d = info["params"]["rotor_radius"], info["params"]["drag_coeff"]
    assert r[0] != r[1] and d[0, 0] != d[1, 0]
    assert np.all((r >= 0.9 * R_CF) & (r <= 1.1 * R_CF))
    np.testing.assert_allclose(d[:, 2] / d[:, 0], cfg.aero.drag_coeff[2] / cfg.aero.drag_coeff[0])


def test_vector_env_reports_aero_params_and_steps_with_aero() -> None:
    """QuadSwarmVectorEnv (CPU) with aero on: info["params"] holds the aero parameters (B, N, ...),
    and a hover start near the floor climbs (ground effect) over 0.1 s."""
    from quadswarm_mj.envs.vector_env import QuadSwarmVectorEnv

    cfg = _aero_cfg(True)
    venv = QuadSwarmVectorEnv(cfg, num_envs=2)
    _, info = venv.reset(seed=0, options={"state": {k: (v if isinstance(v, str) else np.stack([v] * 2))
                                                    for k, v in _START.items()}})
    assert info["params"]["drag_coeff"].shape == (2, 2, 3)
    np.testing.assert_allclose(info["params"]["rotor_radius"], R_CF)
    for _ in range(10):
        _, _, _, _, info = venv.step(np.full((2, 2, 4), cfg.quad.hover_action))
    assert np.all(info["state"]["vel"][:, 0, 2] > 1e-3)
    venv.close()
