"""Run a shipped policy's PPO chain: stages of ``quadswarm-train``, each from the one before, with agent-step budgets.

Each stage stops at its agent-step budget (``--timesteps``) and its learning rate decays over a fixed number of
agent-steps (``--lr-decay-timesteps``), so a chain is reproducible from its seeds on the same machine kind.
Re-running the same command continues a stopped chain: finished stages (``final.npz``) are skipped, a stopped stage
resumes from its last checkpoint (``--resume``) with the rest of its budget; its learning-rate schedule continues
where it was. ``OUT/chain.json`` records each stage's command, agent-steps and wall time (the training budget)::

    python scripts/train_chain.py swarm8_rl --out runs/swarm8_rl_chain            # ~2.5 h on one core
    python scripts/train_chain.py swarm8_rl --out runs/swarm8_rl_chain --dry-run  # the commands only
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

#: stages: (name, agent-steps, learning-rate horizon, options); each stage starts from the previous stage's final.npz
#: (the first from the preset's own ``init_from``). The shipped chain ran on wall-clock budgets (``--minutes``) and
#: kept a checkpoint before the end, so its schedules had not finished decaying: each horizon is the stage's
#: agent-steps over its wall-time fraction (manifest ``train.stages``: wall_s / minutes), e.g. stage 1's 167.7 M at
#: 7212 s of 160 min, and ``--lr-decay-timesteps`` gives it. TRAINING.md "pretrained:swarm8_rl" says what each is for.
_FINE = ["--entropy-cost", "0", "--replay-prob", "0.5"]
CHAINS: dict[str, list[tuple[str, int, int, list[str]]]] = {
    "swarm8_rl": [
        ("s1", 167_739_392, 223_296_000, ["--seed", "0"]),
        ("s3", 49_741_824, 165_734_000, ["--warm-start-std", "0.15", "--entropy-cost", "0", "--seed", "3"]),
        ("s5", 85_458_944, 427_097_000, ["--warm-start-std", "0.1", *_FINE, "--seed", "5"]),
        ("s6", 72_482_816, 144_780_000, ["--warm-start-std", "0.08", *_FINE, "--lr", "3e-5", "--seed", "6"]),
        ("s8", 32_374_784, 107_690_000, ["--warm-start-std", "0.08", *_FINE, "--lr", "3e-5", "--reward",
                                         "quad_collision=7.5", "--reward", "proximity=15", "--seed", "8"]),
        ("s10", 16_547_840, 82_603_000, ["--warm-start-std", "0.08", *_FINE, "--lr", "1.5e-5", "--reward",
                                         "quad_collision=8.5", "--reward", "proximity=17", "--seed", "10"]),
    ],
}
PRESET = {"swarm8_rl": "swarm8_rl"}


def _last_checkpoint_steps(stage_dir: Path) -> int | None:
    """Agent-steps of the stage's last ``step_*.npz`` checkpoint (None: none yet)."""
    steps = [int(p.stem.split("_")[1]) for p in (stage_dir / "checkpoints").glob("step_*.npz")]
    return max(steps) if steps else None


def stage_commands(chain: str, out: Path, cpu_devices: str, checkpoint_minutes: float) -> list[tuple[str, list[str]]]:
    """(stage name, train-CLI arguments) of every stage that is not finished, in order."""
    todo = []
    prev: Path | None = None
    for name, budget, horizon, opts in CHAINS[chain]:
        sdir = out / name
        common = ["--cpu-devices", cpu_devices, "--checkpoint-minutes", str(checkpoint_minutes), "--no-progress"]
        if not (sdir / "final.npz").is_file():
            done = _last_checkpoint_steps(sdir) if (sdir / "checkpoints" / "train_state.npz").is_file() else None
            if done is not None:
                args = ["--resume", str(sdir), *common, "--timesteps", str(budget - done)]
            else:
                init = ["--init-from", str(prev / "final.npz")] if prev is not None else []
                args = ["--preset", PRESET[chain], *init, *opts, *common, "--timesteps", str(budget),
                        "--lr-decay-timesteps", str(horizon), "--out", str(sdir)]
            todo.append((name, args))
        prev = sdir
    return todo


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("chain", choices=sorted(CHAINS))
    p.add_argument("--out", required=True, help="folder of the chain (one sub-folder per stage)")
    p.add_argument("--cpu-devices", default="1", help="as quadswarm-train's (default 1: the shipped chain's)")
    p.add_argument("--checkpoint-minutes", type=float, default=8.0)
    p.add_argument("--dry-run", action="store_true", help="print the commands of the stages left, run nothing")
    args = p.parse_args(argv)
    out = Path(args.out)
    record_file = out / "chain.json"
    record = json.loads(record_file.read_text()) if record_file.is_file() else {"chain": args.chain, "stages": []}
    for name, cmd in stage_commands(args.chain, out, args.cpu_devices, args.checkpoint_minutes):
        line = "quadswarm-train " + " ".join(cmd)
        print(line, flush=True)
        if args.dry_run:
            continue
        out.mkdir(parents=True, exist_ok=True)
        t0 = time.time()
        with open(out / f"{name}.log", "a") as log:
            rc = subprocess.call([sys.executable, "-m", "quadswarm_mj.cli.train", *cmd], stdout=log,
                                 stderr=subprocess.STDOUT)
        record["stages"].append({"stage": name, "command": line, "wall_s": round(time.time() - t0, 1), "rc": rc})
        record_file.write_text(json.dumps(record, indent=1))
        if rc != 0:
            print(f"stage {name} failed (rc {rc}); see {out / (name + '.log')}", file=sys.stderr)
            return rc
    if not args.dry_run:
        total = sum(s["wall_s"] for s in record["stages"])
        print(f"chain {args.chain} done: {total / 3600:.2f} h of training wall time ({record_file})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
