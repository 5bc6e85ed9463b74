"""Cost of the deck sensors (issue 36): samples/s with and without them, on both engines.

* JAX engine: ``B`` worlds x 8 quads, a jitted ``lax.scan`` of ``AutoResetWrapper.vstep`` with hover
  actions (as ``quadswarm_mj.envs.mjx_env.benchmark_mjx``), compiled once per sensor set;
* ``QuadSwarmEnv`` (MuJoCo engine): one world of 8 quads stepped from Python with hover actions.

The sensor sets are timed in alternating rounds (the machine is shared; each figure is the best of
``--repeat`` rounds) and every ratio is of figures of the same run. Two ratios: of samples per wall
second, and of samples per CPU second of this process (``time.process_time``, all its threads), which
a loaded machine disturbs less. Paper defaults otherwise (noise on,
static_same_goal). Usage::

    python scripts/sensor_benchmark.py --worlds 512 --steps 100 --seconds 3 --repeat 3
    python scripts/sensor_benchmark.py --worlds 512 --steps 20 --seconds 1 --repeat 3 --noise-off
"""

from __future__ import annotations

import argparse
import time

import numpy as np

SETS = {
    "off": {},
    "multiranger+flow": {"multiranger": True, "flow": True},
    "depth 8x8": {"depth": (8, 8)},
    "all (mr+flow+depth 8x8)": {"multiranger": True, "flow": True, "depth": (8, 8)},
}


def _cfg(sensors: dict, n: int):
    from quadswarm_mj import EnvConfig, SensorConfig

    return EnvConfig(num_quads=n, sensors=SensorConfig(**sensors))


def jax_runner(sensors: dict, worlds: int, steps: int, n: int):
    """A function timing one compiled rollout of ``steps`` steps (returns samples/s)."""
    import jax
    import jax.numpy as jnp

    from quadswarm_mj.envs.mjx_env import AutoResetWrapper, MjxQuadSwarmEnv

    cfg = _cfg(sensors, n)
    env = AutoResetWrapper(MjxQuadSwarmEnv(cfg))
    hover = jnp.full((worlds, n, 4), cfg.quad.hover_action, jnp.float32)

    def rollout(s):
        return jax.lax.scan(lambda c, _: (env.vstep(c, hover), None), s, None, length=steps)[0]

    state = jax.block_until_ready(jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), worlds)))
    run = jax.jit(rollout).lower(state).compile()
    box = [jax.block_until_ready(run(state))]

    def once() -> tuple[float, float]:
        t0, c0 = time.perf_counter(), time.process_time()
        box[0] = jax.block_until_ready(run(box[0]))
        return worlds * n * steps / (time.perf_counter() - t0), worlds * n * steps / (time.process_time() - c0)

    return once


def cpu_runner(sensors: dict, seconds: float, n: int):
    from quadswarm_mj import QuadSwarmEnv

    env = QuadSwarmEnv(_cfg(sensors, n))
    env.reset(seed=0)
    a = np.full((n, 4), env.cfg.quad.hover_action)

    def once() -> tuple[float, float]:
        steps, t0, c0 = 0, time.perf_counter(), time.process_time()
        while time.perf_counter() - t0 < seconds:
            for _ in range(50):
                if env.step(a)[3]:
                    env.reset()
            steps += 50
        return n * steps / (time.perf_counter() - t0), n * steps / (time.process_time() - c0)

    return once


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--worlds", type=int, default=512)
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--quads", type=int, default=8)
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--skip-jax", action="store_true")
    p.add_argument("--skip-cpu", action="store_true")
    p.add_argument("--no-tune", action="store_true", help="leave JAX's XLA:CPU defaults (no tune_jax_cpu())")
    p.add_argument("--noise-off", action="store_true",
                   help="also time the multi-ranger + flow and depth sets with the sensors' noise off "
                        "(SensorConfig(noise=False): no deck draws), to tell the ray casting from the noise")
    args = p.parse_args()
    if args.noise_off:
        SETS["multiranger+flow, noise off"] = {"multiranger": True, "flow": True, "noise": False}
        SETS["depth 8x8, noise off"] = {"depth": (8, 8), "noise": False}
    if not args.no_tune and not args.skip_jax:
        from quadswarm_mj import tune_jax_cpu

        tune_jax_cpu()
    runners = {}
    for name, s in SETS.items():
        if not args.skip_jax:
            runners[("jax", name)] = jax_runner(s, args.worlds, args.steps, args.quads)
        if not args.skip_cpu:
            runners[("cpu", name)] = cpu_runner(s, args.seconds, args.quads)
    best = {k: 0.0 for k in runners}  # samples per wall second
    best_cpu = {k: 0.0 for k in runners}  # samples per CPU second of this process (all its threads)
    for _ in range(args.repeat):
        for k, run in runners.items():
            wall, cpu = run()
            best[k], best_cpu[k] = max(best[k], wall), max(best_cpu[k], cpu)
    rows = [("jax", f"JAX engine {args.worlds} x {args.quads}"), ("cpu", f"QuadSwarmEnv 1 x {args.quads}")]
    print("| engine | sensors | samples/s | vs off | vs off (CPU time) |\n|---|---|---:|---:|---:|")
    for eng, label in rows:
        if (f"{eng}", "off") not in best:
            continue
        off, off_cpu = best[(eng, "off")], best_cpu[(eng, "off")]
        for name in SETS:
            v, c = best[(eng, name)], best_cpu[(eng, name)]
            print(f"| {label} | {name} | {v:,.0f} | {v / off:.2f}x | {c / off_cpu:.2f}x |")


if __name__ == "__main__":
    main()
