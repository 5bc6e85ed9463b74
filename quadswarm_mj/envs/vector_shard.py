"""The MuJoCo engine's shard of :class:`~quadswarm_mj.envs.vector_env.QuadSwarmVectorEnv`: worlds [lo, hi)
as a ``CpuSwarm`` writing into the shared output arrays (in this process or a worker's), the arrays'
layout, and the shard's copy helpers. Re-exported by :mod:`quadswarm_mj.envs.vector_env`."""

from __future__ import annotations

import pickle
from typing import Any

import numpy as np

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.envs.cpu_core import CpuSwarm
from quadswarm_mj.envs.workers import STEP
from quadswarm_mj.metrics import metric_keys
from quadswarm_mj.rewards import env_terms

INFO_KEYS = ("rewards", "reward_terms", "state", "goals", "goal_vel", "params", "on_floor", "new_collisions",
             "time")
STATE_FIELDS = {"pos": (3,), "vel": (3,), "rot": (3, 3), "omega": (3,), "thrust": (4,)}
PARAM_FIELDS = {"mass": (), "inertia": (3,), "thrust_max": (4,), "torque_max": (4,), "alpha": (),
                "motor_sigma": ()}
AERO_PARAM_FIELDS = {"rotor_radius": (), "drag_coeff": (3,)}  # with cfg.aero on (README "Beyond the paper")


def param_fields(cfg: EnvConfig) -> dict[str, tuple[int, ...]]:
    """The per-quad parameters of ``info["params"]`` (name -> per-quad shape) for ``cfg``."""
    return {**PARAM_FIELDS, **AERO_PARAM_FIELDS} if cfg.aero.any else PARAM_FIELDS
MIN_WORLDS_PER_SHARD = 8


def _layout(cfg: EnvConfig, B: int) -> list[tuple[str, tuple[int, ...], Any]]:
    """(name, shape, dtype) of every shared array; all have the world axis first, except the
    stacked ``terms`` (T, B, N) and ``metrics`` (M, B)."""
    N, D = cfg.num_quads, cfg.obs_dim
    out = [("actions", (B, N, 4), np.float64), ("obs", (B, N, D), np.float32), ("reward", (B,), np.float64),
           ("rewards", (B, N), np.float64), ("terms", (len(env_terms(cfg)), B, N), np.float64),
           ("truncated", (B,), np.bool_), ("done", (B,), np.bool_), ("final_obs", (B, N, D), np.float32),
           ("metrics", (len(metric_keys(cfg)), B), np.float64), ("goals", (B, N, 3), np.float64),
           ("goal_vel", (B, N, 3), np.float64), ("on_floor", (B, N), np.bool_),
           ("new_collisions", (B, N), np.bool_), ("time", (B,), np.float64)]
    out += [(f"state/{k}", (B, N) + t, np.float64) for k, t in STATE_FIELDS.items()]
    out += [(f"params/{k}", (B, N) + t, np.float64) for k, t in param_fields(cfg).items()]
    if cfg.obstacles is not None:  # column centres (B, M_max, 2), NaN in unused slots
        out.append(("obstacles", (B, cfg.obstacles.slots, 2), np.float64))
    return out


class _Shard:
    """Worlds [lo, hi) of the vector env: a CpuSwarm writing into the shared arrays."""

    def __init__(self, cfg: EnvConfig, lo: int, hi: int, arrays: dict[str, np.ndarray], info_keys: tuple[str, ...],
                 backend: str, chunk_worlds: int):
        self.cfg, self.lo, self.hi = cfg, lo, hi
        self.core = CpuSwarm(cfg, hi - lo, backend=backend, visual=False, chunk_worlds=chunk_worlds)
        self.core.phys.first_world = lo  # instability errors name the env's world index
        self.a = {k: (v[:, lo:hi] if k in ("terms", "metrics") else v[lo:hi]) for k, v in arrays.items()}
        self.info_keys = info_keys
        self.state = {k: self.a[f"state/{k}"] for k in STATE_FIELDS}

    def seed(self, seed: Any) -> None:
        self.core.seed(seed)

    def __getstate__(self) -> dict[str, Any]:
        """Without the views of the env's arrays (:meth:`bind` maps them again)."""
        return {k: v for k, v in self.__dict__.items() if k not in ("a", "state")}

    def bind(self, arrays: dict[str, np.ndarray]) -> None:
        """View this shard's rows of the env's arrays (after a copy or unpickling)."""
        lo, hi = self.lo, self.hi
        self.a = {k: (v[:, lo:hi] if k in ("terms", "metrics") else v[lo:hi]) for k, v in arrays.items()}
        self.state = {k: self.a[f"state/{k}"] for k in STATE_FIELDS}

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
            for i, k in enumerate(env_terms(self.cfg)):
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
            for i, k in enumerate(metric_keys(self.cfg)):
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
            for k in param_fields(self.cfg):
                a[f"params/{k}"][...] = c.params[k]
        if params and c.omap is not None:  # the maps change only at resets
            a["obstacles"][...] = np.where(c.omap.valid[..., None], c.omap.centres, np.nan)

    def run(self, msg: Any) -> Any:
        """Run one message: ``STEP`` or a command tuple (same in the main process and in workers)."""
        if msg == STEP:
            self.step()
            return None
        return self.handle(msg)

    def handle(self, msg: tuple) -> Any:
        """Rare commands: ("seed", seed), ("reset", mask, state), ("episode_metrics",), ("call", fn, *args)."""
        op = msg[0]
        if op == "seed":
            self.seed(msg[1])
        elif op == "reset":
            self.reset(msg[1], msg[2])
        elif op == "episode_metrics":
            return self.core.episode_metrics()
        elif op == "call":  # test and debugging hook: ("call", fn, *args) runs fn(shard, *args)
            return msg[1](self, *msg[2:])
        else:
            raise ValueError(f"unknown command {op!r}")
        return None


def _core_bytes(shard: _Shard) -> bytes:
    """A shard's worlds, pickled (run in the shard's process when a vector env with workers is copied)."""
    return pickle.dumps(shard.core, protocol=pickle.HIGHEST_PROTOCOL)


def _load_core(shard: _Shard, blob: bytes) -> None:
    """Replace a shard's worlds by pickled ones (:func:`_core_bytes`) in the copy's processes."""
    shard.core = pickle.loads(blob)


def mujoco_shard(init: dict[str, Any], arrays: dict[str, np.ndarray]) -> _Shard:
    """A worker's MuJoCo-engine shard (the ``factory`` of :func:`quadswarm_mj.envs.workers.worker_main`)."""
    return _Shard(init["cfg"], init["lo"], init["hi"], arrays, init["info_keys"], init["backend"],
                  init["chunk_worlds"])
