"""How a swarm policy holds a formation: per-quad final distances to the goals and each world's closest pair.

    python scripts/formation_spacing.py --policy pretrained:swarm8 [--scenario static_diff_goal] [--worlds 20]

Runs ``--worlds`` episodes of the scenario on the CPU engine (greedy policy, all noise on, the seeding of
``quadswarm-evaluate --seed S``) and prints the success rate, the quantiles of each quad's distance to its goal
over the last second, the share of quads beyond the success radius, and per world the goals' closest spacing
beside the quads' closest pair at the end (m).
"""

from __future__ import annotations

import argparse

import numpy as np

from quadswarm_mj.envs.cpu_core import CpuSwarm
from quadswarm_mj.metrics import SUCCESS_DISTANCE
from quadswarm_mj.policies import load_policy
from quadswarm_mj.training.evaluation import make_eval_config


def closest_pair(points: np.ndarray) -> np.ndarray:
    """(B,) smallest distance between two of the N points of each world (B, N, 3)."""
    d = np.linalg.norm(points[:, :, None] - points[:, None], axis=-1)
    return np.where(np.eye(points.shape[1], dtype=bool), np.inf, d).min(axis=(1, 2))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", required=True)
    ap.add_argument("--scenario", default="static_diff_goal")
    ap.add_argument("--worlds", type=int, default=20)
    ap.add_argument("--seed", type=int, default=11)
    args = ap.parse_args()
    policy = load_policy(args.policy)
    cfg = make_eval_config(policy, args.scenario)
    core = CpuSwarm(cfg, num_worlds=args.worlds)
    core.seed(args.seed * 1_000_003)
    core.reset()
    obs, last = core.observe().astype(np.float32), []
    for t in range(cfg.episode_steps):
        info = {"state": core.state_dict(), "goals": core.sstate.goals, "goal_vel": core.sstate.goal_vel,
                "params": core.params_dict()}
        act = np.asarray(policy.act(obs, info)).reshape(args.worlds, cfg.num_quads, 4)
        obs = core.step(np.clip(act, -1.0, 1.0))["obs"].astype(np.float32)
        if t >= cfg.episode_steps - cfg.control_hz:
            last.append(np.linalg.norm(core.state_dict()["pos"] - core.sstate.goals, axis=-1))
    final = np.mean(last, axis=0)
    print(f"success {core.episode_metrics()['success'].mean():.3f}")
    print("final distance quantiles 10/25/50/75/90/100 %:", np.quantile(final, [.1, .25, .5, .75, .9, 1]).round(3))
    print(f"quads beyond {SUCCESS_DISTANCE} m: {(final >= SUCCESS_DISTANCE).mean():.3f}")
    print("goals' closest spacing per world:", closest_pair(core.sstate.goals).round(2))
    print("quads' closest pair per world:   ", closest_pair(core.state_dict()["pos"]).round(2))


if __name__ == "__main__":
    main()
