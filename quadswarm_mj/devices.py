"""JAX on the CPU for the JAX engine: one device per core (:func:`use_cpu_cores`), XLA:CPU options for its
small programs (:func:`tune_jax_cpu`, :func:`loop_once`) and glibc's allocator (:func:`reuse_freed_memory`).

All of them change the whole process, so the package never calls them on import or use: they are the
user's explicit opt-in (the console commands call them). The device count is fixed at the first JAX
operation of the process, so call :func:`use_cpu_cores` first (or set ``JAX_NUM_CPU_DEVICES``). Why one
device per core pays and what the XLA:CPU settings do: docs/engines.md ("Cores", "XLA:CPU settings").
"""

from __future__ import annotations

import functools
import os
import sys
from collections.abc import Callable
from typing import Any


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


#: XLA:CPU compiles a ``while`` loop whose body touches fewer bytes than this (one iteration, XLA's cost
#: analysis) into ONE kernel (``SmallWhileLoopHoistingPass``; XLA's default limit is 1 kB). 256 kB holds
#: the JAX engine's one-world step (~67 kB) and keeps larger loops (rollouts of many worlds, PPO
#: updates) on XLA's default runtime, which measured faster for them: the trainers lost 20 % with a
#: 64 MB limit.
LOOP_KERNEL_BYTES = 256 * 1024
LOOP_KERNEL_FLAG = f"--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold={LOOP_KERNEL_BYTES}"


def jax_started() -> bool:
    """Whether JAX has created its backends (clients) in this process; options read at client creation
    (``XLA_FLAGS``, ``jax_cpu_enable_async_dispatch``, ``jax_num_cpu_devices``) no longer change then."""
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):
        return True


def tune_jax_cpu(allocator: bool = True) -> dict[str, bool]:
    """Opt-in, process-wide XLA:CPU tuning for the JAX engine's small programs. Call it first thing
    in your program, before JAX starts (the first JAX operation)::

        import quadswarm_mj
        quadswarm_mj.tune_jax_cpu()   # this process only; before anything runs on JAX

    Importing or using quadswarm_mj never does this by itself (the package changes no environment
    variable, JAX config value or allocator setting); the package's console commands
    (``quadswarm-train``, ``quadswarm-benchmark``, ...) and scripts call it. It sets:

    * small loops as single kernels (``XLA_FLAGS`` += :data:`LOOP_KERNEL_FLAG`): the JAX engine's
      one-world step runs in a one-trip loop (:func:`loop_once`) and becomes one kernel instead of
      ~160 kernels handed between XLA:CPU's pool threads;
    * synchronous dispatch on CPU (``jax_cpu_enable_async_dispatch = False``): a single-device
      program runs in the calling thread, which a ``step()`` returning NumPy waits for anyway;
    * with ``allocator=True``, glibc's allocator keeps freed large blocks (:func:`reuse_freed_memory`).

    Both XLA options are set only before JAX has started (else nothing changes); a value you set
    yourself (``xla_cpu_small_while_loop_byte_threshold`` in ``XLA_FLAGS``) is kept, and
    ``QUADSWARM_MJ_TUNE_JAX=0`` turns the call into a no-op (the console commands then run with JAX's
    defaults). Only the speed of CPU programs changes; results agree to float32 rounding. Returns what
    is in force as far as this process's settings tell.

    Caveat: XLA:CPU cannot put its YNNPACK library fusions into a loop kernel and then fails with
    "Fusion kind not implemented on CPU"; none of this project's programs has one in a loop below the
    limit, but if one of yours does, do not call this (or set your own
    ``xla_cpu_small_while_loop_byte_threshold`` in ``XLA_FLAGS``, which is then kept)."""
    on = os.environ.get("QUADSWARM_MJ_TUNE_JAX", "1") != "0"
    started = jax_started()
    flags = os.environ.get("XLA_FLAGS", "")
    if on and not started and "xla_cpu_small_while_loop_byte_threshold" not in flags:
        os.environ["XLA_FLAGS"] = (flags + " " + LOOP_KERNEL_FLAG).strip()
    import jax

    if on and not started:
        jax.config.update("jax_cpu_enable_async_dispatch", False)
    if on and allocator:
        reuse_freed_memory()
    return {"loop_kernels": "xla_cpu_small_while_loop_byte_threshold" in os.environ.get("XLA_FLAGS", ""),
            "sync_dispatch": not jax.config.values.get("jax_cpu_enable_async_dispatch", True)}


@functools.lru_cache(maxsize=1)
def loop_kernels_in_force() -> bool:
    """Whether XLA:CPU compiles a loop with a 32 kB body into one kernel in this process (probed once by
    compiling such a loop: true when :func:`tune_jax_cpu` ran before JAX started)."""
    import jax
    import jax.numpy as jnp

    def loop(x: jax.Array) -> jax.Array:
        n = jax.lax.optimization_barrier(jnp.int32(2))
        return jax.lax.while_loop(lambda c: c[0] < n, lambda c: (c[0] + 1, c[1] * 0.5 + 1.0), (jnp.int32(0), x))[1]

    if jax.default_backend() != "cpu":  # the option is XLA:CPU's
        return False
    text = jax.jit(loop).lower(jnp.zeros(4096, jnp.float32)).compile().as_text()
    return "xla_cpu_small_call" in text


def loop_once(step: Callable[..., tuple]) -> Callable[..., tuple]:
    """``step(state, *args) -> (state, *outputs)`` as the body of a ``while`` loop with one trip (the
    trip count hidden behind an optimization barrier, so XLA keeps the loop). With
    :func:`loop_kernels_in_force` XLA:CPU then compiles the whole step into one kernel instead of
    ~160 separately launched ones (a one-world step: ~185 -> ~40 us per call, BENCHMARKS.md); without
    it the loop only costs, so ``step`` is returned as is. Same results either way."""
    if not loop_kernels_in_force():
        return step

    import jax
    import jax.numpy as jnp

    def run(state: Any, *args: Any) -> tuple:
        outs = jax.eval_shape(lambda s: step(s, *args)[1:], state)
        zeros = jax.tree.map(lambda o: jnp.zeros(o.shape, o.dtype), outs)
        trips = jax.lax.optimization_barrier(jnp.int32(1))

        def body(carry: tuple) -> tuple:
            i, s, _ = carry
            new = step(s, *args)
            return i + 1, new[0], tuple(new[1:])

        _, s, o = jax.lax.while_loop(lambda c: c[0] < trips, body, (jnp.int32(0), state, tuple(zeros)))
        return (s, *o)

    return run


_MALLOC_TUNED: bool | None = None


def reuse_freed_memory() -> bool:
    """Let glibc's allocator keep and reuse the JAX engine's large per-step buffers (Linux only).

    XLA:CPU allocates a step's outputs and temporaries (megabytes for a thousand worlds) at every
    call. glibc serves blocks above its mmap threshold with fresh ``mmap`` pages and unmaps them on
    free, so each step page-faults its buffers in again: measured ~1.4 ms of a 5.5 ms step of 1024
    worlds. This raises the mmap threshold to glibc's maximum (32 MB) and the trim threshold to
    512 MB, so freed blocks return to the heap and the next step reuses them (the process keeps its
    peak heap instead of returning it to the OS; it does not grow with the number of steps).
    Process-wide, so never called by the package itself: :func:`tune_jax_cpu` calls it (opt-in);
    ``QUADSWARM_MJ_MALLOPT=0`` turns it off. Returns whether the settings are in force."""
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


#: The most worlds one jitted, vmapped ``physics="mjx"`` program steps when both XLA:CPU options of
#: :func:`tune_jax_cpu` are in force on jax >= 0.10 (the reason jax was once pinned to 0.9.2: "jit(vmap(
#: mjx.step)) hangs at >= 128 worlds on jax 0.10"). Measured on jax 0.10.2, mujoco-mjx 3.17.0 (CPU, 2
#: shared cores, 8 quads, ``jax.jit(jax.vmap(MjxQuadSwarmEnv(physics="mjx").step))``, one call after
#: compiling, ``scripts/mjx_tuned_hang.py``): with JAX's defaults, either option alone, or both, 512
#: worlds ran in 1.1-3.1 s in 7 of 8 runs; the eighth (both options and the allocator setting) did not
#: return within 160 s after compiling. jax 0.9.2 ran 512 (and, reported, 4096) worlds with both. Not
#: understood beyond that, so the package's own batched ``physics="mjx"`` programs refuse more worlds
#: than this under both options on jax >= 0.10 (:func:`check_mjx_batch`); the default free-body physics
#: and JAX's default settings are not affected.
MJX_TUNED_MAX_WORLDS = 128


def _jax_at_least(major: int, minor: int) -> bool:
    import jax

    parts = [int(p) for p in jax.__version__.split(".")[:2] if p.isdigit()]
    return tuple(parts) >= (major, minor)


def check_mjx_batch(physics: str, num_worlds: int) -> None:
    """RuntimeError before a ``physics="mjx"`` program of more than :data:`MJX_TUNED_MAX_WORLDS` worlds
    is built in a process where it would hang: jax >= 0.10 on CPU with both :func:`tune_jax_cpu`
    options in force. Nothing happens otherwise (other physics, fewer worlds, JAX's defaults)."""
    if physics != "mjx" or num_worlds <= MJX_TUNED_MAX_WORLDS or "jax" not in sys.modules:
        return
    import jax

    if not _jax_at_least(0, 10) or jax.config.values.get("jax_cpu_enable_async_dispatch", True):
        return
    if jax.default_backend() != "cpu" or not loop_kernels_in_force():
        return
    raise RuntimeError(
        f'physics="mjx" with {num_worlds} worlds in one program hangs on jax {jax.__version__} (CPU) when both '
        "XLA:CPU options of quadswarm_mj.tune_jax_cpu() are in force (small loops as single kernels and "
        f"synchronous dispatch); at most {MJX_TUNED_MAX_WORLDS} worlds run then. Run without tune_jax_cpu() "
        "(console commands: QUADSWARM_MJ_TUNE_JAX=0), use the free-body physics (collision_model=\"paper\"), "
        f"or step at most {MJX_TUNED_MAX_WORLDS} worlds per program.")
