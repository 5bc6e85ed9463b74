"""One world on the JAX engine behind ``QuadSwarmEnv(engine="jax")`` and
``QuadSwarmParallelEnv(engine="jax")``: :class:`JaxSingleBackend`, NumPy in and out, with the MuJoCo
engine's ``info`` keys.

A step is one call of the world's compiled step (:mod:`quadswarm_mj.envs.jax_program`): the state
stays on the device as one packed buffer, and the outputs come back as one float array split on the
host with NumPy views (:mod:`quadswarm_mj.perf.packing`). Seeding: ``seed(s)`` derives the JAX keys
from ``np.random.SeedSequence(s)``, so seeded runs are bit-identical.
"""

from __future__ import annotations

import types
from typing import Any

import jax
import numpy as np

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.envs.jax_program import KeyStream, Program, init_arrays, init_variant, program
from quadswarm_mj.envs.workers import check_not_forked_from_jax
from quadswarm_mj.metrics import metric_keys
from quadswarm_mj.perf.packing import OutputLayout
from quadswarm_mj.rewards import env_terms


class JaxSingleBackend:
    """One world on the JAX engine with ``QuadSwarmEnv``'s ``info`` (NumPy in and out).

    ``reset(seed, state) -> (obs_flat (N, obs_dim) float32, info)`` and
    ``step(action (N, 4)) -> (obs, rewards (N,), truncated, info)``; the caller validates inputs.

    JAX starts only at the first seed, reset or step, in the process that runs them: an env built in
    one process (e.g. gymnasium's ``AsyncVectorEnv`` builds one to read the spaces) and stepped in a
    forked one works; in a process forked from one where JAX already ran, every call raises
    RuntimeError (JAX is not fork-safe; use a "spawn" or "forkserver" context). ``copy.deepcopy``
    and ``pickle`` give an independent backend in the same state (the state buffers as host arrays)."""

    def __init__(self, cfg: EnvConfig):
        self.cfg = cfg
        self._prog: Program | None = None
        self._keys: KeyStream | None = None
        self._bufs: tuple | None = None
        self._last: dict[str, np.ndarray] | None = None
        # the episode's constants, from the reset (steps do not return them; each info gets copies, as
        # Gymnasium's checker requires that no two calls return shared objects)
        self._params: dict[str, np.ndarray] = {}
        self._obstacles: np.ndarray | None = None
        self._renderer: Any = None

    @property
    def prog(self) -> Program:
        """The compiled programs of this config (JAX starts here, in the calling process)."""
        check_not_forked_from_jax()
        if self._prog is None:
            self._prog = program(self.cfg, None)
        return self._prog

    def __getstate__(self) -> dict[str, Any]:
        d = {k: v for k, v in self.__dict__.items() if k not in ("_prog", "_renderer")}
        d["_bufs"] = None if self._bufs is None else tuple(np.asarray(b) for b in self._bufs)
        return d

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._prog, self._renderer = None, None

    @property
    def seeded(self) -> bool:
        return self._keys is not None

    def seed(self, seed: int) -> None:
        check_not_forked_from_jax()
        self._keys = KeyStream(seed)

    def _info(self, v: dict[str, np.ndarray]) -> dict[str, Any]:
        info = {"state": {"pos": v["state/pos"], "vel": v["state/vel"], "rot": v["state/rot"],
                          "omega": v["state/omega"], "thrust": v["state/thrust"]},
                "goals": v["goals"], "goal_vel": v["goal_vel"],
                "params": {k: x.copy() for k, x in self._params.items()},
                "on_floor": v["on_floor"] > 0.5, "time": float(v["time"])}
        if self._obstacles is not None:
            info["obstacles"] = self._obstacles.copy()
        return info

    def _split(self, out: jax.Array, layout: OutputLayout) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        o = np.array(out)  # one transfer, writable
        v = layout.split64(o)
        self._last = v
        return o[layout.slices["obs"]].reshape(layout.shapes["obs"]), v

    def reset(self, state: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        if self._keys is None:
            raise RuntimeError("seed() before reset()")
        variant = init_variant(state)
        fn = self.prog.reset_fn(variant, masked=False)
        self._bufs, out = fn(self._keys.draw(), init_arrays(state, self.prog.float))
        obs, v = self._split(out, self.prog.layout)
        if self._renderer is not None:
            self._renderer.reset()
        # the dynamics parameters and the column map are fixed for the episode: kept from here
        self._params = {k[len("params/"):]: v[k].copy() for k in self.prog.layout.params}
        self._obstacles = v["obstacles"][v["obstacles_valid"] > 0.5] if "obstacles" in v else None
        return obs, self._info(v)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, dict[str, Any]]:
        """One control step; returns (obs, team reward (mean over quads), truncated, info)."""
        prog = self.prog
        if self._bufs is not None and isinstance(self._bufs[0], np.ndarray):  # a copy's host buffers
            self._bufs = tuple(jax.device_put(b) for b in self._bufs)
        self._bufs, out = prog.step(self._bufs, action.astype(prog.float))
        obs, v = self._split(out, prog.step_layout)
        info = self._info(v)
        info["rewards"] = v["rewards"]
        info["reward_terms"] = dict(zip(env_terms(self.cfg), v["terms"]))
        info["new_collisions"] = v["new_collisions"] > 0.5
        truncated = bool(v["done"] > 0.5)
        if truncated:
            info["episode_metrics"] = dict(zip(metric_keys(self.cfg), v["metrics"].tolist()))
        return obs, float(v["reward"]), truncated, info

    def render(self) -> np.ndarray:
        """An RGB frame of the current state: the state's ``qpos`` copied into the renderer's
        ``MjData`` (:class:`quadswarm_mj.render.SwarmRenderer` on ``build_arena(cfg, 1)``)."""
        from quadswarm_mj.arena import build_arena
        from quadswarm_mj.render import SwarmRenderer

        if self._last is None:
            raise RuntimeError("call reset() before render()")
        if self._renderer is None:
            arena = build_arena(self.cfg, 1)
            self._renderer = SwarmRenderer(types.SimpleNamespace(arena=arena, model=arena.model))
        v = self._last
        return self._renderer.render(qpos=v["qpos"], goals=v["goals"], obstacles=self._obstacles)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
