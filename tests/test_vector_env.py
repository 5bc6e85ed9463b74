"""QuadSwarmVectorEnv: parity with QuadSwarmEnv, Gymnasium VectorEnv contract, auto-reset, seeding,
bad input, and the CPU engine's physics back ends agreeing bit for bit."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from quadswarm_mj import EnvConfig, QuadSwarmEnv, QuadSwarmVectorEnv
from quadswarm_mj.envs.cpu_core import CpuSwarm
from quadswarm_mj.rewards import TERMS

HOVER = EnvConfig().quad.hover_action


def cluster_state(n: int, rng: np.random.Generator, center=(0.0, 0.0, 1.0)) -> dict[str, np.ndarray]:
    """Quads on a small circle flying inward (they collide), some tilted and spinning (they crash)."""
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    pos = np.asarray(center) + np.stack([0.3 * np.cos(ang), 0.3 * np.sin(ang), 0.05 * np.arange(n)], -1)
    vel = -1.5 * np.stack([np.cos(ang), np.sin(ang), 0 * ang], -1) + 0.1 * rng.standard_normal((n, 3))
    yaw = rng.uniform(-np.pi, np.pi, n)
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.zeros((n, 3, 3))
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = c, -s, s, c, 1.0
    return {"pos": pos, "vel": vel, "rot": rot, "omega": rng.normal(0, 3.0, (n, 3)),
            "motors": np.full((n, 4), 0.5), "goals": np.asarray(center) + rng.uniform(-1, 1, (n, 3))}


def test_spaces_metadata_and_layout():
    cfg = EnvConfig(num_quads=4)
    env = QuadSwarmVectorEnv(cfg, num_envs=3, num_shards=1)
    try:
        assert isinstance(env, gym.vector.VectorEnv)
        assert env.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
        assert env.autoreset_mode == env.metadata["autoreset_mode"]  # also as an attribute (TorchRL reads it there)
        assert env.single_observation_space.shape == (4, cfg.obs_dim)
        assert env.observation_space.shape == (3, 4, cfg.obs_dim)
        assert env.single_action_space.shape == (4, 4) and env.action_space.shape == (3, 4, 4)
        obs, info = env.reset(seed=0)
        assert obs.shape == (3, 4, cfg.obs_dim) and obs.dtype == np.float32
        assert env.observation_space.contains(obs)
        assert info["state"]["rot"].shape == (3, 4, 3, 3) and info["goals"].shape == (3, 4, 3)
        obs, rew, term, trunc, info = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs)
        assert rew.shape == term.shape == trunc.shape == (3,) and not term.any()
        assert info["rewards"].shape == (3, 4)
        # the team reward is the mean of the per-quad rewards, which are the sum of the terms
        np.testing.assert_allclose(rew, info["rewards"].mean(-1), rtol=1e-12)
        total = sum(info["reward_terms"][k] for k in TERMS)
        np.testing.assert_allclose(total, info["rewards"], rtol=1e-12, atol=1e-15)
        # a policy shared across quads sees (B * N, obs_dim)
        assert obs.reshape(-1, cfg.obs_dim).shape == (12, cfg.obs_dim)
    finally:
        env.close()


@pytest.mark.parametrize("shards,backend,chunk", [(2, "auto", 64), (1, "batch", 2)])
def test_world_matches_single_env_step_for_step(shards, backend, chunk):
    """World 1 of the vector env, reset to the state and goals of a QuadSwarmEnv, matches it exactly
    (noise off): same physics, collisions, floor, rewards and observations."""
    cfg = EnvConfig(num_quads=6, episode_seconds=1.2, room_size=(4.0, 4.0, 3.0)).without_noise()
    B, N = 3, cfg.num_quads
    rng = np.random.default_rng(0)
    states = [cluster_state(N, rng, center=(0.2 * b, 0.0, 1.0)) for b in range(B)]
    single = QuadSwarmEnv(cfg)
    vec = QuadSwarmVectorEnv(cfg, num_envs=B, num_shards=shards, backend=backend, chunk_worlds=chunk)
    try:
        obs1, info1 = single.reset(seed=1, options={"state": states[1]})
        vstate = {k: np.stack([s[k] for s in states]) for k in states[0]}
        obsv, infov = vec.reset(seed=2, options={"state": vstate})
        np.testing.assert_array_equal(obsv[1], obs1)
        events = {"collisions": 0, "floor": 0}
        for _ in range(cfg.episode_steps):
            a = HOVER + 0.4 * rng.standard_normal((B, N, 4))
            obs1, r1, _, tr1, info1 = single.step(a[1])
            obsv, rv, _, trv, infov = vec.step(a)
            assert trv[1] == tr1
            if tr1:  # the vector env has auto-reset world 1: compare the episode's last observation
                np.testing.assert_array_equal(infov["final_obs"][1], obs1)
                for k, v in info1["episode_metrics"].items():
                    np.testing.assert_array_equal(infov["episode_metrics"][k][1], v)
                break
            np.testing.assert_array_equal(obsv[1], obs1)
            assert rv[1] == r1
            np.testing.assert_array_equal(infov["rewards"][1], info1["rewards"])
            for k in TERMS:
                np.testing.assert_array_equal(infov["reward_terms"][k][1], info1["reward_terms"][k])
            for k in ("pos", "vel", "rot", "omega", "thrust"):
                np.testing.assert_array_equal(infov["state"][k][1], info1["state"][k])
            np.testing.assert_array_equal(infov["on_floor"][1], info1["on_floor"])
            events["collisions"] += int(info1["new_collisions"].any())
            events["floor"] += int(info1["on_floor"].any())
        assert tr1, "the episode did not end"
        assert events["collisions"] > 0 and events["floor"] > 0, events  # the comparison covered the event models
    finally:
        vec.close()


@pytest.mark.parametrize("collision_model", ["mujoco", "blend"])
@pytest.mark.parametrize("backend,chunk", [("mjdata", 64), ("batch", 2)])
def test_multi_world_mujoco_contacts_match_single_worlds(collision_model, backend, chunk):
    """With MuJoCo contacts, every world of a multi-world model (one 3-world model, or chunks of 2
    worlds) equals its own QuadSwarmEnv up to round-off: no quad feels another world's floor."""
    cfg = EnvConfig(num_quads=6, episode_seconds=1.2, room_size=(4.0, 4.0, 3.0),
                    collision_model=collision_model).without_noise()
    B, N = 3, cfg.num_quads
    rng = np.random.default_rng(0)
    states = [cluster_state(N, rng, center=(0.2 * b, 0.0, 1.0)) for b in range(B)]
    singles = [QuadSwarmEnv(cfg) for _ in range(B)]
    vec = QuadSwarmVectorEnv(cfg, num_envs=B, num_shards=1, backend=backend, chunk_worlds=chunk)
    try:
        for env, st in zip(singles, states):
            env.reset(seed=1, options={"state": st})
        vec.reset(seed=2, options={"state": {k: np.stack([s[k] for s in states]) for k in states[0]}})
        floor = collisions = 0
        for _ in range(cfg.episode_steps - 1):
            a = HOVER + 0.4 * rng.standard_normal((B, N, 4))
            obsv, rv, _, _, infov = vec.step(a)
            for b, env in enumerate(singles):
                obs1, r1, _, _, info1 = env.step(a[b])
                np.testing.assert_allclose(obsv[b], obs1, rtol=0, atol=1e-6)  # float32 observations
                np.testing.assert_allclose(rv[b], r1, rtol=1e-9, atol=1e-12)
                for k in ("pos", "vel", "rot", "omega"):
                    np.testing.assert_allclose(infov["state"][k][b], info1["state"][k], rtol=0, atol=1e-9)
                np.testing.assert_array_equal(infov["on_floor"][b], info1["on_floor"])
                np.testing.assert_array_equal(infov["new_collisions"][b], info1["new_collisions"])
                floor += int(info1["on_floor"].any())
                collisions += int(info1["new_collisions"].any())
        assert floor > 0 and collisions > 0, (floor, collisions)  # the run exercised floor and quad contacts
    finally:
        vec.close()


def test_same_step_autoreset_and_partial_reset():
    cfg = EnvConfig(num_quads=2, episode_seconds=0.1)  # 10 control steps
    env = QuadSwarmVectorEnv(cfg, num_envs=4, num_shards=1)
    try:
        env.reset(seed=3)
        a = np.full((4, 2, 4), HOVER)
        for _ in range(9):
            _, _, _, trunc, info = env.step(a)
            assert not trunc.any() and "episode_metrics" not in info
        obs, rew, term, trunc, info = env.step(a)
        assert trunc.all() and not term.any()
        assert info["_episode_metrics"].all() and info["_final_obs"].all()
        assert set(info["episode_metrics"]) >= {"success", "collisions", "mean_distance"}
        assert not np.array_equal(info["final_obs"], obs)  # obs is the new episode's first observation
        np.testing.assert_array_equal(info["time"], 0.0)  # info describes the new episode
        _, _, _, trunc, info = env.step(a)
        assert not trunc.any()
        np.testing.assert_allclose(info["time"], cfg.control_dt)
        # reset only worlds 0 and 2
        mask = np.array([True, False, True, False])
        obs2, info2 = env.reset(options={"reset_mask": mask})
        np.testing.assert_allclose(info2["time"], np.where(mask, 0.0, cfg.control_dt))
    finally:
        env.close()


def test_seeding_reproducible_and_every_world_differs():
    cfg = EnvConfig(num_quads=3, randomize=True)

    def rollout(seed, shards=2):
        env = QuadSwarmVectorEnv(cfg, num_envs=6, num_shards=shards)
        try:
            obs, info = env.reset(seed=seed)
            out = [obs, info["params"]["mass"]]
            rng = np.random.default_rng(0)
            for _ in range(20):
                obs, rew, *_ = env.step(HOVER + 0.3 * rng.standard_normal((6, 3, 4)))
                out += [obs, rew]
            out.append(env.reset(seed=seed)[0])  # reseeding restarts the same worlds
            return out
        finally:
            env.close()

    a, b, c = rollout(7), rollout(7), rollout(8)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a[-1], a[0])
    assert not np.array_equal(a[0], c[0])
    masses = a[1]
    assert len(np.unique(masses.round(12))) == masses.size  # each world and quad drew its own mass


def test_bad_input_raises_clear_errors():
    cfg = EnvConfig(num_quads=2)
    env = QuadSwarmVectorEnv(cfg, num_envs=2, num_shards=1)
    try:
        with pytest.raises(RuntimeError, match="reset"):
            env.step(np.zeros((2, 2, 4)))
        env.reset(seed=0)
        with pytest.raises(ValueError, match="shape"):
            env.step(np.zeros((2, 4)))
        bad = np.zeros((2, 2, 4))
        bad[1, 0, 2] = np.nan
        with pytest.raises(ValueError, match="NaN"):
            env.step(bad)
        bad[1, 0, 2] = np.inf
        with pytest.raises(ValueError, match="inf"):
            env.step(bad)
        with pytest.raises(ValueError, match="shape"):
            env.reset(options={"state": {"pos": np.zeros((2, 3))}})
        with pytest.raises(ValueError, match="unknown"):
            env.reset(options={"bogus": 1})
        with pytest.raises(ValueError, match="reset_mask"):
            env.reset(options={"reset_mask": np.ones(3, bool)})
        with pytest.raises(ValueError, match="seed"):
            env.reset(seed=[1, 2])
        env.step(np.zeros((2, 2, 4)))  # still usable after rejected calls
    finally:
        env.close()
    with pytest.raises(RuntimeError, match="closed"):
        env.step(np.zeros((2, 2, 4)))
    for kw in ({"num_envs": 0}, {"num_envs": 2, "num_shards": 3}, {"num_envs": 2, "info_keys": ("nope",)},
               {"num_envs": 2, "backend": "gpu"}):
        with pytest.raises(ValueError):
            QuadSwarmVectorEnv(cfg, **kw)


def test_gymnasium_vector_wrappers_and_views():
    cfg = EnvConfig(num_quads=2, episode_seconds=0.05)
    env = gym.wrappers.vector.RecordEpisodeStatistics(
        QuadSwarmVectorEnv(cfg, num_envs=3, num_shards=1, info_keys=("rewards",), copy=False))
    try:
        obs, info = env.reset(seed=0)
        assert set(info) == set() and not obs.flags.writeable  # copy=False: read-only views
        for _ in range(5):
            obs, rew, term, trunc, info = env.step(np.full((3, 2, 4), HOVER))
        assert trunc.all() and "episode" in info and info["_episode"].all()
        np.testing.assert_array_equal(info["episode"]["l"], 5)
        assert set(info) >= {"rewards", "episode_metrics", "final_obs"}
    finally:
        env.close()


def test_close_ends_worker_processes():
    env = QuadSwarmVectorEnv(EnvConfig(num_quads=2), num_envs=4, num_shards=2)
    procs = [w.proc for w in env._res.workers]
    assert procs and all(p.is_alive() for p in procs)
    env.reset(seed=0)
    env.close()
    assert all(p.exitcode == 0 for p in procs)  # they exited on their own when their pipes closed


@pytest.mark.parametrize("collision_model", ["paper", "mujoco"])
def test_physics_backends_agree_bit_for_bit(collision_model):
    """One MjData (visual or lean) and mujoco.batch chunks (padded or not) give the same numbers."""
    cfg = EnvConfig(num_quads=4, episode_seconds=0.5, randomize=True, collision_model=collision_model,
                    room_size=(3.0, 3.0, 3.0))

    def run(**kw):
        c = CpuSwarm(cfg, 3, **kw)
        c.seed(1)
        c.reset()
        rng = np.random.default_rng(5)
        out = []
        for _ in range(80):
            o = c.step(HOVER + 0.5 * rng.standard_normal((3, 4, 4)))
            local = c.qpos[..., :3] - c.offsets  # world-local positions (offsets differ between layouts)
            out.append(np.concatenate([o["obs"].ravel(), o["rewards"].ravel(), local.ravel(), c.qpos[..., 3:].ravel(),
                                       c.qvel.ravel()]))
            if o["truncated"].any():
                c.reset(o["truncated"])
        return np.array(out)

    ref = run(backend="mjdata", visual=True)
    np.testing.assert_array_equal(run(backend="mjdata", visual=False), ref)
    np.testing.assert_array_equal(run(backend="batch", chunk_worlds=3), ref)
    for chunk in (2, 1):
        if collision_model == "paper":  # world offsets are 0: chunking changes nothing
            np.testing.assert_array_equal(run(backend="batch", chunk_worlds=chunk), ref)
        else:  # a world's offset in its model differs: contact positions differ by round-off
            np.testing.assert_allclose(run(backend="batch", chunk_worlds=chunk), ref, rtol=0, atol=1e-9)


def test_size_dependent_fast_paths_agree_exactly():
    """The engine's NumPy fast paths (perf.numpy_small, chosen by array size) give exactly the model's values."""
    from quadswarm_mj import spatial
    from quadswarm_mj.observations import build_obs, neighbor_obs, obs_bounds
    from quadswarm_mj.perf import numpy_small

    rng = np.random.default_rng(0)
    for lead in [(1, 8), (64, 8), (1024, 8)]:  # below and above spatial.BIG
        q = rng.normal(size=lead + (4,))
        q /= np.linalg.norm(q, axis=-1, keepdims=True)
        np.testing.assert_array_equal(numpy_small.quat_to_rotmat(q), spatial.quat_to_rotmat(q))
        for n in (3, 4, 6):
            x = rng.normal(size=lead + (n,)) * np.exp(3 * rng.normal(size=lead + (n,)))
            np.testing.assert_array_equal(spatial.sum_last(x), x.sum(axis=-1))
            np.testing.assert_array_equal(spatial.sumsq_last(x), (x * x).sum(axis=-1))
    # folding the neighbour clip into the final clip changes nothing
    cfg = EnvConfig(num_quads=6, room_size=(2.0, 3.0, 2.5), neighbor_vel_clip=1.0)
    pos, vel = rng.uniform(-3, 3, (5, 6, 3)), rng.normal(0, 5, (5, 6, 3))
    R = spatial.quat_to_rotmat(np.tile([1.0, 0, 0, 0], (5, 6, 1)))
    lo, hi = (b.astype(np.float64) for b in obs_bounds(cfg))
    obs = build_obs(cfg, pos, vel, R, np.zeros((5, 6, 3)), np.zeros((5, 6, 3)), None, lo, hi)
    own = np.concatenate([pos, vel, R.reshape(5, 6, 9), np.zeros((5, 6, 3))], -1)
    ref = np.clip(np.concatenate([own, neighbor_obs(cfg, pos, vel)], -1), lo, hi)
    np.testing.assert_array_equal(obs, ref)
    assert np.abs(obs[..., 18 + 3:18 + 6]).max() <= 1.0  # neighbour velocities clipped to +-1 m/s
