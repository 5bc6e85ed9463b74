"""B worlds on the JAX engine behind ``QuadSwarmVectorEnv(engine="jax")``: :class:`JaxVectorBackend`,
NumPy in and out, with the MuJoCo engine's vector-env outputs (SAME_STEP auto-reset, ``final_obs``
and ``episode_metrics`` with masks).

The worlds run in this process (:class:`~quadswarm_mj.envs.jax_worlds.LocalWorlds`, sharded over
its devices) or in worker processes (:class:`~quadswarm_mj.envs.jax_workers.WorkerWorlds`). The
reset keys are drawn here for all B worlds, so a seed gives the same worlds whatever the split.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.envs.jax_program import STATE_KEYS, KeyStream, program
from quadswarm_mj.envs.jax_workers import WorkerWorlds
from quadswarm_mj.envs.jax_worlds import RENEWED, LocalWorlds
from quadswarm_mj.envs.workers import DEFAULT_WORKER_TIMEOUT_S, check_not_forked_from_jax
from quadswarm_mj.metrics import metric_keys
from quadswarm_mj.rewards import env_terms

VECTOR_INFO_KEYS = ("rewards", "reward_terms", "state", "goals", "goal_vel", "params", "on_floor",
                    "new_collisions", "time")


class JaxVectorBackend:
    """B worlds on the JAX engine with ``QuadSwarmVectorEnv``'s outputs (NumPy in and out,
    SAME_STEP auto-reset, ``final_obs`` and ``episode_metrics`` with masks).

    A step is one jitted call without the auto-reset; only after a step that ended an episode a
    second call renews the finished worlds (the fresh episodes of :class:`AutoResetWrapper`), whose
    observation, state, goals, time, floor flags and episode constants are then returned, with the
    step's rewards, reward terms, new collisions, done flags and episode metrics (as the MuJoCo
    engine's vector env). The episode constants (parameters, column map) are read only after resets
    and renewals and kept on the host.

    ``num_workers`` 0: the worlds run in this process (sharded over its devices); k >= 1: in k worker
    processes (:class:`WorkerWorlds`). Either way every returned array is the caller's: no later
    call writes into it (``copy`` does not apply). The reset keys are drawn here for all B worlds, so
    a seed gives the same worlds whatever the split (bit-identical where each part's worlds x quads
    is a multiple of 16, see the module doc)."""

    RENEWED = RENEWED

    def __init__(self, cfg: EnvConfig, num_envs: int, info_keys: tuple[str, ...] = VECTOR_INFO_KEYS,
                 copy: bool = True, num_workers: int = 0, worker_timeout: float | None = DEFAULT_WORKER_TIMEOUT_S):
        check_not_forked_from_jax()
        self.cfg, self.B = cfg, int(num_envs)
        self.info_keys, self.copy = tuple(info_keys), bool(copy)
        self.num_workers = int(num_workers)
        self.worker_timeout = worker_timeout
        self.prog = program(cfg, self.B)
        self._keys: KeyStream | None = None
        self._v: dict[str, np.ndarray] | None = None
        self._episode: dict[str, np.ndarray] = {}
        self._worlds: LocalWorlds | WorkerWorlds | None = None
        self.start()

    def start(self) -> None:
        """(Re)build the worlds (their state is gone: reset every world next)."""
        self.close()
        self._worlds = (WorkerWorlds(self.cfg, self.B, self.num_workers, self.worker_timeout) if self.num_workers
                        else LocalWorlds(self.cfg, self.B))

    def __getstate__(self) -> dict[str, Any]:
        """For copy/pickle (in-process worlds only: TypeError with worker processes)."""
        if self.num_workers:
            raise TypeError(f"a JAX-engine vector env with worker processes (num_shards={self.num_workers}) cannot be "
                            f"copied or pickled: its worlds live in other processes. Build a new env with the same "
                            f"arguments (num_shards=1 envs can be copied)")
        d = {k: v for k, v in self.__dict__.items() if k != "prog"}
        return d

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.prog = program(self.cfg, self.B)

    def seed(self, seed: int) -> None:
        self._keys = KeyStream(seed)

    def _new_outputs(self) -> dict[str, np.ndarray]:
        N, D = self.cfg.num_quads, self.cfg.obs_dim
        return {"obs": np.empty((self.B, N, D), np.float32), "final_obs": np.empty((self.B, N, D), np.float32),
                "rest": np.empty((self.B, self.prog.step_layout.size)),
                "episode": np.empty((self.B, self.prog.episode_layout.size))}

    def _read(self, out: dict[str, np.ndarray], episode: bool, final: bool = False
              ) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray | None]:
        """(obs (B, N, obs_dim) float32, float64 views of the per-step outputs, final_obs or None)
        from arrays no one else writes; updates the episode constants with ``episode``."""
        v = self.prog.step_layout.views64(out["rest"], (self.B,))
        if episode:  # new read-only arrays at every reset and renewal, shared by the infos until then
            ep = self.prog.episode_layout.views64(out["episode"], (self.B,))
            for x in ep.values():
                x.flags.writeable = False
            self._episode = ep
        return out["obs"], v, (out["final_obs"] if final else None)

    def _info(self, v: dict[str, np.ndarray], step: bool) -> dict[str, Any]:
        keys, out, ep = self.info_keys, {}, self._episode
        if step and "rewards" in keys:
            out["rewards"] = v["rewards"]
        if step and "reward_terms" in keys:
            out["reward_terms"] = {k: v["terms"][:, i] for i, k in enumerate(env_terms(self.cfg))}
        if "state" in keys:
            out["state"] = {k: v[f"state/{k}"] for k in STATE_KEYS}
        for k in ("goals", "goal_vel"):
            if k in keys:
                out[k] = v[k]
        if "params" in keys:
            out["params"] = {k[len("params/"):]: x for k, x in ep.items() if k.startswith("params/")}
        if "on_floor" in keys:
            out["on_floor"] = v["on_floor"] > 0.5
        if step and "new_collisions" in keys:
            out["new_collisions"] = v["new_collisions"] > 0.5
        if "time" in keys:
            out["time"] = v["time"]
        if "obstacles" in ep:  # (B, M_max, 2) centres, NaN in unused slots
            out["obstacles"] = np.where(ep["obstacles_valid"][..., None] > 0.5, ep["obstacles"], np.nan)
        return out

    def reset(self, mask: np.ndarray | None, state: dict[str, Any] | None) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every world, or those in ``mask`` (B,) bool (the first reset must reset all)."""
        if self._keys is None:
            raise RuntimeError("seed() before reset()")
        keys = self._keys.draw((self.B,))
        w = self._worlds
        if isinstance(w, WorkerWorlds):
            out = w.reset(keys, mask, state)
        else:
            out = self._new_outputs()
            w.reset(keys, mask, state, out)
        obs, self._v, _ = self._read(out, episode=True)
        return obs, self._info(self._v, step=False)

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        w = self._worlds
        if isinstance(w, WorkerWorlds):
            out, renewed = w.step(actions)
        else:
            out = self._new_outputs()
            renewed = w.step(actions, out)
        obs, v, final_obs = self._read(out, episode=renewed, final=renewed)
        done = v["done"] > 0.5
        self._v = v
        info = self._info(v, step=True)
        if final_obs is not None:
            info["episode_metrics"] = {k: np.where(done, v["metrics"][:, i], np.nan)
                                       for i, k in enumerate(metric_keys(self.cfg))}
            info["_episode_metrics"] = done.copy()
            info["final_obs"] = final_obs  # (B, N, obs_dim) float32, the stepped observations
            info["_final_obs"] = done.copy()
        return obs, v["rewards"].mean(axis=-1), np.zeros(self.B, dtype=np.bool_), done, info

    def episode_metrics(self) -> dict[str, np.ndarray]:
        """Episode metrics (B,) of the running episodes so far (as of the last reset or step)."""
        if self._v is None:
            raise RuntimeError("call reset() first")
        return {k: self._v["metrics"][:, i].copy() for i, k in enumerate(metric_keys(self.cfg))}

    def close(self) -> None:
        if self._worlds is not None:
            self._worlds.close()
            self._worlds = None
