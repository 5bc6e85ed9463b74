"""Plot a chain of training runs (each stage started with ``--init-from`` a checkpoint of the one before) as one
set of curves: every stage's ``progress.json`` up to the checkpoint the next stage started from (or the shipped
one), agent-steps and wall time added up, a dashed line where each stage begins. The curves of
``pretrained:swarm8_rl`` (TRAINING.md)::

    python scripts/plot_chain.py runs/swarm8_rl:167739392 runs/swarm8_rl_s3:49741824 runs/swarm8_rl_s5:85458944 \\
        runs/swarm8_rl_s6:72482816 runs/swarm8_rl_s8:32374784 runs/swarm8_rl_s10:16547840 \\
        --out docs/training_swarm8_rl.png
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from quadswarm_mj.training.run_logs import plot_curves


def chain_rows(stages: list[tuple[Path, int]]) -> tuple[list[dict], list[tuple[float, str]]]:
    """The stages' progress rows up to each stage's checkpoint (agent-steps), with agent-steps and wall
    seconds made cumulative, and a (agent-steps, label) mark where each stage after the first begins."""
    rows, marks, steps0, wall0 = [], [], 0, 0.0
    for i, (run, until) in enumerate(stages):
        stage = [r for r in json.loads((run / "progress.json").read_text()) if r["env_steps"] <= until]
        if not stage or stage[-1]["env_steps"] != until:
            raise SystemExit(f"error: {run}/progress.json has no row at {until} agent-steps")
        if i:
            marks.append((float(steps0), f"stage {i + 1}: {run.name}"))
        rows += [dict(r, env_steps=r["env_steps"] + steps0, wall_s=r["wall_s"] + wall0) for r in stage]
        steps0, wall0 = steps0 + until, wall0 + stage[-1]["wall_s"]
    return rows, marks


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("stages", nargs="+", help="RUN_DIR:AGENT_STEPS, in training order")
    p.add_argument("--out", required=True, help="PNG to write")
    args = p.parse_args(argv)
    stages = []
    for spec in args.stages:
        run, _, until = spec.rpartition(":")
        if not run or not until.isdigit():
            raise SystemExit(f"error: {spec!r} is not RUN_DIR:AGENT_STEPS")
        stages.append((Path(run), int(until)))
    rows, marks = chain_rows(stages)
    with tempfile.TemporaryDirectory() as tmp:
        progress = Path(tmp) / "progress.json"
        progress.write_text(json.dumps(rows))
        title = (f"{len(stages)} stages, {rows[-1]['env_steps'] / 1e6:.1f} M agent-steps in "
                 f"{rows[-1]['wall_s'] / 3600:.2f} h (stochastic training policy)")
        plot_curves(progress, args.out, title=title, window=150, marks=marks)
    print(f"wrote {args.out}: {rows[-1]['env_steps']} agent-steps, {rows[-1]['wall_s'] / 3600:.2f} h")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
