"""TorchRL PPO (a collector + ``ClipPPOLoss`` + GAE) on the Gymnasium vector env, one quad, static goal.

TorchRL's ``GymWrapper`` takes ``QuadSwarmVectorEnv`` (W worlds of one quad on the batched JAX engine, one
jitted call per step, same-step auto-reset) with ``info_mode="flat"`` (every info entry an array of stable
shape). A small ``VectorWrapper`` hands TorchRL what it reads: the quad axis dropped, the episode metric
``mean_distance`` (NaN until an episode ends) also as the ending episode's ``final_info``, and ``final_obs``
with zeros where no episode ended (NaN there in flat mode, outside the observation box TorchRL checks).

    python examples/torchrl_ppo.py                  # the recorded run: 2 M frames (docs/examples.md)
    python examples/torchrl_ppo.py --smoke          # a few hundred steps (CI)

The held-out evaluation flies ``--eval-episodes`` fresh worlds (seed ``--seed + 1000``) for one episode with
the deterministic policy (the Gaussian's mean) and prints the episode metric ``mean_distance`` (m).
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np
import torch
from tensordict.nn import TensorDictModule
from torch import nn

try:  # tensordict >= 0.7 holds it
    from tensordict.nn import AddStateIndependentNormalScale
except ImportError:  # pragma: no cover - older TorchRL
    from torchrl.modules import AddStateIndependentNormalScale

try:  # TorchRL >= 0.11 names the single-process collector Collector
    from torchrl.collectors import Collector
except ImportError:  # pragma: no cover - older TorchRL
    from torchrl.collectors import SyncDataCollector as Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer, SamplerWithoutReplacement
from torchrl.envs import Compose, DoubleToFloat, GymWrapper, Transform, TransformedEnv, VecNorm
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import IndependentNormal, ProbabilisticActor, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from quadswarm_mj import EnvConfig, QuadSwarmVectorEnv

METRIC = "episode_metrics/mean_distance"  # m, NaN until an episode ends (info_mode="flat")


class OneQuad(gym.vector.VectorWrapper):
    """W worlds of one quad as W envs of (obs_dim,) observations and (4,) actions (clipped to [-1, 1]); ``info``
    reduced to what this script reads, in the shape TorchRL's ``GymWrapper`` reads it. With ``scale_rewards``
    the rewards are divided by the running std of the discounted return (SB3's ``VecNormalize``)."""

    autoreset_mode = gym.vector.AutoresetMode.SAME_STEP  # TorchRL reads it as an attribute

    def __init__(self, env: QuadSwarmVectorEnv, scale_rewards: bool = False, gamma: float = 0.99):
        super().__init__(env)
        self.scale_rewards, self.gamma, self.ret = scale_rewards, gamma, np.zeros(env.num_envs)
        self.count, self.mean, self.var = 1e-4, 0.0, 1.0  # running moments of the discounted return
        o, a = env.single_observation_space, env.single_action_space
        self.single_observation_space = gym.spaces.Box(o.low[0], o.high[0], dtype=np.float32)
        self.single_action_space = gym.spaces.Box(a.low[0], a.high[0], dtype=np.float32)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, env.num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, env.num_envs)

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        return obs[:, 0], self._info(info)

    def step(self, actions):
        obs, reward, terminated, truncated, info = self.env.step(np.clip(actions, -1.0, 1.0)[:, None])
        if self.scale_rewards:
            self.ret = self.ret * self.gamma + reward
            n, m, v = self.ret.size, self.ret.mean(), self.ret.var()
            total = self.count + n
            delta = m - self.mean
            self.mean, self.count = self.mean + delta * n / total, total
            self.var = (self.var * (total - n) + v * n + delta ** 2 * (total - n) * n / total) / total
            reward = np.clip(reward / np.sqrt(self.var + 1e-8), -10.0, 10.0)
            self.ret[terminated | truncated] = 0.0
        return obs[:, 0], reward, terminated, truncated, self._info(info)

    @staticmethod
    def _info(info: dict) -> dict:
        return {METRIC: info[METRIC], "final_obs": np.nan_to_num(info["final_obs"][:, 0]),
                "_final_obs": info["_final_obs"], "final_info": {METRIC: info[METRIC]}}


def make_env(worlds: int, episode_seconds: float, seed: int, engine: str, norm: Transform,
             scale_rewards: bool = False) -> TransformedEnv:
    """``worlds`` worlds of one quad on static_same_goal (the position term at 3x the paper's scale,
    observations scaled into [-1, 1] by the env, then by ``norm``) as one batched TorchRL env."""
    cfg = EnvConfig(num_quads=1, scenario="static_same_goal", rewards={"pos": 3.0}, normalize_obs=True,
                    info_mode="flat", episode_seconds=episode_seconds)
    env = GymWrapper(OneQuad(QuadSwarmVectorEnv(cfg, num_envs=worlds, engine=engine, info_keys=()), scale_rewards))
    env.set_seed(seed)
    return TransformedEnv(env, Compose(DoubleToFloat(), norm))  # the reward is float64


def mlp(n_out: int, last_gain: float) -> nn.Sequential:
    net = nn.Sequential(nn.LazyLinear(64), nn.Tanh(), nn.Linear(64, 64), nn.Tanh(), nn.Linear(64, n_out))
    with torch.no_grad():
        net[-1].weight.mul_(last_gain)  # a small policy output at the start (CleanRL's 0.01)
    return net


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--total-steps", type=int, default=2_000_000, help="frames (agent-steps)")
    p.add_argument("--worlds", type=int, default=64, help="worlds of one quad stepped together")
    p.add_argument("--frames-per-batch", type=int, default=16_384, help="frames per PPO update")
    p.add_argument("--minibatch", type=int, default=1024)
    p.add_argument("--epochs", type=int, default=4)
    p.add_argument("--lr", type=float, default=2e-3, help="initial learning rate, decaying linearly to 10 %%")
    p.add_argument("--log-std", type=float, default=-0.5, help="initial log std of the actions")
    p.add_argument("--engine", choices=("jax", "mujoco"), default="jax", help="the smoke test uses mujoco (no compile)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eval-episodes", type=int, default=20)
    p.add_argument("--smoke", action="store_true", help="a few hundred steps on 0.5 s episodes (CI)")
    args = p.parse_args()
    episode_seconds = 15.0
    if args.smoke:
        args.total_steps, args.frames_per_batch, args.minibatch, args.eval_episodes, args.worlds = 256, 128, 64, 2, 2
        episode_seconds, args.engine = 0.5, "mujoco"
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)  # small networks: one thread, and no contention with the JAX engine's threads
    # running mean/std of the observations (SB3's VecNormalize), frozen for the held-out episodes
    norm = VecNorm(in_keys=["observation"], decay=0.99999, reduce_batch_dims=True, new_api=True)
    env = make_env(args.worlds, episode_seconds, args.seed, args.engine, norm, scale_rewards=True)
    n_act = env.action_spec.shape[-1]
    actor_net = nn.Sequential(mlp(n_act, 0.01), AddStateIndependentNormalScale(n_act, init_value=args.log_std))
    actor = ProbabilisticActor(TensorDictModule(actor_net, in_keys=["observation"], out_keys=["loc", "scale"]),
                               spec=env.action_spec, in_keys=["loc", "scale"], distribution_class=IndependentNormal,
                               return_log_prob=True)
    critic = ValueOperator(mlp(1, 1.0), in_keys=["observation"])
    with torch.no_grad():  # materialize the lazy layers
        td = env.reset()
        actor(td)
        critic(td)
    iters = -(-args.total_steps // args.frames_per_batch)  # PPO updates (whole batches)
    collector = Collector(env, actor, frames_per_batch=args.frames_per_batch,
                          total_frames=iters * args.frames_per_batch)
    buffer = ReplayBuffer(storage=LazyTensorStorage(args.frames_per_batch), sampler=SamplerWithoutReplacement(),
                          batch_size=args.minibatch)
    # GAE stops at "terminated" only: time-limit ends bootstrap from the episode's last observation ("next")
    gae = GAE(gamma=0.99, lmbda=0.95, value_network=critic, average_gae=False)
    loss_fn = ClipPPOLoss(actor, critic, clip_epsilon=0.2, entropy_bonus=False, critic_coeff=0.5,
                          loss_critic_type="l2", normalize_advantage=True)
    optim = torch.optim.Adam(loss_fn.parameters(), args.lr)
    sched = torch.optim.lr_scheduler.LinearLR(optim, 1.0, 0.1, max(1, iters - 1))  # lr to 10 % over the budget
    t0, frames, ended = time.time(), 0, []
    for i, batch in enumerate(collector):
        frames += batch.numel()
        m = batch["next", METRIC]
        ended.append(m[~m.isnan()])  # the training episodes that ended in this batch
        with torch.no_grad():
            gae(batch)
        buffer.extend(batch.reshape(-1))
        for _ in range(args.epochs):
            for mb in buffer:
                losses = loss_fn(mb)
                loss = losses["loss_objective"] + losses["loss_critic"]
                optim.zero_grad()
                loss.backward()
                for net in (actor, critic):  # each its own norm: the critic's scale does not throttle the actor
                    nn.utils.clip_grad_norm_(net.parameters(), 1.0)
                optim.step()
        sched.step()
        if i % 10 == 0 or i == iters - 1:
            ended = torch.cat(ended)
            std = actor_net[-1].state_independent_scale.exp().mean().item()
            print(f"{frames:>9,d} frames  {frames / (time.time() - t0):6.0f}/s  action std {std:.3f}  "
                  f"training episodes ended: {ended.numel()}, mean distance {ended.mean().item():.3f} m", flush=True)
            ended = []
    train_s = time.time() - t0
    collector.shutdown()
    env.close()  # the held-out episodes: fresh worlds, one episode each, the mean action
    env = make_env(args.eval_episodes, episode_seconds, args.seed + 1000, args.engine, norm.frozen_copy())
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.rollout(int(round(episode_seconds * 100)), actor, break_when_any_done=False)
    assert td["next", "truncated"][:, -1].all()
    dists = td["next", METRIC][:, -1].numpy()  # (episodes,) at the episodes' last step
    env.close()
    print(f"held-out ({args.eval_episodes} episodes, seed {args.seed + 1000}): mean distance "
          f"{np.mean(dists):.3f} m  (train {frames:,d} frames in {train_s:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
