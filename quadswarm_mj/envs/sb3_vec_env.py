"""Stable-Baselines3 ``VecEnv`` over :class:`~quadswarm_mj.envs.vector_env.QuadSwarmVectorEnv`: one
SB3 env per quad, so SB3 trains one shared policy on the batched engine without SuperSuit::

    from stable_baselines3 import PPO
    from quadswarm_mj.envs.sb3_vec_env import QuadSwarmSB3VecEnv

    venv = QuadSwarmSB3VecEnv(num_envs=16, num_quads=8, scenario="swap_goals")   # 128 SB3 envs
    PPO("MlpPolicy", venv).learn(100_000)

Layout: B worlds of N quads are B * N SB3 envs, world-major (SB3 env ``b * N + i`` is quad ``i`` of
world ``b``); observations (B * N, obs_dim) float32, actions (B * N, 4), rewards the per-quad rewards
(B * N,) float32. All quads of a world end together at the time limit: ``dones`` is True for each of
them, ``infos[k]["TimeLimit.truncated"]`` is True (the quadswarm episodes never terminate, they are
truncated, so SB3 bootstraps from ``infos[k]["terminal_observation"]``, the quad's last observation
of the ended episode); the world is reset in the same step (the returned observation is the new
episode's first). Importing this module imports stable-baselines3 (``pip install
quadswarm_mj[examples]``); the package itself never does.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
from gymnasium import spaces

try:
    from stable_baselines3.common.vec_env.base_vec_env import VecEnv
except ImportError as e:  # pragma: no cover - depends on the environment
    raise ImportError("quadswarm_mj.envs.sb3_vec_env needs stable-baselines3: pip install stable-baselines3 "
                      "(or quadswarm_mj[examples])") from e

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.envs.vector_env import QuadSwarmVectorEnv


class QuadSwarmSB3VecEnv(VecEnv):
    """SB3 ``VecEnv`` of B worlds x N quads = B * N envs (see the module doc).

    Args:
        env: a :class:`QuadSwarmVectorEnv` to wrap (closed with this env), or None to build one from
            ``cfg``, ``num_envs`` (worlds) and ``kwargs`` (``QuadSwarmVectorEnv`` keywords and
            ``EnvConfig`` field overrides, e.g. ``num_quads=8, engine="jax"``).
    """

    def __init__(self, env: QuadSwarmVectorEnv | None = None, cfg: EnvConfig | None = None, num_envs: int = 1,
                 **kwargs: Any):
        if env is None:
            kwargs.setdefault("info_keys", ("rewards",))
            env = QuadSwarmVectorEnv(cfg, num_envs=num_envs, **kwargs)
        elif not isinstance(env, QuadSwarmVectorEnv):
            raise ValueError(f"env must be a QuadSwarmVectorEnv or None, got {type(env).__name__}")
        elif cfg is not None or kwargs:
            raise ValueError("pass either env or cfg/num_envs/keywords, not both")
        if "rewards" not in env.info_keys:
            raise ValueError("the wrapped QuadSwarmVectorEnv must report per-quad rewards (info_keys with 'rewards')")
        self.venv, self.worlds, self.quads = env, env.num_envs, env.cfg.num_quads
        obs, act = env.single_observation_space, env.single_action_space
        observation_space = spaces.Box(obs.low[0], obs.high[0], dtype=np.float32)
        action_space = spaces.Box(act.low[0], act.high[0], dtype=np.float32)
        super().__init__(self.worlds * self.quads, observation_space, action_space)
        self._actions: np.ndarray | None = None
        self.render_mode = None

    # ------------------------------------------------------------------ SB3 API
    def reset(self) -> np.ndarray:
        seed = self._seeds[0] if getattr(self, "_seeds", None) and self._seeds[0] is not None else None
        obs, _ = self.venv.reset(seed=seed)
        if hasattr(self, "_reset_seeds"):
            self._reset_seeds()
        return self._flat_obs(obs)

    def step_async(self, actions: np.ndarray) -> None:
        a = np.asarray(actions, dtype=np.float32)
        if a.shape not in ((self.num_envs, 4), (self.num_envs * 4,)):
            raise ValueError(f"actions must have shape ({self.num_envs}, 4), got {a.shape}")
        self._actions = a.reshape(self.worlds, self.quads, 4)

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        if self._actions is None:
            raise RuntimeError("step_wait() without step_async()")
        obs, _, terminated, truncated, info = self.venv.step(self._actions)
        self._actions = None
        rewards = np.asarray(info["rewards"], dtype=np.float32).reshape(-1)
        world_done = np.asarray(terminated) | np.asarray(truncated)
        dones = np.repeat(world_done, self.quads)
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        if world_done.any():
            final = np.asarray(info["final_obs"])
            for b in np.flatnonzero(world_done):
                for i in range(self.quads):
                    infos[b * self.quads + i] = {
                        "terminal_observation": final[b, i].astype(np.float32),
                        "TimeLimit.truncated": bool(truncated[b] and not terminated[b]),
                    }
        return self._flat_obs(obs), rewards, dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        return [getattr(self.venv, attr_name)] * len(self._indices(indices))

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any) -> list[Any]:
        result = getattr(self.venv, method_name)(*method_args, **method_kwargs)
        return [result] * len(self._indices(indices))

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        return [False] * len(self._indices(indices))

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [None] * self.num_envs

    # ------------------------------------------------------------------ helpers
    def _flat_obs(self, obs: np.ndarray) -> np.ndarray:
        return np.asarray(obs, dtype=np.float32).reshape(self.num_envs, -1)

    def _indices(self, indices: Any) -> Iterable[int]:
        if indices is None:
            return range(self.num_envs)
        if isinstance(indices, int):
            return [indices]
        return list(indices)
