"""Brax front end: train the MJX swarm with ``brax.training.agents.ppo.train``.

One policy shared by all quads: the quad axis is folded into Brax's batch axis, so every quad is one
Brax "env" (agent) with its own observation, 4 rotor commands and reward; ``num_envs`` counts quads
(worlds x N, a multiple of N) and ``num_timesteps`` quad-steps. Worlds are reset completely at their time
limit (:class:`~quadswarm_mj.envs.mjx_env.AutoResetWrapper`): call ``ppo.train`` with ``wrap_env=False``
and ``action_repeat=1``. Episode ends are time limits (``info["truncation"]``, ``info["time_out"]``);
``info["episode_metrics"]`` carries the reward-term sums and :data:`SWARM_METRICS`. Usage, the
rationale and the constraints: docs/training.md ("Brax's trainer").
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
