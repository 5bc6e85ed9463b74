"""Evaluate a policy on the CPU env: K episodes per scenario, the SPEC §8 episode metrics.

NumPy + MuJoCo only (no JAX). Two paths give the same statistics:

* ``batched`` (default): the CPU engine behind ``QuadSwarmEnv`` (``CpuSwarm``) stepping up to
  ``max_worlds`` episodes at once: same model, same per-episode metrics
  (``CpuSwarm.episode_metrics`` is what ``QuadSwarmEnv`` puts in ``info["episode_metrics"]``),
  many times faster;
* ``gym``: ``QuadSwarmEnv`` itself, one episode after the other, metrics read from
  ``info["episode_metrics"]`` at truncation.

Episodes use the environment defaults (motor_start "zero", all noise on) unless ``env`` overrides
say otherwise; a trained policy's observation layout (``policy.env_kwargs``) is applied first.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.metrics import metric_keys


@dataclass
class EvalResult:
    """Per-episode metrics (episodes,) of one policy on one scenario, with summaries."""

    scenario: str
    num_quads: int
    episodes: int
    per_episode: dict[str, np.ndarray]
    seconds: float = 0.0
    config: dict[str, Any] = field(default_factory=dict)

    def mean(self, key: str) -> float:
        v = self.per_episode[key]
        v = v[np.isfinite(v)]
        return float(v.mean()) if v.size else float("nan")

    def stderr(self, key: str) -> float:
        """Standard error of the mean over episodes (NaN with fewer than 2 finite values)."""
        v = self.per_episode[key]
        v = v[np.isfinite(v)]
        return float(v.std(ddof=1) / math.sqrt(v.size)) if v.size > 1 else float("nan")

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {"scenario": self.scenario, "num_quads": self.num_quads, "episodes": self.episodes,
                               "seconds": round(self.seconds, 1)}
        for k in self.per_episode:
            out[k] = self.mean(k)
            out[k + "_stderr"] = self.stderr(k)
        return out


#: ObstacleConfig fields that fix how a policy observes the columns
OBSTACLE_OBS_FIELDS = ("observe_features", "feature_form", "near_range", "near_speed_reach")


def make_eval_config(policy: Any, scenario: str, num_quads: int | None = None,
                     env: dict[str, Any] | None = None) -> EnvConfig:
    """The EnvConfig for evaluating ``policy``: defaults, then the policy's observation layout,
    then ``num_quads`` and ``env`` overrides. An ``obstacles`` dict override keeps the policy's column
    inputs (``OBSTACLE_OBS_FIELDS``) unless it names them: the policy reads what it was trained on."""
    kw = dict(getattr(policy, "env_kwargs", {}) or {})
    if num_quads is not None:
        kw["num_quads"] = num_quads
    env = dict(env or {})
    own = kw.get("obstacles")
    if isinstance(env.get("obstacles"), dict) and isinstance(own, dict):
        env["obstacles"] = {**{k: own[k] for k in OBSTACLE_OBS_FIELDS if k in own}, **env["obstacles"]}
    kw.update(env)
    kw["scenario"] = scenario
    fields = {f.name for f in dataclasses.fields(EnvConfig)}
    unknown = sorted(str(k) for k in kw if k not in fields)
    if unknown:
        raise ValueError(f"unknown EnvConfig field(s) {', '.join(unknown)}; known: {', '.join(sorted(fields))}")
    return EnvConfig(**kw)


def _batched(policy: Any, cfg: EnvConfig, episodes: int, seed: int, max_worlds: int) -> dict[str, np.ndarray]:
    from quadswarm_mj.envs.cpu_core import CpuSwarm

    keys = metric_keys(cfg)
    out: dict[str, list] = {k: [] for k in keys}
    done_eps, chunk = 0, 0
    while done_eps < episodes:
        B = min(max_worlds, episodes - done_eps)
        core = CpuSwarm(cfg, num_worlds=B)
        core.seed(seed * 1_000_003 + chunk)
        core.reset()
        obs = core.observe().astype(np.float32)
        for _ in range(cfg.episode_steps):
            info = {"state": core.state_dict(), "goals": core.sstate.goals, "goal_vel": core.sstate.goal_vel,
                    "params": core.params_dict()}
            if core.omap is not None:
                info["obstacles"] = core.omap
            a = np.asarray(policy.act(obs, info), dtype=np.float64).reshape(B, cfg.num_quads, 4)
            if not np.all(np.isfinite(a)):
                raise ValueError("the policy returned non-finite actions")
            res = core.step(np.clip(a, -1.0, 1.0))
            obs = res["obs"].astype(np.float32)
        if not np.all(res["truncated"]):
            raise RuntimeError("episodes did not end together")  # pragma: no cover - engine invariant
        m = core.episode_metrics()
        for k in keys:
            out[k].append(np.asarray(m[k], float))
        done_eps += B
        chunk += 1
    return {k: np.concatenate(v) for k, v in out.items()}


def _gym(policy: Any, cfg: EnvConfig, episodes: int, seed: int) -> dict[str, np.ndarray]:
    from quadswarm_mj.envs.gym_env import QuadSwarmEnv

    env = QuadSwarmEnv(cfg)
    keys = metric_keys(cfg)
    out: dict[str, list] = {k: [] for k in keys}
    try:
        for ep in range(episodes):
            obs, info = env.reset(seed=seed * 1_000_003 + ep)
            while True:
                a = policy.act(obs, info)
                obs, _, term, trunc, info = env.step(np.clip(a, -1.0, 1.0))
                if term or trunc:
                    break
            for k in keys:
                out[k].append(float(info["episode_metrics"][k]))
    finally:
        env.close()
    return {k: np.asarray(v, float) for k, v in out.items()}


def evaluate(policy: Any, scenario: str, episodes: int = 50, num_quads: int | None = None, seed: int = 0,
             env: dict[str, Any] | None = None, mode: str = "batched", max_worlds: int = 64) -> EvalResult:
    """Run ``episodes`` full episodes of ``policy`` (``act(obs, info)``) on ``scenario``."""
    if not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes must be an int >= 1, got {episodes!r}")
    if mode not in ("batched", "gym"):
        raise ValueError(f"mode must be 'batched' or 'gym', got {mode!r}")
    cfg = make_eval_config(policy, scenario, num_quads, env)
    if hasattr(policy, "obs_dim") and policy.obs_dim != cfg.obs_dim:
        raise ValueError(f"policy expects obs_dim {policy.obs_dim} but {scenario} with N={cfg.num_quads} gives "
                         f"{cfg.obs_dim}; pass the policy's num_quads / num_neighbors")
    if hasattr(policy, "ctrl"):  # the controller needs this config's airframe
        from quadswarm_mj.policies import ControllerPolicy

        policy = ControllerPolicy(cfg)
    t0 = time.perf_counter()
    if mode == "batched":
        per = _batched(policy, cfg, episodes, seed, max_worlds)
    else:
        per = _gym(policy, cfg, episodes, seed)
    return EvalResult(scenario, cfg.num_quads, episodes, per, time.perf_counter() - t0,
                      {"num_quads": cfg.num_quads, "motor_start": cfg.motor_start, "noise": "default"
                       if cfg.noise == EnvConfig().noise else "custom"})
