"""CleanRL-style single-file PPO in JAX on ``MjxQuadSwarmEnv``: rollouts (``lax.scan`` over a ``vmap`` of
worlds) and updates (optax) in one jitted iteration; no torch, no flax.

One policy shared by every quad (the quad axis folded into the batch), Gaussian actions with a learned
state-independent log std, observations scaled by the env (``normalize_obs=True``), GAE with time-limit ends
bootstrapped from the episode's last observation, the learning rate decaying linearly to 10 %.

    python examples/jax_ppo_cleanrl.py --total-steps 4000000       # the recorded run (docs/examples.md)
    python examples/jax_ppo_cleanrl.py --smoke                     # a few hundred steps (CI)

``--total-steps`` counts agent-steps (quads x control steps). The held-out evaluation flies
``--eval-episodes`` worlds (key from ``--seed + 1000``) with the mean action and prints the mean distance to
the goal over the episode (``mean_distance``) and at its end.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from quadswarm_mj import EnvConfig
from quadswarm_mj.envs.mjx_env import AutoResetWrapper, MjxQuadSwarmEnv


def init_mlp(key: jax.Array, sizes: list[int], last_scale: float) -> list[tuple[jax.Array, jax.Array]]:
    """Orthogonal init (CleanRL's): sqrt(2) gain for the hidden layers, ``last_scale`` for the output."""
    keys = jax.random.split(key, len(sizes) - 1)
    gains = [np.sqrt(2.0)] * (len(sizes) - 2) + [last_scale]
    return [(jax.nn.initializers.orthogonal(g)(k, (a, b)), jnp.zeros(b))
            for k, a, b, g in zip(keys, sizes[:-1], sizes[1:], gains)]


def mlp(params: list, x: jax.Array) -> jax.Array:
    for w, b in params[:-1]:
        x = jnp.tanh(x @ w + b)
    return x @ params[-1][0] + params[-1][1]


def log_prob(mean: jax.Array, log_std: jax.Array, a: jax.Array) -> jax.Array:
    return jnp.sum(-0.5 * ((a - mean) / jnp.exp(log_std)) ** 2 - log_std - 0.5 * jnp.log(2 * jnp.pi), axis=-1)


def make_train(args: argparse.Namespace, cfg: EnvConfig):
    env = AutoResetWrapper(MjxQuadSwarmEnv(cfg))
    W, T, N, D = args.worlds, args.unroll, cfg.num_quads, env.observation_size
    iters = max(1, args.total_steps // (W * T * N))
    batch = W * T * N
    mb = batch // args.minibatches
    sched = optax.linear_schedule(args.lr, 0.1 * args.lr, iters * args.epochs * args.minibatches)
    tx = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(sched))

    def init(key):
        kp, kv, ke = jax.random.split(key, 3)
        params = {"pi": init_mlp(kp, [D, 64, 64, 4], 0.01), "v": init_mlp(kv, [D, 64, 64, 1], 1.0),
                  "log_std": jnp.full(4, -0.5)}
        return params, tx.init(params), jax.vmap(env.reset)(jax.random.split(ke, W))

    def rollout_step(carry, _):
        params, s, key = carry
        key, k = jax.random.split(key)
        obs = s.obs.reshape(W * N, D)
        mean, value = mlp(params["pi"], obs), mlp(params["v"], obs)[:, 0]
        act = mean + jnp.exp(params["log_std"]) * jax.random.normal(k, mean.shape)
        s1 = jax.vmap(env.env.step)(s, act.reshape(W, N, 4))  # the raw step: s1.obs is the episode's last
        done = jnp.repeat(s1.done, N)  # the episodes only end by the time limit: bootstrap from V(last obs)
        reward = s1.reward.reshape(-1) + args.gamma * done * mlp(params["v"], s1.obs.reshape(W * N, D))[:, 0]
        ended = s1.done.sum()
        md = jnp.where(ended > 0, jnp.sum(s1.done * s1.info["episode_metrics"]["mean_distance"]) / ended, jnp.nan)
        return (params, env.renew_finished(s1), key), (obs, act, log_prob(mean, params["log_std"], act), value,
                                                       reward, done, md)

    def loss_fn(params, obs, act, logp_old, adv, ret):
        mean, value = mlp(params["pi"], obs), mlp(params["v"], obs)[:, 0]
        ratio = jnp.exp(log_prob(mean, params["log_std"], act) - logp_old)
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        pg = -jnp.minimum(ratio * adv, jnp.clip(ratio, 1 - args.clip, 1 + args.clip) * adv).mean()
        return pg + 0.5 * ((value - ret) ** 2).mean()

    def iteration(state, _):
        params, opt, s, key = state
        (_, s, key), (obs, act, logp, val, rew, done, md) = jax.lax.scan(rollout_step, (params, s, key), None, T)
        last_v = mlp(params["v"], s.obs.reshape(W * N, D))[:, 0]

        def gae(carry, x):
            adv, next_v = carry
            r, v, d = x
            delta = r + args.gamma * next_v * (1 - d) - v
            adv = delta + args.gamma * args.gae_lambda * (1 - d) * adv
            return (adv, v), adv

        _, adv = jax.lax.scan(gae, (jnp.zeros(W * N), last_v), (rew, val, done), reverse=True)
        data = [x.reshape(batch, *x.shape[2:]) for x in (obs, act, logp, adv, adv + val)]

        def epoch(carry, k):
            params, opt = carry
            perm = jax.random.permutation(k, batch).reshape(args.minibatches, mb)

            def minibatch(carry, idx):
                params, opt = carry
                grads = jax.grad(loss_fn)(params, *[x[idx] for x in data])
                updates, opt = tx.update(grads, opt, params)
                return (optax.apply_updates(params, updates), opt), None

            return jax.lax.scan(minibatch, (params, opt), perm)[0], None

        key, k = jax.random.split(key)
        (params, opt), _ = jax.lax.scan(epoch, (params, opt), jax.random.split(k, args.epochs))
        return (params, opt, s, key), (jnp.nanmean(md), rew.mean())

    return init, jax.jit(iteration), iters, env


def evaluate(env: AutoResetWrapper, params: dict, episodes: int, key: jax.Array) -> dict[str, float]:
    """Fresh worlds flown for one episode with the mean action (no reset at the end)."""
    s = jax.vmap(env.reset)(jax.random.split(key, episodes))

    def step(s, _):
        return jax.vmap(env.env.step)(s, mlp(params["pi"], s.obs)), None

    s, _ = jax.jit(lambda s: jax.lax.scan(step, s, None, env.episode_length))(s)
    final = jnp.linalg.norm(s.info["state"]["pos"] - s.info["goals"], axis=-1)
    return {"mean_distance": float(s.info["episode_metrics"]["mean_distance"].mean()),
            "final_distance": float(final.mean()), "success": float(s.info["episode_metrics"]["success"].mean())}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--total-steps", type=int, default=4_000_000, help="agent-steps (the lr schedule's span)")
    p.add_argument("--num-quads", type=int, default=1)
    p.add_argument("--scenario", default="static_same_goal")
    p.add_argument("--worlds", type=int, default=1024)
    p.add_argument("--unroll", type=int, default=32, help="control steps per world per iteration")
    p.add_argument("--epochs", type=int, default=4)
    p.add_argument("--minibatches", type=int, default=32)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--gamma", type=float, default=0.99)
    p.add_argument("--gae-lambda", type=float, default=0.95)
    p.add_argument("--clip", type=float, default=0.2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eval-episodes", type=int, default=20)
    p.add_argument("--smoke", action="store_true", help="a few hundred steps on 0.5 s episodes (CI)")
    args = p.parse_args()
    episode_seconds = 15.0
    if args.smoke:
        args.total_steps, args.worlds, args.unroll, args.minibatches, args.eval_episodes = 256, 4, 16, 2, 2
        episode_seconds = 0.5
    cfg = EnvConfig(num_quads=args.num_quads, scenario=args.scenario, rewards={"pos": 3.0}, normalize_obs=True,
                    episode_seconds=episode_seconds)
    init, iteration, iters, env = make_train(args, cfg)
    params, opt, s = init(jax.random.key(args.seed))
    state = (params, opt, s, jax.random.key(args.seed + 1))
    t0, last_md = time.time(), float("nan")
    for i in range(iters):
        state, (md, rew) = iteration(state, None)
        last_md = float(md) if np.isfinite(float(md)) else last_md  # NaN in iterations where no episode ended
        if i % 10 == 0 or i == iters - 1:
            steps = (i + 1) * args.worlds * args.unroll * args.num_quads
            print(f"iter {i + 1}/{iters}  {steps:>10,d} agent-steps  {steps / (time.time() - t0):7.0f}/s  reward/step "
                  f"{float(rew):+.4f}  last ended episodes' mean distance {last_md:.3f} m", flush=True)
    train_s = time.time() - t0
    r = evaluate(env, state[0], args.eval_episodes, jax.random.key(args.seed + 1000))
    print(f"held-out ({args.eval_episodes} episodes, key {args.seed + 1000}): "
          f"mean distance {r['mean_distance']:.3f} m, "
          f"final distance {r['final_distance']:.3f} m, success {r['success']:.2f}  (train {train_s:.0f} s incl. "
          f"compile)", flush=True)


if __name__ == "__main__":
    main()
