"""One JAX CPU device per core, so the JAX engine shards worlds over the cores.

JAX exposes a single CPU device by default and parallelizes each XLA kernel over the cores
itself. For the JAX engine's many small kernels (arrays of a few hundred to a few thousand
numbers) that intra-op split costs more than it gains; giving each core its own device and
sharding the worlds over the devices (``quadswarm_mj.envs.sharding``: every device steps its own
worlds, no communication) measured 1.5-2x the samples/s of one device on the 2-core machine
(BENCHMARKS.md). The vector env (``engine="jax"``), ``benchmark_mjx`` and the JAX-engine trainer
use every device whose count divides their number of worlds.

The device count is fixed when JAX creates its CPU client, i.e. at the first JAX operation of the
process, so call this first (or set the environment variable ``JAX_NUM_CPU_DEVICES``)::

    import quadswarm_mj
    quadswarm_mj.use_cpu_cores()          # before anything runs on JAX
    env = quadswarm_mj.QuadSwarmVectorEnv(cfg, num_envs=1024, engine="jax")
"""

from __future__ import annotations

import os
import sys


def cpu_devices_option(text: str) -> int | None:
    """The console commands' ``--cpu-devices`` value: "cores" -> None (one device per core), "N" -> N
    (an int >= 1); ValueError otherwise."""
    if text == "cores":
        return None
    if not text.isdigit() or int(text) < 1:
        raise ValueError(f"--cpu-devices must be 'cores' or an int >= 1, got {text!r}")
    return int(text)


def use_cpu_cores(n: int | None = None, strict: bool = True) -> int:
    """Ask JAX for ``n`` CPU devices (default: the cores this process may run on) and return the
    number it has. If JAX already started with a different number: RuntimeError (call it before any
    JAX operation, or set ``JAX_NUM_CPU_DEVICES``), or with ``strict=False`` a warning and the
    devices JAX has. ValueError for ``n < 1``."""
    if n is None:
        n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise ValueError(f"n must be an int >= 1 (CPU devices), got {n!r}")
    import jax

    try:
        jax.config.update("jax_num_cpu_devices", n)
    except RuntimeError as e:  # the CPU client exists already
        have = len(jax.devices("cpu"))
        if have == n:
            return have
        msg = (f"JAX already runs with {have} CPU device(s), so use_cpu_cores({n}) comes too late: call it "
               f"before any JAX operation of the process, or set JAX_NUM_CPU_DEVICES={n} in the environment")
        if strict:
            raise RuntimeError(msg) from e
        import warnings

        warnings.warn(msg + f"; continuing with {have}", RuntimeWarning, stacklevel=2)
        return have
    return len(jax.devices("cpu"))


_MALLOC_TUNED: bool | None = None


def reuse_freed_memory() -> bool:
    """Let glibc's allocator keep and reuse the JAX engine's large per-step buffers (Linux only).

    XLA:CPU allocates a step's outputs and temporaries (megabytes for a thousand worlds) at every
    call. glibc serves blocks above its mmap threshold with fresh ``mmap`` pages and unmaps them on
    free, so each step page-faults its buffers in again: measured ~1.4 ms of a 5.5 ms step of 1024
    worlds. This raises the mmap threshold to glibc's maximum (32 MB) and the trim threshold to
    512 MB, so freed blocks return to the heap and the next step reuses them (the process keeps its
    peak heap instead of returning it to the OS; it does not grow with the number of steps).
    Called by the JAX engine's vector env; ``QUADSWARM_MJ_MALLOPT=0`` turns it off. Returns whether
    the settings are in force."""
    global _MALLOC_TUNED
    if _MALLOC_TUNED is not None:
        return _MALLOC_TUNED
    _MALLOC_TUNED = False
    if os.environ.get("QUADSWARM_MJ_MALLOPT", "1") == "0" or not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None)
        m_trim_threshold, m_mmap_threshold = -1, -3  # <malloc.h>
        _MALLOC_TUNED = bool(libc.mallopt(m_mmap_threshold, 32 * 1024 * 1024)) and bool(
            libc.mallopt(m_trim_threshold, 512 * 1024 * 1024))
    except (OSError, AttributeError):  # not glibc
        _MALLOC_TUNED = False
    return _MALLOC_TUNED
