"""One JAX CPU device per core (quadswarm_mj.use_cpu_cores): the vector env and the JAX-engine trainer
shard their worlds over the devices. Device counts are fixed when JAX starts, so the multi-device
checks run in subprocesses."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import quadswarm_mj
from quadswarm_mj.devices import reuse_freed_memory


def _run(script: str, timeout: int = 600) -> dict:
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    env.pop("JAX_NUM_CPU_DEVICES", None)
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(script)], capture_output=True, text=True,
                         timeout=timeout, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_use_cpu_cores_rejects_bad_counts():
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="n must be an int >= 1"):
            quadswarm_mj.use_cpu_cores(bad)


def test_use_cpu_cores_before_and_after_jax_starts():
    r = _run("""
        import json, warnings
        import quadswarm_mj
        n = quadswarm_mj.use_cpu_cores(2)
        import jax, jax.numpy as jnp
        float(jnp.ones(3).sum())  # JAX has started
        same = quadswarm_mj.use_cpu_cores(2)  # what it has already: fine
        try:
            quadswarm_mj.use_cpu_cores(3)
            msg = ""
        except RuntimeError as e:
            msg = str(e)
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            lax = quadswarm_mj.use_cpu_cores(3, strict=False)
        print(json.dumps({"n": n, "devices": len(jax.devices()), "same": same, "msg": msg, "lax": lax,
                          "warned": any("too late" in str(x.message) for x in w)}))
    """, timeout=120)
    assert r["n"] == 2 and r["devices"] == 2 and r["same"] == 2
    assert "too late" in r["msg"] and "JAX_NUM_CPU_DEVICES=3" in r["msg"]
    assert r["lax"] == 2 and r["warned"]


def test_reuse_freed_memory_is_on_under_glibc():
    if not sys.platform.startswith("linux"):
        pytest.skip("glibc only")
    assert reuse_freed_memory() is True
    assert reuse_freed_memory() is True  # idempotent


_VECTOR = """
    import json, sys
    import numpy as np
    import quadswarm_mj
    nd = quadswarm_mj.use_cpu_cores(int(sys.argv[1]))
    from quadswarm_mj import EnvConfig, QuadSwarmVectorEnv
    cfg = EnvConfig(num_quads=int(sys.argv[2]), episode_seconds=0.2)  # 20 steps: auto-resets inside the run
    env = QuadSwarmVectorEnv(cfg, num_envs=4, engine="jax")
    obs, info = env.reset(seed=5)
    rng = np.random.default_rng(0)
    out = {"obs": [obs.tolist()], "final": [], "pos": [], "rew": []}
    for t in range(30):
        a = rng.uniform(-1, 1, (4, cfg.num_quads, 4)).astype(np.float32)
        obs, rew, term, trunc, info = env.step(a)
        out["obs"].append(obs.tolist())
        out["rew"].append(rew.tolist())
        out["pos"].append(info["state"]["pos"].tolist())
        if "final_obs" in info:
            out["final"].append([t, info["_final_obs"].tolist(), info["final_obs"].tolist()])
    out["devices"] = nd
    out["shards"] = len(env._jax._worlds.bufs[0].addressable_shards)
    out["obs_dtype"], out["pos_dtype"] = str(obs.dtype), str(info["state"]["pos"].dtype)
    env.close()
    print(json.dumps(out))
"""


def _one_and_two_devices(num_quads: int) -> tuple[dict, dict]:
    script = _VECTOR.replace("sys.argv[2]", str(num_quads))
    one, two = _run(script.replace("sys.argv[1]", "1")), _run(script.replace("sys.argv[1]", "2"))
    assert one["devices"] == 1 and two["devices"] == 2
    assert one["shards"] == 1 and two["shards"] == 2
    assert len(two["final"]) >= 1  # episodes ended during the run
    assert two["obs_dtype"] == "float32" and two["pos_dtype"] == "float64"
    return one, two


def test_vector_env_on_two_devices_equals_one_device():
    """The JAX-engine vector env shards its worlds over the devices: the same seeded run, bit for bit
    (observations, rewards, state, final observations at the auto-resets), when each device's worlds x
    quads fill XLA:CPU's vector loops (here 2 worlds x 8 quads per device; see the next test).

    jax/jaxlib >= 0.10 fuse the float32 observation and reward kernels differently for 2 and 4 worlds
    per program: there the float64 state stays bit for bit and observations and rewards agree within
    float32 rounding (measured on 0.10.2: max 9.5e-7 in the observations, 3.5e-10 in the rewards)."""
    import jax

    one, two = _one_and_two_devices(8)
    assert one["pos"] == two["pos"], "pos"
    if tuple(int(x) for x in jax.__version__.split(".")[:2]) < (0, 10):
        for k in ("obs", "rew", "final"):
            assert one[k] == two[k], k
        return
    for k in ("obs", "rew"):
        np.testing.assert_allclose(np.asarray(one[k]), np.asarray(two[k]), rtol=2.4e-7, atol=1e-6, err_msg=k)
    assert [f[0] for f in one["final"]] == [f[0] for f in two["final"]]


def test_vector_env_on_two_devices_odd_sizes_within_round_off():
    """With 2 worlds x 3 quads per device, XLA:CPU computes some elements in its vector loops' scalar
    remainders, where it contracts a multiply-add into an FMA differently: the runs agree within
    float32 round-off (the same episode ends, the same contacts), not necessarily bit for bit."""
    one, two = _one_and_two_devices(3)
    for k in ("obs", "rew", "pos"):
        np.testing.assert_allclose(np.asarray(one[k]), np.asarray(two[k]), rtol=0, atol=1e-4, err_msg=k)
    assert [f[0] for f in one["final"]] == [f[0] for f in two["final"]]


@pytest.mark.slow
def test_jax_trainer_data_parallel_on_two_devices():
    """The JAX-engine trainer runs one iteration per device slice of the worlds with averaged
    gradients: the parameters stay identical on both devices, learning is finite, no recompiles."""
    r = _run("""
        import json
        import numpy as np
        import quadswarm_mj
        quadswarm_mj.use_cpu_cores(2)
        import jax
        from quadswarm_mj import EnvConfig
        from quadswarm_mj.training.jax_ppo import JaxPPOTrainer
        from quadswarm_mj.training.ppo import PPOConfig
        cfg = EnvConfig(num_quads=2, episode_seconds=0.3)
        ppo = PPOConfig(num_worlds=8, unroll_length=8, num_minibatches=4, num_epochs=2, policy_hidden=(16, 16),
                        value_hidden=(16, 16))
        tr = JaxPPOTrainer([cfg], ppo, seed=0)
        try:
            JaxPPOTrainer([cfg], PPOConfig(num_worlds=6, unroll_length=8, num_minibatches=4, num_epochs=2,
                                           policy_hidden=(16, 16), value_hidden=(16, 16)), devices=2)
            bad = ""
        except ValueError as e:
            bad = str(e)
        rows = tr.train(total_steps=8 * 2 * 8 * 3, progress=False)
        leaves = jax.tree.leaves(tr.state.params)
        same = all(np.array_equal(np.asarray(s.data), np.asarray(x.addressable_shards[0].data))
                   for x in leaves for s in x.addressable_shards)
        print(json.dumps({"devices": tr.num_devices, "same": bool(same), "rows": len(rows),
                          "finite": all(np.isfinite(np.asarray(x)).all() for x in leaves),
                          "episodes": sum(r.get("episodes", 0) for r in rows),
                          "cache": tr._iteration._cache_size(), "bad": bad,
                          "reward": [r["reward_per_step"] for r in rows]}))
    """)
    assert r["devices"] == 2 and r["rows"] == 3
    assert r["same"] and r["finite"]
    assert r["cache"] == 1  # the carry comes back placed as it went in
    assert "must divide every scenario's worlds" in r["bad"]
    assert all(abs(x) < 1e3 for x in r["reward"])


def test_cli_cpu_devices_option_is_checked():
    from quadswarm_mj.cli import benchmark, train

    with pytest.raises(SystemExit) as e:
        benchmark.main(["--cpu-devices", "two", "--no-write", "--rows", "single"])
    assert e.value.code == 2
    for bad in ("two", "0"):
        with pytest.raises(SystemExit, match="--cpu-devices must be 'cores' or an int"):
            train.main(["--engine", "jax", "--cpu-devices", bad, "--timesteps", "1"])
    with pytest.raises(SystemExit) as e:
        benchmark.main(["--cpu-devices", "0", "--no-write", "--rows", "single"])
    assert e.value.code == 2
