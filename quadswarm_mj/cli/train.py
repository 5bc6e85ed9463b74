"""Train a quadswarm_mj policy with PPO (Brax's PPO in JAX, rollouts on the batched CPU engine).

The default run trains the single-quad goal-reaching policy (static and jumping goals)::

    python scripts/train.py --out runs/single --minutes 30

The 8-quad swarm policy (neighbour observations, collision penalties), started from the
single-quad policy::

    python scripts/train.py --preset swarm8 --init-from runs/single/final.npz --out runs/swarm8 --minutes 60

Everything is configurable: ``--scenario`` (repeat it or give a comma list to train on several at
once), ``--num-quads``, reward scales ``--reward quad_collision=5 --reward proximity=10`` (fields of
``RewardScales``), any EnvConfig field ``--env motor_start=hover``, the PPO hyper-parameters
(``--num-worlds``, ``--unroll-length``, ``--lr``, ...), the budget (``--minutes`` and/or
``--timesteps`` in agent-steps = quad control steps) and ``--seed``.

Output in ``--out``: ``progress.csv`` and ``progress.json`` (one row per iteration: agent-steps,
wall time, reward per agent-step, losses, and per scenario the SPEC §8 episode metrics of the
episodes that ended in that iteration), ``curves.png``, ``checkpoints/step_*.npz`` every
``--checkpoint-minutes`` and ``final.npz``. Every ``.npz`` is a policy file that
``scripts/evaluate.py --policy <path>`` and ``quadswarm_mj.policies.load_policy`` read.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

PRESETS: dict[str, dict[str, Any]] = {
    # single quad, static and jumping goals
    "single": {"scenarios": ["static_same_goal", "dynamic_same_goal"], "num_quads": 1, "env": {}, "rewards": {},
               "ppo": {"num_worlds": 1024, "unroll_length": 32}},
    # 8 quads, K = 6 nearest neighbours observed, the paper's reward scales. (The shipped pretrained:swarm8
    # was trained before the reward had the original's time scaling, with quad_collision = proximity = 20:
    # under that scaling a collision cost 20 x 0.01 = 0.2, 20x one metre-step of the position cost; now
    # the paper's 5.0 per collision is 1000x a metre-step of position (0.005) and proximity 10 x 0.01 keeps
    # its old ratio to the position term (20x), so no override is needed.)
    "swarm8": {"scenarios": ["static_diff_goal", "swap_goals"], "num_quads": 8, "env": {},
               "rewards": {},
               "ppo": {"num_worlds": 128, "unroll_length": 32}},
}


def _parse_value(text: str) -> Any:
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _kv(items: list[str] | None, what: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for it in items or []:
        if "=" not in it:
            raise SystemExit(f"error: {what} must be KEY=VALUE, got {it!r}")
        k, v = it.split("=", 1)
        v = _parse_value(v)
        out[k.strip()] = tuple(v) if isinstance(v, list) else v
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", choices=sorted(PRESETS), default="single", help="defaults to start from (single)")
    p.add_argument("--scenario", action="append", help="training scenario(s); repeat or comma-separate")
    p.add_argument("--num-quads", type=int, help="quads per world (N)")
    p.add_argument("--reward", action="append", metavar="TERM=SCALE", help="reward scale (RewardScales field)")
    p.add_argument("--env", action="append", metavar="FIELD=VALUE", help="EnvConfig field (JSON value)")
    p.add_argument("--out", default="runs/train", help="output directory (default runs/train)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--minutes", type=float, help="wall-clock budget in minutes")
    p.add_argument("--timesteps", type=float, help="budget in agent-steps (quad control steps), e.g. 5e7")
    p.add_argument("--init-from", help="start from this policy .npz (e.g. the single-quad policy for swarm8)")
    p.add_argument("--checkpoint-minutes", type=float, default=5.0, help="checkpoint period (default 5)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (log lines only)")
    g = p.add_argument_group("PPO (defaults from the preset, then PPOConfig)")
    g.add_argument("--num-worlds", type=int)
    g.add_argument("--unroll-length", type=int)
    g.add_argument("--num-minibatches", type=int)
    g.add_argument("--num-epochs", type=int)
    g.add_argument("--lr", "--learning-rate", dest="learning_rate", type=float)
    g.add_argument("--entropy-cost", type=float)
    g.add_argument("--lr-schedule", choices=("constant", "linear"), help="linear (default): decay to 10 %% at the end")
    g.add_argument("--discounting", type=float)
    g.add_argument("--gae-lambda", type=float)
    g.add_argument("--clipping-epsilon", type=float)
    g.add_argument("--reward-scaling", type=float)
    g.add_argument("--policy-hidden", help="comma list, e.g. 64,64")
    g.add_argument("--value-hidden", help="comma list, e.g. 64,64")
    g.add_argument("--activation", choices=("tanh", "relu", "swish", "elu"))
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.minutes is None and args.timesteps is None:
        args.minutes = 30.0
    from quadswarm_mj.config import EnvConfig, RewardScales
    from quadswarm_mj.training.ppo import PPOConfig, PPOTrainer

    preset = PRESETS[args.preset]
    scenarios = [s.strip() for item in (args.scenario or preset["scenarios"]) for s in item.split(",") if s.strip()]
    n = args.num_quads if args.num_quads is not None else preset["num_quads"]
    rewards = {**preset["rewards"], **_kv(args.reward, "--reward")}
    env = {**preset["env"], **_kv(args.env, "--env")}
    try:
        scales = RewardScales(**rewards)
        cfgs = [EnvConfig(num_quads=n, scenario=s, rewards=scales, **env) for s in scenarios]
    except (TypeError, ValueError) as e:
        raise SystemExit(f"error: {e}") from None
    ppo_kw = dict(preset["ppo"])
    for k in ("num_worlds", "unroll_length", "num_minibatches", "num_epochs", "learning_rate", "entropy_cost",
              "discounting", "gae_lambda", "clipping_epsilon", "reward_scaling", "activation", "lr_schedule"):
        if getattr(args, k) is not None:
            ppo_kw[k] = getattr(args, k)
    for k in ("policy_hidden", "value_hidden"):
        if getattr(args, k):
            ppo_kw[k] = tuple(int(x) for x in getattr(args, k).split(","))
    try:
        ppo = PPOConfig(**ppo_kw)
        trainer = PPOTrainer(cfgs, ppo, seed=args.seed, init_from=args.init_from)
    except ValueError as e:
        raise SystemExit(f"error: {e}") from None
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    run = {"argv": sys.argv[1:] if argv is None else argv, "scenarios": scenarios, "num_quads": n,
           "env": {k: (list(v) if isinstance(v, tuple) else v) for k, v in env.items()}, "rewards": rewards,
           "ppo": {k: (list(v) if isinstance(v, tuple) else v) for k, v in ppo.__dict__.items()},
           "seed": args.seed, "init_from": args.init_from, "agents": trainer.batch.num_agents,
           "obs_dim": trainer.obs_dim}
    (out / "run.json").write_text(json.dumps(run, indent=1, default=str))
    print(f"training {', '.join(scenarios)} with N={n}: {trainer.batch.num_agents} agents, obs_dim "
          f"{trainer.obs_dim}; output in {out}", flush=True)

    def log(row: dict[str, Any]) -> None:
        if args.no_progress:
            parts = [f"it {row['iteration']}", f"{row['env_steps'] / 1e6:.2f} M steps", f"{row['wall_s'] / 60:.1f} min",
                     f"r/step {row['reward_per_step']:.4f}"]
            for s in scenarios:
                for key in ("success", "goal_reach_rate", "collisions"):
                    v = row.get(f"{s}/{key}")
                    if v is not None and v == v:
                        parts.append(f"{s}/{key} {v:.3f}")
            print(" | ".join(parts), flush=True)

    trainer.train(total_steps=None if args.timesteps is None else int(args.timesteps),
                  seconds=None if args.minutes is None else 60.0 * args.minutes, out_dir=out,
                  checkpoint_every_s=60.0 * args.checkpoint_minutes, progress=not args.no_progress, callback=log)
    print(f"done: {trainer.env_steps} agent-steps; policy {out / 'final.npz'}, curves {out / 'curves.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
