"""Stable-Baselines3 PPO on 8 quads: one policy shared by every quad, on the batched engine.

``QuadSwarmSB3VecEnv`` turns W worlds of 8 quads (``QuadSwarmVectorEnv``) into W * 8 SB3 envs, one per
quad; SB3 sees each quad as an env of its own (observation: own state + 6 nearest neighbours, 54 floats),
and time-limit ends arrive as ``TimeLimit.truncated`` so that PPO bootstraps them. No SuperSuit needed.
What makes it learn (docs/examples.md): the neighbour inputs start at zero weight (each quad first learns to
fly to its own goal), and the collision/proximity penalties are off.

    python examples/sb3_ppo_swarm.py                                # the recorded run: 6 M agent-steps
    python examples/sb3_ppo_swarm.py --smoke                        # a few hundred steps (CI)

The held-out evaluation flies ``--eval-episodes`` fresh episodes (seed ``--seed + 1000``) with the
deterministic policy and prints the episode metrics (means over quads and episodes).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecNormalize

from quadswarm_mj import EnvConfig, QuadSwarmVectorEnv
from quadswarm_mj.envs.sb3_vec_env import QuadSwarmSB3VecEnv


class Progress(BaseCallback):
    """Prints agent-steps, agent-steps/s and the mean reward per step (unnormalized) every ``every`` seconds."""

    def __init__(self, every: float = 30.0):
        super().__init__()
        self.every, self.t0, self.last, self.rewards = every, time.time(), 0.0, []

    def _on_step(self) -> bool:
        self.rewards.append(float(self.training_env.get_original_reward().mean()))
        now = time.time()
        if now - self.last >= self.every:
            self.last = now
            print(f"{self.num_timesteps:>10,d} agent-steps  {self.num_timesteps / (now - self.t0):6.0f}/s  "
                  f"{now - self.t0:5.0f} s  reward/step {np.mean(self.rewards):+.4f}", flush=True)
            self.rewards.clear()
        return True


def evaluate(model: PPO, norm: VecNormalize, cfg: EnvConfig, episodes: int, seed: int, engine: str
             ) -> dict[str, float]:
    """``episodes`` worlds flown once each with the deterministic shared policy; episode-metric means."""
    env = QuadSwarmVectorEnv(cfg, num_envs=episodes, engine=engine, info_keys=("rewards",))
    obs, _ = env.reset(seed=seed)
    n = cfg.num_quads
    for _ in range(cfg.episode_steps):
        act, _ = model.predict(norm.normalize_obs(obs.reshape(episodes * n, -1)), deterministic=True)
        obs, _, _, truncated, info = env.step(act.reshape(episodes, n, 4))
    env.close()
    assert truncated.all()
    m = info["episode_metrics"]
    return {k: float(np.mean(m[k])) for k in ("mean_distance", "success", "collisions", "floor_hits")}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--total-steps", type=int, default=6_000_000, help="agent-steps (quads x control steps)")
    p.add_argument("--scenario", default="static_diff_goal", help="quadswarm_mj.list_scenarios()")
    p.add_argument("--worlds", type=int, default=16, help="worlds of 8 quads (SB3 envs: worlds x 8)")
    p.add_argument("--n-steps", type=int, default=128, help="rollout steps per quad per PPO update")
    p.add_argument("--lr", type=float, default=2e-3, help="initial learning rate, decaying linearly to 10 %%")
    p.add_argument("--engine", choices=("jax", "mujoco"), default="jax", help="the smoke test uses mujoco (no compile)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eval-episodes", type=int, default=20)
    p.add_argument("--neighbors", type=int, default=6, help="nearest neighbours observed (K)")
    p.add_argument("--random-neighbor-init", action="store_true", help="keep SB3's init of the neighbour inputs")
    p.add_argument("--reward", action="append", default=[], metavar="TERM=SCALE",
                   help="reward scale overrides (repeatable), e.g. quad_collision=5 (the paper's)")
    p.add_argument("--smoke", action="store_true", help="a few hundred steps on 0.5 s episodes (CI)")
    args = p.parse_args()
    episode_seconds = 15.0
    if args.smoke:
        args.total_steps, args.worlds, args.n_steps, args.eval_episodes = 512, 2, 32, 2
        episode_seconds, args.engine = 0.5, "mujoco"
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)  # small networks: one thread, and no contention with the JAX engine's threads
    # the position term at 3x the paper's scale, no collision/proximity penalty (docs/examples.md: with them
    # the shared policy did not learn in the budget); --reward TERM=SCALE overrides
    rewards = {"pos": 3.0, "quad_collision": 0.0, "proximity": 0.0,
               **{k: float(v) for k, v in (r.split("=") for r in args.reward)}}
    cfg = EnvConfig(num_quads=8, scenario=args.scenario, rewards=rewards, episode_seconds=episode_seconds,
                    num_neighbors=args.neighbors)
    venv = QuadSwarmSB3VecEnv(cfg=cfg, num_envs=args.worlds, engine=args.engine)  # worlds x 8 SB3 envs
    venv.seed(args.seed)
    venv = VecNormalize(venv, norm_obs=True, norm_reward=True, gamma=0.99)
    lr0 = args.lr
    model = PPO("MlpPolicy", venv, n_steps=args.n_steps, batch_size=min(2048, venv.num_envs * args.n_steps),
                n_epochs=4, learning_rate=lambda frac: lr0 * (0.1 + 0.9 * frac), gamma=0.99, gae_lambda=0.95,
                clip_range=0.2, ent_coef=0.0, max_grad_norm=1.0, seed=args.seed,
                policy_kwargs={"log_std_init": -0.5, "net_arch": [64, 64]}, verbose=0)
    if not args.random_neighbor_init:  # neighbour inputs at zero weight: each quad first learns to reach its goal
        with torch.no_grad():
            for net in (model.policy.mlp_extractor.policy_net, model.policy.mlp_extractor.value_net):
                net[0].weight[:, cfg.self_obs_dim:] = 0.0
    print(f"{venv.num_envs} SB3 envs ({args.worlds} worlds x 8 quads), observation {venv.observation_space.shape}",
          flush=True)
    t0 = time.time()
    model.learn(args.total_steps, callback=Progress())
    train_s = time.time() - t0
    venv.close()
    r = evaluate(model, venv, cfg, args.eval_episodes, seed=args.seed + 1000, engine=args.engine)
    print(f"held-out ({args.eval_episodes} episodes, seed {args.seed + 1000}, {args.scenario}): mean distance "
          f"{r['mean_distance']:.3f} m, success {r['success']:.2f}, collisions/quad {r['collisions']:.2f}, "
          f"floor hits/quad {r['floor_hits']:.2f}  (train {train_s:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
