"""MJX env (quadswarm_mj.envs.mjx_env): parity with the CPU env, the State contract, batched
randomized worlds whose parameters reach the physics, full auto-reset, scenarios under jit.

Compiles are the cost on CPU: each test compiles one reset and one step at most.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytest.importorskip("mujoco.mjx")
import jax.numpy as jnp  # noqa: E402

from quadswarm_mj import EnvConfig, QuadSwarmEnv  # noqa: E402
from quadswarm_mj.actuation import body_wrench, rotor_positions  # noqa: E402
from quadswarm_mj.envs.mjx_env import AutoResetWrapper, MjxQuadSwarmEnv  # noqa: E402
from quadswarm_mj.rewards import TERMS  # noqa: E402
from quadswarm_mj.scenarios.mix import MIX_CHOICES  # noqa: E402
from quadswarm_mj.spatial import yaw_rotmat  # noqa: E402

N = 8
T = 150


def _parity_setup(cfg: EnvConfig) -> tuple[dict, np.ndarray]:
    """Start state (4 x 2 grid, 1 m apart, yawed, slowly moving and spinning) and T actions:
    hover + a collective and a yaw oscillation + a small roll/pitch perturbation per rotor."""
    xy = np.stack(np.meshgrid(np.arange(4) - 1.5, np.arange(2) - 0.5, indexing="ij"), -1).reshape(N, 2)
    pos = np.concatenate([xy, 2.0 + 0.1 * np.arange(N)[:, None]], -1)
    init = {"pos": pos, "vel": np.tile([0.1, -0.05, 0.02], (N, 1)), "rot": yaw_rotmat(np.linspace(-2.5, 2.5, N)),
            "omega": np.tile([0.01, -0.01, 0.3], (N, 1)), "goals": pos + np.array([0.3, -0.2, 0.5])}
    t = np.arange(T)[:, None, None] * cfg.control_dt
    i = np.arange(N)[None, :, None]
    r = np.arange(4)[None, None, :]
    spin = np.array([-1.0, 1.0, -1.0, 1.0])
    acts = (cfg.quad.hover_action + 0.03 * np.sin(2 * np.pi * (0.5 + 0.1 * i) * t + 0.3 * i)
            + 0.03 * spin * np.cos(2 * np.pi * 0.7 * t + i) + 0.002 * np.sin(2 * np.pi * (1 + 0.2 * r) * t + r + i))
    return init, acts


@pytest.fixture(scope="module", params=["freebody", "mjx"])
def parity_run(request):
    cfg = EnvConfig(num_quads=N).without_noise()
    init, acts = _parity_setup(cfg)
    cpu = QuadSwarmEnv(cfg)
    _, info = cpu.reset(seed=0, options={"state": {**init, "motors": "hover"}})
    cpu_pos, cpu_rew, cpu_floor = [], [], []
    for k in range(T):
        _, _, _, _, info = cpu.step(acts[k])
        cpu_pos.append(info["state"]["pos"])
        cpu_rew.append(info["rewards"])
        cpu_floor.append(info["on_floor"])
    env = MjxQuadSwarmEnv(cfg, physics=request.param)
    reset = jax.jit(lambda key, s: env.reset(key, {**s, "motors": "hover"}))  # "hover" is static
    step = jax.jit(env.step)
    state0 = reset(jax.random.key(0), init)
    state = state0
    mjx_pos, mjx_rew = [], []
    for k in range(T):
        state = step(state, jnp.asarray(acts[k], jnp.float32))
        mjx_pos.append(np.asarray(state.info["state"]["pos"]))
        mjx_rew.append(np.asarray(state.reward))
    return {"cfg": cfg, "init": init, "cpu_pos": np.array(cpu_pos), "cpu_rew": np.array(cpu_rew),
            "cpu_floor": np.array(cpu_floor), "mjx_pos": np.array(mjx_pos), "mjx_rew": np.array(mjx_rew),
            "state0": state0, "state": state, "cpu_info": info}


def test_parity_with_cpu_env_150_steps(parity_run):
    r = parity_run
    cp, mp = r["cpu_pos"], r["mjx_pos"]
    # the run is a real test: quads move, nobody touches the floor or comes near another quad
    assert np.abs(cp - r["init"]["pos"]).max() > 0.2
    assert not r["cpu_floor"].any() and cp[..., 2].min() > 1.0
    d = np.linalg.norm(cp[:, :, None] - cp[:, None], axis=-1) + 10 * np.eye(N)
    falloff = r["cfg"].rewards.proximity_falloff_arms * r["cfg"].quad.arm
    assert d.min() > falloff
    assert np.abs(cp - mp).max() < 2e-3
    scale = np.abs(r["cpu_rew"]).max()
    assert scale > 0
    assert np.abs(r["cpu_rew"] - r["mjx_rew"]).max() < 2e-3 * scale
    # rotation and angular velocity at the end agree too (frames: R body->world, omega body)
    s = r["state"].info["state"]
    np.testing.assert_allclose(np.asarray(s["rot"]), r["cpu_info"]["state"]["rot"], atol=1e-3)
    np.testing.assert_allclose(np.asarray(s["omega"]), r["cpu_info"]["state"]["omega"], atol=1e-3)
    np.testing.assert_allclose(np.asarray(s["thrust"]), r["cpu_info"]["state"]["thrust"], atol=1e-5)


def test_state_contract(parity_run):
    cfg, s0, s = parity_run["cfg"], parity_run["state0"], parity_run["state"]
    assert s.obs.shape == (N, cfg.obs_dim) and s.reward.shape == (N,) and s.done.shape == ()
    assert set(s.metrics) == {f"reward/{t}" for t in TERMS}
    total = sum(np.asarray(s.metrics[f"reward/{t}"], np.float64) for t in TERMS)
    np.testing.assert_allclose(total, np.asarray(s.reward), rtol=1e-6, atol=1e-9)
    st = s.info["state"]
    assert {k: v.shape for k, v in st.items()} == {"pos": (N, 3), "vel": (N, 3), "rot": (N, 3, 3),
                                                   "omega": (N, 3), "thrust": (N, 4)}
    q = np.asarray(s.data.qpos).reshape(N, 7)
    np.testing.assert_allclose(q[:, :3], np.asarray(st["pos"]), atol=1e-6)
    np.testing.assert_allclose(np.asarray(s.info["params"]["mass"]), cfg.quad.mass, rtol=1e-6)
    assert {"mass", "inertia", "thrust_max", "torque_max", "alpha", "motor_sigma"} <= set(s.info["params"])
    np.testing.assert_allclose(np.asarray(s.info["goals"]), parity_run["init"]["goals"], atol=1e-6)
    assert int(s.info["step"]) == T and int(s.info["total_steps"]) == T and not bool(s.done)
    assert float(s.info["time"]) == pytest.approx(T * cfg.control_dt)
    assert set(s.info["episode_metrics"]) >= {"success", "collisions", "mean_distance"}
    # reset: the start state is exactly the requested one, motors at hover, zero counters
    np.testing.assert_allclose(np.asarray(s0.info["state"]["pos"]), parity_run["init"]["pos"], atol=1e-6)
    np.testing.assert_allclose(np.asarray(s0.info["state"]["rot"]), parity_run["init"]["rot"], atol=1e-6)
    np.testing.assert_allclose(np.asarray(s0.info["state"]["thrust"]), cfg.quad.hover_command, rtol=1e-5)
    assert int(s0.info["step"]) == 0 and np.all(np.asarray(s0.reward) == 0)
    # reset and step states have identical leaf types (else a jitted step compiles twice)
    def avals(x):
        return jax.tree.map(lambda a: (a.shape, a.dtype, a.weak_type), jax.tree.map(jax.typeof, x))
    assert jax.tree.structure(s0) == jax.tree.structure(s) and avals(s0) == avals(s)


def test_bad_input_raises_before_any_work():
    cfg = EnvConfig(num_quads=2)
    with pytest.raises(ValueError, match="collision_model"):
        MjxQuadSwarmEnv(cfg.replace(collision_model="mujoco"), physics="freebody")
    with pytest.raises(ValueError, match="physics must be one of"):
        MjxQuadSwarmEnv(cfg, physics="euler")
    env = MjxQuadSwarmEnv(cfg)
    key = jax.random.key(0)
    # init_state is validated outside jit as the CPU env validates options["state"], naming the key
    with pytest.raises(ValueError, match=r"init_state\['pos'\] contains NaN"):
        env.reset(key, {"pos": np.full((2, 3), np.nan)})
    with pytest.raises(ValueError, match=r"init_state\['rot'\] must hold proper rotation"):
        env.reset(key, {"rot": np.ones((2, 3, 3))})
    with pytest.raises(ValueError, match=r"init_state\['goals'\] must be inside the room"):
        env.reset(key, {"goals": np.full((2, 3), 100.0)})
    with pytest.raises(ValueError, match=r"init_state\['vel'\] has the wrong shape"):  # under jit: shapes only
        jax.jit(lambda k, v: env.reset(k, {"vel": v}))(key, jnp.zeros((3, 3)))
    jax.eval_shape(lambda k, p: env.reset(k, {"pos": p}), key, jnp.zeros((2, 3)))  # tracers: no value checks
    with pytest.raises(ValueError, match="unknown keys"):
        env.reset(key, {"position": np.zeros((2, 3))})
    with pytest.raises(ValueError, match="motors"):
        env.reset(key, {"motors": "spinning"})
    with pytest.raises(ValueError, match="wrong shape"):
        env.reset(key, {"pos": np.zeros((3, 3))})
    with pytest.raises(ValueError, match="wrong shape"):
        jax.eval_shape(env.step, jax.eval_shape(env.reset, key), jnp.zeros((8,)))


@pytest.mark.slow
def test_jit_vmap_256_randomized_worlds_physics_and_full_autoreset():
    """256 worlds x 8 quads, randomize=True, scenario mix, 3-step episodes.

    Step 1 checks that each world's drawn mass, inertia and rotor constants are what its physics
    uses; step 3 ends the episode and checks that the auto-reset renews everything."""
    W = 256
    cfg = EnvConfig(num_quads=N, randomize=True, scenario="mix", episode_seconds=0.03)
    core = MjxQuadSwarmEnv(cfg)
    env = AutoResetWrapper(core)
    f_hover = cfg.quad.hover_command
    grid = np.stack(np.meshgrid(np.arange(4) - 1.5, np.arange(2) - 0.5, indexing="ij"), -1).reshape(N, 2)
    init = {"pos": np.concatenate([grid, np.full((N, 1), 3.0)], -1), "rot": np.broadcast_to(np.eye(3), (N, 3, 3)),
            "vel": np.zeros((N, 3)), "omega": np.zeros((N, 3)), "motors": np.full((N, 4), f_hover)}
    reset = jax.jit(jax.vmap(lambda k: env.reset(k, init)))
    step = jax.jit(jax.vmap(env.step))
    s0 = reset(jax.random.split(jax.random.key(42), W))
    action = jnp.full((W, N, 4), 2 * f_hover - 1, jnp.float32)  # command = the start thrust: motors steady
    s1 = step(s0, action)
    for leaf in jax.tree.leaves((s1.obs, s1.reward, s1.metrics, s1.info["state"], s1.data.qpos, s1.data.qvel)):
        assert np.all(np.isfinite(np.asarray(leaf)))
    p = {k: np.asarray(v, np.float64) for k, v in s1.info["params"].items()}
    mass = p["mass"]
    assert mass.shape == (W, N)
    assert np.unique(mass[:, 0]).size == W and mass.std() > 0.01 * cfg.quad.mass
    lo, hi = cfg.randomization.mass_scale
    assert mass.min() >= lo * cfg.quad.mass - 1e-9 and mass.max() <= hi * cfg.quad.mass + 1e-9
    # vertical velocity after one control step (2 Euler sub-steps): (sum thrust / m - g) * control_dt
    thrust = np.asarray(s1.info["state"]["thrust"], np.float64)  # applied f_norm (motor noise included)
    force_b, torque_b = body_wrench(thrust, p["thrust_max"], p["torque_max"], rotor_positions(cfg.quad))
    vz_expected = (force_b[..., 2] / mass - cfg.quad.gravity) * cfg.control_dt
    vz = np.asarray(s1.info["state"]["vel"], np.float64)[..., 2]
    np.testing.assert_allclose(vz, vz_expected, rtol=2e-3, atol=2e-5)
    vz_nominal_mass = (force_b[..., 2] / cfg.quad.mass - cfg.quad.gravity) * cfg.control_dt
    assert np.abs(vz - vz_nominal_mass).max() > 50 * np.abs(vz - vz_expected).max()
    # body angular velocity after one step: torque / inertia * control_dt (from rest)
    omega = np.asarray(s1.info["state"]["omega"], np.float64)
    om_expected = torque_b / p["inertia"] * cfg.control_dt
    tol = 0.02 * np.abs(om_expected).max()
    np.testing.assert_allclose(omega, om_expected, rtol=0.02, atol=tol)
    om_nominal = torque_b / np.asarray(cfg.quad.inertia) * cfg.control_dt
    assert np.abs(omega - om_nominal).max() > 5 * tol
    # mix: every world runs one sub-scenario, many kinds across worlds, goals inside the room
    kinds = np.asarray(s1.info["scenario"].kind)
    assert set(np.unique(kinds)) <= set(range(len(MIX_CHOICES))) and np.unique(kinds).size >= 5
    goals = np.asarray(s1.info["goals"])
    assert np.all(goals >= np.asarray(cfg.room_low)) and np.all(goals <= np.asarray(cfg.room_high))

    s2 = step(s1, action)
    s3 = step(s2, action)  # third step: time limit -> full reset
    assert np.all(np.asarray(s2.done) == 0) and np.all(np.asarray(s3.done))
    i3 = s3.info
    assert np.all(np.asarray(i3["step"]) == 0) and np.all(np.asarray(i3["time"]) == 0)
    assert np.all(np.asarray(i3["total_steps"]) == 3)  # kept across episodes (reward annealing)
    assert np.all(np.asarray(i3["motor_u"]) == 0) and np.all(np.asarray(i3["motor_eps"]) == 0)  # motor_start zero
    assert np.all(np.asarray(i3["metrics_acc"]["steps"]) == 0)
    assert np.all(np.asarray(i3["metrics_acc"]["dist_sum"]) == 0)
    assert np.mean(np.asarray(i3["params"]["mass"]) != mass) > 0.99  # parameters redrawn
    assert np.mean(np.any(np.asarray(i3["goals"]) != np.asarray(s2.info["goals"]), axis=(-1, -2))) > 0.5
    # the episode's start state replaces the end state (positions spawned near the new goals)
    pos3 = np.asarray(i3["state"]["pos"])
    np.testing.assert_allclose(np.asarray(s3.data.qpos).reshape(W, N, 7)[..., :3], pos3, atol=1e-6)
    assert np.all(np.abs(pos3 - np.asarray(i3["goals"])) <= 2.0 + 1e-5) and np.all(pos3[..., 2] >= 0.75 - 1e-6)
    np.testing.assert_allclose(np.asarray(i3["state"]["vel"]), 0.0)
    # the finished episode's metrics are reported at the done step
    em = {k: np.asarray(v) for k, v in i3["episode_metrics"].items()}
    assert np.all(em["mean_distance"] > 0) and np.all(np.isfinite(em["mean_distance"]))
    assert np.all(np.isfinite(np.asarray(s3.reward)))
    s4 = step(s3, action)
    assert not np.any(np.asarray(s4.done)) and np.all(np.asarray(s4.info["step"]) == 1)


_X64_SCRIPT = textwrap.dedent("""
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    from quadswarm_mj import EnvConfig, QuadSwarmEnv
    from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv
    from quadswarm_mj.spatial import yaw_rotmat

    N, T = 8, 150
    cfg = EnvConfig(num_quads=N, room_size=(4.0, 4.0, 3.0)).without_noise()
    pos = np.array([[-0.5, 0.0, 1.5], [0.5, 0.0, 1.5],       # head-on pair
                    [0.0, 1.0, 1.0], [0.0, 1.0, 1.3],        # stacked pair, the lower one rises into the upper
                    [1.8, -1.0, 1.5],                        # flies into the +x wall
                    [-1.0, -1.0, 2.8],                       # flies into the ceiling
                    [1.0, 1.0, 0.3],                         # falls to the floor (motors start at zero)
                    [-1.2, 1.2, 1.5]])
    vel = np.zeros((N, 3))
    vel[0, 0], vel[1, 0], vel[3, 2] = 1.5, -1.5, -0.6
    vel[4, 0], vel[5, 2] = 2.0, 1.5
    motors = np.full((N, 4), cfg.quad.hover_command)
    motors[6] = 0.0
    init = {"pos": pos, "vel": vel, "rot": yaw_rotmat(np.linspace(-1.0, 1.0, N)), "omega": np.zeros((N, 3)),
            "motors": motors, "goals": pos + 0.2}
    t = np.arange(T)[:, None, None] * cfg.control_dt
    phase = np.arange(4)[None, None] + np.arange(N)[None, :, None]
    acts = cfg.quad.hover_action + 0.05 * np.sin(2 * np.pi * 1.3 * t + phase)
    cpu = QuadSwarmEnv(cfg)
    cpu.reset(seed=0, options={"state": init})
    env = MjxQuadSwarmEnv(cfg, physics=sys.argv[1])
    s = jax.jit(env.reset)(jax.random.key(0), init)
    step = jax.jit(env.step)
    err_p = err_r = 0.0
    events = {"floor": 0, "wall": 0, "ceiling": 0, "quad": 0}
    for k in range(T):
        _, _, _, _, info = cpu.step(acts[k])
        s = step(s, jnp.asarray(acts[k]))
        err_p = max(err_p, float(np.abs(info["state"]["pos"] - np.asarray(s.info["state"]["pos"])).max()))
        err_r = max(err_r, float(np.abs(info["rewards"] - np.asarray(s.reward)).max()))
        terms = info["reward_terms"]
        events["floor"] += int(np.asarray(s.info["on_floor"]).any())
        events["wall"] += int(np.asarray(s.info["at_wall"]).any())
        events["ceiling"] += int(np.asarray(s.info["at_ceiling"]).any())
        events["quad"] += int(np.asarray(s.info["contact"]).any())
        assert np.array_equal(info["on_floor"], np.asarray(s.info["on_floor"])), k
    em_cpu = cpu.core.episode_metrics()
    em_mjx = s.info["episode_metrics"]
    print(json.dumps({"err_p": err_p, "err_r": err_r, "events": events,
                      "coll_cpu": float(cpu.core.metrics["collisions"].sum()),
                      "coll_mjx": float(np.asarray(s.info["metrics_acc"]["collisions"]).sum()),
                      "dist_cpu": float(em_cpu["mean_distance"][0]), "dist_mjx": float(em_mjx["mean_distance"])}))
""")


@pytest.mark.slow
@pytest.mark.parametrize("physics", ["freebody", "mjx"])
def test_parity_x64_through_floor_wall_ceiling_and_quad_collisions(physics):
    """With float64 on both sides the two engines agree to round-off through every contact model
    (paper floor with landing, wall and ceiling bounces, quad-quad responses), motors given as an
    (N, 4) array."""
    out = subprocess.run([sys.executable, "-c", _X64_SCRIPT, physics], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "JAX_PLATFORMS": "cpu"})
    assert out.returncode == 0, out.stderr[-3000:]
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert all(v > 0 for v in r["events"].values()), r
    assert r["err_p"] < 1e-9 and r["err_r"] < 1e-9, r
    assert r["coll_cpu"] == r["coll_mjx"]
    assert r["dist_mjx"] == pytest.approx(r["dist_cpu"], rel=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("model", ["mujoco", "blend"])
def test_mujoco_contacts_headon_case_matches_cpu_env(model):
    """collision_model 'mujoco'/'blend' through physics='mjx': the reference head-on case
    (golden_d setup) on the JAX engine stays within 5 mm of the CPU env with the same model."""
    from test_reference_parity import load  # tests/ is on sys.path (pytest rootdir-relative import)

    ref, meta = load("golden_d_headon_collision_noisefree.npz")
    n = meta["num_quads"]
    cfg = EnvConfig(num_quads=n, room_size=tuple(meta["room_dims"]), scenario="static_same_goal",
                    collision_model=model).without_noise()
    motors = "hover" if meta["motors_prespun_to_hover"] else "zero"
    init = {"pos": ref["init_pos"], "vel": ref["init_vel"], "rot": ref["init_rot"], "omega": ref["init_omega"]}
    cpu = QuadSwarmEnv(cfg)
    cpu.reset(seed=0, options={"state": {**init, "motors": motors}})
    acts = ref["actions_raw"].reshape(-1, n, 4)
    cpu_pos, cpu_vel = [], []
    for a in acts:
        _, _, _, _, info = cpu.step(a)
        cpu_pos.append(info["state"]["pos"])
        cpu_vel.append(info["state"]["vel"])
    cpu_pos, cpu_vel = np.array(cpu_pos), np.array(cpu_vel)
    with pytest.raises(ValueError, match="physics='mjx'"):
        MjxQuadSwarmEnv(cfg, physics="freebody")
    env = MjxQuadSwarmEnv(cfg)
    assert env.physics == "mjx"
    s = jax.jit(lambda k, st: env.reset(k, {**st, "motors": motors}))(jax.random.key(0), init)

    def run(s, acts):
        def body(s, a):
            s = env.step(s, a)
            return s, (s.info["state"]["pos"], s.info["state"]["vel"])
        return jax.lax.scan(body, s, acts)[1]

    pos, vel = jax.jit(run)(s, jnp.asarray(acts, jnp.float32))
    pos, vel = np.asarray(pos), np.asarray(vel)
    assert np.abs(cpu_vel[-1, :, 0] - cpu_vel[0, :, 0]).max() > 0.5  # the quads did collide (velocity reversed)
    assert np.abs(pos - cpu_pos).max() < 5e-3
