#!/usr/bin/env python
"""One row of the per-program compile options A/B (quadswarm_mj/perf/xla_options.py), in this fresh
process: ``QuadSwarmEnv(engine="jax")``, random actions, resets included; prints the time from
construction to the first step's return and the best of 3 x ``--seconds`` env steps/s. Run each
variant in its own process, alternating, e.g.::

    for v in default options tune tune+options; do python scripts/bench_xla_options.py --variant $v --quads 1; done
"""

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--variant", choices=("default", "options", "tune", "tune+options"), default="options")
    p.add_argument("--quads", type=int, default=1)
    p.add_argument("--seconds", type=float, default=1.5)
    args = p.parse_args()
    import quadswarm_mj
    from quadswarm_mj.perf import xla_options

    if args.variant.startswith("tune"):
        quadswarm_mj.tune_jax_cpu(allocator=False)
    xla_options.ENABLED = args.variant.endswith("options")
    import numpy as np

    t0 = time.perf_counter()
    env = quadswarm_mj.QuadSwarmEnv(quadswarm_mj.EnvConfig(num_quads=args.quads), engine="jax")
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    pool = [rng.uniform(-1, 1, env.action_space.shape).astype(np.float32) for _ in range(64)]
    env.step(pool[0])
    first = time.perf_counter() - t0
    for i in range(50):
        env.step(pool[i % 64])
    best = 0.0
    for _ in range(3):
        t, k = time.perf_counter(), 0
        while time.perf_counter() - t < args.seconds:
            _, _, term, trunc, _ = env.step(pool[k % 64])
            k += 1
            if term or trunc:
                env.reset()
        best = max(best, k / (time.perf_counter() - t))
    print(f"{args.variant:13s} quads={args.quads}: first step {first:5.1f} s, {best:7.0f} env steps/s "
          f"(options in force: {env._jax.prog.compiler_options})")


if __name__ == "__main__":
    main()
