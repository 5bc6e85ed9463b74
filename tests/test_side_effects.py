"""The package changes nothing of the user's process: no environment variable, no JAX config value, no
allocator setting, at import or while stepping both engines (the XLA:CPU tuning is the explicit opt-in
``quadswarm_mj.tune_jax_cpu()``, tests/test_xla_tuning.py). Each check runs in a fresh process that
set its own values first. The baseline is taken after importing the dependencies themselves
(pettingzoo's import sets SDL and pygame variables for its pygame envs: pettingzoo's doing, not this
package's)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
USER_FLAGS = "--xla_force_host_platform_device_count=1"


def _run(script: str, timeout: int = 600) -> dict:
    env = {k: v for k, v in os.environ.items()
           if k not in ("QUADSWARM_MJ_TUNE_JAX", "JAX_NUM_CPU_DEVICES", "MUJOCO_GL", "PYOPENGL_PLATFORM")}
    env.update({"XLA_FLAGS": USER_FLAGS, "JAX_PLATFORMS": "cpu"})
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(script)], capture_output=True, text=True,
                         timeout=timeout, env=env, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


STEP_BOTH_ENGINES = """
    import json, os
    import gymnasium, jax, mujoco, pettingzoo  # the dependencies' own import-time settings
    import numpy as np
    jax.config.update("jax_cpu_enable_async_dispatch", True)  # the user's own JAX settings
    jax.config.update("jax_default_matmul_precision", "highest")

    def snapshot():
        return {"env": dict(os.environ), "jax": {k: repr(v) for k, v in jax.config.values.items()}}

    before = snapshot()
    import quadswarm_mj
    from quadswarm_mj import devices
    after_import = snapshot()
    for engine in ("mujoco", "jax"):
        env = quadswarm_mj.QuadSwarmEnv(quadswarm_mj.EnvConfig(num_quads=2), engine=engine)
        env.reset(seed=0)
        for _ in range(3):
            env.step(np.zeros((2, 4), np.float32))
    venv = quadswarm_mj.QuadSwarmVectorEnv(quadswarm_mj.EnvConfig(num_quads=2), num_envs=2, engine="jax")
    venv.reset(seed=0)
    venv.step(np.zeros((2, 2, 4), np.float32))
    after_use = snapshot()

    def diff(a, b):
        return {part: sorted(k for k in set(a[part]) | set(b[part]) if a[part].get(k) != b[part].get(k))
                for part in a}

    print(json.dumps({"import": diff(before, after_import), "use": diff(before, after_use),
                      "xla_flags": os.environ.get("XLA_FLAGS"), "allocator_tuned": devices._MALLOC_TUNED,
                      "async": bool(jax.config.values["jax_cpu_enable_async_dispatch"])}))
"""


def test_import_and_both_engines_leave_the_process_unchanged():
    r = _run(STEP_BOTH_ENGINES)
    assert r["import"] == {"env": [], "jax": []}, r["import"]
    assert r["use"] == {"env": [], "jax": []}, r["use"]
    assert r["xla_flags"] == USER_FLAGS and r["async"] is True
    assert r["allocator_tuned"] is None  # glibc's mallopt was never called

