"""Stable-Baselines3 PPO: one quad flies to a static goal and holds it (``static_same_goal``).

SB3 trains on the batched JAX engine through the VecEnv adapter (``QuadSwarmSB3VecEnv``: W worlds of one
quad are W SB3 envs, stepped in one jitted call), with the settings that learn (docs/examples.md):

    python examples/sb3_ppo_single.py --total-steps 2000000        # the recorded run (docs/examples.md)
    python examples/sb3_ppo_single.py --smoke                      # a few hundred steps (CI)

The held-out evaluation flies ``--eval-episodes`` fresh episodes (seed ``--seed + 1000``, never used in
training) with the deterministic policy and prints the episode's mean distance to the goal (``mean_distance``,
the episode metric: take-off included) and the distance at the episode's end (from the last observation).
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


def make_cfg(episode_seconds: float) -> EnvConfig:
    """The training env: one quad, static goal, the position reward at 3x the paper's scale (hover precision)."""
    return EnvConfig(num_quads=1, scenario="static_same_goal", rewards={"pos": 3.0}, episode_seconds=episode_seconds)


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
    """``episodes`` worlds flown once each with the deterministic policy; means over the episodes (m)."""
    env = QuadSwarmVectorEnv(cfg, num_envs=episodes, engine=engine, info_keys=("rewards",))
    obs, _ = env.reset(seed=seed)
    for _ in range(cfg.episode_steps):
        act, _ = model.predict(norm.normalize_obs(obs.reshape(episodes, -1)), deterministic=True)
        obs, _, _, truncated, info = env.step(act.reshape(episodes, 1, 4))
    env.close()
    assert truncated.all()
    final_dist = np.linalg.norm(info["final_obs"][:, 0, :3], axis=-1)  # p - goal, noisy observation
    return {"mean_distance": float(np.mean(info["episode_metrics"]["mean_distance"])),
            "final_distance": float(final_dist.mean()), "final_distance_std": float(final_dist.std()),
            "success": float(np.mean(info["episode_metrics"]["success"]))}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--total-steps", type=int, default=2_000_000, help="agent-steps (the lr schedule's span)")
    p.add_argument("--worlds", type=int, default=64, help="worlds of one quad stepped together (SB3 envs)")
    p.add_argument("--n-steps", type=int, default=256, help="rollout steps per world per PPO update")
    p.add_argument("--lr", type=float, default=2e-3, help="initial learning rate, decaying linearly to 10 %%")
    p.add_argument("--engine", choices=("jax", "mujoco"), default="jax", help="the smoke test uses mujoco (no compile)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eval-episodes", type=int, default=20)
    p.add_argument("--save", help="write the model (.zip) and the normalizer (.pkl) with this prefix")
    p.add_argument("--smoke", action="store_true", help="a few hundred steps on 0.5 s episodes (CI)")
    args = p.parse_args()
    episode_seconds = 15.0
    if args.smoke:
        args.total_steps, args.worlds, args.n_steps, args.eval_episodes = 512, 4, 32, 2
        episode_seconds, args.engine = 0.5, "mujoco"
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)  # small networks: one thread, and no contention with the JAX engine's threads
    cfg = make_cfg(episode_seconds)
    venv = QuadSwarmSB3VecEnv(cfg=cfg, num_envs=args.worlds, engine=args.engine)
    venv.seed(args.seed)
    venv = VecNormalize(venv, norm_obs=True, norm_reward=True, gamma=0.99)
    lr0 = args.lr
    model = PPO("MlpPolicy", venv, n_steps=args.n_steps, batch_size=min(1024, args.worlds * args.n_steps),
                n_epochs=4, learning_rate=lambda frac: lr0 * (0.1 + 0.9 * frac), gamma=0.99, gae_lambda=0.95,
                clip_range=0.2, ent_coef=0.0, max_grad_norm=1.0, seed=args.seed,
                policy_kwargs={"log_std_init": -0.5, "net_arch": [64, 64]}, verbose=0)
    t0 = time.time()
    model.learn(args.total_steps, callback=Progress())
    train_s = time.time() - t0
    print(f"trained {model.num_timesteps:,d} agent-steps in {train_s:.0f} s", flush=True)
    if args.save:
        model.save(args.save + ".zip")
        venv.save(args.save + "_vecnormalize.pkl")
    venv.close()
    r = evaluate(model, venv, cfg, args.eval_episodes, seed=args.seed + 1000, engine=args.engine)
    print(f"held-out ({args.eval_episodes} episodes, seed {args.seed + 1000}): mean distance "
          f"{r['mean_distance']:.3f} m, final distance {r['final_distance']:.3f} +- {r['final_distance_std']:.3f} m, "
          f"success {r['success']:.2f}  (train {train_s:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
