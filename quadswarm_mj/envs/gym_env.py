"""``QuadSwarmEnv``: a Gymnasium env of one world of N quads on CPU MuJoCo.

Spaces: observation (N, obs_dim) float32 and action (N, 4) in [-1, 1]; flattened to (obs_dim,)
and (4,) when N = 1. ``step`` returns the team reward (mean over quads, a float) so any
single-agent library works; per-quad rewards are in ``info["rewards"]``. Episodes end by
truncation after ``episode_seconds`` (1500 control steps by default), never by termination.

``engine="mujoco"`` (default, the reference) steps CPU MuJoCo; ``engine="jax"`` runs the same model
on MJX through :class:`quadswarm_mj.envs.jax_engine.JaxSingleBackend` (same spaces, info keys,
validation and seeding contract; float32, its own random streams).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.envs.registration import EnvSpec

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.control_modes import action_box_bounds
from quadswarm_mj.envs.cpu_core import CpuSwarm, PhysicsInstabilityError
from quadswarm_mj.envs.flat_info import gym_flattener
from quadswarm_mj.envs.validation import check_action, check_engine, check_obstacles, check_state
from quadswarm_mj.observations import obs_bounds

#: the keys ``QuadSwarmEnv.reset`` accepts in ``options``
RESET_OPTIONS = ("obstacles", "state")


def make_config(cfg: EnvConfig | None, kwargs: dict[str, Any]) -> EnvConfig:
    """``cfg`` with keyword overrides (EnvConfig field names), validated."""
    if cfg is None:
        return EnvConfig(**kwargs)
    if not isinstance(cfg, EnvConfig):
        raise ValueError(f"cfg must be an EnvConfig, got {type(cfg).__name__}")
    return cfg.replace(**kwargs) if kwargs else cfg


class QuadSwarmEnv(gym.Env):
    """One world of ``cfg.num_quads`` Crazyflies under per-rotor thrust control."""

    #: ``render_fps`` is set per instance to the control rate (``cfg.control_hz``): one frame per step.
    metadata = {"render_modes": ["rgb_array"], "render_fps": 100}
    _spec: EnvSpec | None = None

    @property
    def spec(self) -> EnvSpec | None:  # type: ignore[override]
        """``gym.make``'s spec, with ``max_episode_steps`` = the env's own time limit (``cfg.episode_steps``;
        the env truncates itself, so no ``TimeLimit`` wrapper is added)."""
        return self._spec

    @spec.setter
    def spec(self, value: EnvSpec | None) -> None:
        if value is not None and value.max_episode_steps is None:
            value = dataclasses.replace(value, max_episode_steps=self.cfg.episode_steps)
        self._spec = value

    def __init__(self, cfg: EnvConfig | None = None, render_mode: str | None = None, engine: str = "mujoco",
                 **kwargs: Any):
        self.cfg = make_config(cfg, kwargs)
        self.engine = check_engine(engine)
        self.metadata = {**self.metadata, "render_fps": self.cfg.control_hz}
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        self.render_mode = render_mode
        self._jax: Any = None
        if self.engine == "jax":
            from quadswarm_mj.envs.jax_engine import JaxSingleBackend

            self._jax = JaxSingleBackend(self.cfg)
        else:
            # without columns the engine steps a model without the visual geoms (half MuJoCo's kinematics; the
            # same dynamics; the decks cast analytically), and the renderer draws a visual twin (CpuSwarm.visual_arena)
            lean = self.cfg.obstacles is None
            self.core = CpuSwarm(self.cfg, num_worlds=1, visual=not lean)
        n, d = self.cfg.num_quads, self.cfg.obs_dim
        low, high = obs_bounds(self.cfg)
        if self.cfg.normalize_obs:
            scale = np.maximum(np.abs(low), np.abs(high))
            low, high = low / scale, high / scale
        self.single = n == 1
        obs_shape = (d,) if self.single else (n, d)
        act_shape = (4,) if self.single else (n, 4)
        self.observation_space = spaces.Box(np.broadcast_to(low, obs_shape).astype(np.float32),
                                            np.broadcast_to(high, obs_shape).astype(np.float32), dtype=np.float32)
        self.action_space = spaces.Box(*action_box_bounds(self.cfg, act_shape), dtype=np.float32)
        self._renderer: Any = None
        self._needs_reset = True
        self._seeded = False
        self._params: dict[str, np.ndarray] = {}  # world 0's dynamics parameters of the episode (set by reset)
        self.closed = False
        self._flat = gym_flattener(self.cfg) if self.cfg.info_mode == "flat" else None  # envs/flat_info.py
        self._control_dt = self.cfg.control_dt

    # ------------------------------------------------------------------ helpers
    def _obs(self, obs: np.ndarray) -> np.ndarray:
        o = obs[0].astype(np.float32)
        return o[0] if self.single else o

    def _info(self) -> dict[str, Any]:
        """The info entries of reset and step: fresh copies (nothing shared with the engine or with
        another call's info)."""
        c = self.core
        q, v = c.qpos[0], c.qvel[0]  # world 0's (N, 7), (N, 6) views: c.state_dict()'s values, world 0 only
        rot = c._rotations()[0].copy()
        st = c.state
        scn = st.scenario
        idx = self.__dict__.get("_info_idx")
        if idx is None:  # flat indices of world 0's positions in qpos (None: offsets not all +0.0) and velocities
            n, o = self.cfg.num_quads, c.offsets[0]
            rows = np.arange(n)[:, None]
            idx = self._info_idx = (7 * rows + np.arange(3) if not np.any(o) and not np.signbit(o).any() else None,
                                    6 * rows + np.arange(3) + np.array([[[0]], [[3]]]))
        # q - 0.0 is q (signs of zero included): with offsets +0.0 the positions are a gather of qpos
        pos = q[:, :3] - c.offsets[0] if idx[0] is None else q.take(idx[0])
        vo = v.take(idx[1])  # (vel, omega): two rows of one fresh array
        return {
            "state": {"pos": pos, "vel": vo[0], "rot": rot, "omega": vo[1], "thrust": st.thrust[0].copy()},
            "goals": scn.goals[0].copy(),
            "goal_vel": scn.goal_vel[0].copy(),
            "params": {k: v.copy() for k, v in self._params.items()},
            "on_floor": st.on_floor[0].copy(),
            "time": int(st.step[0]) * self._control_dt,
            **({"obstacles": c.obstacle_centres(0)} if c.omap is not None else {}),
        }

    def _info_out(self, info: dict[str, Any], obs: np.ndarray | None = None) -> dict[str, Any]:
        """``info`` as returned: nested, or flat with ``cfg.info_mode="flat"`` (envs/flat_info.py); with
        the deck sensors on, their readings from ``obs`` (N, obs_dim) (``quadswarm_mj.sensors.deck_info``)."""
        if obs is not None and self.cfg.sensors.any:
            deck = self.__dict__.get("_deck_info_args")
            if deck is None:  # (deck_info of an observation, its shape), made once
                from quadswarm_mj.observations import obs_scale
                from quadswarm_mj.sensors import numpy_deck_info

                deck = self._deck_info_args = (numpy_deck_info(
                    self.cfg, obs_scale(self.cfg) if self.cfg.normalize_obs else None),
                    (self.cfg.num_quads, self.cfg.obs_dim))
            info.update(deck[0](obs.reshape(deck[1]) if type(obs) is np.ndarray else np.reshape(obs, deck[1])))
        return info if self._flat is None else self._flat(info)

    # ------------------------------------------------------------------ API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Start an episode. ``options={"state": {...}}`` starts from exactly that state: keys
        ``pos`` (N, 3), ``vel`` (N, 3), ``rot`` (N, 3, 3), ``omega`` (N, 3), ``motors`` ("zero",
        "hover" or (N, 4) normalized thrusts), ``goals`` (N, 3); missing keys take the defaults.
        With obstacles on, ``options={"obstacles": (M, 2)}`` places exactly those columns (centres
        x, y in m; radius ``obstacles.size / 2``) instead of a random map; ``info["obstacles"]`` is
        the (M, 2) array of the columns in force (after reset and every step). Other keys raise ValueError."""
        self._check_open()
        state = None
        if options is not None:
            if not isinstance(options, dict):
                raise ValueError(f"options must be a dict, got {type(options).__name__}")
            unknown = set(options) - set(RESET_OPTIONS)
            if unknown:
                raise ValueError(f"unknown reset options {sorted(unknown, key=str)}; allowed: {list(RESET_OPTIONS)}")
            if options.get("state") is not None:
                state = check_state(options["state"], self.cfg.num_quads, room=(self.cfg.room_low, self.cfg.room_high))
            if options.get("obstacles") is not None:
                state = {**(state or {}), "obstacles": check_obstacles(options["obstacles"], self.cfg)}
        super().reset(seed=seed)
        if self._jax is not None:
            if seed is not None or not self._jax.seeded:
                self._jax.seed(seed if seed is not None else int(self.np_random.integers(2**63 - 1)))
            obs, info = self._jax.reset(state)
            self._needs_reset = False
            return (obs[0] if self.single else obs), self._info_out(info, obs)
        if seed is not None:
            self.core.seed(seed)
        elif not self._seeded:
            self.core.seed(int(self.np_random.integers(2**63 - 1)))
        self._seeded = True
        if state is not None:
            state = {k: (v if isinstance(v, str) else v[None]) for k, v in state.items()}
        self.core.reset(state=state)
        self._params = {k: v[0] for k, v in self.core.params_dict().items()}  # the episode's (copies)
        self._needs_reset = False
        obs = self._obs(self.core.observe())
        return obs, self._info_out(self._info(), obs)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self._check_open()
        if self._needs_reset:
            raise RuntimeError("call reset() before step() (and after an episode ends)")
        if self._jax is not None:
            a = check_action(action, self.action_space.shape, dtype=np.float32)
            obs, reward, truncated, info = self._jax.step(a.reshape(self.cfg.num_quads, 4))
            self._needs_reset = truncated
            return (obs[0] if self.single else obs), reward, False, truncated, self._info_out(info, obs)
        a = check_action(action, self.action_space.shape)
        try:
            out = self.core.step(a.reshape(1, self.cfg.num_quads, 4))
        except PhysicsInstabilityError:  # the world's state is lost: only reset() goes on
            self._needs_reset = True
            raise
        truncated = bool(out["truncated"][0])
        info = self._info()
        terms = out["terms"]
        if self.single:  # (1, 1) arrays: their values into one fresh (1 + terms, 1) array
            rows = np.array([out["rewards"].item(), *[v.item() for v in terms.values()]]).reshape(-1, 1)
        elif out["rows"] is not None:  # the task's fresh (1 + terms, 1, N) block of the reward and the terms
            rows = out["rows"].reshape(len(terms) + 1, -1)
        else:
            rows = np.concatenate([out["rewards"], *terms.values()])  # (1 + terms, N): one copy of them all
        info["rewards"] = rows[0]
        info["reward_terms"] = dict(zip(terms, rows[1:]))
        if self.single:  # one quad: no pair, so no collision; the mean of one value is that value
            info["new_collisions"] = np.zeros(1, bool)
            reward = rows[0, 0].item()
        else:
            new = out["kin"]["new_contact"][0]
            info["new_collisions"] = (np.logical_or.reduce(new, axis=-1) if np.count_nonzero(new)  # = .any(-1)
                                      else np.zeros(self.cfg.num_quads, bool))
            reward = float(np.add.reduce(rows[0])) / self.cfg.num_quads  # = np.mean: the same sum and division
        if truncated:
            info["episode_metrics"] = {k: float(v[0]) for k, v in self.core.episode_metrics().items()}
            self._needs_reset = True
        obs = self._obs(out["obs"])
        return obs, reward, False, truncated, self._info_out(info, obs)

    def render(self) -> np.ndarray | None:
        self._check_open()  # a closed env reopens nothing (its renderer is released)
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array'")
            return None
        if self._jax is not None:
            return self._jax.render()
        from quadswarm_mj.render import SwarmRenderer

        if self._renderer is None:
            self._renderer = SwarmRenderer(self.core)
        return self._renderer.render()

    def _check_open(self) -> None:
        if self.closed:
            raise RuntimeError("the env is closed: create a new one")

    def __getstate__(self) -> dict[str, Any]:
        """For ``copy.deepcopy``/``pickle``: an independent env in the same state, stepping exactly as
        this one from here (both engines); the renderer is not copied (the copy opens its own)."""
        return {**self.__dict__, "_renderer": None}

    def close(self) -> None:
        """Release the renderer (and the JAX engine); then ``step``, ``reset`` and ``render`` raise RuntimeError."""
        self.closed = True
        if self._jax is not None:
            self._jax.close()
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
