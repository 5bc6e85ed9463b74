"""``QuadSwarmVectorEnv``: B worlds of N quads as one Gymnasium ``VectorEnv`` on CPU MuJoCo.

Layout (a policy shared across quads reshapes observations to (B * N, obs_dim)):

* observations (B, N, obs_dim) float32, actions (B, N, 4) in [-1, 1] (also for N = 1);
* reward (B,) float64, the team mean per world; terminated (B,) always False (no early end);
  truncated (B,) after ``episode_seconds``;
* ``info`` has QuadSwarmEnv's keys with a leading world axis: ``rewards`` (B, N) per-quad rewards,
  ``reward_terms`` {term: (B, N)}, ``state`` {pos, vel, rot, omega, thrust}, ``goals``, ``goal_vel``,
  ``params``, ``on_floor``, ``new_collisions`` (B, N), ``time`` (B,) (``info_keys`` selects them);
  in a step where worlds finish, ``episode_metrics`` {metric: (B,)} (NaN for the others) with the
  mask ``_episode_metrics``, and ``final_obs`` (B, N, obs_dim) with the mask ``_final_obs``.

Auto-reset: ``AutoresetMode.SAME_STEP`` (in ``metadata["autoreset_mode"]``). A world whose episode
ends in a step is reset at the end of that step: the step returns its last reward and
``truncated=True``, its observation and ``info`` are those of the new episode, and the last
observation of the old one is ``info["final_obs"]``. Every world is stepped in every call.
``reset(options={"reset_mask": mask})`` resets only some worlds.

Engine: the worlds are split into ``num_shards`` contiguous shards, each a
:class:`~quadswarm_mj.envs.cpu_core.CpuSwarm` whose model math runs on whole (B_shard, N) arrays
and whose worlds are stepped by one MuJoCo call per physics sub-step. Shard 0 runs in the calling
process, the others in worker processes (``python -c ...`` running :func:`_worker_main`) that share
the action and output arrays with it through one memory-mapped file, so a step costs two one-byte
pipe messages per worker. Processes rather than threads: NumPy and MuJoCo release the GIL only
inside their C loops, and the model math is many small NumPy calls: at 256 worlds two threads
measured 1.25x one process, two processes 1.6x (BENCHMARKS.md). A worker exits when its pipe
closes, so none outlives the env (``close()``, garbage collection, or the parent's exit).

Seeding: ``reset(seed=s)`` seeds shard k with ``SeedSequence(s).spawn(num_shards)[k]``; every world
draws from its shard's generator (randomization, scenario, spawn, noise), so one seed fixes every
world. Results depend on (seed, num_envs, num_shards, chunk_worlds); ``num_shards`` defaults to 2
(1 for fewer than 16 worlds) whatever the machine, so seeded runs are reproducible anywhere.

``engine="jax"`` runs the B worlds instead as one jitted, vmapped MJX step
(:class:`quadswarm_mj.envs.jax_engine.JaxVectorBackend`, in this process; ``num_shards``, ``backend``
and ``chunk_worlds`` do not apply), with the same spaces, info, auto-reset and reset options.
"""

from __future__ import annotations

import mmap
import os
import pickle
import struct
import subprocess
import sys
import tempfile
import weakref
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.envs.cpu_core import CpuSwarm
from quadswarm_mj.envs.validation import check_action, check_engine, check_state
from quadswarm_mj.metrics import METRIC_KEYS
from quadswarm_mj.observations import obs_bounds
from quadswarm_mj.rewards import TERMS

INFO_KEYS = ("rewards", "reward_terms", "state", "goals", "goal_vel", "params", "on_floor", "new_collisions",
             "time")
STATE_FIELDS = {"pos": (3,), "vel": (3,), "rot": (3, 3), "omega": (3,), "thrust": (4,)}
PARAM_FIELDS = {"mass": (), "inertia": (3,), "thrust_max": (4,), "torque_max": (4,), "alpha": (),
                "motor_sigma": ()}
MIN_WORLDS_PER_SHARD = 8


def _layout(cfg: EnvConfig, B: int) -> list[tuple[str, tuple[int, ...], Any]]:
    """(name, shape, dtype) of every shared array; all have the world axis first, except the
    stacked ``terms`` (T, B, N) and ``metrics`` (M, B)."""
    N, D = cfg.num_quads, cfg.obs_dim
    out = [("actions", (B, N, 4), np.float64), ("obs", (B, N, D), np.float32), ("reward", (B,), np.float64),
           ("rewards", (B, N), np.float64), ("terms", (len(TERMS), B, N), np.float64),
           ("truncated", (B,), np.bool_), ("done", (B,), np.bool_), ("final_obs", (B, N, D), np.float32),
           ("metrics", (len(METRIC_KEYS), B), np.float64), ("goals", (B, N, 3), np.float64),
           ("goal_vel", (B, N, 3), np.float64), ("on_floor", (B, N), np.bool_),
           ("new_collisions", (B, N), np.bool_), ("time", (B,), np.float64)]
    out += [(f"state/{k}", (B, N) + t, np.float64) for k, t in STATE_FIELDS.items()]
    out += [(f"params/{k}", (B, N) + t, np.float64) for k, t in PARAM_FIELDS.items()]
    return out


def _map_arrays(buf: Any, layout: list) -> dict[str, np.ndarray]:
    arrays, off = {}, 0
    for name, shape, dtype in layout:
        n = int(np.prod(shape)) * np.dtype(dtype).itemsize
        arrays[name] = np.ndarray(shape, dtype=dtype, buffer=buf, offset=off)
        off += -(-n // 64) * 64  # 64-byte aligned
    return arrays


def _layout_bytes(layout: list) -> int:
    return sum(-(-int(np.prod(s)) * np.dtype(d).itemsize // 64) * 64 for _, s, d in layout)


class _Shard:
    """Worlds [lo, hi) of the vector env: a CpuSwarm writing into the shared arrays."""

    def __init__(self, cfg: EnvConfig, lo: int, hi: int, arrays: dict[str, np.ndarray], info_keys: tuple[str, ...],
                 backend: str, chunk_worlds: int):
        self.cfg, self.lo, self.hi = cfg, lo, hi
        self.core = CpuSwarm(cfg, hi - lo, backend=backend, visual=False, chunk_worlds=chunk_worlds)
        self.a = {k: (v[:, lo:hi] if k in ("terms", "metrics") else v[lo:hi]) for k, v in arrays.items()}
        self.info_keys = info_keys
        self.state = {k: self.a[f"state/{k}"] for k in STATE_FIELDS}

    def seed(self, seed: Any) -> None:
        self.core.seed(seed)

    def reset(self, mask: np.ndarray | None, state: dict[str, Any] | None) -> None:
        c, a = self.core, self.a
        if mask is not None and not mask.any():
            return
        c.reset(mask=mask, state=state)
        if mask is None:
            a["obs"][...] = c.observe()
        else:
            w = np.flatnonzero(mask)
            a["obs"][w] = c.observe(worlds=w)
        a["done"][...] = False
        self._write_info(params=True)

    def step(self) -> None:
        c, a = self.core, self.a
        out = c.step(a["actions"])
        a["obs"][...] = out["obs"]
        rewards = out["rewards"]
        a["rewards"][...] = rewards
        a["reward"][...] = np.mean(rewards, axis=-1)  # the team reward, as QuadSwarmEnv's float(mean)
        if "reward_terms" in self.info_keys:
            for i, k in enumerate(TERMS):
                a["terms"][i] = out["terms"][k]
        a["new_collisions"][...] = out["kin"]["new_contact"].any(-1)
        done = out["truncated"]
        a["truncated"][...] = done
        a["done"][...] = done
        reset = bool(done.any())
        if reset:  # SAME_STEP auto-reset of the finished worlds
            w = np.flatnonzero(done)
            a["final_obs"][w] = a["obs"][w]
            m = c.episode_metrics()
            for i, k in enumerate(METRIC_KEYS):
                a["metrics"][i] = np.where(done, m[k], np.nan)
            c.reset(mask=done)
            a["obs"][w] = c.observe(worlds=w)
        self._write_info(params=reset)

    def _write_info(self, params: bool) -> None:
        c, a, keys = self.core, self.a, self.info_keys
        if "state" in keys:
            c.state_into(self.state)
        if "goals" in keys:
            a["goals"][...] = c.sstate.goals
        if "goal_vel" in keys:
            a["goal_vel"][...] = c.sstate.goal_vel
        if "on_floor" in keys:
            a["on_floor"][...] = c.on_floor
        if "time" in keys:
            np.multiply(c.steps, self.cfg.control_dt, out=a["time"])
        if params and "params" in keys:
            for k in PARAM_FIELDS:
                a[f"params/{k}"][...] = c.params[k]

    def handle(self, msg: tuple) -> Any:
        """Rare commands (same in the main process and in workers)."""
        op = msg[0]
        if op == "seed":
            self.seed(msg[1])
        elif op == "reset":
            self.reset(msg[1], msg[2])
        elif op == "episode_metrics":
            return self.core.episode_metrics()
        elif op == "get":
            return getattr(self.core, msg[1])
        else:
            raise ValueError(f"unknown command {op!r}")
        return None


# ---------------------------------------------------------------------------------------- workers
def _send(fd: int, obj: Any) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    os.write(fd, b"m" + struct.pack("<Q", len(data)))
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def _read_exact(fd: int, n: int) -> bytes:
    chunks, got = [], 0
    while got < n:
        b = os.read(fd, n - got)
        if not b:
            raise EOFError("pipe closed")
        chunks.append(b)
        got += len(b)
    return b"".join(chunks)


def _recv_payload(fd: int) -> Any:
    (n,) = struct.unpack("<Q", _read_exact(fd, 8))
    return pickle.loads(_read_exact(fd, n))


def _worker_main(rfd: int, wfd: int) -> None:
    """Worker loop: b"s" steps the shard; b"m" + pickle runs a command; EOF ends the process."""
    try:  # die with the parent even if it is killed (Linux)
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6").prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except Exception:  # noqa: BLE001 - best effort; the closed pipe ends the worker anyway
        pass
    if _read_exact(rfd, 1) != b"m":
        return
    init = _recv_payload(rfd)
    with open(init["path"], "r+b") as f:
        buf = mmap.mmap(f.fileno(), 0)
    arrays = _map_arrays(buf, init["layout"])
    try:
        shard = _Shard(init["cfg"], init["lo"], init["hi"], arrays, init["info_keys"], init["backend"],
                       init["chunk_worlds"])
        _send(wfd, ("ok", None))
    except Exception as e:  # noqa: BLE001 - reported to the parent
        _send(wfd, ("error", e))
        return
    while True:
        try:
            cmd = _read_exact(rfd, 1)
        except EOFError:
            return
        try:
            if cmd == b"s":
                shard.step()
                os.write(wfd, b"k")
                continue
            msg = _recv_payload(rfd)
            if msg[0] == "close":
                _send(wfd, ("ok", None))
                return
            _send(wfd, ("ok", shard.handle(msg)))
        except Exception as e:  # noqa: BLE001 - reported to the parent, which raises it
            _send(wfd, ("error", e))


_WORKER_CMD = ("import sys; from quadswarm_mj.envs.vector_env import _worker_main; "
               "_worker_main(*map(int, sys.argv[1:3]))")


class _Worker:
    """Parent-side handle of a worker process."""

    def __init__(self, init: dict[str, Any]):
        p_r, c_w = os.pipe()  # child -> parent
        c_r, p_w = os.pipe()  # parent -> child
        env = dict(os.environ)
        env.setdefault("OMP_NUM_THREADS", "1")
        env.setdefault("OPENBLAS_NUM_THREADS", "1")
        self.proc = subprocess.Popen([sys.executable, "-c", _WORKER_CMD, str(c_r), str(c_w)], pass_fds=(c_r, c_w),
                                     env=env)
        os.close(c_r)
        os.close(c_w)
        self.rfd, self.wfd = p_r, p_w
        _send(self.wfd, init)

    def wait_ready(self) -> None:
        self.result()

    def result(self) -> Any:
        tag = _read_exact(self.rfd, 1)
        if tag == b"k":
            return None
        status, value = _recv_payload(self.rfd)
        if status == "error":
            raise RuntimeError(f"vector env worker failed: {value!r}") from value
        return value

    def close(self) -> None:
        try:
            _send(self.wfd, ("close",))
            self.result()
        except Exception:  # noqa: BLE001 - the worker may be gone already
            pass
        for fd in (self.rfd, self.wfd):
            try:
                os.close(fd)
            except OSError:
                pass
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def _shutdown(workers: list[_Worker]) -> None:
    for w in workers:
        w.close()
    workers.clear()


# ------------------------------------------------------------------------------------ the env
class QuadSwarmVectorEnv(VectorEnv):
    """``num_envs`` worlds of ``cfg.num_quads`` Crazyflies stepped together (see the module doc).

    Args:
        cfg: the world config (keyword overrides as in ``QuadSwarmEnv``).
        num_envs: B, the number of worlds.
        num_shards: processes sharing the worlds (default 2, or 1 below 16 worlds).
        info_keys: which per-step ``info`` entries to fill (default: all of ``INFO_KEYS``); fewer
            keys make steps cheaper. Episode metrics and ``final_obs`` are always reported.
        copy: return copies (default) or read-only views of the shared arrays, valid until the next
            call (faster for large B).
        backend, chunk_worlds: the shards' physics (``CpuSwarm``): "mjdata" (one MjData per shard,
            used up to ``chunk_worlds`` worlds) or "batch" (``mujoco.batch`` of ``chunk_worlds``-world
            models); "auto" picks.
        engine: "mujoco" (default: CPU MuJoCo shards as above) or "jax" (MJX, all worlds in one jitted call).
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, cfg: EnvConfig | None = None, num_envs: int = 64, *, num_shards: int | None = None,
                 info_keys: tuple[str, ...] | None = None, copy: bool = True, backend: str = "auto",
                 chunk_worlds: int = 64, engine: str = "mujoco", **kwargs: Any):
        from quadswarm_mj.envs.gym_env import make_config

        self.cfg = make_config(cfg, kwargs)
        self.engine = check_engine(engine)
        self._jax: Any = None
        if not isinstance(num_envs, (int, np.integer)) or isinstance(num_envs, bool) or num_envs < 1:
            raise ValueError(f"num_envs must be an int >= 1, got {num_envs!r}")
        B = self.num_envs = int(num_envs)
        if num_shards is None:
            num_shards = 2 if B >= 2 * MIN_WORLDS_PER_SHARD else 1
        if not isinstance(num_shards, (int, np.integer)) or not 1 <= num_shards <= B:
            raise ValueError(f"num_shards must be an int in [1, num_envs={B}], got {num_shards!r}")
        info_keys = INFO_KEYS if info_keys is None else tuple(info_keys)
        unknown = set(info_keys) - set(INFO_KEYS)
        if unknown:
            raise ValueError(f"unknown info_keys {sorted(unknown)}; known: {list(INFO_KEYS)}")
        if backend not in ("auto", "mjdata", "batch"):
            raise ValueError(f"backend must be 'auto', 'mjdata' or 'batch', got {backend!r}")
        if not isinstance(chunk_worlds, (int, np.integer)) or chunk_worlds < 1:
            raise ValueError(f"chunk_worlds must be an int >= 1, got {chunk_worlds!r}")
        self.info_keys, self.copy, self.num_shards = info_keys, bool(copy), int(num_shards)
        N = self.cfg.num_quads
        # spaces
        low, high = obs_bounds(self.cfg)
        if self.cfg.normalize_obs:
            scale = np.maximum(np.abs(low), np.abs(high))
            low, high = low / scale, high / scale
        self.single_observation_space = spaces.Box(np.broadcast_to(low, (N, low.size)).astype(np.float32),
                                                   np.broadcast_to(high, (N, high.size)).astype(np.float32),
                                                   dtype=np.float32)
        self.single_action_space = spaces.Box(-1.0, 1.0, (N, 4), dtype=np.float32)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, B)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, B)
        self.render_mode = None
        if self.engine == "jax":
            from quadswarm_mj.envs.jax_engine import JaxVectorBackend

            self._jax = JaxVectorBackend(self.cfg, B, info_keys=info_keys, copy=copy)
            self._workers, self._needs_reset, self._seeded, self.closed = [], True, False, False
            self._finalizer = weakref.finalize(self, _shutdown, self._workers)
            return
        # shared arrays
        self._layout = _layout(self.cfg, B)
        bounds = np.linspace(0, B, self.num_shards + 1).round().astype(int)
        self._bounds = [(int(bounds[k]), int(bounds[k + 1])) for k in range(self.num_shards)]
        self._workers: list[_Worker] = []
        self._finalizer = weakref.finalize(self, _shutdown, self._workers)
        if self.num_shards > 1:
            fd, self._path = tempfile.mkstemp(prefix="quadswarm_vec_", dir="/dev/shm" if os.path.isdir("/dev/shm")
                                              else None)
            size = _layout_bytes(self._layout)
            os.ftruncate(fd, size)
            self._buf: Any = mmap.mmap(fd, size)
            os.close(fd)
        else:
            self._path = None
            self._buf = bytearray(_layout_bytes(self._layout))
        self._a = _map_arrays(self._buf, self._layout)

        def backend_for(n: int) -> str:
            return ("mjdata" if n <= chunk_worlds else "batch") if backend == "auto" else backend

        try:
            for lo, hi in self._bounds[1:]:
                self._workers.append(_Worker({"path": self._path, "layout": self._layout, "cfg": self.cfg, "lo": lo,
                                              "hi": hi, "info_keys": info_keys, "backend": backend_for(hi - lo),
                                              "chunk_worlds": chunk_worlds}))
            lo, hi = self._bounds[0]
            self._shard = _Shard(self.cfg, lo, hi, self._a, info_keys, backend_for(hi - lo), chunk_worlds)
            for w in self._workers:
                w.wait_ready()
        finally:
            if self._path is not None:  # every process has it mapped (or failed): the name can go
                os.unlink(self._path)
        self._needs_reset = True
        self._seeded = False
        self.closed = False

    # ------------------------------------------------------------------ plumbing
    def _all(self, msg_for_shard: Any) -> list[Any]:
        """Run a command on every shard (``msg_for_shard(k)`` gives shard k's message)."""
        for k, w in enumerate(self._workers, start=1):
            _send(w.wfd, msg_for_shard(k))
        try:
            out: list[Any] = [self._shard.handle(msg_for_shard(0))]
        finally:
            out += self._collect()
        return out

    def _collect(self) -> list[Any]:
        """Read every worker's reply (all of them, so the pipes stay in step), then raise the first error."""
        results, error = [], None
        for w in self._workers:
            try:
                results.append(w.result())
            except Exception as e:  # noqa: BLE001 - re-raised below
                results.append(None)
                error = error or e
        if error is not None:
            raise error
        return results

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
            out["reward_terms"] = {k: self._out(a["terms"][i]) for i, k in enumerate(TERMS)}
        if "state" in keys:
            out["state"] = {k: self._out(a[f"state/{k}"]) for k in STATE_FIELDS}
        for k in ("goals", "goal_vel"):
            if k in keys:
                out[k] = self._out(a[k])
        if "params" in keys:
            out["params"] = {k: self._out(a[f"params/{k}"]) for k in PARAM_FIELDS}
        for k in ("on_floor", "new_collisions", "time"):
            if k in keys and (step or k != "new_collisions"):
                out[k] = self._out(a[k])
        return out

    # ------------------------------------------------------------------ API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Reset every world (or those in ``options["reset_mask"]``, (B,) bool).

        ``options={"state": {...}}`` starts the worlds from exactly that state, with the keys of
        ``QuadSwarmEnv.reset`` and a leading world axis: ``pos`` (B, N, 3), ``vel`` (B, N, 3), ``rot``
        (B, N, 3, 3), ``omega`` (B, N, 3), ``motors`` ("zero", "hover" or (B, N, 4) normalized
        thrusts), ``goals`` (B, N, 3). ``seed`` (an int) reseeds every world (see the module doc)."""
        self._check_open()
        B, N = self.num_envs, self.cfg.num_quads
        state, mask = None, None
        if options is not None:
            if not isinstance(options, dict):
                raise ValueError(f"options must be a dict, got {type(options).__name__}")
            unknown = set(options) - {"state", "reset_mask"}
            if unknown:
                raise ValueError(f"unknown reset options {sorted(unknown)}; allowed: ['reset_mask', 'state']")
            if options.get("state") is not None:
                state = check_state(options["state"], N, lead=(B,))
            if options.get("reset_mask") is not None:
                mask = np.asarray(options["reset_mask"])
                if mask.shape != (B,) or mask.dtype != np.bool_:
                    raise ValueError(f"options['reset_mask'] must be a bool array of shape ({B},), got "
                                     f"{mask.dtype} {mask.shape}")
                if self._needs_reset and not mask.all():
                    raise ValueError("the first reset must reset every world (no reset_mask, or all True)")
        if seed is not None and not isinstance(seed, (int, np.integer)):
            raise ValueError(f"seed must be an int or None (one seed seeds every world), got {seed!r}")
        super().reset(seed=None if seed is None else int(seed))
        if self._jax is not None:
            if seed is not None or not self._seeded:
                self._jax.seed(int(seed) if seed is not None else int(self.np_random.integers(2**63 - 1)))
                self._seeded = True
            obs, info = self._jax.reset(mask, state)
            self._needs_reset = False
            return obs, info
        if seed is not None or not self._seeded:
            ss = np.random.SeedSequence(None if seed is None else int(seed)).spawn(self.num_shards)
            self._all(lambda k: ("seed", ss[k]))
            self._seeded = True

        def sub_state(k: int) -> dict[str, Any] | None:
            if state is None:
                return None
            return {key: (v if isinstance(v, str) else self._split(v, k)) for key, v in state.items()}

        self._all(lambda k: ("reset", self._split(mask, k), sub_state(k)))
        self._needs_reset = False
        info = self._info()
        return self._out(self._a["obs"]), info

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every world with ``actions`` (B, N, 4) (NaN, inf or a wrong shape raise ValueError)."""
        self._check_open()
        if self._needs_reset:
            raise RuntimeError("call reset() before step()")
        a = check_action(actions, self.action_space.shape)
        if self._jax is not None:
            return self._jax.step(a)
        self._a["actions"][...] = a
        for w in self._workers:
            os.write(w.wfd, b"s")
        try:
            self._shard.step()
        finally:
            self._collect()
        A = self._a
        info = self._info(step=True)
        done = A["done"]
        if done.any():
            info["episode_metrics"] = {k: A["metrics"][i].copy() for i, k in enumerate(METRIC_KEYS)}
            info["_episode_metrics"] = done.copy()
            info["final_obs"] = A["final_obs"].copy()
            info["_final_obs"] = done.copy()
        terminated = np.zeros(self.num_envs, dtype=np.bool_)
        return self._out(A["obs"]), A["reward"].copy(), terminated, A["truncated"].copy(), info

    def episode_metrics(self) -> dict[str, np.ndarray]:
        """Episode metrics (B,) of the running episodes so far."""
        if self._jax is not None:
            return self._jax.episode_metrics()
        parts = self._all(lambda k: ("episode_metrics",))
        return {k: np.concatenate([p[k] for p in parts]) for k in METRIC_KEYS}

    def _check_open(self) -> None:
        if self.closed:
            raise RuntimeError("the vector env is closed")

    def close_extras(self, **kwargs: Any) -> None:
        _shutdown(self._workers)
        self._finalizer.detach()
