"""skrl PPO on the PettingZoo API: IPPO (skrl's independent PPO), every quad a PettingZoo agent.

The agents share one policy and one value network (parameter sharing: the same model objects for every agent,
each agent's batch updating them in turn), with skrl's running observation and value normalizers, and
time-limit ends bootstrapped (``time_limit_bootstrap``). Training runs on ``BatchedParallelEnv``: PettingZoo's
parallel API over the W worlds of ``QuadSwarmVectorEnv`` (every value with a leading world axis, which skrl's
PettingZoo wrapper reads from ``num_envs``; one jitted engine call per step). ``--worlds 1`` trains on
``quadswarm_v0.parallel_env`` itself (one world: about 1.5 ms of CPU per agent-step in skrl). As in
``sb3_ppo_swarm.py``: the neighbour inputs start at zero weight, no collision/proximity penalty.

    python examples/skrl_ppo_pettingzoo.py                          # the recorded run (docs/examples.md)
    python examples/skrl_ppo_pettingzoo.py --smoke                  # a few hundred steps (CI)

``--total-steps`` counts env steps (each steps every quad of every world). The held-out evaluation flies
``--eval-episodes`` episodes of ``quadswarm_v0.parallel_env`` (seeds from ``--seed + 1000``) with the mean
actions and prints the episode metrics.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
import torch.nn as nn
from gymnasium import spaces
from skrl.envs.wrappers.torch import wrap_env
from skrl.memories.torch import RandomMemory
from skrl.models.torch import DeterministicMixin, GaussianMixin, Model
from skrl.multi_agents.torch.ippo import IPPO, IPPO_CFG
from skrl.resources.preprocessors.torch import RunningStandardScaler
from skrl.trainers.torch import SequentialTrainer
from skrl.utils import set_seed

from quadswarm_mj import EnvConfig, QuadSwarmVectorEnv, quadswarm_v0


class BatchedParallelEnv:
    """PettingZoo's parallel API over ``QuadSwarmVectorEnv``: agent ``quad_i`` gets (W, ...) arrays, one row per
    world; same-step auto-reset (skrl's trainer expects it when ``num_envs > 1``)."""

    def __init__(self, cfg: EnvConfig, worlds: int, engine: str):
        self.venv = QuadSwarmVectorEnv(cfg, num_envs=worlds, engine=engine, info_keys=("rewards",))
        self.num_envs, n = worlds, cfg.num_quads
        self.possible_agents = [f"quad_{i}" for i in range(n)]
        self.agents = list(self.possible_agents)
        o, a = self.venv.single_observation_space, self.venv.single_action_space
        self.observation_spaces = {u: spaces.Box(o.low[i], o.high[i]) for i, u in enumerate(self.possible_agents)}
        self.action_spaces = {u: spaces.Box(a.low[i], a.high[i]) for i, u in enumerate(self.possible_agents)}
        self.state_space = spaces.Box(o.low.ravel(), o.high.ravel())  # the joint observation (IPPO ignores it)

    def reset(self, seed: int | None = None, options: dict | None = None):
        self.obs, _ = self.venv.reset(seed=seed)
        return {u: self.obs[:, i] for i, u in enumerate(self.possible_agents)}, {u: {} for u in self.agents}

    def step(self, actions: dict):
        act = np.clip(np.stack([actions[u] for u in self.possible_agents], axis=1), -1.0, 1.0)
        self.obs, _, terminated, truncated, info = self.venv.step(act)
        split = {u: self.obs[:, i] for i, u in enumerate(self.possible_agents)}
        return (split, {u: info["rewards"][:, i] for i, u in enumerate(self.possible_agents)},
                {u: terminated for u in self.agents}, {u: truncated for u in self.agents}, {u: {} for u in self.agents})

    def state(self) -> np.ndarray:
        return self.obs.reshape(self.num_envs, -1)

    def close(self) -> None:
        self.venv.close()


def mlp(n_in: int, n_out: int, own: int) -> nn.Sequential:
    """MLP 64-64 tanh; the inputs past the first ``own`` (the neighbours, when ``own < n_in``) start at zero weight."""
    net = nn.Sequential(nn.Linear(n_in, 64), nn.Tanh(), nn.Linear(64, 64), nn.Tanh(), nn.Linear(64, n_out))
    with torch.no_grad():
        net[0].weight[:, own:] = 0.0
    return net


class Policy(GaussianMixin, Model):
    """Gaussian policy: MLP 64-64 (tanh) for the mean, a learned state-independent log std."""

    def __init__(self, observation_space, action_space, own: int, device=None):
        Model.__init__(self, observation_space=observation_space, action_space=action_space, device=device)
        GaussianMixin.__init__(self, clip_actions=False)  # the env clips actions into [-1, 1]
        self.net = mlp(self.num_observations, self.num_actions, own)
        self.log_std = nn.Parameter(torch.full((self.num_actions,), -0.5))

    def compute(self, inputs, role=""):
        return self.net(inputs["observations"]), {"log_std": self.log_std}


class Value(DeterministicMixin, Model):
    def __init__(self, observation_space, action_space, own: int, device=None):
        Model.__init__(self, observation_space=observation_space, action_space=action_space, device=device)
        DeterministicMixin.__init__(self)
        self.net = mlp(self.num_observations, 1, own)

    def compute(self, inputs, role=""):
        return self.net(inputs["observations"]), {}


def evaluate(agent: IPPO, env_kwargs: dict, episodes: int, seed: int) -> dict[str, float]:
    """Episodes flown with the policy's mean actions; episode-metric means over episodes."""
    env = quadswarm_v0.parallel_env(**env_kwargs)
    metrics = []
    for ep in range(episodes):
        obs, infos = env.reset(seed=seed + ep)
        while env.agents:
            with torch.no_grad():
                acts = {}
                for uid, o in obs.items():
                    x = agent._observation_preprocessor[uid](torch.as_tensor(o[None], dtype=torch.float32))
                    acts[uid] = agent.policies[uid].act({"observations": x}, role="policy")[1]["mean_actions"][0]
            obs, _, _, _, infos = env.step({uid: a.numpy() for uid, a in acts.items()})
        metrics.append(infos[env.possible_agents[0]]["episode_metrics"])
    env.close()
    return {k: float(np.mean([m[k] for m in metrics])) for k in ("mean_distance", "success", "collisions")}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--total-steps", type=int, default=28_000, help="env steps (every quad of every world acts)")
    p.add_argument("--num-quads", type=int, default=4)
    p.add_argument("--scenario", default="static_diff_goal", help="quadswarm_mj.list_scenarios()")
    p.add_argument("--worlds", type=int, default=64, help="worlds stepped together (1: quadswarm_v0.parallel_env)")
    p.add_argument("--rollouts", type=int, default=64, help="env steps per PPO update")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--mini-batches", type=int, default=4, help="minibatches per agent per epoch")
    p.add_argument("--engine", choices=("jax", "mujoco"), default="jax", help="the smoke test uses mujoco (no compile)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eval-episodes", type=int, default=5)
    p.add_argument("--random-neighbor-init", action="store_true", help="keep torch's init of the neighbour inputs")
    p.add_argument("--reward", action="append", default=[], metavar="TERM=SCALE",
                   help="reward scale overrides (repeatable), e.g. quad_collision=5 (the paper's)")
    p.add_argument("--smoke", action="store_true", help="a few hundred steps on 0.5 s episodes (CI)")
    args = p.parse_args()
    rewards = {"pos": 3.0, "quad_collision": 0.0, "proximity": 0.0,  # no collision penalty (docs/examples.md)
               **{k: float(v) for k, v in (r.split("=") for r in args.reward)}}
    env_kwargs = {"num_quads": args.num_quads, "scenario": args.scenario, "rewards": rewards,
                  "engine": args.engine}
    if args.smoke:
        args.total_steps, args.rollouts, args.eval_episodes, args.worlds = 150, 50, 1, 2
        env_kwargs.update(episode_seconds=0.5, engine="mujoco")
    set_seed(args.seed)  # torch and skrl's env seed
    torch.set_num_threads(1)  # small networks: one thread, and no contention with the JAX engine's threads
    if args.worlds == 1:
        raw = quadswarm_v0.parallel_env(**env_kwargs)
    else:
        cfg = EnvConfig(**{k: v for k, v in env_kwargs.items() if k != "engine"})
        raw = BatchedParallelEnv(cfg, args.worlds, env_kwargs["engine"])
    env = wrap_env(raw, wrapper="pettingzoo")
    obs_space, act_space = env.observation_spaces[env.possible_agents[0]], env.action_spaces[env.possible_agents[0]]
    # the neighbour inputs (after the quad's own block) start at zero weight: each quad first learns its goal
    own = obs_space.shape[0] if args.random_neighbor_init else EnvConfig(num_quads=args.num_quads).self_obs_dim
    policy, value = Policy(obs_space, act_space, own), Value(obs_space, act_space, own)  # shared by every quad
    def each(v: dict) -> dict:
        return {uid: v for uid in env.possible_agents}

    models = {uid: {"policy": policy, "value": value} for uid in env.possible_agents}
    memories = {uid: RandomMemory(memory_size=args.rollouts, num_envs=env.num_envs) for uid in env.possible_agents}
    cfg = IPPO_CFG(rollouts=args.rollouts, learning_epochs=4, mini_batches=args.mini_batches, learning_rate=args.lr,
                   discount_factor=0.99, gae_lambda=0.95, grad_norm_clip=1.0, entropy_loss_scale=0.0,
                   value_loss_scale=1.0, time_limit_bootstrap=True,
                   observation_preprocessor=RunningStandardScaler,
                   value_preprocessor=RunningStandardScaler,
                   # dict-valued settings per agent (skrl reads a dict as agent -> value)
                   observation_preprocessor_kwargs=each({"size": obs_space}),
                   value_preprocessor_kwargs=each({"size": 1}),
                   state_preprocessor_kwargs=each({}), learning_rate_scheduler_kwargs=each({}))
    agent = IPPO(possible_agents=env.possible_agents, models=models, memories=memories,
                 observation_spaces=env.observation_spaces, action_spaces=env.action_spaces,
                 state_spaces=env.state_spaces, cfg=cfg)
    trainer = SequentialTrainer(env=env, agents=agent, cfg={"timesteps": args.total_steps, "headless": True,
                                                            "disable_progressbar": None,
                                                            "close_environment_at_exit": False})
    t0 = time.time()
    trainer.train()
    train_s = time.time() - t0
    print(f"trained {args.total_steps:,d} env steps x {args.worlds} worlds x {args.num_quads} quads in {train_s:.0f} s",
          flush=True)
    env.close()
    r = evaluate(agent, env_kwargs, args.eval_episodes, seed=args.seed + 1000)
    print(f"held-out ({args.eval_episodes} episodes, seeds {args.seed + 1000}+, {args.scenario}, {args.num_quads} "
          f"quads): mean distance {r['mean_distance']:.3f} m, success {r['success']:.2f}, collisions/quad "
          f"{r['collisions']:.2f}  (train {train_s:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
