"""Input validation of issue 32 (items 2, 3 and 8): physical bounds on reset states and airframe
parameters, dtype-aware checks (the JAX engine runs float32), real numeric dtypes only, unknown
option keys, closed envs, PettingZoo action containers. Every rejected call is a ValueError (or a
RuntimeError for a closed env) naming the field and the allowed range, and leaves the env unchanged.

JAX compiles are kept few: one module-scoped env per engine (and one boundary-config env)."""

from __future__ import annotations

import datetime
import warnings

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, QuadSwarmEnv, QuadSwarmParallelEnv, QuadSwarmVectorEnv
from quadswarm_mj.config import (
    MAX_ANGULAR_ACCEL,
    MAX_EPISODE_SECONDS,
    MAX_ROOM_SIDE,
    MAX_THRUST_TO_WEIGHT,
    OMEGA_LIMIT,
    SPEED_LIMIT,
)

ENGINES = ["mujoco", "jax"]
N = 4
# four quads well inside the default 10 m room, away from each other
POS = np.array([[0.0, 0.0, 5.0], [2.0, 2.0, 5.0], [-2.0, -2.0, 5.0], [2.0, -2.0, 5.0]])


@pytest.fixture(scope="module", params=ENGINES)
def env(request):
    e = QuadSwarmEnv(num_quads=N, engine=request.param)
    yield e
    e.close()


def _state_of(env: QuadSwarmEnv, info: dict) -> dict[str, np.ndarray]:
    s = {k: np.array(v, copy=True) for k, v in info["state"].items()}
    s["goals"] = np.array(info["goals"], copy=True)
    return s


def _mujoco_warnings(env: QuadSwarmEnv) -> list[int]:
    d = env.core.phys.data
    return [int(d.warning[k].number) for k in range(len(d.warning))]


# ------------------------------------------------------------------------ item 2: reset state bounds
@pytest.mark.parametrize("key,value,words", [
    ("vel", np.full((N, 3), 30.0), ["options['state']['vel']", f"{SPEED_LIMIT:g} m/s", "(0,)"]),
    ("vel", np.array([[0, 0, 0]] * 3 + [[0, 0, -1e6]]), ["'vel'", f"{SPEED_LIMIT:g} m/s", "(3,)"]),
    ("omega", np.full((N, 3), 1e6), ["options['state']['omega']", f"{OMEGA_LIMIT:g} rad/s", "(0,"]),
    ("omega", np.full((N, 3), 1e200), ["'omega'", f"{OMEGA_LIMIT:g} rad/s"]),  # item 3: inf in float32
    ("motors", np.full((N, 4), 1.5), ["'motors'", "[0, 1]"]),
    ("motors", np.full((N, 4), -0.1), ["'motors'", "[0, 1]"]),
    ("vel", [[10**400, 0, 0]] * N, ["options['state']['vel']", "float64"]),  # item 8: no OverflowError
])
def test_reset_state_beyond_the_physical_bounds_is_rejected(env, key, value, words):
    with pytest.raises(ValueError) as e:
        env.reset(seed=0, options={"state": {key: value}})
    for w in words:
        assert w in str(e.value), (w, str(e.value))


def test_boundary_state_runs_finite_and_stable(env):
    """|vel| = SPEED_LIMIT and |omega| = OMEGA_LIMIT per axis: 200 steps finite, no MuJoCo instability
    (nothing teleported to the default pose), the first step moves each quad by about vel * dt."""
    vel = np.array([[SPEED_LIMIT, 0, 0], [0, -SPEED_LIMIT, 0], [0, 0, SPEED_LIMIT], [-SPEED_LIMIT / np.sqrt(3)] * 3])
    omega = np.array([[1, 1, 1], [-1, 1, -1], [1, -1, 0], [-1, -1, -1]]) * OMEGA_LIMIT
    _, info = env.reset(seed=0, options={"state": {"pos": POS, "vel": vel, "omega": omega}})
    rng = np.random.default_rng(0)
    for i in range(200):
        obs, reward, _, _, info = env.step(rng.uniform(-1, 1, (N, 4)))
        s = info["state"]
        assert all(np.isfinite(v).all() for v in s.values()) and np.isfinite(obs).all() and np.isfinite(reward), i
        if i == 0:
            moved = s["pos"] - POS
            np.testing.assert_allclose(moved, vel * env.cfg.control_dt, atol=0.05)
    if env.engine == "mujoco":
        assert _mujoco_warnings(env) == [0] * len(_mujoco_warnings(env))


# the strongest accepted airframe: thrust-to-weight, spin limit and angular acceleration at their bounds
_ARM, _MASS, _G = 0.04596194, 0.028, 9.81
_I_MIN = 4 * _ARM * (_G * _MASS * MAX_THRUST_TO_WEIGHT / 4) / MAX_ANGULAR_ACCEL
BOUNDARY_QUAD = {"max_omega": OMEGA_LIMIT, "thrust_to_weight": MAX_THRUST_TO_WEIGHT,
                 "inertia": (_I_MIN * 1.0001, _I_MIN * 1.0001, _I_MIN * 1.8)}


@pytest.mark.parametrize("engine", ENGINES)
def test_boundary_airframe_runs_finite_and_stable(engine):
    env = QuadSwarmEnv(num_quads=N, engine=engine, quad=BOUNDARY_QUAD)
    try:
        omega = np.array([[1, 1, 1], [-1, 1, -1], [1, -1, 0], [-1, -1, -1]]) * OMEGA_LIMIT
        env.reset(seed=0, options={"state": {"pos": POS, "vel": np.full((N, 3), 20.0), "omega": omega}})
        rng = np.random.default_rng(1)
        for i in range(200):
            obs, reward, _, _, info = env.step(rng.uniform(-1, 1, (N, 4)))
            assert all(np.isfinite(v).all() for v in info["state"].values()) and np.isfinite(obs).all(), i
            assert np.isfinite(reward)
        if engine == "mujoco":
            assert _mujoco_warnings(env) == [0] * len(_mujoco_warnings(env))
    finally:
        env.close()


def test_vector_env_rejects_one_spinning_world_and_unknown_keys():
    """The issue's reproduction: omega 1e6 rad/s in one world of a 16-world vector env (MuJoCo then
    reset the shared data: every quad of the shard teleported) is refused, naming the field, the bound
    and the world; so are misspelt option keys (naming the allowed ones); the env is unchanged."""
    W = 16
    vec = QuadSwarmVectorEnv(num_quads=2, num_envs=W, num_shards=1)
    try:
        _, info = vec.reset(seed=0)
        ref = vec.step(np.zeros((W, 2, 4)))[4]["state"]["pos"].copy()
        vec.reset(seed=0)
        omega = np.zeros((W, 2, 3))
        omega[5, 1, 2] = 1e6
        bad = [({"state": {"omega": omega}}, ["options['state']['omega']", f"{OMEGA_LIMIT:g} rad/s", "(5, 1, 2)"]),
               ({"State": {}}, ["'State'", "allowed", "'state'", "'reset_mask'"]),
               ({"state": {"Pos": np.zeros((W, 2, 3))}}, ["'Pos'", "allowed", "'pos'"])]
        for options, words in bad:
            with pytest.raises(ValueError) as e:
                vec.reset(seed=1, options=options)
            for w in words:
                assert w in str(e.value), (w, str(e.value))
        np.testing.assert_array_equal(vec.step(np.zeros((W, 2, 4)))[4]["state"]["pos"], ref)
    finally:
        vec.close()


# ------------------------------------------------------------------------ item 2: the instability backstop
@pytest.mark.parametrize("backend", ["mjdata", "batch"])
def test_instability_names_the_world_and_quad_and_resets_no_other(backend):
    """A state MuJoCo finds unstable (written past validation: omega 1e6 rad/s on world 2, quad 1)
    stops the step with an error naming the world and the quad; no other quad is teleported to the
    default pose (MuJoCo's auto-reset of the shared data is off)."""
    from quadswarm_mj.envs.cpu_core import CpuSwarm, PhysicsInstabilityError

    B = 4
    core = CpuSwarm(EnvConfig(num_quads=N), num_worlds=B, backend=backend, visual=False, chunk_worlds=2)
    core.seed(0)
    core.reset()
    core.step(np.zeros((B, N, 4)))
    before = core.qpos[..., :3].copy()
    core.qvel[2, 1, 3:] = 1e6
    core.phys.touch()
    with pytest.raises(PhysicsInstabilityError, match=r"world 2, quad 1\b") as e:
        core.step(np.zeros((B, N, 4)))
    assert isinstance(e.value, RuntimeError) and "unstable" in str(e.value)
    others = np.ones((B, N), bool)
    others[2, 1] = False
    moved = np.linalg.norm(core.qpos[..., :3] - before, axis=-1)
    assert np.isfinite(moved[others]).all() and moved[others].max() < 0.05, moved


def _spin_up(shard, world: int, quad: int) -> None:
    """(runs in the shard's process) omega 1e6 rad/s on env world ``world`` if this shard holds it."""
    if shard.lo <= world < shard.hi:
        shard.core.qvel[world - shard.lo, quad, 3:] = 1e6
        shard.core.phys.touch()


def test_instability_in_a_vector_env_worker_names_the_env_world():
    vec = QuadSwarmVectorEnv(num_quads=2, num_envs=4, num_shards=2)
    try:
        vec.reset(seed=0)
        vec._call_shards(_spin_up, 3, 1)  # world 3 is in the worker's shard (worlds 2, 3)
        with pytest.raises(RuntimeError, match=r"world 3, quad 1\b"):
            vec.step(np.zeros((4, 2, 4)))
        with pytest.raises(RuntimeError, match=r"reset\(\)"):
            vec.step(np.zeros((4, 2, 4)))
        vec.reset(seed=0)
        obs, reward, *_ = vec.step(np.zeros((4, 2, 4)))
        assert np.isfinite(obs).all() and np.isfinite(reward).all()
    finally:
        vec.close()


def test_instability_in_the_single_env_needs_a_reset():
    env = QuadSwarmEnv(num_quads=N)
    env.reset(seed=0)
    env.core.qvel[0, 3, 3:] = 1e6
    env.core.phys.touch()
    with pytest.raises(RuntimeError, match=r"world 0, quad 3\b"):
        env.step(np.zeros((N, 4)))
    with pytest.raises(RuntimeError, match=r"reset\(\)"):
        env.step(np.zeros((N, 4)))
    _, info_fresh = env.reset(seed=0)
    _, info_new = QuadSwarmEnv(num_quads=N).reset(seed=0)
    np.testing.assert_array_equal(info_fresh["state"]["pos"], info_new["state"]["pos"])
    obs, reward, *_ = env.step(np.zeros((N, 4)))
    assert np.isfinite(obs).all() and np.isfinite(reward)


# ------------------------------------------------------------------------ item 2: config bounds
@pytest.mark.parametrize("kwargs,words", [
    ({"quad": {"inertia": (1e-30,) * 3}}, ["quad.inertia", "kg m^2"]),
    ({"quad": {"inertia": (1e-7,) * 3}}, ["quad.inertia", "angular acceleration", f"{MAX_ANGULAR_ACCEL:g} rad/s^2"]),
    ({"quad": {"inertia": (2.0, 2.0, 2.0)}}, ["quad.inertia", "<= 1"]),
    ({"quad": {"mass": 1e-9}}, ["quad.mass", ">= 0.001"]),
    ({"quad": {"mass": 1e3}}, ["quad.mass", "<= 10"]),
    ({"quad": {"thrust_to_weight": 1e6}}, ["quad.thrust_to_weight", f"<= {MAX_THRUST_TO_WEIGHT:g}"]),
    ({"quad": {"max_omega": 1e6}}, ["quad.max_omega", f"<= {OMEGA_LIMIT:g}"]),
    ({"quad": {"gravity": 1e300}}, ["quad.gravity", "<= 100"]),
    ({"quad": {"torque_to_thrust": 10.0}}, ["quad.torque_to_thrust", "angular acceleration"]),
    ({"randomize": True, "randomization": {"mass_scale": (1e-9, 1e-9)}}, ["randomization.mass_scale", ">= 0.1"]),
    ({"randomize": True, "randomization": {"inertia_scale": (1e-9, 1.0)}}, ["randomization.inertia_scale", ">= 0.1"]),
    ({"randomize": True, "randomization": {"rotor_thrust_scale": (1.0, 1e9)}},
     ["randomization.rotor_thrust_scale", "<= 10"]),
    ({"randomize": True, "randomization": {"thrust_to_weight": (1.0, 9.0), "rotor_thrust_scale": (1.0, 1.5)}},
     ["randomization", "thrust-to-weight", f"{MAX_THRUST_TO_WEIGHT:g}"]),
    ({"randomize": True, "randomization": {"motor_noise_ratio": (0.0, 1e300)}},
     ["randomization.motor_noise_ratio", "<= 1"]),
    ({"noise": {"motor_noise_ratio": 1e300}}, ["noise.motor_noise_ratio", "<= 1"]),
    ({"collision": {"kick_omega": (1e6, 1e6)}}, ["collision.kick_omega", f"<= {OMEGA_LIMIT:g}"]),
    ({"aero": {"ground_effect_max_gain": 1e300}}, ["aero.ground_effect_max_gain", "<= 2"]),
    ({"aero": {"drag": True, "drag_coeff": (1.0, 1.0, 1.0)}}, ["aero.drag_coeff", "sim_dt"]),
    ({"aero": {"drag": True, "thrust_coeff": 1e-300}}, ["aero.thrust_coeff", "sim_dt"]),
    # values that overflow float32 (the JAX engine) or blow a state up, beyond any physical meaning
    ({"noise": {"sensor_pos_std": 1e300}}, ["noise.sensor_pos_std", "<= 200"]),
    ({"noise": {"sensor_omega_std": 1e300}}, ["noise.sensor_omega_std", f"<= {OMEGA_LIMIT:g}"]),
    ({"rewards": {"pos": 1e300}}, ["rewards.pos", "<= 1000000"]),
    ({"collision_decay": (0.5, 1e300)}, ["collision_decay[1]", "<= 1"]),
    ({"neighbor_vel_clip": 1e300}, ["neighbor_vel_clip", f"<= {2 * SPEED_LIMIT:g}"]),
    ({"formation_center": (1e300, 0.0, 2.0)}, ["formation_center", f"{MAX_ROOM_SIDE:g} m"]),
    ({"collision": {"wall_speed_limits": (0.1, 1e300)}}, ["collision.wall_speed_limits[1]", f"<= {SPEED_LIMIT:g}"]),
])
def test_airframe_beyond_the_physical_bounds_is_rejected(kwargs, words):
    with pytest.raises(ValueError) as e:
        EnvConfig(**kwargs)
    for w in words:
        assert w in str(e.value), (w, str(e.value))


def test_airframe_bounds_leave_the_presets_and_defaults():
    EnvConfig()
    EnvConfig(randomize=True)
    EnvConfig(quad="crazyflie21_identified", randomize=True, aero={"drag": True, "ground_effect": True})
    EnvConfig(quad=BOUNDARY_QUAD)


# ------------------------------------------------------------------------ item 3: actions and dtypes
@pytest.mark.parametrize("big", [1e20, 1e300, -1e300])
def test_huge_finite_actions_are_clipped(env, big):
    """Accepted and clipped: the same physics as a step with the action at its bound (+-1)."""
    env.reset(seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow in a cast to the engine's dtype either
        obs, reward, _, _, info = env.step(np.full((N, 4), big))
    assert np.isfinite(obs).all() and all(np.isfinite(v).all() for v in info["state"].values())
    env.reset(seed=0)
    obs_clipped, reward_clipped, _, _, info_clipped = env.step(np.full((N, 4), np.sign(big)))
    np.testing.assert_array_equal(obs, obs_clipped)
    for k, v in info_clipped["state"].items():
        np.testing.assert_array_equal(info["state"][k], v, err_msg=k)
    # every reward term (the effort term too) sees the clipped action
    assert np.isfinite(reward) and reward == reward_clipped
    for k, v in info_clipped["reward_terms"].items():
        np.testing.assert_array_equal(info["reward_terms"][k], v, err_msg=k)


@pytest.mark.parametrize("kwargs", [{"episode_seconds": 10**400}, {"quad": {"mass": 10**400}},
                                    {"room_size": (10**400, 10, 10)}, {"randomization": {"mass_scale": (1, 10**400)}}])
def test_python_int_beyond_float64_in_the_config_is_a_value_error(kwargs):
    with pytest.raises(ValueError, match=list(kwargs)[0]):
        EnvConfig(**kwargs)


def test_python_int_beyond_float64_is_a_value_error(env):
    env.reset(seed=0)
    act = [[0.0] * 4 for _ in range(N)]
    act[1][2] = 10**400
    with pytest.raises(ValueError, match=r"action.*float64"):
        env.step(act)


# ------------------------------------------------------------------------ item 8: real numeric dtypes only
NON_NUMERIC = {
    "str": lambda shape: np.full(shape, "0.1"),
    "bytes": lambda shape: np.full(shape, b"0.1"),
    "complex": lambda shape: np.full(shape, 0.1 + 0j),
    "bool": lambda shape: np.full(shape, True),
    "datetime": lambda shape: np.full(shape, np.datetime64("2020-01-01")),
    "timedelta": lambda shape: np.full(shape, np.timedelta64(1, "s")),
    "object": lambda shape: np.full(shape, 0.1, dtype=object),
    "pydatetime": lambda shape: np.full(shape, datetime.datetime(2020, 1, 1), dtype=object),
    "list_of_str": lambda shape: np.full(shape, "0.1").tolist(),
    "none": lambda shape: np.full(shape, None).tolist(),
}


@pytest.mark.parametrize("kind", NON_NUMERIC)
def test_non_numeric_actions_are_rejected(env, kind):
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action.*real numbers"):
        env.step(NON_NUMERIC[kind]((N, 4)))


@pytest.mark.parametrize("kind", ["str", "bytes", "bool", "complex", "datetime", "object", "list_of_str"])
@pytest.mark.parametrize("key,tail", [("pos", (3,)), ("vel", (3,)), ("omega", (3,)), ("motors", (4,)),
                                      ("goals", (3,))])
def test_non_numeric_states_are_rejected(key, tail, kind):
    env = QuadSwarmEnv(num_quads=N)
    with pytest.raises(ValueError, match=rf"options\['state'\]\['{key}'\].*real numbers"):
        env.reset(seed=0, options={"state": {key: NON_NUMERIC[kind]((N,) + tail)}})


def test_integer_actions_and_states_are_accepted(env):
    env.reset(seed=0, options={"state": {"pos": POS.astype(np.int64), "vel": np.zeros((N, 3), np.int32),
                                         "motors": np.ones((N, 4), np.uint8)}})
    obs, *_ = env.step(np.zeros((N, 4), np.int64))
    assert np.isfinite(obs).all()


def test_parallel_and_vector_envs_reject_non_numeric_actions():
    par = QuadSwarmParallelEnv(num_quads=2)
    par.reset(seed=0)
    with pytest.raises(ValueError, match=r"quad_1.*real numbers"):
        par.step({"quad_0": np.zeros(4), "quad_1": np.full(4, "0.1")})
    vec = QuadSwarmVectorEnv(num_quads=2, num_envs=2, num_shards=1)
    try:
        vec.reset(seed=0)
        with pytest.raises(ValueError, match=r"action.*real numbers"):
            vec.step(np.full((2, 2, 4), "0.1"))
        with pytest.raises(ValueError, match=r"options\['state'\]\['vel'\].*real numbers"):
            vec.reset(options={"state": {"vel": np.full((2, 2, 3), True)}})
        with pytest.raises(ValueError, match=r"'vel'.*50 m/s"):
            vec.reset(options={"state": {"vel": np.full((2, 2, 3), 1e6)}})
    finally:
        vec.close()


def test_mjx_env_reset_checks_the_bounds():
    import jax

    from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv

    mjx_env = MjxQuadSwarmEnv(EnvConfig(num_quads=2))
    with pytest.raises(ValueError, match=rf"init_state\['omega'\].*{OMEGA_LIMIT:g} rad/s"):
        mjx_env.reset(jax.random.PRNGKey(0), {"omega": np.full((2, 3), 1e200)})
    with pytest.raises(ValueError, match=r"init_state\['motors'\].*real numbers"):
        mjx_env.reset(jax.random.PRNGKey(0), {"motors": np.full((2, 4), "0.5")})


# ------------------------------------------------------------------------ item 8: reset option keys
@pytest.mark.parametrize("options,words", [
    ({"State": {"pos": POS}}, ["'State'", "allowed", "'state'", "'obstacles'"]),
    ({"state": {"Pos": POS}}, ["'Pos'", "allowed", "'pos'"]),
    ({"reset_mask": np.ones(1, bool)}, ["'reset_mask'", "allowed"]),  # a vector-env option
])
def test_unknown_reset_options_are_rejected(env, options, words):
    with pytest.raises(ValueError) as e:
        env.reset(seed=0, options=options)
    for w in words:
        assert w in str(e.value), (w, str(e.value))


def test_parallel_env_rejects_unknown_reset_options():
    par = QuadSwarmParallelEnv(num_quads=2)
    with pytest.raises(ValueError, match=r"unknown reset options \['State'\]; allowed: \[.*'state'"):
        par.reset(seed=0, options={"State": {}})


# ------------------------------------------------------------------------ item 8: config scalars
@pytest.mark.parametrize("room", ["999", "10", b"999", ("10", "10", "10"), (10.0, 10.0, "10"), (True, 10.0, 10.0)])
def test_room_size_must_be_numbers(room):
    with pytest.raises(ValueError, match=r"room_size must be 3 numbers \(m\).*" + f"{MAX_ROOM_SIDE:g}"):
        EnvConfig(room_size=room)


def test_room_size_range():
    with pytest.raises(ValueError, match=rf"room_size.*<= {MAX_ROOM_SIDE:g} m"):
        EnvConfig(room_size=(10.0, 1e9, 10.0))
    assert EnvConfig(room_size=np.array([10, 10, 10])).room_size == (10.0, 10.0, 10.0)
    EnvConfig(room_size=(MAX_ROOM_SIDE,) * 3)


@pytest.mark.parametrize("bad", ["123", ("0", "0", "2")])
def test_other_number_tuples_reject_strings(bad):
    with pytest.raises(ValueError, match="formation_center"):
        EnvConfig(formation_center=bad)
    with pytest.raises(ValueError, match="randomization.mass_scale"):
        EnvConfig(randomization={"mass_scale": ("0.8", "1.2")})
    with pytest.raises(ValueError, match="quad.inertia"):
        EnvConfig(quad={"inertia": ("1e-5", "1e-5", "2e-5")})


@pytest.mark.parametrize("seconds,words", [
    (0.004, ["episode_seconds", "one control step", "0.01"]),
    (0.0, ["episode_seconds"]),
    (1e307, ["episode_seconds", f"{MAX_EPISODE_SECONDS:g}"]),
    ("15", ["episode_seconds"]),
])
def test_episode_seconds_bounds(seconds, words):
    with pytest.raises(ValueError) as e:
        EnvConfig(episode_seconds=seconds)
    for w in words:
        assert w in str(e.value), (w, str(e.value))


def test_episode_seconds_limits_are_accepted():
    assert EnvConfig(episode_seconds=0.01).episode_steps == 1
    assert EnvConfig(episode_seconds=MAX_EPISODE_SECONDS).episode_steps == int(MAX_EPISODE_SECONDS * 100)
    with pytest.raises(ValueError, match=r"episode_seconds.*2\^24"):  # the JAX engine's float32 step time
        EnvConfig(episode_seconds=MAX_EPISODE_SECONDS, control_hz=1000, sim_hz=1000)


def test_numpy_integers_are_integers():
    cfg = EnvConfig(num_quads=np.int64(8), control_hz=np.int32(100), sim_hz=np.uint16(200), num_neighbors=np.int8(3),
                    rewards={"anneal_steps": np.int64(10)}, collision={"tries": np.int16(2)})
    assert cfg.num_quads == 8 and type(cfg.num_quads) is int
    assert type(cfg.control_hz) is int and type(cfg.sim_hz) is int and type(cfg.num_neighbors) is int
    assert type(cfg.rewards.anneal_steps) is int and type(cfg.collision.tries) is int
    assert QuadSwarmEnv(num_quads=np.int64(2)).cfg.num_quads == 2
    for bad in (True, np.bool_(True), 8.0, "8"):
        with pytest.raises(ValueError, match="num_quads must be an int"):
            EnvConfig(num_quads=bad)


# ------------------------------------------------------------------------ item 8: close()
@pytest.mark.parametrize("engine", ENGINES)
def test_closed_env_refuses_steps_and_resets(engine):
    e = QuadSwarmEnv(num_quads=N, engine=engine)
    if engine == "mujoco":  # (the JAX engine: no reset, so no compile)
        e.reset(seed=0)
    e.close()
    for call in (lambda: e.step(np.zeros((N, 4))), lambda: e.reset(seed=0), e.render):
        with pytest.raises(RuntimeError, match="closed"):
            call()
    e.close()  # closing twice is fine


def test_closed_env_does_not_reopen_its_renderer():
    e = QuadSwarmEnv(num_quads=2, render_mode="rgb_array")
    e.reset(seed=0)
    assert e.render().ndim == 3
    e.close()
    with pytest.raises(RuntimeError, match="closed"):
        e.render()
    assert e._renderer is None


def test_closed_parallel_env_refuses_steps():
    par = QuadSwarmParallelEnv(num_quads=2)
    par.reset(seed=0)
    par.close()
    with pytest.raises(RuntimeError, match="closed"):
        par.step({"quad_0": np.zeros(4), "quad_1": np.zeros(4)})
    with pytest.raises(RuntimeError, match="closed"):
        par.reset(seed=0)
    with pytest.raises(RuntimeError, match="closed"):
        par.render()


# ------------------------------------------------------------------------ item 8: PettingZoo containers
@pytest.mark.parametrize("actions", [[np.zeros(4), np.zeros(4)], (np.zeros(4), np.zeros(4)), np.zeros((2, 4))])
def test_parallel_env_actions_must_be_a_dict(actions):
    par = QuadSwarmParallelEnv(num_quads=2)
    par.reset(seed=0)
    with pytest.raises(ValueError, match=r"actions must be a dict \{agent: action\}"):
        par.step(actions)


# ------------------------------------------------------------------------ a rejected call changes nothing
BAD_CALLS = {
    "step_str": lambda e: e.step(np.full((N, 4), "0.1")),
    "step_overflow": lambda e: e.step([[10**400] * 4] * N),
    "step_bool": lambda e: e.step(np.ones((N, 4), bool)),
    "reset_typo": lambda e: e.reset(seed=5, options={"State": {}}),
    "reset_omega": lambda e: e.reset(seed=5, options={"state": {"omega": np.full((N, 3), 1e200)}}),
    "reset_vel": lambda e: e.reset(seed=5, options={"state": {"vel": np.full((N, 3), 1e3)}}),
    "reset_motors": lambda e: e.reset(seed=5, options={"state": {"motors": np.full((N, 4), 2.0)}}),
    "reset_state_str": lambda e: e.reset(seed=5, options={"state": {"pos": np.full((N, 3), "1")}}),
}


@pytest.mark.parametrize("bad", BAD_CALLS)
def test_rejected_call_leaves_the_env_unchanged(env, bad):
    def run(with_bad: bool) -> list[dict[str, np.ndarray]]:
        _, info = env.reset(seed=3)
        out = [_state_of(env, info)]
        for i in range(4):
            if with_bad and i == 2:
                with pytest.raises(ValueError):
                    BAD_CALLS[bad](env)
            _, _, _, _, info = env.step(np.full((N, 4), 0.1 * i))
            out.append(_state_of(env, info))
        return out

    ref, got = run(False), run(True)
    for a, b in zip(ref, got):
        for k in a:
            np.testing.assert_array_equal(b[k], a[k], err_msg=k)
