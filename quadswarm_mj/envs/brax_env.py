"""Brax front end: train the MJX swarm with ``brax.training.agents.ppo.train``.

Design choice: ONE POLICY SHARED BY ALL QUADS, the quad axis folded into Brax's batch axis.
Every quad is one Brax "env" (an agent): it observes its own (obs_dim,) observation (own state
relative to its goal and its K nearest neighbours), outputs its own 4 rotor commands and receives
its own reward. ``num_envs`` in ``ppo.train`` therefore counts quads (agents), i.e. worlds x N,
and ``num_timesteps`` counts quad-steps. Why this rather than a centralized policy
(obs N*obs_dim, action N*4, team reward):

* it is the QuadSwarm paper's setting: decentralized control with parameter sharing, the
  observation built for exactly that (neighbour terms relative to the quad, nearest first);
* it is independent of N: the same network flies 2 or 64 quads, and the learner gets N samples
  per world-step instead of one, with per-quad credit assignment (a crash penalizes the quad that
  crashed, not the team mean);
* a centralized policy's input and output grow with N, it is tied to one swarm size and the
  team-mean reward dilutes each quad's credit by 1/N.

The price is that the value function sees only the quad's own observation (as in the paper).

Episodes: every world is reset completely when its time limit is reached
(:class:`~quadswarm_mj.envs.mjx_env.AutoResetWrapper`: dynamics parameters redrawn, motors,
goals, scenario timers and metrics reset), so call ``ppo.train`` with ``wrap_env=False`` (Brax's
own wrappers would reset only the physics data)::

    from brax.training.agents.ppo import train as ppo
    from quadswarm_mj import EnvConfig
    from quadswarm_mj.envs.brax_env import BraxQuadSwarmEnv

    env = BraxQuadSwarmEnv(EnvConfig(num_quads=8, randomize=True))
    make_policy, params, metrics = ppo.train(
        env, wrap_env=False, num_timesteps=10_000_000, episode_length=env.episode_length,
        num_envs=256 * 8, num_eval_envs=32 * 8, batch_size=1024, num_minibatches=16,
        unroll_length=32, action_repeat=1)

Constraints: ``num_envs`` (per device) and ``num_eval_envs`` must be multiples of N (else
``reset`` raises ValueError); keep ``action_repeat=1``. All episode ends are time limits, reported as
``info["truncation"] = 1`` (and ``info["time_out"]``, for ``bootstrap_on_timeout``).

Per-agent ``metrics`` are the reward terms ``"reward/<term>"``; ``info["episode_metrics"]`` holds
Brax's ``sum_reward`` and ``length`` plus the reward-term sums and the swarm's episode metrics
(``success``, ``collisions``, ``floor_hits``, ``wall_hits``, ``ceiling_hits``,
``mean_distance``; per world, repeated for its quads; ``goal_reach_rate`` is left out because it
is NaN when no goal segment was long enough), which Brax logs at episode ends.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.envs.mjx_env import AutoResetWrapper, MjxQuadSwarmEnv

#: Swarm episode metrics forwarded to Brax's episode logger.
SWARM_METRICS = ("success", "collisions", "floor_hits", "wall_hits", "ceiling_hits", "mean_distance")


def _is_typed_key(x: Any) -> bool:
    return jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


class BraxQuadSwarmEnv(Env):
    """A batched Brax ``Env`` of worlds x N agents sharing one policy (see the module docstring).

    ``reset(rng)`` takes one key per agent, shape (E, 2) (or E typed keys), E a multiple of N;
    world ``w`` is reset from the key of its first agent ``w * N``. ``step`` takes actions (E, 4)
    in [-1, 1]. Observations are (E, obs_dim), rewards and dones (E,). Agents of one world are
    consecutive: agent ``w * N + i`` is quad ``i`` of world ``w``. ``state.pipeline_state`` is the
    batched :class:`~quadswarm_mj.envs.mjx_env.State` of the worlds.
    """

    def __init__(self, cfg: EnvConfig | None = None):
        self.mjx_env = MjxQuadSwarmEnv(cfg)
        self.cfg = self.mjx_env.cfg
        self.N = self.cfg.num_quads
        self._env = AutoResetWrapper(self.mjx_env)

    @property
    def observation_size(self) -> int:
        return self.cfg.obs_dim

    @property
    def action_size(self) -> int:
        return 4

    @property
    def backend(self) -> str:
        return "mjx"

    @property
    def episode_length(self) -> int:
        """Control steps per episode (pass as ``episode_length`` to ``ppo.train``)."""
        return self.cfg.episode_steps

    @property
    def dt(self) -> float:
        return self.cfg.control_dt

    # ------------------------------------------------------------------ folding
    def _fold(self, x: jax.Array) -> jax.Array:
        """(W, N, ...) -> (W * N, ...)."""
        return x.reshape((-1,) + x.shape[2:])

    def _per_agent(self, x: jax.Array) -> jax.Array:
        """(W,) per-world values -> (W * N,) repeated for each quad."""
        return jnp.repeat(x, self.N, axis=0)

    def _world_keys(self, rng: jax.Array) -> jax.Array:
        batched = rng.ndim >= (1 if _is_typed_key(rng) else 2)
        if not batched:
            rng = rng[None]
            return rng
        e = rng.shape[0]
        if e % self.N != 0:
            raise ValueError(f"the number of Brax envs (agents) must be a multiple of num_quads={self.N} "
                             f"(per device), got {e}")
        return rng[::self.N]

    def _episode_metrics(self, core: Any, sums: dict[str, jax.Array]) -> dict[str, jax.Array]:
        out = dict(sums)
        for k in SWARM_METRICS:
            out[k] = self._per_agent(core.info["episode_metrics"][k]).astype(jnp.float32)
        return out

    # ------------------------------------------------------------------ API
    def reset(self, rng: jax.Array) -> State:
        core = jax.vmap(self._env.reset)(self._world_keys(rng))
        e = core.reward.shape[0] * self.N
        zero = jnp.zeros((e,), jnp.float32)
        metrics = {k: self._fold(v).astype(jnp.float32) for k, v in core.metrics.items()}
        sums = {"sum_reward": zero, "length": zero, **{k: zero for k in metrics}}
        info = {"steps": zero, "truncation": zero, "time_out": zero, "episode_done": zero,
                "episode_metrics": self._episode_metrics(core, sums)}
        return State(pipeline_state=core, obs=self._fold(core.obs).astype(jnp.float32), reward=zero, done=zero,
                     metrics=metrics, info=info)

    def step(self, state: State, action: jax.Array) -> State:
        core = state.pipeline_state
        w = core.reward.shape[0]
        core = self._env.vstep(core, action.reshape(w, self.N, 4))
        reward = self._fold(core.reward).astype(jnp.float32)
        done = self._per_agent(core.done).astype(jnp.float32)
        metrics = {k: self._fold(v).astype(jnp.float32) for k, v in core.metrics.items()}
        keep = 1.0 - state.info["episode_done"]  # accumulators restart after an episode end
        old = state.info["episode_metrics"]
        sums = {"sum_reward": old["sum_reward"] * keep + reward, "length": old["length"] * keep + 1.0,
                **{k: old[k] * keep + v for k, v in metrics.items()}}
        info = {"steps": state.info["steps"] * keep + 1.0, "truncation": done, "time_out": done,
                "episode_done": done, "episode_metrics": self._episode_metrics(core, sums)}
        return State(pipeline_state=core, obs=self._fold(core.obs).astype(jnp.float32), reward=reward, done=done,
                     metrics=metrics, info=info)
