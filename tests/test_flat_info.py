"""``info_mode="flat"`` (quadswarm_mj.envs.flat_info): every info entry a NumPy array of one key set,
shape and dtype at every step (reset included), NaN episode metrics until an episode ends; the nested
default unchanged; ``env.spec.max_episode_steps``; the id made in a fresh spawn child."""

from __future__ import annotations

import functools

import gymnasium as gym
import numpy as np
import pytest

from quadswarm_mj import EnvConfig, QuadSwarmEnv, QuadSwarmParallelEnv, QuadSwarmVectorEnv

SHORT = {"episode_seconds": 0.05}  # 5 control steps


def layout(info: dict) -> dict:
    assert all(isinstance(v, np.ndarray) for v in info.values()), {k: type(v) for k, v in info.items()}
    return {k: (v.shape, v.dtype) for k, v in info.items()}


def test_gym_env_flat_info_is_stable_through_an_episode():
    env = gym.make("QuadSwarm-v0", num_quads=2, info_mode="flat", **SHORT)
    _, info = env.reset(seed=0)
    want = layout(info)
    for k in ("state/pos", "params/mass", "reward_terms/effort", "episode_metrics/success", "rewards", "time"):
        assert k in want, k
    assert want["state/pos"] == ((2, 3), np.float32) and want["episode_metrics/success"] == ((), np.float32)
    assert np.isnan(info["episode_metrics/success"]) and np.isnan(info["reward_terms/effort"]).all()
    truncated = False
    while not truncated:
        _, reward, _, truncated, info = env.step(env.action_space.sample())
        assert layout(info) == want
        assert np.isfinite(info["reward_terms/effort"]).all()
        assert np.isnan(info["episode_metrics/success"]) != truncated  # NaN until the episode ends
    _, info = env.reset()
    assert layout(info) == want and np.isnan(info["episode_metrics/success"])


def test_nested_stays_the_default_and_bad_mode_is_rejected():
    env = QuadSwarmEnv(num_quads=2, **SHORT)
    _, info = env.reset(seed=0)
    assert info["state"]["pos"].shape == (2, 3) and "state/pos" not in info
    with pytest.raises(ValueError, match="info_mode"):
        EnvConfig(info_mode="flattened")


def test_flat_matches_nested_values():
    nested, flat = QuadSwarmEnv(num_quads=2, **SHORT), QuadSwarmEnv(num_quads=2, info_mode="flat", **SHORT)
    nested.reset(seed=3)
    flat.reset(seed=3)
    a = np.full((2, 4), 0.2, np.float32)
    _, _, _, _, n = nested.step(a)
    _, _, _, _, f = flat.step(a)
    np.testing.assert_array_equal(f["state/pos"], n["state"]["pos"].astype(np.float32))
    np.testing.assert_array_equal(f["reward_terms/pos"], n["reward_terms"]["pos"].astype(np.float32))


def test_parallel_env_flat_agent_infos():
    env = QuadSwarmParallelEnv(num_quads=3, info_mode="flat", **SHORT)
    _, infos = env.reset(seed=0)
    want = layout(infos["quad_0"])
    assert want["state/pos"] == ((3,), np.float32) and want["reward_terms/effort"] == ((), np.float32)
    while env.agents:
        _, _, _, trunc, infos = env.step({a: env.action_space(a).sample() for a in env.agents})
        for a in env.possible_agents:
            assert layout(infos[a]) == want
    assert np.isfinite(infos["quad_2"]["episode_metrics/success"])


def test_vector_env_flat_info_through_autoreset():
    env = QuadSwarmVectorEnv(EnvConfig(num_quads=2, info_mode="flat", **SHORT), num_envs=2, num_shards=1)
    try:
        assert env.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
        _, info = env.reset(seed=0)
        want = layout(info)
        assert want["state/pos"] == ((2, 2, 3), np.float32) and want["final_obs"][0] == (2, 2, env.cfg.obs_dim)
        ended = False
        for _ in range(6):
            _, _, _, trunc, info = env.step(np.zeros((2, 2, 4), np.float32))
            assert layout(info) == want
            np.testing.assert_array_equal(info["_final_obs"], trunc)
            assert (np.isnan(info["episode_metrics/success"]) == ~trunc).all()
            # final_obs: finite, zeros (inside the observation box) where no episode ended
            assert np.isfinite(info["final_obs"]).all() and (info["final_obs"][~trunc] == 0).all()
            ended |= bool(trunc.any())
        assert ended
    finally:
        env.close()


def test_spec_max_episode_steps_without_time_limit_wrapper():
    env = gym.make("QuadSwarm-v0", num_quads=1, episode_seconds=2.0)
    assert env.spec.max_episode_steps == 200 == env.unwrapped.cfg.episode_steps
    assert not any(isinstance(w, gym.wrappers.TimeLimit) for w in _wrappers(env))


def _wrappers(env: gym.Env) -> list:
    out = []
    while isinstance(env, gym.Wrapper):
        out.append(env)
        env = env.env
    return out


def test_make_by_module_id_in_a_fresh_spawn_child():
    """gymnasium's "module:id" form imports the package in a child that never imported it (spawn)."""
    envs = gym.vector.AsyncVectorEnv(
        [functools.partial(gym.make, "quadswarm_mj:QuadSwarm-v0", num_quads=1, info_mode="flat")] * 2,
        context="spawn")
    try:
        obs, info = envs.reset(seed=0)
        assert obs.shape[0] == 2 and "state/pos" in info
    finally:
        envs.close()


def test_jax_engine_flat_info_has_the_mujoco_engine_layout():
    """The same flat keys, shapes and dtypes on both engines, through an episode end."""
    want = layout(QuadSwarmEnv(num_quads=2, info_mode="flat", **SHORT).reset(seed=0)[1])
    env = QuadSwarmEnv(num_quads=2, info_mode="flat", engine="jax", **SHORT)
    _, info = env.reset(seed=0)
    assert layout(info) == want
    truncated = False
    while not truncated:
        _, _, _, truncated, info = env.step(np.zeros((2, 4), np.float32))
        assert layout(info) == want
    assert np.isfinite(info["episode_metrics/success"])
