"""Plot the curves of DAgger runs (``quadswarm_mj.training.distill``'s ``progress.json``): imitation loss and,
at every iteration whose student episodes ended, the students' success and quad-quad collisions per quad.

    python scripts/plot_distill.py /work/runs/sensors_obstacles --labels "multi-ranger student" \\
        --out docs/training_sensors.png
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", help="distill output directories (each with progress.json)")
    p.add_argument("--labels", help="comma list, one per run (default: the directory names)")
    p.add_argument("--out", required=True, help="PNG to write")
    args = p.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = args.labels.split(",") if args.labels else [Path(r).name for r in args.runs]
    if len(labels) != len(args.runs):
        raise SystemExit(f"error: {len(labels)} labels for {len(args.runs)} runs")
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    for run, label in zip(args.runs, labels):
        rows = json.loads((Path(run) / "progress.json").read_text())
        ms = [r["samples"] / 1e6 for r in rows]
        axes[0].plot(ms, [r["loss"] for r in rows], label=label)
        ended = [r for r in rows if r["student_episodes"] and math.isfinite(r["student_success"])]
        axes[1].plot([r["samples"] / 1e6 for r in ended], [r["student_success"] for r in ended], "o-", label=label)
        axes[2].plot([r["samples"] / 1e6 for r in ended], [r["student_collisions"] for r in ended], "o-",
                     label=label)
    axes[0].set_yscale("log")
    for ax, title in zip(axes, ("imitation loss (MSE of tanh(mean))", "student success (training worlds)",
                                "student quad-quad collisions / quad")):
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("samples (M)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out, dpi=80)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
