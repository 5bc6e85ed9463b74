#!/usr/bin/env python
"""The deck sensors' cost (issue 36), printed: :mod:`quadswarm_mj.bench.sensor_rows` (samples/s with and
without the decks on both engines, alternating rounds, median ratios). For BENCHMARKS.md use
``python scripts/benchmark.py --rows sensors``. Usage::

    python scripts/sensor_benchmark.py --worlds 512 --steps 50 --seconds 2 --rounds 5
    python scripts/sensor_benchmark.py --skip-cpu --noise-off
    python scripts/sensor_benchmark.py --parts          # the deck part and the casters alone
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

# From a source checkout the checkout's package is used, installed or not.
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--worlds", type=int, default=512)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--seconds", type=float, default=2.0)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--skip-jax", action="store_true")
    p.add_argument("--skip-cpu", action="store_true")
    p.add_argument("--noise-off", action="store_true",
                   help="also the multi-ranger + flow and depth sets with the sensors' noise off")
    p.add_argument("--parts", action="store_true",
                   help="time the deck part and the casters alone instead (bench.sensor_rows.part_timings)")
    args = p.parse_args()
    engines = tuple(e for e, skip in (("jax", args.skip_jax), ("cpu", args.skip_cpu)) if not skip)
    if "jax" in engines:
        from quadswarm_mj import tune_jax_cpu, use_cpu_cores

        tune_jax_cpu()
        use_cpu_cores(strict=False)
    from quadswarm_mj.bench.sensor_rows import part_timings, sensor_rows, sensor_table

    if args.parts:
        print("| part | us per call |\n|---|---:|")
        for label, us in part_timings(args.worlds):
            print(f"| {label} | {us:,.1f} |")
        return

    print(sensor_table(sensor_rows(args.worlds, args.steps, args.seconds, args.rounds, engines, args.noise_off)))


if __name__ == "__main__":
    main()
