"""Observations (SPEC §7): own state relative to the goal, K nearest neighbours, sensor noise.

Layout per quad (``cfg.obs_dim`` floats; the table with bounds: docs/model.md, "Observations"):
p - goal (m, world), v (m/s, world), R body-to-world row-major (9), omega (rad/s, body), then z (m,
``obs_self="floor"``) or the 6 wall/floor/ceiling distances (m, <= 5, ``obs_self="wall"``), then per
neighbour p_j - p_i (m) and v_j - v_i (m/s) nearest first (``neighbor_form="near"``: the local
form of :func:`near_neighbors`), then with obstacles the 9 column distance
features (m; SPEC_obstacles A.2; none when ``obstacles.observe_features`` is False), last with sensors
the deck readings (``sensors.deck_layout``).

Sensor noise (Gaussian: p 0.005 m, v 0.01 m/s, omega 1.75e-4 rad/s) perturbs the quad's own
measurements; neighbour terms are noise-free by default (``noise.neighbor_obs_noise``), as in the
original. Every component is clipped into the finite bounds of :func:`obs_bounds`.
Pure functions, any leading batch dims, NumPy or ``jax.numpy``.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from quadswarm_mj._xp import array_namespace
from quadswarm_mj.collisions import off_diagonal
from quadswarm_mj.config import EnvConfig
from quadswarm_mj.random_draws import DrawSpec, Normal
from quadswarm_mj.spatial import norm_last, sum_last

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
    if cfg.obstacles is not None and cfg.obstacles.observe_features:  # the 9 features (SPEC_obstacles A.2)
        from quadswarm_mj.obstacles import feature_bounds

        f_lo, f_hi = feature_bounds(cfg)
        lo, hi = lo + f_lo.tolist(), hi + f_hi.tolist()
    if cfg.sensors.any:  # the deck readings, last (quadswarm_mj.sensors)
        from quadswarm_mj.sensors import deck_bounds

        s_lo, s_hi = deck_bounds(cfg)
        lo, hi = lo + s_lo.tolist(), hi + s_hi.tolist()
    return np.asarray(lo, dtype=np.float32), np.asarray(hi, dtype=np.float32)


def obs_scale(cfg: EnvConfig) -> np.ndarray:
    """Per-component scale used by ``normalize_obs``, so normalized obs lie in [-1, 1]: max |bound|,
    except the neighbour relative velocities, which are clipped to +-``neighbor_vel_clip`` (m/s)
    and so are divided by the clip (they reach +-1)."""
    lo, hi = obs_bounds(cfg)
    scale = np.maximum(np.abs(lo), np.abs(hi)).astype(np.float64)
    d = cfg.self_obs_dim
    for j in range(cfg.neighbors):
        scale[d + 6 * j + 3:d + 6 * j + 6] = cfg.neighbor_vel_clip
    return scale


def _self_parts(xp: Any, cfg: EnvConfig, pos: Any, vel: Any, R: Any, omega: Any, goals: Any) -> list[Any]:
    parts = [pos - goals, vel, R.reshape(R.shape[:-2] + (9,)), omega]
    if cfg.obs_self == "floor":
        parts.append(pos[..., 2:3])
    elif cfg.obs_self == "wall":
        lo = xp.asarray(cfg.room_low, dtype=pos.dtype)
        hi = xp.asarray(cfg.room_high, dtype=pos.dtype)
        d = xp.stack([pos - lo, hi - pos], axis=-1).reshape(pos.shape[:-1] + (6,))
        parts.append(xp.clip(d, 0.0, MAX_WALL_DIST))
    return parts


@functools.lru_cache(maxsize=64)
def _gather_index(rows: int, n: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Constants for gathering K of N quads per (world, quad) row: the flat index of quad 0 of each
    row's world (rows, 1), and each row's own index repeated K times (rows * K,)."""
    first = (np.arange(rows) // n * n)[:, None]
    own = np.repeat(np.arange(rows), k)
    first.setflags(write=False)
    own.setflags(write=False)
    return first, own


def _sorted_position_rows_first(xp: Any, key: Any) -> Any:
    """(N, N, *batch) int32: [i, j] = the position of ``key[i, j]`` in a stable ascending sort of row
    ``key[i, :]`` (NaNs last, ties by index), for ``key`` (N, N, *batch) with any batch axes LAST."""
    n = key.shape[0]
    tail = (1,) * (key.ndim - 2)
    nan = xp.isnan(key)
    kk = xp.where(nan, xp.inf, key)
    before = (np.arange(n)[None, :] < np.arange(n)[:, None]).reshape((1, n, n) + tail)  # [j, l] = l < j
    kl, kj = kk[:, None, :], kk[:, :, None]  # [i, j, l] = key[i, l], key[i, j]
    nl, nj = nan[:, None, :], nan[:, :, None]
    less = (nl < nj) | ((nl == nj) & ((kl < kj) | ((kl == kj) & before)))
    return xp.sum(less.astype(xp.int32), axis=2)


def _nearest_one_hot(xp: Any, key: Any, k: int, rank_fn: Any = None) -> Any:
    """(..., N, K, N) bool: [i, r, j] = j is the r-th smallest ``key[..., i, :]``, exactly as a stable
    argsort (``jnp.argsort``) orders them: ascending, NaNs last, ties by index. A sort-free form for
    small N (an (N, N, N) comparison count), which XLA fuses and vectorizes. ``rank_fn``: an optional
    JAX kernel with :func:`_sorted_position_rows_first`'s integers for one world's (N, N) ``key``."""
    if xp is np or key.ndim != 2 or rank_fn is None:
        lead = key.ndim - 2
        moved = xp.moveaxis(xp.moveaxis(key, -1, 0), -1, 0) if lead else key  # (N, N, ...)
        rank = _sorted_position_rows_first(xp, moved)
        rank = xp.moveaxis(xp.moveaxis(rank, 0, -1), 0, -1) if lead else rank
    else:
        import jax

        rank = rank_fn(jax.lax.stop_gradient(key))  # (N, N)
    return rank[..., :, None, :] == np.arange(k)[:, None]


def _neighbor_bounds(cfg: EnvConfig) -> np.ndarray:
    return np.asarray(tuple(cfg.room_size) + (cfg.neighbor_vel_clip,) * 3, dtype=np.float64)


def neighbor_obs(cfg: EnvConfig, pos: Any, vel: Any, dist: Any | None = None, clip: bool = True,
                 rank_fn: Any = None) -> Any:
    """(..., N, 6 K): relative position and velocity of the K nearest other quads, clipped to
    +-room size (position) and +-``neighbor_vel_clip`` (velocity) unless ``clip`` is False.

    ``dist`` optionally passes the (..., N, N) distances between the ``pos`` already computed by
    :func:`quadswarm_mj.collisions.pairwise_contacts` (the same values), to save recomputing them;
    ``rank_fn`` the JAX rank kernel of :func:`_nearest_one_hot` (the JAX engine's ops pass a faster
    layout with the same integers).
    """
    xp = array_namespace(pos, vel)
    k, n = cfg.neighbors, pos.shape[-2]
    if k == 0:
        return xp.zeros(pos.shape[:-1] + (0,), dtype=pos.dtype)
    pv = xp.concatenate([pos, vel], axis=-1)  # (..., N, 6)
    if cfg.neighbor_sort == "original" or dist is None:
        rel = pv[..., None, :, :] - pv[..., :, None, :]  # [i, j] = (p_j - p_i, v_j - v_i)
        if dist is None:
            dist = norm_last(rel[..., :3])
    if cfg.neighbor_sort == "original":
        d = xp.maximum(dist, 0.01)
        key = d + sum_last((rel[..., :3] / d[..., None]) * rel[..., 3:])
    else:
        key = dist
    key = xp.where(off_diagonal(n), key, xp.inf)
    if xp is not np:
        # jax: rank by comparison + one-hot selection (a stable argsort's first K, same order and ties)
        hot = _nearest_one_hot(xp, key, k, rank_fn)  # (..., N, K, N)
        idx = xp.sum(xp.where(hot, np.arange(n, dtype=np.int32), 0), axis=-1)  # (..., N, K)
        g = xp.take_along_axis(pv[..., None, :, :], idx[..., None], axis=-2) - pv[..., :, None, :]
        if clip:
            bound = xp.asarray(_neighbor_bounds(cfg), dtype=pos.dtype)
            g = xp.minimum(xp.maximum(g, -bound), bound)
        return g.reshape(pos.shape[:-1] + (6 * k,))
    idx = xp.argsort(key, axis=-1)[..., :k]  # (..., N, K)
    # gather rows of (p, v): the K neighbours j of every (world, quad) row i, and i itself K times;
    # p_j - p_i is computed on the gathered rows (one contiguous subtraction)
    rows = math.prod(pos.shape[:-1])
    first, own = _gather_index(rows, n, k)
    pv2 = pv.reshape((rows, 6))
    g = xp.take(pv2, (idx.reshape((rows, k)) + first).reshape(-1), axis=0) - xp.take(pv2, own, axis=0)
    if clip:
        bound = xp.asarray(_neighbor_bounds(cfg), dtype=pos.dtype)
        g = xp.minimum(xp.maximum(g, -bound), bound)
    return g.reshape(pos.shape[:-1] + (6 * k,))


def near_neighbors(nb: Any, near_range: float) -> Any:
    """``neighbor_form="near"``: each neighbour's (r, v) = (p_j - p_i, v_j - v_i) of ``nb`` (..., N, 6 K) becomes
    (w r / |r|, w v) with the proximity ``w = clip(1 - |r| / near_range, 0, 1)`` (``near_range`` in m): the
    direction to the neighbour scaled by how near it is (0 at ``near_range`` and beyond, 1 at contact) and the
    relative velocity (m/s) weighted alike. All 0 when no neighbour is within ``near_range``, so a policy's
    hover does not depend on where far quads are."""
    xp = array_namespace(nb)
    g = nb.reshape(nb.shape[:-1] + (-1, 6))
    r, v = g[..., :3], g[..., 3:]
    d = norm_last(r)[..., None]
    w = xp.clip(1.0 - d / near_range, 0.0, 1.0)
    return xp.concatenate([r * (w / xp.maximum(d, 1e-6)), v * w], axis=-1).reshape(nb.shape)


@functools.lru_cache(maxsize=16)
def _obs_neighbor_bounds(self_dim: int, k: int, bound: tuple[float, ...],
                         tail: int = 0) -> tuple[np.ndarray, np.ndarray]:
    hi = np.concatenate([np.full(self_dim, np.inf), np.tile(np.asarray(bound), k), np.full(tail, np.inf)])
    lo = -hi
    lo.setflags(write=False)
    hi.setflags(write=False)
    return lo, hi


def build_obs(cfg: EnvConfig, pos: Any, vel: Any, R: Any, omega: Any, goals: Any,
              noise: dict[str, Any] | None, low: Any, high: Any, scale: Any | None = None,
              dist: Any | None = None, obstacles: Any | None = None, obstacle_feats: Any | None = None,
              deck_draws: dict[str, Any] | None = None, rank_fn: Any = None, deck_fn: Any = None) -> Any:
    """Full observation (..., N, obs_dim): noisy own state + neighbours (+ the 9 obstacle features
    of the true ``pos`` when ``obstacles`` = (centres, valid, radius) of the map is given), clipped
    into [low, high] and divided by ``scale`` when normalization is on. ``dist``: optional
    (..., N, N) distances between the true ``pos`` (see :func:`neighbor_obs`); ``obstacle_feats``:
    optional (..., N, 9) features of these ``pos`` already computed (the CPU engine's obstacle stage).
    With ``cfg.sensors`` on, the deck readings of the true state (:func:`quadswarm_mj.sensors.deck_part`,
    noise from ``deck_draws`` = draws of ``sensors.deck_draw_spec``, None: noise-free) come last.
    ``rank_fn``: see :func:`neighbor_obs`; ``deck_fn``: an engine's same-values form of ``deck_part`` (its
    signature; None: ``deck_part``).

    The neighbour clip of :func:`neighbor_obs` is folded into the final clip: clipping into one
    interval and then into another equals clipping into their intersection."""
    xp = array_namespace(pos, vel)
    if noise is not None:
        m_pos, m_vel, m_omega = pos + noise["pos"], vel + noise["vel"], omega + noise["omega"]
    else:
        m_pos, m_vel, m_omega = pos, vel, omega
    parts = _self_parts(xp, cfg, m_pos, m_vel, R, m_omega, goals)
    if cfg.neighbors > 0:
        if cfg.noise.neighbor_obs_noise:
            nb = neighbor_obs(cfg, m_pos, m_vel, clip=False, rank_fn=rank_fn)
        else:
            nb = neighbor_obs(cfg, pos, vel, dist, clip=False, rank_fn=rank_fn)
        parts.append(near_neighbors(nb, cfg.neighbor_near_range) if cfg.neighbor_form == "near" else nb)
        nb_lo, nb_hi = _obs_neighbor_bounds(cfg.self_obs_dim, cfg.neighbors, tuple(_neighbor_bounds(cfg)),
                                      cfg.obs_dim - cfg.self_obs_dim - 6 * cfg.neighbors)
        low = xp.maximum(xp.asarray(low), xp.asarray(nb_lo, dtype=pos.dtype))
        high = xp.minimum(xp.asarray(high), xp.asarray(nb_hi, dtype=pos.dtype))
    if obstacles is not None and cfg.obstacles.observe_features:
        from quadswarm_mj.obstacles import observed_features, obstacle_features

        feats = obstacle_feats if obstacle_feats is not None else obstacle_features(pos, *obstacles)
        o = cfg.obstacles
        parts.append(observed_features(feats, o.feature_form, o.near_range, o.near_speed_reach, m_vel))
    if cfg.sensors.any:
        if deck_fn is None:
            from quadswarm_mj.sensors import deck_part as deck_fn
        parts.append(deck_fn(cfg, pos, vel, R, omega, obstacles, deck_draws))
    if xp is np:
        obs = np.minimum(np.maximum(np.concatenate(parts, axis=-1), low), high)  # = clip into the bounds
    else:  # each part clipped into its bounds, then concatenated: the same values, and XLA:CPU then
        # copies the parts into place instead of choosing a source for each of the N x D elements
        low, high, start, clipped = xp.asarray(low, pos.dtype), xp.asarray(high, pos.dtype), 0, []
        for part in parts:
            w = part.shape[-1]
            clipped.append(xp.minimum(xp.maximum(part, low[..., start:start + w]), high[..., start:start + w]))
            start += w
        obs = xp.concatenate(clipped, axis=-1)
    return obs if scale is None else obs / scale
