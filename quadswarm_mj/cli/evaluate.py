"""Evaluate a policy on the CPU env: K episodes per scenario, the SPEC §8 episode metrics.

    python scripts/evaluate.py --policy pretrained:single --scenarios static_same_goal,dynamic_same_goal
    python scripts/evaluate.py --policy pretrained:swarm8 --scenarios static_diff_goal,swap_goals --episodes 50
    python scripts/evaluate.py --policy runs/single/final.npz          # a training checkpoint
    python scripts/evaluate.py --policy controller --num-quads 8 --scenarios swap_goals
    python scripts/evaluate.py --policy random

Prints, per scenario: success rate (fraction of quads with no quad-quad collision after the
grace period and mean distance to goal over the last 5 steps < 0.5 m), collisions per quad per
episode (after the grace period), mean distance to goal (m), goal-reach rate (fraction of goal
segments of >= 3 s in which the quad came within 0.3 m of its goal), floor hits per quad per
episode, each with the standard error over episodes. ``--json FILE`` writes the same numbers.

Episodes run with the environment defaults (motor_start "zero", all noise on) unless ``--env``
overrides them. ``--mode gym`` steps ``QuadSwarmEnv`` one episode at a time; the default
``batched`` mode steps the same CPU engine with many episodes at once (same metrics, faster).
No JAX is needed.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

DEFAULT_SCENARIOS = {"single": "static_same_goal,dynamic_same_goal", "swarm": "static_diff_goal,swap_goals"}


def _kv(items: list[str] | None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for it in items or []:
        if "=" not in it:
            raise SystemExit(f"error: --env must be FIELD=VALUE, got {it!r}")
        k, v = it.split("=", 1)
        try:
            val = json.loads(v)
        except json.JSONDecodeError:
            val = v
        out[k.strip()] = tuple(val) if isinstance(val, list) else val
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policy", default="pretrained:single",
                   help="pretrained:<name>, a policy .npz path, 'controller' or 'random' (default pretrained:single)")
    p.add_argument("--scenarios", help="comma list (default: the policy's evaluation scenarios)")
    p.add_argument("--episodes", type=int, default=50, help="episodes per scenario (default 50)")
    p.add_argument("--num-quads", type=int, help="quads per world (default: the policy's, else 1)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--env", action="append", metavar="FIELD=VALUE", help="EnvConfig override (JSON value)")
    p.add_argument("--mode", choices=("batched", "gym"), default="batched")
    p.add_argument("--max-worlds", type=int, default=64, help="episodes stepped together in batched mode")
    p.add_argument("--json", help="write the results to this file")
    args = p.parse_args(argv)

    from quadswarm_mj.policies import load_policy
    from quadswarm_mj.training.evaluation import evaluate

    try:
        policy = load_policy(args.policy, seed=args.seed)
    except ValueError as e:
        raise SystemExit(f"error: {e}") from None
    n = args.num_quads
    if n is None:
        n = getattr(policy, "env_kwargs", {}).get("num_quads", 1)
    scen = args.scenarios or DEFAULT_SCENARIOS["single" if n == 1 else "swarm"]
    results = []
    header = (f"{'scenario':<20} {'N':>3} {'eps':>4} {'success':>15} {'collisions/quad':>17} {'mean dist (m)':>15} "
              f"{'goal reach':>15} {'floor hits':>11} {'time':>6}")
    print(f"policy {args.policy}; {args.episodes} episodes per scenario; mode {args.mode}")
    print(header)
    for s in [x.strip() for x in scen.split(",") if x.strip()]:
        try:
            r = evaluate(policy, s, episodes=args.episodes, num_quads=n, seed=args.seed, env=_kv(args.env),
                         mode=args.mode, max_worlds=args.max_worlds)
        except ValueError as e:
            raise SystemExit(f"error: {e}") from None
        sm = r.summary()
        results.append(sm)

        def f(k: str, w: int = 15, d: int = 3, sm: dict = sm) -> str:
            return f"{sm[k]:.{d}f}±{sm[k + '_stderr']:.{d}f}".rjust(w)

        print(f"{s:<20} {r.num_quads:>3} {r.episodes:>4} {f('success')} {f('collisions', 17)} {f('mean_distance')} "
              f"{f('goal_reach_rate')} {sm['floor_hits']:>11.3f} {sm['seconds']:>5.0f}s", flush=True)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"policy": args.policy, "episodes": args.episodes, "seed": args.seed, "mode": args.mode,
                       "env": {k: (list(v) if isinstance(v, tuple) else v) for k, v in _kv(args.env).items()},
                       "results": results}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
