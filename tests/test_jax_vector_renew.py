"""QuadSwarmVectorEnv(engine="jax") steps without the auto-reset and renews the finished worlds in a
second call only after a step that ended an episode: the results are those of
``AutoResetWrapper.vstep`` (the in-jit auto-reset) from the same keys, the returned info follows the
MuJoCo engine's vector env at episode ends (the step's rewards and new collisions, the fresh
episode's state), and the episode constants are shared read-only arrays, renewed at episode ends."""

from __future__ import annotations

import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytest.importorskip("mujoco.mjx")

from quadswarm_mj import EnvConfig, QuadSwarmVectorEnv  # noqa: E402
from quadswarm_mj.envs.jax_engine import KeyStream  # noqa: E402
from quadswarm_mj.envs.mjx_env import AutoResetWrapper, MjxQuadSwarmEnv  # noqa: E402

B = 2
CFG = EnvConfig(num_quads=3, episode_seconds=0.2, randomize=True)  # all noise on, 20-step episodes
STEPS = 45  # two episode ends


def test_step_and_renew_equal_the_in_jit_autoreset():
    env = QuadSwarmVectorEnv(CFG, num_envs=B, engine="jax")
    rng = np.random.default_rng(3)
    actions = rng.uniform(-1.0, 1.0, (STEPS, B, CFG.num_quads, 4)).astype(np.float32)
    obs, info = env.reset(seed=11)
    # the reference: the same reset keys, then AutoResetWrapper.vstep in one jitted function per step
    auto = AutoResetWrapper(MjxQuadSwarmEnv(CFG))
    keys = jax.random.wrap_key_data(KeyStream(11).draw((B,)))
    ref = jax.jit(jax.vmap(auto.reset))(keys)
    vstep = jax.jit(auto.vstep)
    np.testing.assert_array_equal(obs, np.asarray(ref.obs))
    ends = 0
    params0 = info["params"]["mass"]
    for t in range(STEPS):
        ref = vstep(ref, actions[t])
        obs, reward, term, trunc, info = env.step(actions[t])
        np.testing.assert_allclose(obs, np.asarray(ref.obs), atol=1e-5)
        np.testing.assert_allclose(info["state"]["pos"], np.asarray(ref.info["state"]["pos"]), atol=1e-5)
        np.testing.assert_allclose(info["rewards"], np.asarray(ref.reward), atol=1e-5)
        np.testing.assert_array_equal(trunc, np.asarray(ref.done))
        assert not term.any()
        with pytest.raises(ValueError):  # shared episode constants are read-only
            info["params"]["mass"][0, 0] = 1.0
        if trunc.any():
            ends += 1
            assert "final_obs" in info and info["_final_obs"].all()
            assert not np.allclose(info["final_obs"], obs)
            np.testing.assert_array_equal(info["time"], 0.0)  # the fresh episodes' state and time
            # the parameters are redrawn with the fresh episodes
            assert not np.array_equal(info["params"]["mass"], params0)
            params0 = info["params"]["mass"]
            # new collisions of the step that ended the episode (not of the fresh episode)
            assert info["new_collisions"].shape == (B, CFG.num_quads)
        else:
            assert "final_obs" not in info
            assert info["params"]["mass"] is params0  # the same arrays until the next episode end
    assert ends == 2
    env.close()
