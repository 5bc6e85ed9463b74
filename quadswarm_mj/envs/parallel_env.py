"""``QuadSwarmParallelEnv``: the swarm as a PettingZoo ``ParallelEnv``.

Agents ``quad_0`` ... ``quad_{N-1}``; each has its own observation (obs_dim,), action (4,) in
[-1, 1] and reward (its per-quad reward). ``state()`` is the global state: for every quad
[p (3), v (3), R row-major (9), omega (3), goal (3)] concatenated, (21 N,). All agents are
truncated together at the time limit; there is no termination. Built on ``QuadSwarmEnv``
(``engine="mujoco"`` or ``"jax"``, passed through).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.control_modes import action_box_bounds
from quadswarm_mj.envs.flat_info import agent_flattener
from quadswarm_mj.envs.gym_env import QuadSwarmEnv, make_config
from quadswarm_mj.envs.validation import as_real_array
from quadswarm_mj.sensors import DECK_INFO_KEYS

#: the reset option key PettingZoo's ``parallel_api_test`` passes (ignored; any other unknown key raises)
PETTINGZOO_PROBE = "options"


class QuadSwarmParallelEnv(ParallelEnv):
    """PettingZoo parallel API over one world of N quads."""

    metadata = {"render_modes": ["rgb_array"], "name": "quadswarm_v0", "render_fps": 100, "is_parallelizable": True}

    def __init__(self, cfg: EnvConfig | None = None, render_mode: str | None = None, engine: str = "mujoco",
                 **kwargs: Any):
        self.cfg = make_config(cfg, kwargs)
        self.metadata = {**self.metadata, "render_fps": self.cfg.control_hz}  # one frame per control step
        self.env = QuadSwarmEnv(self.cfg.replace(info_mode="nested"), render_mode=render_mode, engine=engine)
        self._flat = agent_flattener(self.cfg) if self.cfg.info_mode == "flat" else None  # envs/flat_info.py
        self.render_mode = render_mode
        n = self.cfg.num_quads
        self.possible_agents = [f"quad_{i}" for i in range(n)]
        self.agents: list[str] = []
        box = self.env.observation_space
        low = box.low.reshape(-1, self.cfg.obs_dim)[0]
        high = box.high.reshape(-1, self.cfg.obs_dim)[0]
        self.observation_spaces = {a: spaces.Box(low, high, dtype=np.float32) for a in self.possible_agents}
        box = action_box_bounds(self.cfg, (4,))  # physical bounds of cfg.control_mode ([-1, 1]: rotor)
        self.action_spaces = {a: spaces.Box(*box, dtype=np.float32) for a in self.possible_agents}
        L, W, H = self.cfg.room_size
        per = np.array([L, W, H] + [20.0] * 3 + [1.0] * 9 + [self.cfg.quad.max_omega] * 3 + [L, W, H], np.float32)
        self.state_space = spaces.Box(-np.tile(per, n), np.tile(per, n), dtype=np.float32)
        self._last_info: dict[str, Any] = {}

    def observation_space(self, agent: str) -> spaces.Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Box:
        return self.action_spaces[agent]

    def _split_obs(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        obs = obs.reshape(self.cfg.num_quads, self.cfg.obs_dim)
        return {a: obs[i] for i, a in enumerate(self.possible_agents)}

    def _agent_infos(self, info: dict[str, Any]) -> dict[str, dict[str, Any]]:
        out = {}
        for i, a in enumerate(self.possible_agents):
            d = {"state": {k: v[i].copy() for k, v in info["state"].items()}, "goal": info["goals"][i].copy(),
                 "goal_vel": info["goal_vel"][i].copy()}
            if "reward_terms" in info:
                d["reward_terms"] = {k: float(v[i]) for k, v in info["reward_terms"].items()}
            if "episode_metrics" in info:
                d["episode_metrics"] = dict(info["episode_metrics"])
            if "obstacles" in info:  # (M, 2) column centres (x, y) in m, world frame, the same for every agent
                d["obstacles"] = info["obstacles"].copy()
            for k in DECK_INFO_KEYS:  # the agent's deck sensor readings (quadswarm_mj.sensors.deck_info)
                if k in info:
                    d[k] = info[k][i].copy()
            out[a] = d if self._flat is None else self._flat(d)
        return out

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode (``options`` as ``QuadSwarmEnv.reset``; other keys raise ValueError, except
        ``"options"``: PettingZoo's ``parallel_api_test`` passes ``{"options": 1}`` to see that reset takes
        options, and that key alone is ignored)."""
        if isinstance(options, dict) and PETTINGZOO_PROBE in options:
            options = {k: v for k, v in options.items() if k != PETTINGZOO_PROBE}
        obs, info = self.env.reset(seed=seed, options=options)
        self.agents = list(self.possible_agents)
        self._last_info = info
        return self._split_obs(obs), self._agent_infos(info)

    def step(self, actions: dict[str, Any]):
        self.env._check_open()
        if not self.agents:
            raise RuntimeError("call reset() before step() (and after the episode ends)")
        if not isinstance(actions, dict):
            raise ValueError(f"actions must be a dict {{agent: action}} with one entry per live agent "
                             f"({self.possible_agents[:3]}...), got {type(actions).__name__}")
        missing = [a for a in self.agents if a not in actions]
        unknown = [a for a in actions if a not in self.possible_agents]
        if missing or unknown:
            raise ValueError(f"actions must have one entry per live agent; missing {missing}, unknown {unknown}")
        per_agent = [as_real_array(actions[a], f"actions['{a}']") for a in self.possible_agents]
        for a, x in zip(self.possible_agents, per_agent):
            if x.shape != (4,):
                raise ValueError(f"each agent's action must have shape (4,); actions['{a}'] has shape {x.shape}")
        act = np.stack(per_agent)
        obs, _, terminated, truncated, info = self.env.step(act[0] if self.cfg.num_quads == 1 else act)
        self._last_info = info
        rewards = {a: float(info["rewards"][i]) for i, a in enumerate(self.possible_agents)}
        terminations = {a: bool(terminated) for a in self.possible_agents}
        truncations = {a: bool(truncated) for a in self.possible_agents}
        infos = self._agent_infos(info)
        if terminated or truncated:
            self.agents = []
        return self._split_obs(obs), rewards, terminations, truncations, infos

    def state(self) -> np.ndarray:
        """Global state (21 N,) float32: per quad p, v, R (row-major), omega (body), goal."""
        info = self._last_info
        s = info["state"]
        n = self.cfg.num_quads
        per = np.concatenate([s["pos"], s["vel"], s["rot"].reshape(n, 9), s["omega"], info["goals"]], axis=-1)
        return np.clip(per.reshape(-1), self.state_space.low, self.state_space.high).astype(np.float32)

    def render(self) -> np.ndarray | None:
        return self.env.render()

    def close(self) -> None:
        self.env.close()


def parallel_env(**kwargs: Any) -> QuadSwarmParallelEnv:
    """PettingZoo-style constructor: ``parallel_env(num_quads=8, scenario="swap_goals")``."""
    return QuadSwarmParallelEnv(**kwargs)
