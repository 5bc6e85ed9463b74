"""Evaluate a policy on the CPU env: K episodes per scenario, the SPEC §8 episode metrics.

    python scripts/evaluate.py --policy pretrained:swarm8 --scenarios static_diff_goal,swap_goals --episodes 50
    python scripts/evaluate.py --policy pretrained:swarm8_obstacles --episodes 100   # the obstacle scenarios
    python scripts/evaluate.py --policy runs/single/final.npz          # a training checkpoint
    python scripts/evaluate.py --policy controller --num-quads 8 --scenarios swap_goals

Default scenarios: the eleven paper scenarios for a swarm policy, the obstacle scenarios for a policy
trained among obstacles (or with ``--env obstacles='{"density": 0.2}'``), static/dynamic same goal for
one quad. Prints, per scenario and with standard errors over episodes: success rate, collisions per quad,
collision rate, obstacle collisions per quad, goal-reach rate, mean distance to goal (m), floor hits per
quad (definitions: docs/model.md). ``--json FILE`` writes the same numbers (checked writable first,
replaced atomically; on a failed write the JSON is printed and the exit status is 1).

Episodes run with the environment defaults (motor_start "zero", all noise on) unless ``--env`` overrides
them; ``--mode gym`` steps ``QuadSwarmEnv`` one episode at a time, the default ``batched`` mode the same
CPU engine with many episodes at once. No JAX is needed.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

#: the eleven paper scenarios (the ten named ones and their ``mix``) and the obstacle scenarios (with ``mix``)
PAPER_SCENARIOS = ("static_same_goal", "static_diff_goal", "dynamic_same_goal", "dynamic_diff_goal",
                   "dynamic_formations", "swap_goals", "swarm_vs_swarm", "ep_lissajous3D", "ep_rand_bezier",
                   "run_away", "mix")
OBSTACLE_SCENARIOS = ("o_random", "o_static_same_goal", "o_dynamic_same_goal", "o_swap_goals", "o_ep_rand_bezier",
                      "mix")
DEFAULT_SCENARIOS = {"single": "static_same_goal,dynamic_same_goal", "swarm": ",".join(PAPER_SCENARIOS),
                     "obstacles": ",".join(OBSTACLE_SCENARIOS)}
#: columns of the printed table: metric key, header, width
COLUMNS = (("success", "success", 13), ("collisions", "coll/quad", 13), ("collision_rate", "coll rate", 13),
           ("obstacle_collisions", "obst coll", 13), ("goal_reach_rate", "goal reach", 13),
           ("mean_distance", "mean dist m", 13), ("floor_hits", "floor hits", 13))


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


def _check_not_other_file(path: str) -> None:
    """``ValueError`` if ``path`` is an existing regular file that is not a JSON document (a policy, a
    video, notes: ``--json`` replaces only earlier results)."""
    p = Path(path)
    if not p.is_file() or p.stat().st_size == 0:
        return
    try:
        if p.stat().st_size > (64 << 20):
            raise ValueError("larger than 64 MiB")
        json.loads(p.read_bytes().decode("utf-8"))
    except (ValueError, RecursionError, OSError):
        raise ValueError(f"--json {path!r} exists and is not a JSON file; refusing to overwrite it: choose another "
                         "file or remove it") from None


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # run as a command: the opt-in XLA:CPU tuning (quadswarm_mj.tune_jax_cpu), before JAX starts
        from quadswarm_mj.devices import tune_jax_cpu

        tune_jax_cpu()
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

    from quadswarm_mj.outfiles import atomic_write_text, check_writable
    from quadswarm_mj.policies import load_policy
    from quadswarm_mj.training.evaluation import evaluate

    if args.json:  # before the work: a results file that cannot be written is known now, not after it
        try:
            check_writable(args.json, "--json")
            _check_not_other_file(args.json)
        except ValueError as e:
            raise SystemExit(f"error: {e}") from None
    try:
        policy = load_policy(args.policy, seed=args.seed)
    except ValueError as e:
        raise SystemExit(f"error: {e}") from None
    n = args.num_quads
    if n is None:
        n = getattr(policy, "env_kwargs", {}).get("num_quads", 1)
    env_over = _kv(args.env)
    obstacles = env_over.get("obstacles", getattr(policy, "env_kwargs", {}).get("obstacles"))
    kind = "single" if n == 1 else ("obstacles" if obstacles is not None else "swarm")
    scen = args.scenarios or DEFAULT_SCENARIOS[kind]
    results = []
    header = f"{'scenario':<20} {'N':>3} {'eps':>4} " + " ".join(h.rjust(w) for _, h, w in COLUMNS) + f" {'time':>6}"
    print(f"policy {args.policy}; {args.episodes} episodes per scenario; mode {args.mode}; mean ± standard error")
    print(header)
    for s in [x.strip() for x in scen.split(",") if x.strip()]:
        try:
            r = evaluate(policy, s, episodes=args.episodes, num_quads=n, seed=args.seed, env=env_over,
                         mode=args.mode, max_worlds=args.max_worlds)
        except ValueError as e:
            raise SystemExit(f"error: {e}") from None
        sm = r.summary()
        results.append(sm)

        def f(k: str, w: int, sm: dict = sm) -> str:
            if k not in sm:
                return "-".rjust(w)
            return f"{sm[k]:.3f}±{sm[k + '_stderr']:.3f}".rjust(w)

        print(f"{s:<20} {r.num_quads:>3} {r.episodes:>4} " + " ".join(f(k, w) for k, _, w in COLUMNS)
              + f" {sm['seconds']:>5.0f}s", flush=True)
    if args.json:
        text = json.dumps({"policy": args.policy, "episodes": args.episodes, "seed": args.seed, "mode": args.mode,
                           "env": {k: (list(v) if isinstance(v, tuple) else v) for k, v in _kv(args.env).items()},
                           "results": results}, indent=1)
        try:
            atomic_write_text(args.json, text)
        except OSError as e:  # e.g. the disk filled up or the directory went away during the evaluation
            print(f"error: could not write --json {args.json!r} ({e.strerror or e}); the results follow on stdout",
                  file=sys.stderr)
            print(text, flush=True)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
