"""B worlds of the JAX engine on this process's devices (:class:`LocalWorlds`), their outputs read
into host arrays; used by the vector back end in this process and by each worker process.

A step is one call of the compiled step without the auto-reset; only after a step that ended an
episode a second call renews the finished worlds (SAME_STEP auto-reset). Each device's rows are
copied straight into the caller's host arrays (no gather copy).
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.envs.jax_program import STATE_KEYS, host_rows, init_arrays, init_variant, program

#: per-step outputs replaced by those of the fresh episodes after a renewal
RENEWED = ("goals", "goal_vel", "on_floor", "time") + tuple(f"state/{k}" for k in STATE_KEYS)


def _copy_rows(dst: np.ndarray, x: jax.Array) -> None:
    """Copy a batched device array into the host array ``dst`` (converting dtype), each device's rows
    read in place (no gather copy)."""
    lo = 0
    for part in host_rows(x):
        hi = lo + part.shape[0]
        np.copyto(dst[lo:hi], part, casting="same_kind")
        lo = hi


class LocalWorlds:
    """B worlds on this process's JAX devices, their outputs read into host arrays.

    ``out`` arrays (given by the caller: fresh ones, or a worker's rows of the shared block):
    ``obs`` (B, N, obs_dim) float32, ``final_obs`` (B, N, obs_dim) float32, ``rest`` (B, S) float64
    (the per-step outputs of :attr:`Program.step_layout`) and ``episode`` (B, E) float64 (the episode
    constants of :attr:`Program.episode_layout`)."""

    def __init__(self, cfg: EnvConfig, num_worlds: int):
        self.cfg, self.B = cfg, int(num_worlds)
        self.prog = program(cfg, self.B)
        self.bufs: tuple | None = None
        lay = self.prog.step_layout
        self._done = lay.slices["done"].start
        self._renewed = [lay.slices[k] for k in RENEWED]

    def reset(self, keys: np.ndarray, mask: np.ndarray | None, state: dict[str, Any] | None,
              out: dict[str, np.ndarray]) -> None:
        """Reset every world (or those in ``mask``) from the key data ``keys`` (B, *key_shape) uint32;
        writes ``obs``, ``rest`` and ``episode``."""
        variant = init_variant(state)
        arrays = init_arrays(state, self.prog.float)
        if mask is None or self.bufs is None:
            self.bufs, obs, rest, episode = self.prog.reset_fn(variant, masked=False)(keys, arrays)
        else:
            self.bufs, obs, rest, episode = self.prog.reset_fn(variant, masked=True)(self.bufs, keys, arrays,
                                                                                     np.asarray(mask))
        for name, x in (("obs", obs), ("rest", rest), ("episode", episode)):
            _copy_rows(out[name], x)

    def step(self, actions: np.ndarray, out: dict[str, np.ndarray]) -> bool:
        """One control step; writes ``obs`` and ``rest``. Where an episode ended, also ``final_obs``
        (the stepped observations), the fresh episodes' ``obs``, their :data:`RENEWED` columns of
        ``rest`` and ``episode``; returns whether that happened (SAME_STEP auto-reset)."""
        self.bufs, rest = self.prog.step(self.bufs, actions.astype(self.prog.float, copy=False))
        obs = self.bufs[self.prog.obs_leaf]  # read (copied out) before the next call donates it
        _copy_rows(out["rest"], rest)
        if not (out["rest"][:, self._done] > 0.5).any():
            _copy_rows(out["obs"], obs)
            return False
        _copy_rows(out["final_obs"], obs)
        self.bufs, obs, rest, episode = self.prog.renew(self.bufs)
        _copy_rows(out["obs"], obs)
        _copy_rows(out["episode"], episode)
        fresh = np.concatenate(host_rows(rest))
        for sl in self._renewed:
            out["rest"][:, sl] = fresh[:, sl]
        return True

    def close(self) -> None:
        self.bufs = None

    def __getstate__(self) -> dict[str, Any]:
        """For copy/pickle: the state leaves as host arrays (put back on the devices by :meth:`__setstate__`)."""
        d = {k: v for k, v in self.__dict__.items() if k != "prog"}
        d["bufs"] = None if self.bufs is None else tuple(np.array(b) for b in self.bufs)
        return d

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.prog = program(self.cfg, self.B)
        ws = self.prog.worlds
        put = (lambda x: jax.device_put(x)) if ws is None or ws.num_devices == 1 else (
            lambda x: jax.device_put(x, ws.sharding))
        if self.bufs is not None:
            self.bufs = tuple(put(b) for b in self.bufs)
