"""Training over several processes and hosts with ``jax.distributed`` (the JAX-engine trainer).

Every process runs the same program (SPMD): the trainer's mesh spans the devices of all processes, each
process steps the worlds of its own devices, and the update's one ``pmean`` per minibatch averages the
gradients over every device of every process (XLA collectives; on CPU through gloo), so the replicated
parameters stay the same everywhere. :func:`initialize` starts it (before JAX does anything else in the
process: the console command calls it, the package never does on import); :func:`launch_local` starts N
local processes of ``quadswarm-train`` for testing (``python -m quadswarm_mj.training.distributed``).
The host-side helpers here keep the processes' decisions in step: :func:`broadcast_from_main` (stop,
checkpoint and the learning rate come from process 0's clock), :func:`gather_worlds` (world-sharded arrays
for the checkpoint) and :func:`global_array` (host values onto the global mesh).

See docs/training.md "Several processes and hosts" for the commands.
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
from typing import Any

import numpy as np


def initialize(num_processes: int, process_id: int | None = None, coordinator: str | None = None,
               cpu_devices: int | None = None) -> None:
    """Join the ``num_processes``-process job as ``process_id`` (coordinator ``host:port``, process 0's
    address). Sets, for this process only and before JAX starts: CPU collectives through gloo
    (``jax_cpu_collectives_implementation``, the default of recent JAX), ``cpu_devices`` local CPU devices
    (None: one per core) and then calls ``jax.distributed.initialize``. ``process_id``/``coordinator`` left
    None are detected by JAX on a cluster (SLURM, Open MPI, ...). Raises RuntimeError if JAX has already
    started."""
    from quadswarm_mj.devices import jax_started

    if not isinstance(num_processes, int) or num_processes < 1:
        raise ValueError(f"num_processes must be an int >= 1, got {num_processes!r}")
    if process_id is not None and not 0 <= process_id < num_processes:
        raise ValueError(f"process_id must be in [0, {num_processes}), got {process_id!r}")
    if jax_started():
        raise RuntimeError("jax.distributed must be initialized before JAX starts (the first JAX operation)")
    import jax

    if cpu_devices is None:
        cpu_devices = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.config.update("jax_num_cpu_devices", cpu_devices)  # (asking jax.devices() now would start JAX too early)
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes, process_id=process_id)


def process_count() -> int:
    import jax

    return jax.process_count()


def is_main() -> bool:
    """Whether this is process 0 (the one that writes logs, checkpoints and the policy file)."""
    import jax

    return jax.process_index() == 0


def broadcast_from_main(values: np.ndarray) -> np.ndarray:
    """Process 0's ``values`` (a small float64 array) on every process; ``values`` itself with one process."""
    import jax

    if jax.process_count() == 1:
        return values
    from jax.experimental import multihost_utils

    return np.asarray(multihost_utils.broadcast_one_to_all(np.asarray(values, np.float64)))


def gather_worlds(x: Any) -> np.ndarray:
    """The full value of a global array sharded over the worlds axis, on every process (a collective: every
    process must call it)."""
    import jax

    if jax.process_count() == 1 or x.is_fully_addressable:
        return np.asarray(x)
    from jax.experimental import multihost_utils

    return np.asarray(multihost_utils.process_allgather(x, tiled=True))


def global_array(x: Any, sharding: Any) -> Any:
    """``x`` (a host value, the same on every process, with its global shape) as an array of ``sharding``:
    each process places only the slices of its own devices (no value crosses processes)."""
    import jax

    x = np.asarray(x)
    return jax.make_array_from_callback(x.shape, sharding, lambda idx: x[idx])


# ---------------------------------------------------------------------------- local launcher
def free_port() -> int:
    """A TCP port free on this host now (for the coordinator of a local job)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def launch_local(n: int, train_argv: list[str], port: int | None = None, cpu_devices: int | None = None,
                 env: dict[str, str] | None = None, command: list[str] | None = None,
                 **popen: Any) -> list[subprocess.Popen]:
    """Start ``n`` processes of ``quadswarm-train train_argv`` on this host, joined through a coordinator on
    ``127.0.0.1:port`` (default: a free port); each gets ``--cpu-devices`` (default: the cores divided
    among the processes, at least 1). ``command``: the program instead of ``python -m
    quadswarm_mj.cli.train`` (it gets the same options); ``env`` is added to the environment, ``popen``
    goes to ``subprocess.Popen``. Returns the processes (see :func:`wait_all`)."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    port = free_port() if port is None else port
    if cpu_devices is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        cpu_devices = max(1, cores // n)
    procs = []
    for i in range(n):
        argv = [*(command or [sys.executable, "-m", "quadswarm_mj.cli.train"]), *train_argv, "--cpu-devices",
                str(cpu_devices), "--num-processes", str(n), "--process-id", str(i), "--coordinator",
                f"127.0.0.1:{port}"]
        procs.append(subprocess.Popen(argv, env={**os.environ, **(env or {})}, **popen))
    return procs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description="Start N local processes of quadswarm-train as one data-parallel job (testing the multi-host "
                    "setup on one machine). Example: python -m quadswarm_mj.training.distributed -n 2 -- "
                    "--preset single --timesteps 1e6 --out runs/two")
    ap.add_argument("-n", "--num-processes", type=int, default=2)
    ap.add_argument("--port", type=int, help="coordinator port (default: a free one)")
    ap.add_argument("--cpu-devices", type=int, help="CPU devices per process (default: cores / processes)")
    ap.add_argument("train_argv", nargs=argparse.REMAINDER, help="-- then the quadswarm-train options")
    a = ap.parse_args(argv)
    rest = a.train_argv[1:] if a.train_argv[:1] == ["--"] else a.train_argv
    procs = launch_local(a.num_processes, rest, a.port, a.cpu_devices)
    codes = wait_all(procs)
    bad = [i for i, c in enumerate(codes) if c]
    if bad:
        print(f"processes {bad} failed with exit codes {[codes[i] for i in bad]}", file=sys.stderr)
    return max(codes, key=abs) if bad else 0


def wait_all(procs: list[subprocess.Popen], poll_s: float = 0.5, timeout: float | None = None) -> list[int]:
    """Wait for the processes of one job; if one fails, the others (which would wait for it in their next
    collective) are terminated. Returns the exit codes; TimeoutError after ``timeout`` seconds (the
    processes are left running)."""
    import time

    t0 = time.monotonic()
    while any(p.poll() is None for p in procs):
        if any(p.poll() not in (None, 0) for p in procs):
            for p in procs:
                if p.poll() is None:
                    p.terminate()
            break
        if timeout is not None and time.monotonic() - t0 > timeout:
            raise TimeoutError(f"the job's processes did not end within {timeout} s")
        time.sleep(poll_s)
    return [p.wait() for p in procs]


if __name__ == "__main__":
    raise SystemExit(main())
