"""Parity with trajectories recorded from the original QuadSwarm simulator (noise off).

See tests/reference_data/README.md (a copy of shared/reference) for the cases. MuJoCo's Euler
integrator differs from the original's at O(dt) (SPEC §3); tolerances follow the spec.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, QuadSwarmEnv

DATA = Path(__file__).parent / "reference_data"


def load(name: str) -> tuple[dict, dict]:
    z = np.load(DATA / name)
    return {k: z[k] for k in z.files if k != "meta"}, json.loads(str(z["meta"]))


def replay(name: str) -> tuple[dict, dict, dict]:
    ref, meta = load(name)
    n = meta["num_quads"]
    cfg = EnvConfig(num_quads=n, room_size=tuple(meta["room_dims"]), scenario="static_same_goal").without_noise()
    env = QuadSwarmEnv(cfg)
    state = {"pos": ref["init_pos"], "vel": ref["init_vel"], "rot": ref["init_rot"], "omega": ref["init_omega"],
             "motors": "hover" if meta["motors_prespun_to_hover"] else "zero"}
    _, info = env.reset(seed=0, options={"state": state})
    np.testing.assert_allclose(info["state"]["pos"], ref["init_pos"], atol=1e-12)
    out = {k: [] for k in ("pos", "vel", "rot", "omega", "thrust")}
    for a in ref["actions_raw"]:
        _, _, _, _, info = env.step(a[0] if n == 1 else a)
        for k in out:
            out[k].append(info["state"][k])
    return {k: np.array(v) for k, v in out.items()}, ref, meta


def angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    rel = np.einsum("...ji,...jk->...ik", Ra, Rb)
    c = np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1) / 2, -1, 1)
    return np.degrees(np.arccos(c))


@pytest.mark.parametrize("name", ["golden_a_hover.npz", "golden_a2_hover_prespun.npz", "golden_b_motor0_step.npz",
                                  "golden_f_floor_drop.npz", "golden_d_headon_collision_noisefree.npz"])
def test_motor_thrusts_match(name):
    out, ref, _ = replay(name)
    np.testing.assert_allclose(out["thrust"], ref["ctrl_thrust_cmds_damp"], atol=1e-6)


@pytest.mark.parametrize("name", ["golden_a_hover.npz", "golden_a2_hover_prespun.npz"])
def test_hover_within_5mm(name):
    out, ref, _ = replay(name)
    err = np.abs(out["pos"] - ref["ctrl_pos"]).max()
    assert err < 5e-3, err
    if "a2" in name:
        assert np.abs(out["pos"][..., 2] - 2.0).max() < 1e-9  # motors at hover hold z = 2 exactly


def test_motor_step_within_integrator_difference():
    out, ref, _ = replay("golden_b_motor0_step.npz")
    np.testing.assert_allclose(out["omega"], ref["ctrl_omega"], atol=1e-6, rtol=1e-6)  # round-off level
    pos_err = np.linalg.norm(out["pos"] - ref["ctrl_pos"], axis=-1).max()
    ang_err = angle_deg(out["rot"], ref["ctrl_rot"]).max()
    assert pos_err < 0.03, pos_err  # SPEC §3: ~22 mm; a wrong rotor order gives ~100 mm
    assert ang_err < 7.0, ang_err  # SPEC §3: ~5.7 deg; a wrong spin sign gives ~36 deg
    assert ang_err > 0.5  # the quad really does tumble: the test is not vacuous


def test_headon_collision_bounces_at_step_45():
    out, ref, _ = replay("golden_d_headon_collision_noisefree.npz")
    vx = out["vel"][..., 0]
    np.testing.assert_allclose(vx[44], [1.0, -1.0], atol=1e-6)
    np.testing.assert_allclose(vx[45], [-0.5, 0.5], atol=1e-6)
    np.testing.assert_allclose(out["vel"], ref["ctrl_vel"], atol=1e-6)
    np.testing.assert_allclose(out["pos"], ref["ctrl_pos"], atol=5e-3)


def test_floor_drop_rests_at_step_30():
    out, ref, _ = replay("golden_f_floor_drop.npz")
    z = out["pos"][:, 0, 2]
    assert z[29] > 0.05
    np.testing.assert_allclose(z[30:], 0.046, atol=5e-4)
    np.testing.assert_allclose(out["vel"][30:], 0.0, atol=1e-12)
    np.testing.assert_allclose(z[30:], ref["ctrl_pos"][30:, 0, 2], atol=1e-9)


# ------------------------------------------------------------------------- the JAX engine, both physics
CASES = ["golden_a_hover.npz", "golden_a2_hover_prespun.npz", "golden_b_motor0_step.npz", "golden_f_floor_drop.npz",
         "golden_d_headon_collision_noisefree.npz"]


def replay_mjx(name: str, physics: str) -> tuple[dict, dict, dict]:
    """The case of :func:`replay` through ``MjxQuadSwarmEnv(cfg, physics=physics)`` (float32)."""
    jax = pytest.importorskip("jax")
    pytest.importorskip("mujoco.mjx")
    import jax.numpy as jnp

    from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv

    ref, meta = load(name)
    n = meta["num_quads"]
    cfg = EnvConfig(num_quads=n, room_size=tuple(meta["room_dims"]), scenario="static_same_goal").without_noise()
    env = MjxQuadSwarmEnv(cfg, physics=physics)
    motors = "hover" if meta["motors_prespun_to_hover"] else "zero"
    state = {"pos": ref["init_pos"], "vel": ref["init_vel"], "rot": ref["init_rot"], "omega": ref["init_omega"]}
    s = jax.jit(lambda k, st: env.reset(k, {**st, "motors": motors}))(jax.random.key(0), state)

    def run(s, acts):
        def body(s, a):
            s = env.step(s, a)
            return s, s.info["state"]
        return jax.lax.scan(body, s, acts)[1]

    acts = jnp.asarray(ref["actions_raw"].reshape(-1, n, 4), jnp.float32)
    out = jax.jit(run)(s, acts)
    return {k: np.asarray(v, np.float64) for k, v in out.items()}, ref, meta


@pytest.mark.slow
@pytest.mark.parametrize("physics", ["freebody", "mjx"])
@pytest.mark.parametrize("name", CASES)
def test_reference_cases_through_jax_engine(name, physics):
    """Every reference case through the JAX engine with either physics agrees with the CPU engine's
    replay (float32 vs float64) and passes the case's own check against the original simulator."""
    out, ref, _ = replay_mjx(name, physics)
    cpu, _, _ = replay(name)
    assert np.abs(out["pos"] - cpu["pos"]).max() < 2e-3
    assert np.abs(out["thrust"] - cpu["thrust"]).max() < 1e-5
    if "hover" in name:
        assert np.abs(out["pos"] - ref["ctrl_pos"]).max() < 5e-3
    elif "headon" in name:
        np.testing.assert_allclose(out["vel"][45, :, 0], [-0.5, 0.5], atol=1e-4)
        np.testing.assert_allclose(out["pos"], ref["ctrl_pos"], atol=5e-3)
    elif "floor" in name:
        np.testing.assert_allclose(out["pos"][30:, 0, 2], 0.046, atol=5e-4)
        np.testing.assert_allclose(out["vel"][30:], 0.0, atol=1e-6)
    else:
        assert np.linalg.norm(out["pos"] - ref["ctrl_pos"], axis=-1).max() < 0.03
