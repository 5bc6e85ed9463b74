"""Stable-Baselines3 VecEnv adapter over QuadSwarmVectorEnv (quadswarm_mj.envs.sb3_vec_env): one SB3 env
per quad, truncation reported as "TimeLimit.truncated" with the terminal observation; SB3's PPO runs on it.
Skipped without stable-baselines3 (the optional extra ``examples``)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from quadswarm_mj import EnvConfig, QuadSwarmVectorEnv  # noqa: E402
from quadswarm_mj.envs.sb3_vec_env import QuadSwarmSB3VecEnv  # noqa: E402

CFG = EnvConfig(num_quads=2, episode_seconds=0.05)  # 5 control steps


@pytest.fixture(scope="module")
def venv():
    env = QuadSwarmSB3VecEnv(cfg=CFG, num_envs=2, num_shards=1)
    yield env
    env.close()


def test_layout_and_truncation(venv):
    assert venv.num_envs == 4 and venv.observation_space.shape == (CFG.obs_dim,) and venv.action_space.shape == (4,)
    venv.seed(0)
    obs = venv.reset()
    assert obs.shape == (4, CFG.obs_dim) and obs.dtype == np.float32
    for t in range(1, 6):
        obs, rewards, dones, infos = venv.step(np.zeros((4, 4), np.float32))
        assert rewards.shape == (4,) and np.isfinite(rewards).all() and obs.shape == (4, CFG.obs_dim)
        if t < 5:
            assert not dones.any() and all(i == {} for i in infos)
    assert dones.all()
    for k, info in enumerate(infos):
        assert info["TimeLimit.truncated"] is True
        assert info["terminal_observation"].shape == (CFG.obs_dim,)
        assert not np.array_equal(info["terminal_observation"], obs[k])  # obs is the new episode's first


def test_per_quad_rewards_match_the_vector_env():
    ref = QuadSwarmVectorEnv(CFG, num_envs=2, num_shards=1)
    sb3 = QuadSwarmSB3VecEnv(cfg=CFG, num_envs=2, num_shards=1)
    try:
        ref.reset(seed=5)
        sb3.seed(5)
        o = sb3.reset()
        a = np.random.default_rng(0).uniform(-1, 1, (2, 2, 4)).astype(np.float32)
        obs, _, _, _, info = ref.step(a)
        o, r, _, _ = sb3.step(a.reshape(4, 4))
        np.testing.assert_array_equal(o, obs.reshape(4, -1))
        np.testing.assert_allclose(r, info["rewards"].reshape(-1).astype(np.float32))
    finally:
        ref.close()
        sb3.close()


def test_bad_input():
    with pytest.raises(ValueError, match="env must be"):
        QuadSwarmSB3VecEnv(env="not an env")
    env = QuadSwarmVectorEnv(CFG, num_envs=1, info_keys=("state",))
    try:
        with pytest.raises(ValueError, match="rewards"):
            QuadSwarmSB3VecEnv(env=env)
    finally:
        env.close()


def test_ppo_learns_a_few_steps(venv):
    from stable_baselines3 import PPO

    model = PPO("MlpPolicy", venv, n_steps=16, batch_size=32, n_epochs=1, device="cpu", seed=0)
    model.learn(total_timesteps=128)
    assert model.num_timesteps >= 128
