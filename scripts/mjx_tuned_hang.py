#!/usr/bin/env python
"""Reproduction: ``jax.jit(jax.vmap(step))`` of ``MjxQuadSwarmEnv(physics="mjx")`` under the XLA:CPU options
of ``quadswarm_mj.tune_jax_cpu()`` (see ``quadswarm_mj.devices.MJX_TUNED_MAX_WORLDS``).

Each case runs in a fresh process with a timeout and prints its compile and run times, or TIMEOUT::

    python scripts/mjx_tuned_hang.py --worlds 128 512 --modes defaults flag sync both --timeout 600

Modes: ``defaults`` (JAX's own settings), ``flag`` (``XLA_FLAGS`` small-loop kernels only), ``sync``
(``jax_cpu_enable_async_dispatch=False`` only), ``both`` (what ``tune_jax_cpu()`` sets). The package's
own batched ``physics="mjx"`` programs raise a RuntimeError instead of hanging (``check_mjx_batch``).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

CHILD = """
import os, sys, time
mode, worlds = sys.argv[1], int(sys.argv[2])
if mode in ("flag", "both"):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_extra_options="
                               "xla_cpu_small_while_loop_byte_threshold=262144").strip()
import jax, jax.numpy as jnp
if mode in ("sync", "both"):
    jax.config.update("jax_cpu_enable_async_dispatch", False)
from quadswarm_mj import EnvConfig
from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv
env = MjxQuadSwarmEnv(EnvConfig(num_quads=8), physics="mjx")
s = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), worlds))
a = jnp.zeros((worlds, 8, 4))
t = time.time(); step = jax.jit(jax.vmap(env.step)).lower(s, a).compile(); c = time.time() - t
t = time.time(); jax.block_until_ready(step(s, a)); r = time.time() - t
print(f"jax {jax.__version__}: compiled {c:.1f} s, ran {r:.2f} s")
"""


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--worlds", type=int, nargs="+", default=[128, 512])
    p.add_argument("--modes", nargs="+", default=["defaults", "both"], choices=["defaults", "flag", "sync", "both"])
    p.add_argument("--timeout", type=float, default=600.0, help="seconds per case (compile included)")
    a = p.parse_args(argv)
    root = str(Path(__file__).resolve().parent.parent)
    for worlds in a.worlds:
        for mode in a.modes:
            t0 = time.time()
            try:
                out = subprocess.run([sys.executable, "-c", CHILD, mode, str(worlds)], capture_output=True, text=True,
                                     timeout=a.timeout, cwd=root)
                line = out.stdout.strip().splitlines()[-1] if out.returncode == 0 else f"FAILED: {out.stderr[-300:]}"
            except subprocess.TimeoutExpired:
                line = f"TIMEOUT after {time.time() - t0:.0f} s"
            print(f"{worlds:5d} worlds, {mode:8s}: {line}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
