"""Where the JAX engine's control step spends its time: the XLA kernels of one auto-reset step of W
worlds, from a ``jax.profiler`` trace (per-kernel wall time, averaged over the traced steps).

    quadswarm-profile-jax --worlds 512 --steps 50 --top 30 [--without-noise] [--obstacles]
                          [--sensors multiranger,flow,depth=8x8]
    python scripts/profile_jax_step.py ...   (the same, from a source checkout)

Each row is one XLA kernel ("thunk") of the compiled step: its time per control step, its share of
the step, how often it runs per step (kernels inside the sub-step loop run once per sub-step), its
output shape and the JAX operation it comes from. Kernels inside loops are listed as their own rows
(the loop rows are the loop's control overhead plus its body). Times are wall times on a shared
machine: compare kernels within one run.
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import re
import sys
import tempfile


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # run as a command: the opt-in XLA:CPU tuning (quadswarm_mj.tune_jax_cpu), before JAX starts
        from quadswarm_mj.devices import tune_jax_cpu

        tune_jax_cpu()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--worlds", type=int, default=512, help="worlds stepped together (default 512)")
    p.add_argument("--quads", type=int, default=8, help="quads per world (default 8)")
    p.add_argument("--steps", type=int, default=50, help="control steps traced (default 50)")
    p.add_argument("--top", type=int, default=30, help="kernels listed (default 30)")
    p.add_argument("--without-noise", action="store_true", help="EnvConfig.without_noise()")
    p.add_argument("--obstacles", action="store_true", help="columns on (ObstacleConfig())")
    p.add_argument("--sensors", default="", help="deck sensors on, comma-separated: multiranger, flow, "
                   "depth=HxW (SensorConfig; default none)")
    args = p.parse_args(argv)
    if args.worlds < 1 or args.steps < 1 or args.quads < 1:
        p.error("--worlds, --quads and --steps must be >= 1")

    import jax
    import jax.numpy as jnp

    from quadswarm_mj import EnvConfig, ObstacleConfig, SensorConfig
    from quadswarm_mj.envs.mjx_env import AutoResetWrapper, MjxQuadSwarmEnv

    cfg = EnvConfig(num_quads=args.quads)
    if args.without_noise:
        cfg = cfg.without_noise()
    if args.obstacles:
        cfg = cfg.replace(obstacles=ObstacleConfig())
    if args.sensors:
        decks: dict = {}
        for item in args.sensors.split(","):
            name, _, value = item.strip().partition("=")
            if name in ("multiranger", "flow") and not value:
                decks[name] = True
            elif name == "depth" and re.fullmatch(r"\d+x\d+", value):
                decks["depth"] = tuple(int(x) for x in value.split("x"))
            else:
                p.error(f"--sensors: unknown item {item!r} (multiranger, flow, depth=HxW)")
        cfg = cfg.replace(sensors=SensorConfig(**decks, noise=not args.without_noise))
    W = args.worlds
    env = AutoResetWrapper(MjxQuadSwarmEnv(cfg))
    hover = jnp.full((W, cfg.num_quads, 4), cfg.quad.hover_action, jnp.float32)
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), W))
    step = jax.jit(lambda s: env.vstep(s, hover), donate_argnums=0)
    print(f"compiling the step of {W} worlds x {cfg.num_quads} quads ...", flush=True)
    hlo = jax.jit(lambda s: env.vstep(s, hover)).lower(state).compile().as_text()
    for _ in range(5):
        state = step(state)
    jax.block_until_ready(state)
    with tempfile.TemporaryDirectory() as tmp:
        with jax.profiler.trace(tmp, create_perfetto_trace=True):
            for _ in range(args.steps):
                state = step(state)
            jax.block_until_ready(state)
        files = glob.glob(f"{tmp}/**/*.trace.json.gz", recursive=True)
        if not files:
            print("no trace written (jax.profiler unavailable?)", file=sys.stderr)
            return 1
        trace = json.load(gzip.open(files[0]))
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    shapes, sources = {}, {}
    for ln in hlo.splitlines():
        m = re.match(r"\s*(?:ROOT )?%([\w.\-]+) = (\S+) ", ln)
        if m and m.group(1) not in shapes:
            shapes[m.group(1)] = m.group(2).split("{")[0]
            op = re.search(r'op_name="([^"]*)"', ln)
            sources[m.group(1)] = op.group(1).replace("jit(<lambda>)/", "") if op else ""
    total, count = collections.Counter(), collections.Counter()
    step_us = 0.0
    for e in events:
        if e.get("ph") != "X":
            continue
        name = e["name"]
        if name == "ThunkExecutor::Execute (wait for completion)":
            step_us += e.get("dur", 0)
        elif name in shapes:
            total[name] += e.get("dur", 0)
            count[name] += 1
    n = args.steps
    step_us /= n
    print(f"\n{W} worlds x {cfg.num_quads} quads: {step_us / 1e3:.2f} ms per control step under the profiler "
          f"({len(total)} kernels; {sum(count.values()) / n:.0f} kernel launches per step)\n")
    print(f"{'us/step':>9} {'share':>6} {'runs':>5}  {'kernel':34s} {'output':28s} from")
    for name, t in total.most_common(args.top):
        print(f"{t / n:9.1f} {100 * t / n / step_us:5.1f}% {count[name] / n:5.1f}  {name:34s} "
              f"{shapes[name][:28]:28s} {sources[name][-60:]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
