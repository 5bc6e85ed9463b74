"""CPU time per env step of the default Gymnasium env with the MuJoCo engine's fused NumPy forms on and off
(``quadswarm_mj.perf.numpy_fast_forms``): random actions, resets included, alternating rounds in one process.

    python scripts/numpy_forms_cost.py --quads 1 8 --steps 3000 --rounds 3
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np

import quadswarm_mj  # noqa: F401  (registers QuadSwarm-v0)
from quadswarm_mj.perf import numpy_fast_forms


def steps_per_cpu_second(num_quads: int, steps: int, enabled: bool, seed: int = 0) -> float:
    """Env steps per second of this thread's CPU time with the fused forms ``enabled``."""
    env = gym.make("QuadSwarm-v0", num_quads=num_quads)
    env.reset(seed=seed)
    env.action_space.seed(seed)
    actions = [env.action_space.sample() for _ in range(steps)]
    with numpy_fast_forms(enabled):
        start = time.thread_time()
        for a in actions:
            _, _, terminated, truncated, _ = env.step(a)
            if terminated or truncated:
                env.reset()
        rate = steps / (time.thread_time() - start)
    env.close()
    return rate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quads", type=int, nargs="+", default=[1, 8])
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    for n in args.quads:
        pairs = [(steps_per_cpu_second(n, args.steps, True), steps_per_cpu_second(n, args.steps, False))
                 for _ in range(args.rounds)]
        ratios = [on / off for on, off in pairs]
        rounds = ", ".join(f"{r:.2f}" for r in ratios)
        print(f"{n} quad(s): on {np.median([p[0] for p in pairs]):.0f} / off {np.median([p[1] for p in pairs]):.0f}"
              f" steps per CPU second, on/off median {np.median(ratios):.2f}x (rounds {rounds})")


if __name__ == "__main__":
    main()
