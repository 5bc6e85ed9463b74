"""``info_mode="flat"``: the env's ``info`` as one level of NumPy arrays of stable shape and dtype.

The default ``info`` (``info_mode="nested"``) has nested dicts (``info["state"]["pos"]``,
``info["reward_terms"]``, ``info["episode_metrics"]``) and keys that appear only after a step or at an
episode's end. Libraries that build specs from the info (TorchRL's ``GymEnv``/``GymWrapper``,
``PettingZooWrapper``) need every entry to be an array whose key, shape and dtype never change. In
flat mode:

* nested keys are joined with "/": ``state/pos``, ``params/mass``, ``reward_terms/effort``,
  ``episode_metrics/success``;
* every key is present at every step, reset included: ``rewards``, ``reward_terms/*`` and
  ``new_collisions`` hold NaN (False) after a reset, ``episode_metrics/*`` NaN until an episode ends
  (and in the vector env for the worlds that did not end in that step); the vector env's
  ``final_obs`` is zeros where no episode ended (inside the observation box, as TorchRL's spec
  checks want), with its masks ``_final_obs`` / ``_episode_metrics``;
* floating entries are float32, booleans bool, integers int64; scalars are 0-d arrays.

Shapes are those of the nested layout (per-quad arrays keep their quad axis; the vector env's
keep their leading world axis; the PettingZoo env's per-agent infos have one quad's rows).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.metrics import metric_keys
from quadswarm_mj.rewards import env_terms

SEP = "/"


def _array(v: Any) -> np.ndarray:
    a = np.asarray(v)
    if a.dtype.kind == "f":
        return a.astype(np.float32, copy=False)
    if a.dtype.kind in "iu":
        return a.astype(np.int64, copy=False)
    if a.dtype.kind == "b":
        return a
    raise ValueError(f"info entry of dtype {a.dtype} cannot be flattened")


def flatten(info: Mapping[str, Any], prefix: str = "", out: dict[str, np.ndarray] | None = None
            ) -> dict[str, np.ndarray]:
    """``{"state": {"pos": x}}`` -> ``{"state/pos": x}`` (arrays as described in the module doc)."""
    out = {} if out is None else out
    for k, v in info.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            flatten(v, key + SEP, out)
        else:
            out[key] = _array(v)
    return out


def step_only_keys(cfg: EnvConfig, lead: tuple[int, ...] = (), per_quad: bool = True,
                   rewards: bool = True) -> dict[str, np.ndarray]:
    """The flat keys a reset's info lacks, with their fill values: ``rewards`` / ``reward_terms/*``
    (``lead`` + (N,) NaN, or ``lead`` NaN with ``per_quad=False``), ``new_collisions`` (False) and
    ``episode_metrics/*`` (``lead`` NaN)."""
    quad = lead + ((cfg.num_quads,) if per_quad else ())
    out: dict[str, np.ndarray] = {}
    if rewards:
        out["rewards"] = np.full(quad, np.nan, np.float32)
        out["new_collisions"] = np.zeros(quad, np.bool_)
    out.update({f"reward_terms{SEP}{t}": np.full(quad, np.nan, np.float32) for t in env_terms(cfg)})
    out.update({f"episode_metrics{SEP}{m}": np.full(lead, np.nan, np.float32) for m in metric_keys(cfg)})
    return out


class InfoFlattener:
    """Turns each nested ``info`` of one env into the flat layout, filling the keys it lacks from
    ``defaults`` (:func:`step_only_keys`). The first flattened info fixes the keys, shapes and dtypes;
    a later info whose entry changes shape raises a RuntimeError (a bug, not a user error)."""

    def __init__(self, defaults: dict[str, np.ndarray]):
        self.defaults = defaults
        self.layout: dict[str, tuple[tuple[int, ...], np.dtype]] | None = None

    def __call__(self, info: Mapping[str, Any]) -> dict[str, np.ndarray]:
        flat = flatten(info)
        for k, v in self.defaults.items():
            if k not in flat:
                flat[k] = v.copy()
        if self.layout is None:
            self.layout = {k: (v.shape, v.dtype) for k, v in flat.items()}
        out = {}
        for k, (shape, dtype) in self.layout.items():
            v = flat.get(k)
            if v is None:  # an entry of some steps only (e.g. a vector env's masks): its fill value
                v = self.defaults[k].copy() if k in self.defaults else (
                    np.zeros(shape, dtype) if dtype.kind == "b" else np.full(shape, np.nan, dtype))
            elif v.shape != shape:
                raise RuntimeError(f"flat info entry {k!r} changed shape {shape} -> {v.shape}")
            out[k] = v.astype(dtype, copy=False)
        if "_final_obs" in out:  # rows of worlds whose episode did not end: zeros
            out["final_obs"] = np.where(out["_final_obs"].reshape((-1,) + (1,) * (out["final_obs"].ndim - 1)),
                                        out["final_obs"], np.float32(0.0))
        return out


def gym_flattener(cfg: EnvConfig) -> InfoFlattener:
    """For :class:`~quadswarm_mj.envs.gym_env.QuadSwarmEnv` (one world)."""
    return InfoFlattener(step_only_keys(cfg))


def agent_flattener(cfg: EnvConfig) -> InfoFlattener:
    """For one agent's info of :class:`~quadswarm_mj.envs.parallel_env.QuadSwarmParallelEnv`."""
    return InfoFlattener(step_only_keys(cfg, per_quad=False, rewards=False))


def vector_flattener(cfg: EnvConfig, num_envs: int, obs_dim: int) -> InfoFlattener:
    """For :class:`~quadswarm_mj.envs.vector_env.QuadSwarmVectorEnv` (leading world axis), with the
    episode-end entries ``final_obs`` (zeros) and the masks ``_final_obs``/``_episode_metrics`` (False)."""
    d = step_only_keys(cfg, lead=(num_envs,))
    d["final_obs"] = np.zeros((num_envs, cfg.num_quads, obs_dim), np.float32)
    d["_final_obs"] = np.zeros(num_envs, np.bool_)
    d["_episode_metrics"] = np.zeros(num_envs, np.bool_)
    return InfoFlattener(d)
