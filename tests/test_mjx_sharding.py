"""Worlds sharded over several JAX devices (2 forced host devices, in a subprocess so the flag
takes effect before JAX starts): every leaf is split along the worlds axis, and the sharded
reset/step (batched auto-reset) give the same states as a single-device jit(vmap) of the
per-world step, through an episode end."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

pytest.importorskip("jax")
pytest.importorskip("mujoco.mjx")

_SCRIPT = textwrap.dedent("""
    import json
    import jax
    import jax.numpy as jnp
    import numpy as np
    from quadswarm_mj import EnvConfig
    from quadswarm_mj.envs.mjx_env import AutoResetWrapper, MjxQuadSwarmEnv
    from quadswarm_mj.envs.sharding import ShardedEnv, WorldSharding, world_devices

    assert jax.device_count() == 2, jax.devices()
    W, N = 4, 4
    cfg = EnvConfig(num_quads=N, randomize=True, scenario="static_diff_goal", episode_seconds=0.02)
    env = AutoResetWrapper(MjxQuadSwarmEnv(cfg))  # 2-step episodes: the second step resets every world
    senv = ShardedEnv(env, num_worlds=W)
    key = jax.random.key(7)
    s0 = senv.reset(key)
    actions = jnp.asarray(np.random.default_rng(0).uniform(-0.2, 0.4, (W, N, 4)), jnp.float32)
    s1 = senv.step(s0, jax.device_put(actions, senv.sharding))
    s2 = senv.step(s1, jax.device_put(actions, senv.sharding))
    out = {"devices": jax.device_count()}
    leaves = jax.tree.leaves(s2)
    out["leaves_on_2_devices"] = all(len(x.sharding.device_set) == 2 for x in leaves)
    out["shard_rows"] = sorted({s.data.shape[0] for x in leaves for s in x.addressable_shards})
    out["obs_shard_devices"] = sorted(str(s.device) for s in s2.obs.addressable_shards)
    # single-device reference on the same keys
    ref_reset = jax.jit(jax.vmap(env.reset))
    ref_step = jax.jit(jax.vmap(env.step))
    r0 = ref_reset(jax.random.split(key, W))
    r1 = ref_step(r0, actions)
    r2 = ref_step(r1, actions)
    out["pos1_err"] = float(np.abs(np.asarray(s1.info["state"]["pos"]) - np.asarray(r1.info["state"]["pos"])).max())
    out["done"] = [bool(np.asarray(s1.done).any()), bool(np.asarray(s2.done).all())]
    out["step2"] = np.asarray(s2.info["step"]).tolist()
    out["obs0_err"] = float(np.abs(np.asarray(s0.obs) - np.asarray(r0.obs)).max())
    out["pos_err"] = float(np.abs(np.asarray(s2.info["state"]["pos"]) - np.asarray(r2.info["state"]["pos"])).max())
    out["rew_err"] = float(np.abs(np.asarray(s2.reward) - np.asarray(r2.reward)).max())
    out["mass_differs"] = bool(np.unique(np.asarray(s2.info["params"]["mass"])[:, 0]).size == W)
    out["finite"] = bool(all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves((s2.obs, s2.reward))))
    # a batched start state (leading worlds axis) with the static motor start "hover"
    pos = np.broadcast_to(np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [1.0, 1.0, 1.0]]), (W, N, 3))
    si = senv.reset(key, {"pos": pos + np.arange(W)[:, None, None], "motors": "hover"})
    out["init_pos_err"] = float(np.abs(np.asarray(si.info["state"]["pos"]) - (pos + np.arange(W)[:, None, None])).max())
    prm = si.info["params"]
    hover = np.asarray(prm["mass"]) * cfg.quad.gravity / np.asarray(prm["thrust_max"]).sum(-1)
    out["init_thrust_err"] = float(np.abs(np.asarray(si.info["state"]["thrust"]) - hover[..., None]).max())
    try:
        ShardedEnv(env, num_worlds=3)
        out["odd_raises"] = False
    except ValueError:
        out["odd_raises"] = True
    out["world_devices_3"] = len(world_devices(3))
    out["world_sharding_6"] = WorldSharding(6).num_devices
    print(json.dumps(out))
""")


@pytest.mark.slow
def test_worlds_sharded_over_two_host_devices():
    env = {**os.environ, "JAX_PLATFORMS": "cpu",
           "XLA_FLAGS": (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
                         " --xla_backend_optimization_level=0").strip()}  # faster compiles (CPU CI)
    out = subprocess.run([sys.executable, "-c", _SCRIPT], capture_output=True, text=True, timeout=400, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["devices"] == 2
    assert r["leaves_on_2_devices"], r
    assert r["shard_rows"] == [2], r  # 4 worlds -> 2 per device, on every leaf
    assert len(set(r["obs_shard_devices"])) == 2
    assert r["finite"] and r["mass_differs"]
    # sharded (batched auto-reset, lax.cond) == single-device jit(vmap) of the per-world step
    assert r["obs0_err"] < 1e-5 and r["pos1_err"] < 1e-5 and r["pos_err"] < 1e-5 and r["rew_err"] < 1e-6, r
    assert r["done"] == [False, True] and r["step2"] == [0, 0, 0, 0]
    assert r["init_pos_err"] < 1e-6 and r["init_thrust_err"] < 1e-6, r
    assert r["odd_raises"]
    assert r["world_devices_3"] == 1 and r["world_sharding_6"] == 2
