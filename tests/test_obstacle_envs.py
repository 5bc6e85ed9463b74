"""Obstacles on every front end (issue 12): API contract of reset(options={"obstacles"}), the 9
features last in the observation, finite spaces, reward term and metrics, MuJoCo columns, and an
o_random episode on QuadSwarmEnv (both engines), the PettingZoo env, the vector env (both engines),
MjxQuadSwarmEnv (both physics) and the Brax env."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test

from quadswarm_mj import EnvConfig, ObstacleConfig, QuadSwarmEnv, QuadSwarmParallelEnv, QuadSwarmVectorEnv
from quadswarm_mj import obstacles as ob
from quadswarm_mj.metrics import OBSTACLE_METRIC_KEYS, metric_keys
from quadswarm_mj.rewards import TERMS, env_terms

COLS = np.array([[0.0, 0.0], [2.0, -1.0], [-3.0, 2.5]])


def cfg_o(n: int = 3, seconds: float = 0.3, **kw) -> EnvConfig:
    return EnvConfig(num_quads=n, scenario=kw.pop("scenario", "o_random"), obstacles=ObstacleConfig(**kw),
                     episode_seconds=seconds)


def features_of(pos: np.ndarray, cols: np.ndarray, size: float) -> np.ndarray:
    m = ob.map_from_centres(ObstacleConfig(size=size), cols)
    return ob.obstacle_features(pos, m.centres, m.valid, m.radius)


def test_terms_and_metric_keys_follow_the_config():
    assert env_terms(EnvConfig()) == TERMS and "obstacle_collision" not in TERMS
    assert env_terms(cfg_o())[-1] == "obstacle_collision"
    assert set(OBSTACLE_METRIC_KEYS) <= set(metric_keys(cfg_o())) and not set(OBSTACLE_METRIC_KEYS) & set(
        metric_keys(EnvConfig()))


def test_check_env_with_obstacles():
    env = QuadSwarmEnv(cfg_o(3, 15.0))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=True)
    assert not caught, [str(w.message) for w in caught]
    assert np.all(np.isfinite(env.observation_space.low)) and np.all(np.isfinite(env.observation_space.high))


def test_parallel_api_with_obstacles():
    parallel_api_test(QuadSwarmParallelEnv(cfg_o(3, 0.5)), num_cycles=60)


def test_parallel_env_gives_every_agent_the_columns():
    env = QuadSwarmParallelEnv(cfg_o(3, 0.5))
    _, infos = env.reset(seed=0, options={"obstacles": COLS})
    for a in env.agents:
        np.testing.assert_array_equal(infos[a]["obstacles"], COLS)
    _, _, _, _, infos = env.step({a: np.zeros(4) for a in env.agents})
    for a in env.agents:
        np.testing.assert_array_equal(infos[a]["obstacles"], COLS)
    infos[env.agents[0]]["obstacles"][0] = 99.0  # copies: one agent's info cannot corrupt another's
    assert infos[env.agents[1]]["obstacles"][0, 0] == COLS[0, 0]


def test_given_columns_features_last_and_reward_sum_cpu():
    cfg = cfg_o(2, 2.0, scenario="static_same_goal")
    env = QuadSwarmEnv(cfg)
    state = {"pos": np.array([[-0.6, 0.0, 2.0], [2.0, 1.0, 2.0]]), "vel": np.array([[1.0, 0, 0], [0, 0, 0]])}
    obs, info = env.reset(seed=1, options={"state": state, "obstacles": COLS})
    np.testing.assert_array_equal(info["obstacles"], COLS)
    np.testing.assert_allclose(obs[:, -9:], features_of(info["state"]["pos"], COLS, 0.6), rtol=1e-6, atol=1e-6)
    # the columns are in the MuJoCo model (moved onto the map; unused slots parked below the floor)
    a, d = env.core.arena, env.core.data
    mp = d.mocap_pos[a.obstacle_mocap_ids[0]]
    np.testing.assert_allclose(mp[:3, :2], COLS)
    assert np.all(mp[3:, 2] < 0)
    pens = []
    for _ in range(40):
        obs, _, _, _, info = env.step(np.zeros((2, 4)))
        np.testing.assert_array_equal(info["obstacles"], COLS)
        terms = info["reward_terms"]
        np.testing.assert_allclose(sum(terms[k] for k in env_terms(cfg)), info["rewards"], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(obs[:, -9:], features_of(info["state"]["pos"], COLS, 0.6), rtol=1e-5, atol=1e-5)
        pens.append(terms["obstacle_collision"].copy())
    pens = np.array(pens)
    assert (pens[:, 0] < 0).sum() == 1 and pens.min() == -cfg.obstacles.collision_reward  # one penalty per contact
    assert np.all(pens[:, 1] == 0)
    env.close()


def test_random_maps_are_redrawn_and_avoid_spawns():
    env = QuadSwarmEnv(cfg_o(4, 1.0))
    seen = []
    for s in range(3):
        _, info = env.reset(seed=s)
        c = info["obstacles"]
        assert c.shape == (12, 2)
        d = np.linalg.norm(info["state"]["pos"][:, None, :2] - c[None], axis=-1)
        assert d.min() > 0.3 + env.cfg.quad.arm  # no quad starts inside or touching a column
        seen.append(c)
    assert not np.array_equal(seen[0], seen[1])


def test_bad_obstacle_options_are_rejected_and_change_nothing():
    env = QuadSwarmEnv(cfg_o(2))
    _, info = env.reset(seed=0)
    before = info["obstacles"].copy()
    for bad, match in ((np.zeros((3,)), "shape"), (np.zeros((13, 2)), "slots"), (np.full((1, 2), np.nan), "NaN"),
                       (np.array([[7.0, 0.0]]), "inside the room")):
        with pytest.raises(ValueError, match=match):
            env.reset(options={"obstacles": bad})
    np.testing.assert_array_equal(env.core.obstacle_centres(0), before)
    with pytest.raises(ValueError, match="obstacles are off"):
        QuadSwarmEnv(EnvConfig(num_quads=2)).reset(options={"obstacles": COLS})


def test_mujoco_collision_model_columns_stop_the_quad():
    cfg = EnvConfig(num_quads=1, collision_model="mujoco", obstacles=ObstacleConfig(), motor_start="hover",
                    episode_seconds=2.0).without_noise()
    env = QuadSwarmEnv(cfg)
    st = {"pos": np.array([[-1.0, 0.0, 2.0]]), "vel": np.array([[1.5, 0.0, 0.0]])}
    env.reset(seed=0, options={"state": st, "obstacles": np.zeros((1, 2))})
    xs, pens = [], []
    for _ in range(120):
        _, _, _, _, info = env.step(np.full(4, cfg.quad.hover_action))
        xs.append(info["state"]["pos"][0, 0])
        pens.append(info["reward_terms"]["obstacle_collision"][0])
    assert max(xs) < -(0.3 + cfg.quad.arm) + 0.02  # MuJoCo's contact stopped it at the column surface
    assert sum(p < 0 for p in pens) >= 1  # the contact is still detected and penalized


def test_episode_metrics_count_obstacle_collisions_after_grace():
    cfg = cfg_o(1, 2.0, scenario="static_same_goal").replace(grace_period_s=0.0)
    env = QuadSwarmEnv(cfg.without_noise())
    env.reset(seed=0, options={"state": {"pos": np.array([[-0.6, 0.0, 2.0]]), "vel": np.array([[1.0, 0, 0]]),
                                         "goals": np.array([[3.0, 3.0, 2.0]])}, "obstacles": np.zeros((1, 2))})
    done = False
    while not done:
        _, _, _, done, info = env.step(np.full(4, cfg.quad.hover_action))
    m = info["episode_metrics"]
    assert m["obstacle_collisions"] >= 1 and m["collision_rate"] == 1.0 and m["success"] == 0.0


def _episode(env, n_steps, act):
    for _ in range(n_steps):
        out = env.step(act())
    return out


def test_vector_env_cpu_given_maps_per_world():
    cfg = cfg_o(2, 0.2)
    v = QuadSwarmVectorEnv(cfg, num_envs=2)
    per = np.stack([COLS, COLS[::-1]])
    obs, info = v.reset(seed=0, options={"obstacles": per})
    np.testing.assert_array_equal(info["obstacles"][:, :3], per)
    assert np.isnan(info["obstacles"][:, 3:]).all()
    np.testing.assert_allclose(obs[1, :, -9:], features_of(info["state"]["pos"][1], per[1], 0.6), atol=1e-5)
    out = _episode(v, 20, lambda: np.zeros((2, 2, 4)))
    info = out[-1]
    assert set(info["episode_metrics"]) == set(metric_keys(cfg))
    assert info["obstacles"].shape == (2, 12, 2) and not np.array_equal(info["obstacles"][:, :3], per)  # redrawn
    v.close()


def test_seeded_runs_repeat_with_obstacles():
    def run():
        env = QuadSwarmEnv(cfg_o(3, 1.0, density_random=True, size_random=True))
        obs, info = env.reset(seed=3)
        out = [obs, info["obstacles"]]
        for _ in range(30):
            obs, r, *_ = env.step(np.zeros((3, 4)))
            out.append(obs)
        return out

    a, b = run(), run()
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


# ------------------------------------------------------------------------------- JAX engine


@pytest.mark.slow
@pytest.mark.parametrize("physics", ["freebody", "mjx"])
def test_mjx_env_o_random_episode(physics):
    jax = pytest.importorskip("jax")
    import jax.numpy as jnp

    from quadswarm_mj.envs.mjx_env import AutoResetWrapper, MjxQuadSwarmEnv

    cfg = cfg_o(2, 0.1) if physics == "freebody" else cfg_o(2, 0.1).replace(collision_model="mujoco")
    env = AutoResetWrapper(MjxQuadSwarmEnv(cfg, physics=physics))
    s = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), 2))
    assert s.info["obstacles"].shape == (2, 12, 2) and s.obs.shape == (2, 2, cfg.obs_dim)
    np.testing.assert_allclose(np.asarray(s.obs[..., -9:]),
                               ob.obstacle_features(np.asarray(s.info["state"]["pos"], np.float64),
                                                    np.asarray(s.info["obstacles"], np.float64),
                                                    np.asarray(s.info["obstacles_valid"]),
                                                    np.asarray(s.info["obstacle_radius"], np.float64)), atol=1e-4)
    step = jax.jit(env.vstep)
    for _ in range(cfg.episode_steps):
        s = step(s, jnp.zeros((2, 2, 4)))
    assert bool(s.done.all())
    assert set(OBSTACLE_METRIC_KEYS) <= set(s.info["episode_metrics"]) and "reward/obstacle_collision" in s.metrics
    total = sum(s.metrics[f"reward/{k}"] for k in env_terms(cfg))
    np.testing.assert_allclose(np.asarray(total), np.asarray(s.reward), rtol=1e-5, atol=1e-5)
    # init_state["obstacles"] places exactly those columns, also in the MuJoCo model (mocap)
    s1 = MjxQuadSwarmEnv(cfg, physics=physics).reset(jax.random.key(1), init_state={"obstacles": COLS})
    valid = np.asarray(s1.info["obstacles_valid"])
    np.testing.assert_allclose(np.asarray(s1.info["obstacles"])[valid], COLS, atol=1e-6)
    np.testing.assert_allclose(np.asarray(s1.data.mocap_pos)[:3, :2], COLS, atol=1e-6)
    with pytest.raises(ValueError, match="slots"):
        MjxQuadSwarmEnv(cfg, physics=physics).reset(jax.random.key(1), init_state={"obstacles": np.zeros((13, 2))})


@pytest.mark.slow
def test_jax_engine_front_ends_o_random_episode():
    pytest.importorskip("jax")
    cfg = cfg_o(2, 0.1)
    env = QuadSwarmEnv(cfg, engine="jax")
    obs, info = env.reset(seed=0, options={"obstacles": COLS})
    np.testing.assert_allclose(info["obstacles"], COLS, atol=1e-6)
    np.testing.assert_allclose(obs[:, -9:], features_of(info["state"]["pos"], COLS, 0.6), atol=1e-4)
    done = False
    while not done:
        obs, _, _, done, info = env.step(np.zeros((2, 4)))
    assert set(info["episode_metrics"]) == set(metric_keys(cfg)) and "obstacle_collision" in info["reward_terms"]
    env.close()
    v = QuadSwarmVectorEnv(cfg, num_envs=2, engine="jax")
    obs, info = v.reset(seed=0, options={"obstacles": COLS})
    np.testing.assert_allclose(info["obstacles"][:, :3], np.stack([COLS, COLS]), atol=1e-6)
    for _ in range(cfg.episode_steps):
        obs, _, _, done, info = v.step(np.zeros((2, 2, 4)))
    assert done.all() and set(info["episode_metrics"]) == set(metric_keys(cfg))
    v.close()


@pytest.mark.slow
def test_brax_env_with_obstacles():
    jax = pytest.importorskip("jax")
    pytest.importorskip("brax")
    import jax.numpy as jnp

    from quadswarm_mj.envs.brax_env import BraxQuadSwarmEnv

    cfg = cfg_o(2, 0.05)
    env = BraxQuadSwarmEnv(cfg)
    s = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(0), 2))
    assert s.obs.shape[-1] == cfg.obs_dim
    step = jax.jit(env.step)
    for _ in range(cfg.episode_steps):
        s = step(s, jnp.zeros((s.obs.shape[0], 4)))
    assert np.all(np.isfinite(np.asarray(s.obs))) and "reward/obstacle_collision" in s.metrics


@pytest.mark.parametrize("backend", ["mjdata", "batch"])
def test_cpu_backends_move_the_columns_for_mujoco_contacts(backend):
    """Both physics back ends of the CPU engine put the columns where the map says (world 1 of a
    2-world chunk in the batch back end included): a quad flying at a column is stopped there."""
    from quadswarm_mj.envs.cpu_core import CpuSwarm

    cfg = EnvConfig(num_quads=1, collision_model="mujoco", obstacles=ObstacleConfig(), motor_start="hover",
                    episode_seconds=2.0).without_noise()
    c = CpuSwarm(cfg, 3, backend=backend, visual=False, chunk_worlds=2)
    cols = np.array([[[0.0, 0.0]], [[1.0, 1.0]], [[-2.0, 2.0]]])
    start = cols[:, :, None, :] + np.array([-0.8, 0.0])  # (B, 1 quad, 1, 2)
    pos = np.concatenate([start[:, :, 0], np.full((3, 1, 1), 2.0)], -1)
    c.reset(state={"pos": pos, "vel": np.tile([1.5, 0.0, 0.0], (3, 1, 1)), "motors": "hover", "obstacles": cols})
    xmax = np.full(3, -np.inf)
    for _ in range(100):
        c.step(np.full((3, 1, 4), cfg.quad.hover_action))
        xmax = np.maximum(xmax, c.state_dict()["pos"][:, 0, 0] - cols[:, 0, 0])
    assert np.all(xmax < -(0.3 + cfg.quad.arm) + 0.02), xmax


@pytest.mark.slow
def test_mjx_mujoco_contacts_use_each_worlds_column_radius():
    """physics='mjx' with MuJoCo contacts and size randomization: the column pool is built with the
    largest radius (0.25 m), the contact geoms get the world's radius (a given map: the configured
    0.3 m diameter), so a quad flown at the thin column gets as close as it allows and no closer."""
    jax = pytest.importorskip("jax")
    from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv

    ocfg = ObstacleConfig(size=0.3, size_random=True, size_values=(0.3, 0.5))
    cfg = EnvConfig(num_quads=1, collision_model="mujoco", obstacles=ocfg, motor_start="hover",
                    episode_seconds=2.0, scenario="o_random").without_noise()
    env = MjxQuadSwarmEnv(cfg, physics="mjx")
    pool = env.mj_model.geom_size[env.arena.obstacle_geom_ids[0], 0]
    assert np.allclose(pool, 0.25)
    init = {"pos": np.array([[-0.8, 0.0, 2.0]]), "vel": np.array([[1.5, 0.0, 0.0]]), "motors": "hover",
            "obstacles": np.array([[0.0, 0.0]])}
    s = jax.jit(lambda k: env.reset(k, init))(jax.random.key(0))
    r = float(s.info["obstacle_radius"])
    assert r == pytest.approx(0.15)
    hover = np.full((1, 4), cfg.quad.hover_action, np.float32)

    def run(s):
        def body(s, _):
            s = env.step(s, hover)
            return s, s.info["state"]["pos"][0, 0]
        return jax.lax.scan(body, s, None, length=100)[1]

    xmax = float(np.max(np.asarray(jax.jit(run)(s))))
    assert -(r + cfg.quad.arm) - 0.03 < xmax < -(r + cfg.quad.arm) + 0.02, (r, xmax)


@pytest.mark.slow
def test_jax_engine_responds_to_more_simultaneous_column_hits_than_its_draw_budget():
    """The JAX engine draws the obstacle response for OBSTACLE_BUDGET new contacts per step; more
    simultaneous new contacts reuse those draws, so every quad that hits a column still bounces
    outward (noise on)."""
    jax = pytest.importorskip("jax")
    from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv

    n = ob.OBSTACLE_BUDGET + 2
    cols = np.array([[-3.0 + 2.0 * i, 0.0] for i in range(n)])
    cfg = EnvConfig(num_quads=n, scenario="static_same_goal", obstacles=ObstacleConfig(), motor_start="hover",
                    episode_seconds=1.0)
    env = MjxQuadSwarmEnv(cfg)
    # every quad 0.36 m from its column's axis, flying at it at 1 m/s: all touch within the first step
    pos = np.concatenate([cols + np.array([-0.36, 0.0]), np.full((n, 1), 2.0)], -1)
    init = {"pos": pos, "vel": np.tile([1.0, 0.0, 0.0], (n, 1)), "motors": "hover", "obstacles": cols}
    s = jax.jit(lambda k: env.reset(k, init))(jax.random.key(3))
    step = jax.jit(env.step)
    hover = np.full((n, 4), cfg.quad.hover_action, np.float32)
    hit = np.zeros(n, bool)
    for _ in range(3):
        s = step(s, hover)
        hit |= np.asarray(s.info["obstacle_contact"])
        if hit.all():
            break
    assert hit.all()
    vx = np.asarray(s.info["state"]["vel"])[:, 0]
    assert np.all(vx < 0.0), vx  # bounced back (radially outward, away from +x)
