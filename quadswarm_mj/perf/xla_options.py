"""Per-program XLA:CPU compile options for the JAX engine's one-world programs: process-local speed
without :func:`quadswarm_mj.tune_jax_cpu`'s process-wide settings.

``jax.jit(f, compiler_options=...)`` sets XLA ``DebugOptions`` fields for that program only (no
``XLA_FLAGS``, no JAX config). ``xla_cpu_use_fusion_emitters=False`` (XLA:CPU's older fused-loop
emitter) compiles the one-world programs faster: measured on the 2-core machine under varying load
(``python scripts/bench_xla_options.py --variant default|options|tune|tune+options --quads 1|8``,
two alternating rounds), the time from construction to the first step's return was 0.67-0.9x that
of JAX's defaults; steady-state steps/s stayed within the run-to-run noise (0.7-1.3x). It does NOT
reach :func:`quadswarm_mj.tune_jax_cpu` (~3x the steps/s of the defaults in the same rounds): its
small-loop threshold cannot be set per program (``xla_backend_extra_options`` is a map field, which
compile options do not take) and synchronous dispatch is a client setting. Results are the same bit
for bit (``tests/test_perf_xla_options.py``). Applied on the CPU backend only, where this jax
accepts the option (:func:`one_world_options` probes it once); ``ENABLED = False`` turns it off.
"""

from __future__ import annotations

import functools
from typing import Any

#: the compile options of the one-world programs on CPU
ONE_WORLD_CPU_OPTIONS: dict[str, Any] = {"xla_cpu_use_fusion_emitters": False}
#: set to False (before the first env of a config is built) for JAX's default compile options
ENABLED = True


@functools.lru_cache(maxsize=1)
def _accepted() -> dict[str, Any]:
    import jax
    import jax.numpy as jnp

    if jax.default_backend() != "cpu":
        return {}
    try:
        jax.jit(lambda x: x + 1, compiler_options=ONE_WORLD_CPU_OPTIONS).lower(jnp.zeros(2)).compile()
    except Exception:  # noqa: BLE001 - an XLA without this option: JAX's defaults
        return {}
    return dict(ONE_WORLD_CPU_OPTIONS)


def one_world_options() -> dict[str, Any]:
    """The compile options for a one-world program here: :data:`ONE_WORLD_CPU_OPTIONS` on a CPU
    backend whose XLA accepts them and with :data:`ENABLED`, else ``{}`` (JAX's defaults)."""
    return _accepted() if ENABLED else {}
