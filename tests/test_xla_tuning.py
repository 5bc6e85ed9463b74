"""XLA:CPU tuning for the JAX engine (quadswarm_mj.tune_jax_cpu, the explicit opt-in; loop_once): small
loops as one kernel and synchronous CPU dispatch, set before JAX starts. Both are process-wide, so the
checks run in fresh subprocesses."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np

from quadswarm_mj.devices import LOOP_KERNEL_FLAG


def _run(script: str, env_extra: dict[str, str] | None = None, timeout: int = 300) -> dict:
    env = {**os.environ, "JAX_PLATFORMS": "cpu", **(env_extra or {})}
    for k in ("JAX_NUM_CPU_DEVICES", "QUADSWARM_MJ_TUNE_JAX"):
        if k not in (env_extra or {}):
            env.pop(k, None)
    env["XLA_FLAGS"] = (env_extra or {}).get("XLA_FLAGS", "")
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(script)], capture_output=True, text=True,
                         timeout=timeout, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


PROBE = """
    import json, os
    import quadswarm_mj
    quadswarm_mj.tune_jax_cpu()  # the opt-in, before JAX starts
    flags = os.environ.get("XLA_FLAGS", "")
    import quadswarm_mj.envs.mjx_env
    import jax
    from quadswarm_mj.devices import loop_kernels_in_force
    print(json.dumps({"flags": flags, "async": bool(jax.config.values["jax_cpu_enable_async_dispatch"]),
                      "loops": loop_kernels_in_force()}))
"""


def test_tune_sets_loop_kernels_and_sync_dispatch():
    r = _run(PROBE)
    assert LOOP_KERNEL_FLAG in r["flags"]
    assert r["async"] is False and r["loops"] is True


def test_opt_out_and_user_settings_are_kept():
    off = _run(PROBE, {"QUADSWARM_MJ_TUNE_JAX": "0"})
    assert LOOP_KERNEL_FLAG not in off["flags"] and off["async"] is True and off["loops"] is False
    own = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1"
    mine = _run(PROBE, {"XLA_FLAGS": own})
    assert mine["flags"] == own and mine["loops"] is False  # the user's limit wins (nothing hoisted)


def test_too_late_once_jax_has_started():
    r = _run("""
        import json, os
        import jax, jax.numpy as jnp
        float(jnp.ones(2).sum())  # JAX has started before the opt-in
        import quadswarm_mj, quadswarm_mj.envs.mjx_env
        print(json.dumps({"flags": os.environ.get("XLA_FLAGS", ""), "state": quadswarm_mj.tune_jax_cpu(),
                          "async": bool(jax.config.values["jax_cpu_enable_async_dispatch"])}))
    """)
    assert LOOP_KERNEL_FLAG not in r["flags"] and r["async"] is True
    assert r["state"] == {"loop_kernels": False, "sync_dispatch": False}


def test_loop_once_is_the_same_step():
    import jax
    import jax.numpy as jnp

    from quadswarm_mj.devices import loop_once

    def step(s: jax.Array, a: jax.Array) -> tuple:
        s2 = jnp.sin(s) * 1.1 + a
        return s2, jnp.sum(s2 ** 2), s2[:3]

    s, a = jnp.linspace(0.0, 1.0, 32, dtype=jnp.float32), jnp.float32(0.25)
    want = jax.jit(step)(s, a)
    got = jax.jit(loop_once(step))(s, a)
    for w, g in zip(want, got):
        np.testing.assert_array_equal(np.asarray(g), np.asarray(w))


def test_single_env_same_episode_with_and_without_tuning():
    """A seeded QuadSwarmEnv(engine="jax") episode with the tuning (one-kernel step) and without it:
    the same physics; float32 kernels compiled two ways may round differently, so within 1e-5."""
    script = """
        import json
        import numpy as np
        import quadswarm_mj
        quadswarm_mj.tune_jax_cpu()  # a no-op with QUADSWARM_MJ_TUNE_JAX=0
        env = quadswarm_mj.QuadSwarmEnv(quadswarm_mj.EnvConfig(num_quads=4), engine="jax")
        obs, info = env.reset(seed=3)
        rng = np.random.default_rng(0)
        out = []
        for _ in range(60):
            obs, r, term, trunc, info = env.step(rng.uniform(-1, 1, (4, 4)).astype(np.float32))
            out.append(np.concatenate([obs.ravel(), info["state"]["pos"].ravel(), [r]]).tolist())
        print(json.dumps(out))
    """
    on = np.asarray(_run(script, timeout=600))
    off = np.asarray(_run(script, {"QUADSWARM_MJ_TUNE_JAX": "0"}, timeout=600))
    np.testing.assert_allclose(on, off, rtol=1e-5, atol=1e-5)
