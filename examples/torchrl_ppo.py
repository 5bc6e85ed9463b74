"""TorchRL PPO (a collector + ``ClipPPOLoss`` + GAE) on the Gymnasium env, one quad, static goal.

TorchRL builds its specs from the env's ``info``, so the env runs with ``info_mode="flat"`` (every info entry
an array of stable shape: ``episode_metrics/mean_distance`` is NaN until an episode ends). The id
``quadswarm_mj:QuadSwarm-v0`` imports the package itself (also in worker processes). One ``GymEnv`` steps at
a few hundred frames/s here (TorchRL's per-step cost); 16 envs in a ``SyncVectorEnv`` share that cost.

    python examples/torchrl_ppo.py --total-steps 2000000     # the budget SB3 needed (docs/examples.md)
    python examples/torchrl_ppo.py --smoke                   # a few hundred steps (CI)

The held-out evaluation flies ``--eval-episodes`` episodes (seed ``--seed + 1000``) with the deterministic
policy (the mode of the tanh-Gaussian) and prints the episode metric ``mean_distance`` (m).
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np
import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn

try:  # TorchRL >= 0.11 names the single-process collector Collector
    from torchrl.collectors import Collector
except ImportError:  # pragma: no cover - older TorchRL
    from torchrl.collectors import SyncDataCollector as Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer, SamplerWithoutReplacement, Unbounded
from torchrl.envs import DoubleToFloat, GymWrapper, TransformedEnv
from torchrl.envs.gym_like import default_info_dict_reader
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

METRIC = "episode_metrics/mean_distance"  # m, NaN until an episode ends (info_mode="flat")


def make_env(num_envs: int, episode_seconds: float, seed: int, engine: str) -> TransformedEnv:
    """``num_envs`` envs of one quad on static_same_goal (the position term at 3x the paper's scale, observations
    scaled into [-1, 1] by the env) in one gymnasium ``SyncVectorEnv`` (same-step auto-reset, as TorchRL's
    ``GymWrapper`` wants): TorchRL's per-step cost is paid once for the batch."""
    def make() -> gym.Env:
        return gym.make("quadswarm_mj:QuadSwarm-v0", num_quads=1, scenario="static_same_goal", engine=engine,
                        info_mode="flat", rewards={"pos": 3.0}, normalize_obs=True, episode_seconds=episode_seconds)

    venv = gym.vector.SyncVectorEnv([make] * num_envs, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
    env = GymWrapper(venv)
    # the flat info's key into the tensordict (batched spec given: TorchRL cannot infer it through the wrapper)
    env.base_env.set_info_dict_reader(default_info_dict_reader(
        [METRIC], spec={METRIC: Unbounded(shape=(num_envs,), dtype=torch.float32)}))
    env.set_seed(seed)
    return TransformedEnv(env, DoubleToFloat())


def mlp(n_out: int) -> nn.Sequential:
    return nn.Sequential(nn.LazyLinear(64), nn.Tanh(), nn.Linear(64, 64), nn.Tanh(), nn.Linear(64, n_out))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--total-steps", type=int, default=2_000_000, help="env steps (frames)")
    p.add_argument("--num-envs", type=int, default=16, help="envs stepped together (a gymnasium SyncVectorEnv)")
    p.add_argument("--frames-per-batch", type=int, default=4096)
    p.add_argument("--minibatch", type=int, default=512)
    p.add_argument("--epochs", type=int, default=4)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--engine", choices=("jax", "mujoco"), default="jax", help="the smoke test uses mujoco (no compile)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eval-episodes", type=int, default=5)
    p.add_argument("--smoke", action="store_true", help="a few hundred steps on 0.5 s episodes (CI)")
    args = p.parse_args()
    episode_seconds = 15.0
    if args.smoke:
        args.total_steps, args.frames_per_batch, args.minibatch, args.eval_episodes, args.num_envs = 256, 128, 64, 2, 2
        episode_seconds, args.engine = 0.5, "mujoco"
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)
    env = make_env(args.num_envs, episode_seconds, args.seed, args.engine)
    act_spec = env.action_spec_unbatched if hasattr(env, "action_spec_unbatched") else env.action_spec
    actor_net = nn.Sequential(mlp(2 * act_spec.shape[-1]), NormalParamExtractor())
    actor = ProbabilisticActor(TensorDictModule(actor_net, in_keys=["observation"], out_keys=["loc", "scale"]),
                               spec=env.action_spec, in_keys=["loc", "scale"], distribution_class=TanhNormal,
                               distribution_kwargs={"low": act_spec.space.low, "high": act_spec.space.high},
                               return_log_prob=True)
    critic = ValueOperator(mlp(1), in_keys=["observation"])
    with torch.no_grad():  # materialize the lazy layers
        td = env.reset()
        actor(td)
        critic(td)
    collector = Collector(env, actor, frames_per_batch=args.frames_per_batch, total_frames=args.total_steps)
    buffer = ReplayBuffer(storage=LazyTensorStorage(args.frames_per_batch), sampler=SamplerWithoutReplacement(),
                          batch_size=args.minibatch)
    gae = GAE(gamma=0.99, lmbda=0.95, value_network=critic, average_gae=True)
    loss_fn = ClipPPOLoss(actor, critic, clip_epsilon=0.2, entropy_bonus=False, critic_coeff=1.0,
                          loss_critic_type="smooth_l1")
    optim = torch.optim.Adam(loss_fn.parameters(), args.lr)
    iters = max(1, args.total_steps // args.frames_per_batch)
    sched = torch.optim.lr_scheduler.LinearLR(optim, 1.0, 0.1, iters)  # lr to 10 % over the budget
    t0, frames = time.time(), 0
    for i, batch in enumerate(collector):
        frames += batch.numel()
        for _ in range(args.epochs):
            with torch.no_grad():
                gae(batch)
            buffer.extend(batch.reshape(-1))
            for mb in buffer:
                losses = loss_fn(mb)
                loss = losses["loss_objective"] + losses["loss_critic"]
                optim.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(loss_fn.parameters(), 1.0)
                optim.step()
        sched.step()
        if i % 10 == 0 or frames >= args.total_steps:
            print(f"{frames:>9,d} frames  {frames / (time.time() - t0):6.0f}/s  reward/step "
                  f"{batch['next', 'reward'].mean().item():+.4f}", flush=True)
    train_s = time.time() - t0
    env.close()  # the held-out episodes: fresh envs, one episode each, the mode of the policy
    env = make_env(args.eval_episodes, episode_seconds, args.seed + 1000, args.engine)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.rollout(int(round(episode_seconds * 100)), actor, break_when_any_done=False)
    dists = td["next", METRIC][:, -1].numpy()  # (episodes,) at the episodes' last step
    env.close()
    print(f"held-out ({args.eval_episodes} episodes, seeds {args.seed + 1000}+): mean distance "
          f"{np.mean(dists):.3f} m  (train {frames:,d} frames in {train_s:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
