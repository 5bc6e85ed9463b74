"""The JAX engine's worker-process layout: B worlds split over worker processes, each a
single-device JAX program pinned to one CPU core (:class:`WorkerWorlds` in the env's process,
:class:`WorkerShard` in each worker), on the transport of :mod:`quadswarm_mj.envs.workers` shared
with the MuJoCo engine's vector env.

The control block (actions, final observations, episode constants, flags) is one shared block;
observations and per-step outputs go into the transport's output blocks
(:class:`~quadswarm_mj.envs.workers.OutputBlocks`), handed out as views and taken back once no
array views them. Only the layout of the blocks and the shard's commands are the JAX engine's.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.envs.jax_program import program
from quadswarm_mj.envs.jax_worlds import LocalWorlds
from quadswarm_mj.envs.workers import (
    DEFAULT_WORKER_TIMEOUT_S,
    STEP_INTO,
    OutputBlocks,
    Resources,
    SharedBlock,
    Worker,
    layout_bytes,
    map_arrays,
    map_block_rows,
    run_on_workers,
    wait_started,
)

#: on CPU the JAX engine's vector env runs in worker processes (one core each) from this many worlds per
#: worker (measured on 2 cores: 1024 worlds 1.04-1.24x the in-process engine, 256 worlds 0.86-1.36x)
MIN_WORLDS_PER_WORKER = 256

#: output blocks a worker-process vector env hands out before it falls back to copying (see WorkerWorlds)
MAX_OUTPUT_BLOCKS = 8


class WorkerShard:
    """Worlds [lo, hi) of a worker process (the ``factory`` :func:`jax_shard`): a :class:`LocalWorlds`
    on the worker's one CPU core, writing its rows of the shared arrays: ``obs`` and ``rest`` into the
    output block the step names, the rest into the control block."""

    def __init__(self, init: dict[str, Any], arrays: dict[str, np.ndarray]):
        self.lo, self.hi = init["lo"], init["hi"]
        self.index, self.out_layout = init["index"], init["out_layout"]
        self.worlds = LocalWorlds(init["cfg"], self.hi - self.lo)
        self.ctrl = {k: v[self.lo:self.hi] for k, v in arrays.items() if k != "renewed"}
        self.renewed = arrays["renewed"]
        self.blocks: dict[int, tuple[Any, dict[str, np.ndarray]]] = {}

    def _out(self, block: int) -> dict[str, np.ndarray]:
        rows = self.blocks[block][1]
        return {"obs": rows["obs"], "rest": rows["rest"], "final_obs": self.ctrl["final_obs"],
                "episode": self.ctrl["episode"]}

    def step_into(self, block: int) -> None:
        self.renewed[self.index] = self.worlds.step(self.ctrl["actions"], self._out(block))

    def handle(self, msg: tuple) -> Any:
        """("map", block, name), ("reset", keys, mask, state, block) or ("call", fn, *args) (a test
        hook: fn(shard, *args))."""
        if msg[0] == "map":  # a new output block of the env
            self.blocks[msg[1]] = map_block_rows(msg[2], self.out_layout, self.lo, self.hi)
            return None
        if msg[0] == "reset":
            self.worlds.reset(msg[1], msg[2], msg[3], self._out(msg[4]))
            return None
        if msg[0] == "call":
            return msg[1](self, *msg[2:])
        raise ValueError(f"unknown command {msg[0]!r}")


def jax_shard(init: dict[str, Any], arrays: dict[str, np.ndarray]) -> WorkerShard:
    """A worker's JAX-engine shard (the ``factory`` of :func:`quadswarm_mj.envs.workers.worker_main`)."""
    return WorkerShard(init, arrays)


def worker_environ() -> dict[str, str | None]:
    """The environment of a JAX-engine worker: JAX on CPU with ONE device (the parent's device count,
    e.g. from :func:`quadswarm_mj.use_cpu_cores` or ``--xla_force_host_platform_device_count``, is
    not inherited)."""
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split()
             if not f.startswith("--xla_force_host_platform_device_count")]
    return {"JAX_PLATFORMS": "cpu", "JAX_NUM_CPU_DEVICES": "1", "XLA_FLAGS": " ".join(flags) or None}


class WorkerWorlds:
    """B worlds split over ``num_workers`` worker processes, each a single-device JAX program pinned
    to one CPU core (worker k to the k-th core this process may run on, cyclically).

    Why (one program per core beats one sharded program on CPU): docs/engines.md ("Cores").

    Transport (:mod:`quadswarm_mj.envs.workers`): a control block (actions, final observations,
    episode constants, flags) and output blocks of shared memory
    (:class:`~quadswarm_mj.envs.workers.OutputBlocks`, at most :data:`MAX_OUTPUT_BLOCKS`). Each
    step's observations and per-step outputs are written by the workers straight into an output
    block that nothing views any more, and the env returns views of it: no copy in this process."""

    def __init__(self, cfg: EnvConfig, num_worlds: int, num_workers: int,
                 timeout: float | None = DEFAULT_WORKER_TIMEOUT_S):
        self.cfg, self.B, self.n = cfg, int(num_worlds), int(num_workers)
        prog = program(cfg, self.B)  # layouts only (traced, not compiled, in this process)
        N, D = cfg.num_quads, cfg.obs_dim
        self.layout = [("actions", (self.B, N, 4), np.float32), ("final_obs", (self.B, N, D), np.float32),
                       ("episode", (self.B, prog.episode_layout.size), np.float64), ("renewed", (self.n,), np.bool_)]
        self.out_layout = [("obs", (self.B, N, D), np.float32), ("rest", (self.B, prog.step_layout.size), np.float64)]
        edges = np.linspace(0, self.B, self.n + 1).round().astype(int)
        self.bounds = [(int(edges[k]), int(edges[k + 1])) for k in range(self.n)]
        cores = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else [None]
        self.res = res = Resources()
        self.out: OutputBlocks | None = None  # the output blocks
        try:
            self.a = map_arrays(res.create_block(layout_bytes(self.layout)).buf, self.layout)
            env = worker_environ()
            for k, (lo, hi) in enumerate(self.bounds):
                init = {"factory": "quadswarm_mj.envs.jax_workers:jax_shard", "shm": res.shm.name,
                        "layout": self.layout, "out_layout": self.out_layout, "cfg": cfg, "lo": lo, "hi": hi,
                        "index": k, "cpu": cores[k % len(cores)], "timeout": timeout}
                res.workers.append(Worker(k, lo, hi, init, environ=env))
            wait_started(res.workers)
            res.unlink()  # every worker has mapped the block: its name can go
            self.out = OutputBlocks(self.out_layout, MAX_OUTPUT_BLOCKS, self._run)
        except BaseException:
            self.close()
            raise

    def _run(self, what: str, msg_for: Any) -> None:
        run_on_workers(self.res.workers, what, msg_for, self.n)

    @property
    def blocks(self) -> list[SharedBlock]:
        """The output blocks (0: the scratch block)."""
        return [] if self.out is None else self.out.blocks

    @property
    def free(self) -> list[bool]:
        """Which output blocks no returned array views."""
        return [] if self.out is None else self.out.free

    def _episode_outputs(self, out: dict[str, np.ndarray], renewed: np.ndarray | None) -> dict[str, np.ndarray]:
        a = self.a
        out["episode"] = a["episode"].copy()
        if renewed is not None:
            final = a["final_obs"].copy()
            for k, (lo, hi) in enumerate(self.bounds):  # no episode ended there: stepped = current observation
                if not renewed[k]:
                    final[lo:hi] = out["obs"][lo:hi]
            out["final_obs"] = final
        return out

    def reset(self, keys: np.ndarray, mask: np.ndarray | None, state: dict[str, Any] | None
              ) -> dict[str, np.ndarray]:
        """Reset every world (or those in ``mask``); returns ``obs``, ``rest`` and ``episode``."""
        def rows(x: Any, k: int) -> Any:
            lo, hi = self.bounds[k]
            return None if x is None else x[lo:hi]

        block = self.out.acquire()

        def msg(k: int) -> tuple:
            sub = None if state is None else {key: (v if isinstance(v, str) or v is None else rows(v, k))
                                              for key, v in state.items()}
            return ("reset", rows(keys, k), rows(mask, k), sub, block)

        self._run("reset", msg)
        return self._episode_outputs(self.out.arrays(block), None)

    def step(self, actions: np.ndarray) -> tuple[dict[str, np.ndarray], bool]:
        """Step every worker: (``obs`` and ``rest``, with ``final_obs`` and ``episode`` if an episode
        ended anywhere; every world's stepped observation in ``final_obs``), and whether one ended."""
        a = self.a
        np.copyto(a["actions"], actions, casting="same_kind")
        block = self.out.acquire()
        msg = STEP_INTO + block.to_bytes(2, "little")
        self._run("step", lambda _: msg)
        out = self.out.arrays(block)
        renewed = a["renewed"]
        if not renewed.any():
            return out, False
        return self._episode_outputs(out, renewed.copy()), True

    def close(self) -> None:
        self.res.release()
        if self.out is not None:
            self.out.close()
