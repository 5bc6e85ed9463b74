"""What the policy modules share: activations, the observation-layout fields of a policy file's env,
normalized observation rows. NumPy only."""

from __future__ import annotations

from typing import Any

import numpy as np

ACTIVATIONS = ("tanh", "relu", "swish", "elu")
#: EnvConfig fields that fix the observation layout; stored in a policy's ``meta["env"]``.
OBS_ENV_FIELDS = ("num_quads", "num_neighbors", "obs_self", "neighbor_sort", "neighbor_vel_clip", "normalize_obs",
                  "room_size")


def _activation(name: str, x: np.ndarray) -> np.ndarray:
    if name == "tanh":
        return np.tanh(x)
    if name == "relu":
        return np.maximum(x, 0.0)
    if name == "swish":
        return x / (1.0 + np.exp(-x))
    if name == "elu":
        return np.where(x > 0, x, np.expm1(np.minimum(x, 0.0)))
    raise ValueError(f"activation must be one of {ACTIVATIONS}, got {name!r}")


def _env_kwargs(meta: dict[str, Any]) -> dict[str, Any]:
    """The EnvConfig overrides recorded in a policy file's metadata (JSON lists back to tuples)."""
    env = meta.get("env", {})
    env = dict(env) if isinstance(env, dict) else {}  # a loaded file's env was checked (_check_meta)
    if isinstance(env.get("room_size"), list):
        env["room_size"] = tuple(env["room_size"])
    return env


def _normalized_rows(obs: Any, obs_dim: int, mean: np.ndarray, std: np.ndarray) -> tuple[tuple[int, ...], np.ndarray]:
    """(leading shape, (rows, obs_dim) normalized float64 observations); ValueError on a wrong last axis."""
    x = np.asarray(obs, dtype=np.float64)
    if x.ndim < 1 or x.shape[-1] != obs_dim:
        raise ValueError(f"observations must have shape (..., {obs_dim}), e.g. (N, {obs_dim}); got {x.shape}")
    return x.shape[:-1], (x.reshape(-1, obs_dim) - mean) / std

