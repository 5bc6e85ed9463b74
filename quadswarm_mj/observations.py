"""Observations (SPEC §7): own state relative to the goal, K nearest neighbours, sensor noise.

Layout per quad (``cfg.obs_dim`` floats):

====================== ===== ==========================================================
slice                  size  content (units; frame)
====================== ===== ==========================================================
0:3                    3     p - goal (m; world)
3:6                    3     v (m/s; world)
6:15                   9     R body-to-world, row-major
15:18                  3     omega (rad/s; body)
18 ("floor" only)      1     z (m)
18:24 ("wall" only)    6     distances to the walls -x, +x, -y, +y, floor, ceiling (m, <= 5)
then, per neighbour    6     p_j - p_i (m), v_j - v_i (m/s), nearest first
====================== ===== ==========================================================

Sensor noise (Gaussian: p 0.005 m, v 0.01 m/s, omega 1.75e-4 rad/s) perturbs the quad's own
measurements; neighbour terms are noise-free by default (``noise.neighbor_obs_noise``), as in the
original. Every component is clipped into the finite bounds of :func:`obs_bounds`.
Pure functions, any leading batch dims, NumPy or ``jax.numpy``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from quadswarm_mj._xp import array_namespace
from quadswarm_mj.config import EnvConfig
from quadswarm_mj.random_draws import DrawSpec, Normal

MAX_VEL = 20.0  # m/s, bound of own velocity
MAX_NEIGHBOR_VEL = 40.0  # m/s, bound of neighbour relative velocity
MAX_WALL_DIST = 5.0  # m


def sensor_noise_spec(cfg: EnvConfig) -> DrawSpec:
    n, s = cfg.num_quads, cfg.noise
    return {"pos": Normal(0.0, s.sensor_pos_std, (n, 3)), "vel": Normal(0.0, s.sensor_vel_std, (n, 3)),
            "omega": Normal(0.0, s.sensor_omega_std, (n, 3))}


def obs_bounds(cfg: EnvConfig) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) float32 bounds of one quad's observation (before normalization)."""
    L, W, H = cfg.room_size
    hi = [L, W, H] + [MAX_VEL] * 3 + [1.0] * 9 + [cfg.quad.max_omega] * 3
    lo = [-x for x in hi]
    if cfg.obs_self == "floor":
        lo, hi = lo + [0.0], hi + [H]
    elif cfg.obs_self == "wall":
        lo, hi = lo + [0.0] * 6, hi + [MAX_WALL_DIST] * 6
    nb_hi = [L, W, H] + [MAX_NEIGHBOR_VEL] * 3
    lo += [-x for x in nb_hi] * cfg.neighbors
    hi += nb_hi * cfg.neighbors
    return np.asarray(lo, dtype=np.float32), np.asarray(hi, dtype=np.float32)


def obs_scale(cfg: EnvConfig) -> np.ndarray:
    """Per-component scale used by ``normalize_obs`` (max |bound|), so normalized obs lie in [-1, 1]."""
    lo, hi = obs_bounds(cfg)
    return np.maximum(np.abs(lo), np.abs(hi)).astype(np.float64)


def self_obs(cfg: EnvConfig, pos: Any, vel: Any, R: Any, omega: Any, goals: Any) -> Any:
    """(..., N, self_obs_dim) own-state observation (no noise, no clipping)."""
    xp = array_namespace(pos, vel)
    parts = [pos - goals, vel, R.reshape(R.shape[:-2] + (9,)), omega]
    if cfg.obs_self == "floor":
        parts.append(pos[..., 2:3])
    elif cfg.obs_self == "wall":
        lo = xp.asarray(cfg.room_low, dtype=pos.dtype)
        hi = xp.asarray(cfg.room_high, dtype=pos.dtype)
        d = xp.stack([pos - lo, hi - pos], axis=-1).reshape(pos.shape[:-1] + (6,))
        parts.append(xp.clip(d, 0.0, MAX_WALL_DIST))
    return xp.concatenate(parts, axis=-1)


def neighbor_obs(cfg: EnvConfig, pos: Any, vel: Any) -> Any:
    """(..., N, 6 K): relative position and velocity of the K nearest other quads."""
    xp = array_namespace(pos, vel)
    k, n = cfg.neighbors, pos.shape[-2]
    if k == 0:
        return xp.zeros(pos.shape[:-1] + (0,), dtype=pos.dtype)
    rel_p = pos[..., None, :, :] - pos[..., :, None, :]  # [i, j] = p_j - p_i
    rel_v = vel[..., None, :, :] - vel[..., :, None, :]
    dist = xp.sqrt(xp.sum(rel_p * rel_p, axis=-1))
    if cfg.neighbor_sort == "original":
        d = xp.maximum(dist, 0.01)
        key = d + xp.sum((rel_p / d[..., None]) * rel_v, axis=-1)
    else:
        key = dist
    key = xp.where(xp.eye(n, dtype=bool), xp.inf, key)
    idx = xp.argsort(key, axis=-1)[..., :k]  # (..., N, K)
    rp = xp.take_along_axis(rel_p, idx[..., None], axis=-2)
    rv = xp.take_along_axis(rel_v, idx[..., None], axis=-2)
    room = xp.asarray(cfg.room_size, dtype=pos.dtype)
    rp = xp.clip(rp, -room, room)
    rv = xp.clip(rv, -cfg.neighbor_vel_clip, cfg.neighbor_vel_clip)
    return xp.concatenate([rp, rv], axis=-1).reshape(pos.shape[:-1] + (6 * k,))


def build_obs(cfg: EnvConfig, pos: Any, vel: Any, R: Any, omega: Any, goals: Any,
              noise: dict[str, Any] | None, low: Any, high: Any, scale: Any | None = None) -> Any:
    """Full observation (..., N, obs_dim): noisy own state + neighbours, clipped into [low, high]
    and divided by ``scale`` when normalization is on."""
    xp = array_namespace(pos, vel)
    if noise is not None:
        m_pos, m_vel, m_omega = pos + noise["pos"], vel + noise["vel"], omega + noise["omega"]
    else:
        m_pos, m_vel, m_omega = pos, vel, omega
    own = self_obs(cfg, m_pos, m_vel, R, m_omega, goals)
    if cfg.neighbors > 0:
        nb = neighbor_obs(cfg, m_pos, m_vel) if cfg.noise.neighbor_obs_noise else neighbor_obs(cfg, pos, vel)
        obs = xp.concatenate([own, nb], axis=-1)
    else:
        obs = own
    obs = xp.clip(obs, low, high)
    return obs if scale is None else obs / scale
