"""``QuadSwarmVectorEnv``: B worlds of N quads as one Gymnasium ``VectorEnv`` (CPU MuJoCo or JAX engine).

* observations (B, N, obs_dim) float32, actions (B, N, 4) in [-1, 1] (also for N = 1);
* reward (B,) float64, the team mean per world; terminated (B,) always False; truncated (B,) after
  ``episode_seconds``;
* ``info``: QuadSwarmEnv's keys with a leading world axis (``rewards`` (B, N) per quad, ``state``,
  ``goals``, ...; ``info_keys`` selects them), ``episode_metrics`` / ``final_obs`` with their masks.

Auto-reset is ``AutoresetMode.SAME_STEP``; ``reset(options={"reset_mask": mask})`` resets some worlds.
The MuJoCo engine splits the worlds into ``num_shards`` :class:`~quadswarm_mj.envs.cpu_core.CpuSwarm`
shards, shard 0 here and the others in worker processes (:mod:`quadswarm_mj.envs.workers`);
``engine="jax"`` runs them as jitted MJX steps (:mod:`quadswarm_mj.envs.jax_vector`). Failures,
seeding, array ownership and the JAX-engine split: docs/api.md ("The vector env"); the design:
docs/engines.md.
"""

from __future__ import annotations

import os
import weakref
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.control_modes import action_box_bounds
from quadswarm_mj.envs.flat_info import vector_flattener
from quadswarm_mj.envs.validation import check_action, check_engine, check_obstacles, check_state
from quadswarm_mj.envs.vector_shard import (  # noqa: F401  (re-exported)
    AERO_PARAM_FIELDS,
    INFO_KEYS,
    MIN_WORLDS_PER_SHARD,
    PARAM_FIELDS,
    STATE_FIELDS,
    _core_bytes,
    _layout,
    _load_core,
    _Shard,
    mujoco_shard,
    param_fields,
)
from quadswarm_mj.envs.workers import (
    DEFAULT_WORKER_TIMEOUT_S,
    STEP,
    Resources,
    Worker,
    exclusive,
    layout_bytes,
    map_arrays,
    run_on_workers,
    wait_started,
)
from quadswarm_mj.envs.workers import (
    WorkerError as WorkerError,  # re-exported: the error a failed worker raises
)
from quadswarm_mj.metrics import metric_keys
from quadswarm_mj.observations import obs_bounds
from quadswarm_mj.rewards import env_terms


def _default_jax_shards(B: int) -> int:
    """The JAX engine's default split: on CPU one worker process per core this process may run on,
    with at least ``MIN_WORLDS_PER_WORKER`` worlds each; 1 (this process) otherwise or on accelerators."""
    import jax

    from quadswarm_mj.envs.jax_workers import MIN_WORLDS_PER_WORKER

    if jax.default_backend() != "cpu":
        return 1
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    k = min(cores, B // MIN_WORLDS_PER_WORKER)
    return k if k >= 2 else 1


def _check_worker_timeout(t: Any) -> float | None:
    """``worker_timeout``: None (wait forever) or a number of seconds > 0."""
    if t is None:
        return None
    if isinstance(t, bool) or not isinstance(t, (int, float, np.integer, np.floating)) or not 0 < float(t) < np.inf:
        raise ValueError(f"worker_timeout must be a number of seconds > 0 (finite) or None, got {t!r}")
    return float(t)


# ------------------------------------------------------------------------------------ the env
class QuadSwarmVectorEnv(VectorEnv):
    """``num_envs`` worlds of ``cfg.num_quads`` Crazyflies stepped together (see the module doc).

    Args:
        cfg: the world config (keyword overrides as in ``QuadSwarmEnv``).
        num_envs: B, the number of worlds.
        num_shards: processes sharing the worlds (default 2, or 1 below 16 worlds; engine "jax": see
            the module doc).
        info_keys: which per-step ``info`` entries to fill (default: all of ``INFO_KEYS``); fewer
            keys make steps cheaper. Episode metrics and ``final_obs`` are always reported.
        copy: return copies (default) or read-only views of the shared arrays, valid until the next
            call (faster for large B).
        backend, chunk_worlds: the shards' physics (``CpuSwarm``): "mjdata" (one MjData per shard,
            used up to ``chunk_worlds`` worlds) or "batch" (``mujoco.batch`` of ``chunk_worlds``-world
            models); "auto" picks.
        engine: "mujoco" (default: CPU MuJoCo shards as above) or "jax" (MJX: jitted calls in this process
            or, on CPU with many worlds, in one worker process per core).
        worker_timeout: the longest wait for one reply of a worker process to a step or command (s; None:
            no limit; a worker's start waits at least 600 s); a worker that does not answer in time
            raises :class:`WorkerError` naming it.

    Threads, ``os.fork()``, ``copy.deepcopy`` and ``pickle``: docs/api.md ("Processes, threads and copies").
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}
    #: the same as ``metadata["autoreset_mode"]``, as an attribute too (TorchRL's ``GymWrapper`` reads it there)
    autoreset_mode = AutoresetMode.SAME_STEP

    def __init__(self, cfg: EnvConfig | None = None, num_envs: int = 64, *, num_shards: int | None = None,
                 info_keys: tuple[str, ...] | None = None, copy: bool = True, backend: str = "auto",
                 chunk_worlds: int = 64, engine: str = "mujoco",
                 worker_timeout: float | None = DEFAULT_WORKER_TIMEOUT_S, **kwargs: Any):
        from quadswarm_mj.envs.gym_env import make_config

        self._owner_pid = os.getpid()  # a forked copy refuses calls when it has workers or runs JAX
        self.worker_timeout = _check_worker_timeout(worker_timeout)
        self.cfg = make_config(cfg, kwargs)
        self.engine = check_engine(engine)
        self._jax: Any = None
        if not isinstance(num_envs, (int, np.integer)) or isinstance(num_envs, bool) or num_envs < 1:
            raise ValueError(f"num_envs must be an int >= 1, got {num_envs!r}")
        B = self.num_envs = int(num_envs)
        if num_shards is not None and (not isinstance(num_shards, (int, np.integer)) or isinstance(num_shards, bool)
                                       or not 1 <= num_shards <= B):
            raise ValueError(f"num_shards must be an int in [1, num_envs={B}], got {num_shards!r}")
        if num_shards is None and self.engine == "jax":
            num_shards = _default_jax_shards(B)
        elif num_shards is None:
            num_shards = 2 if B >= 2 * MIN_WORLDS_PER_SHARD else 1
        info_keys = INFO_KEYS if info_keys is None else tuple(info_keys)
        unknown = set(info_keys) - set(INFO_KEYS)
        if unknown:
            raise ValueError(f"unknown info_keys {sorted(unknown)}; known: {list(INFO_KEYS)}")
        if backend not in ("auto", "mjdata", "batch"):
            raise ValueError(f"backend must be 'auto', 'mjdata' or 'batch', got {backend!r}")
        if not isinstance(chunk_worlds, (int, np.integer)) or chunk_worlds < 1:
            raise ValueError(f"chunk_worlds must be an int >= 1, got {chunk_worlds!r}")
        self.info_keys, self.copy, self.num_shards = info_keys, bool(copy), int(num_shards)
        self._backend, self._chunk_worlds = backend, int(chunk_worlds)
        N = self.cfg.num_quads
        # spaces
        low, high = obs_bounds(self.cfg)
        if self.cfg.normalize_obs:
            scale = np.maximum(np.abs(low), np.abs(high))
            low, high = low / scale, high / scale
        self.single_observation_space = spaces.Box(np.broadcast_to(low, (N, low.size)).astype(np.float32),
                                                   np.broadcast_to(high, (N, high.size)).astype(np.float32),
                                                   dtype=np.float32)
        self.single_action_space = spaces.Box(*action_box_bounds(self.cfg, (N, 4)), dtype=np.float32)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, B)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, B)
        self.render_mode = None
        if self.engine == "jax":
            from quadswarm_mj.envs.jax_vector import JaxVectorBackend

            self._jax = JaxVectorBackend(self.cfg, B, info_keys=info_keys, copy=copy,
                                         num_workers=0 if self.num_shards == 1 else self.num_shards,
                                         worker_timeout=self.worker_timeout)
            self._failure = None
            self._needs_reset, self._seeded, self.closed = True, False, False
            self._finalizer = weakref.finalize(self, self._jax.close)
            return
        # shards: worlds [lo, hi) each; shard 0 here, the others in workers
        self._layout = _layout(self.cfg, B)
        bounds = np.linspace(0, B, self.num_shards + 1).round().astype(int)
        self._bounds = [(int(bounds[k]), int(bounds[k + 1])) for k in range(self.num_shards)]
        self._res = Resources()
        self._finalizer = weakref.finalize(self, self._res.release)
        self.closed = False
        self._build()

    # ------------------------------------------------------------------ plumbing
    def _build(self) -> None:
        """Create the shared arrays, start the workers and build shard 0 (also after a failure)."""
        res, size = self._res, layout_bytes(self._layout)
        self._failure: BaseException | None = None
        self._needs_reset, self._seeded = True, False
        if self.num_shards == 1:
            self._a = map_arrays(bytearray(size), self._layout)
        else:
            self._a = map_arrays(res.create_block(size).buf, self._layout)

        def backend_for(n: int) -> str:
            if self._backend != "auto":
                return self._backend
            return "mjdata" if n <= self._chunk_worlds else "batch"

        try:
            for k, (lo, hi) in enumerate(self._bounds[1:], start=1):  # workers build while shard 0 does
                init = {"factory": mujoco_shard, "shm": res.shm.name if res.shm else None, "layout": self._layout,
                        "cfg": self.cfg,
                        "lo": lo, "hi": hi, "info_keys": self.info_keys, "backend": backend_for(hi - lo),
                        "chunk_worlds": self._chunk_worlds, "timeout": self.worker_timeout}
                res.workers.append(Worker(k, lo, hi, init))
            lo, hi = self._bounds[0]
            self._shard = _Shard(self.cfg, lo, hi, self._a, self.info_keys, backend_for(hi - lo), self._chunk_worlds)
            wait_started(res.workers)
        except BaseException as e:
            res.release()
            self._failure = e  # reset() tries again
            raise
        res.unlink()  # every worker has mapped the block: its name can go

    def _run(self, what: str, msg_for: Callable[[int], Any]) -> list[Any]:
        """Run a message on every shard (``msg_for(k)`` gives shard k's): send it to the workers, run
        shard 0 here, then read every reply. Any failure marks the env as failed and raises."""
        try:
            return run_on_workers(self._res.workers, what, msg_for, self.num_shards,
                                  local=lambda: self._shard.run(msg_for(0)))
        except BaseException as e:
            self._failure, self._needs_reset = e, True
            raise

    def _call_jax(self, fn: Callable[..., Any], *args: Any) -> Any:
        """A JAX-engine call; any failure (a worker's, or an interrupt in the middle) marks the env as
        failed: the next ``reset()`` rebuilds the worlds."""
        try:
            return fn(*args)
        except BaseException as e:
            self._failure, self._needs_reset = e, True
            raise

    def _check_usable(self) -> None:
        if self.closed:
            raise RuntimeError("the vector env is closed")
        if self._failure is not None:
            first = str(self._failure).splitlines()[0] if str(self._failure) else ""
            raise RuntimeError(f"the vector env failed ({type(self._failure).__name__}: {first}) and must be reset: "
                               f"call reset() to rebuild its workers") from self._failure

    @exclusive
    def _call_shards(self, fn: Callable[..., Any], *args: Any) -> list[Any]:
        """``fn(shard, *args)`` on every shard, in its process (a test hook; ``fn`` must be picklable)."""
        self._check_usable()
        return self._run("call", lambda k: ("call", fn, *args))

    def _split(self, x: Any, k: int) -> Any:
        lo, hi = self._bounds[k]
        return None if x is None else x[lo:hi]

    def _out(self, x: np.ndarray) -> np.ndarray:
        if self.copy:
            return x.copy()
        v = x.view()
        v.flags.writeable = False
        return v

    def _info(self, step: bool = False) -> dict[str, Any]:
        a, keys, out = self._a, self.info_keys, {}
        if step and "rewards" in keys:
            out["rewards"] = self._out(a["rewards"])
        if step and "reward_terms" in keys:
            out["reward_terms"] = {k: self._out(a["terms"][i]) for i, k in enumerate(env_terms(self.cfg))}
        if "state" in keys:
            out["state"] = {k: self._out(a[f"state/{k}"]) for k in STATE_FIELDS}
        for k in ("goals", "goal_vel"):
            if k in keys:
                out[k] = self._out(a[k])
        if "params" in keys:
            out["params"] = {k: self._out(a[f"params/{k}"]) for k in param_fields(self.cfg)}
        for k in ("on_floor", "new_collisions", "time"):
            if k in keys and (step or k != "new_collisions"):
                out[k] = self._out(a[k])
        if "obstacles" in a:
            out["obstacles"] = self._out(a["obstacles"])
        return out

    def _info_out(self, info: dict[str, Any], obs: np.ndarray | None = None) -> dict[str, Any]:
        """``info`` as returned: nested, or flat with ``cfg.info_mode="flat"`` (envs/flat_info.py); with
        the deck sensors on, their readings (B, N, ...) from ``obs`` (``quadswarm_mj.sensors.deck_info``)."""
        if obs is not None and self.cfg.sensors.any:
            from quadswarm_mj.observations import obs_scale
            from quadswarm_mj.sensors import deck_info

            info.update(deck_info(self.cfg, obs, obs_scale(self.cfg) if self.cfg.normalize_obs else None))
        if self.cfg.info_mode != "flat":
            return info
        if getattr(self, "_flat", None) is None:
            self._flat = vector_flattener(self.cfg, self.num_envs, self.cfg.obs_dim)
        return self._flat(info)

    # ------------------------------------------------------------------ API
    @exclusive
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Reset every world (or those in ``options["reset_mask"]``, (B,) bool).

        ``options={"state": {...}}`` starts the worlds from exactly that state, with the keys of
        ``QuadSwarmEnv.reset`` and a leading world axis: ``pos`` (B, N, 3), ``vel`` (B, N, 3), ``rot``
        (B, N, 3, 3), ``omega`` (B, N, 3), ``motors`` ("zero", "hover" or (B, N, 4) normalized
        thrusts), ``goals`` (B, N, 3). ``seed`` (an int) reseeds every world (see the module doc).
        With obstacles on, ``options={"obstacles": c}`` places exactly the columns ``c`` (centres x, y
        m): (M, 2) for every reset world, or (B, M, 2) one map per world; ``info["obstacles"]`` is
        the (B, M_max, 2) array of the columns in force, NaN in unused slots.
        After a failure (see the module doc) the workers are rebuilt first."""
        if self.closed:
            raise RuntimeError("the vector env is closed")
        B, N = self.num_envs, self.cfg.num_quads
        state, mask = None, None
        if options is not None:
            if not isinstance(options, dict):
                raise ValueError(f"options must be a dict, got {type(options).__name__}")
            unknown = set(options) - {"state", "reset_mask", "obstacles"}
            if unknown:
                raise ValueError(f"unknown reset options {sorted(unknown)}; allowed: ['obstacles', 'reset_mask', "
                                 f"'state']")
            if options.get("state") is not None:
                state = check_state(options["state"], N, lead=(B,), room=(self.cfg.room_low, self.cfg.room_high))
            if options.get("obstacles") is not None:
                c = check_obstacles(options["obstacles"], self.cfg, lead=(B,))
                state = {**(state or {}), "obstacles": np.broadcast_to(c, (B,) + c.shape[-2:]).copy()}
            if options.get("reset_mask") is not None:
                mask = np.asarray(options["reset_mask"])
                if mask.shape != (B,) or mask.dtype != np.bool_:
                    raise ValueError(f"options['reset_mask'] must be a bool array of shape ({B},), got "
                                     f"{mask.dtype} {mask.shape}")
                if self._needs_reset and not mask.all():
                    raise ValueError("the first reset (and the first after a failure) must reset every world "
                                     "(no reset_mask, or all True)")
        if seed is not None and not isinstance(seed, (int, np.integer)):
            raise ValueError(f"seed must be an int or None (one seed seeds every world), got {seed!r}")
        if self._failure is not None and self._jax is None:  # rebuild the workers and shard 0
            self._res.release()
            self._build()
        elif self._failure is not None:  # the JAX engine's worlds (and workers) afresh
            self._jax.start()
            self._failure, self._seeded = None, False
        super().reset(seed=None if seed is None else int(seed))
        if self._jax is not None:
            if seed is not None or not self._seeded:
                self._jax.seed(int(seed) if seed is not None else int(self.np_random.integers(2**63 - 1)))
                self._seeded = True
            obs, info = self._call_jax(self._jax.reset, mask, state)
            self._needs_reset = False
            return obs, self._info_out(info, obs)
        if seed is not None or not self._seeded:
            ss = np.random.SeedSequence(None if seed is None else int(seed)).spawn(self.num_shards)
            self._run("seed", lambda k: ("seed", ss[k]))
            self._seeded = True

        def sub_state(k: int) -> dict[str, Any] | None:
            if state is None:
                return None
            return {key: (v if isinstance(v, str) else self._split(v, k)) for key, v in state.items()}

        self._run("reset", lambda k: ("reset", self._split(mask, k), sub_state(k)))
        self._needs_reset = False
        info = self._info()
        return self._out(self._a["obs"]), self._info_out(info, self._a["obs"])

    @exclusive
    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every world with ``actions`` (B, N, 4) (NaN, inf or a wrong shape raise ValueError)."""
        self._check_usable()
        if self._needs_reset:
            raise RuntimeError("call reset() before step()")
        a = check_action(actions, self.action_space.shape, dtype=np.float64 if self._jax is None else np.float32)
        if self._jax is not None:
            *out, info = self._call_jax(self._jax.step, a)
            return (*out, self._info_out(info, out[0]))
        self._a["actions"][...] = a
        self._run("step", lambda k: STEP)
        A = self._a
        info = self._info(step=True)
        done = A["done"]
        if done.any():
            info["episode_metrics"] = {k: A["metrics"][i].copy() for i, k in enumerate(metric_keys(self.cfg))}
            info["_episode_metrics"] = done.copy()
            info["final_obs"] = A["final_obs"].copy()
            info["_final_obs"] = done.copy()
        terminated = np.zeros(self.num_envs, dtype=np.bool_)
        return (self._out(A["obs"]), A["reward"].copy(), terminated, A["truncated"].copy(),
                self._info_out(info, A["obs"]))

    @exclusive
    def episode_metrics(self) -> dict[str, np.ndarray]:
        """Episode metrics (B,) of the running episodes so far."""
        self._check_usable()
        if self._jax is not None:
            return self._jax.episode_metrics()
        parts = self._run("episode_metrics", lambda k: ("episode_metrics",))
        return {k: np.concatenate([p[k] for p in parts]) for k in metric_keys(self.cfg)}

    def close_extras(self, **kwargs: Any) -> None:
        self._finalizer()  # ends the workers (once), frees the shared block

    # ------------------------------------------------------------------ fork, copy, pickle
    def _forked_use_error(self) -> str | None:
        """Why a forked copy of this env cannot be used (None: it can, as an independent copy)."""
        if self._jax is not None:
            return "it runs JAX, which is not fork-safe"
        if self.num_shards > 1:
            return ("its worker processes and shared memory belong to that process (a step here would advance "
                    "its worlds)")
        return None

    @exclusive
    def __getstate__(self) -> dict[str, Any]:
        """The env's state for ``copy.deepcopy``/``pickle``: the worlds (MuJoCo data, generators,
        episode state) and the shared arrays' contents; TypeError where a copy cannot be independent."""
        name = type(self).__name__
        if self.closed:
            raise TypeError(f"a closed {name} cannot be copied or pickled")
        if self._jax is None and any(self._shard_backend(hi - lo) == "batch" for lo, hi in self._bounds):
            raise TypeError(f"a {name} whose shards run the 'batch' back end (mujoco.batch) cannot be copied or "
                            f"pickled; pass backend='mjdata' for an env to copy")
        d = {k: v for k, v in self.__dict__.items() if k not in ("_finalizer", "_call_lock", "_res")}
        if d.get("_failure") is not None:  # the copy needs reset() too (exceptions need not pickle)
            d["_failure"] = RuntimeError(str(self._failure))
        if self._jax is None:
            d["_a"] = {k: v.copy() for k, v in self._a.items()}
        if self._jax is None and self.num_shards > 1:  # the workers' worlds, fetched from their processes
            d.pop("_shard")
            d["_cores"] = None if self._failure is not None else self._run("copy", lambda k: ("call", _core_bytes))
        return d

    def _shard_backend(self, n: int) -> str:
        """The physics back end of a shard of ``n`` worlds (as :meth:`_build` picks it)."""
        if self._backend != "auto":
            return self._backend
        return "mjdata" if n <= self._chunk_worlds else "batch"

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._owner_pid = os.getpid()
        if self._jax is not None:
            self._finalizer = weakref.finalize(self, self._jax.close)
            return
        if "_cores" in state:  # with workers: new ones, loaded with the original's worlds
            cores = self.__dict__.pop("_cores")
            self._res = Resources()
            self._finalizer = weakref.finalize(self, self._res.release)
            self._build()
            if cores is not None:
                self._run("copy", lambda k: ("call", _load_core, cores[k]))
            for k, v in state["_a"].items():
                self._a[k][...] = v
            self._failure, self._needs_reset, self._seeded = (state["_failure"], state["_needs_reset"],
                                                             state["_seeded"])
            return
        arrays = map_arrays(bytearray(layout_bytes(self._layout)), self._layout)
        for k, v in state["_a"].items():
            arrays[k][...] = v
        self._a = arrays
        self._shard.bind(arrays)
        self._res = Resources()
        self._finalizer = weakref.finalize(self, self._res.release)
