"""Array-namespace helpers: the model is written once against ``xp`` (NumPy or jax.numpy).

JAX is never imported here; a namespace is chosen from the types of the inputs, so the
CPU path runs without JAX installed.
"""

from __future__ import annotations

from types import ModuleType
from typing import Any

import numpy as np


def is_jax_array(x: Any) -> bool:
    """True for ``jax.Array`` values and tracers (checked by module name, no import)."""
    return type(x).__module__.startswith(("jax", "jaxlib"))


def array_namespace(*arrays: Any) -> ModuleType:
    """Return ``jax.numpy`` if any input is a JAX array or tracer, else ``numpy``."""
    for a in arrays:
        if type(a) is np.ndarray:  # (the common case, without a call)
            continue
        if is_jax_array(a):
            import jax.numpy as jnp

            return jnp
    return np


def safe_normalize(xp: ModuleType, v: Any, eps: float = 1e-5) -> Any:
    """Normalize along the last axis; a zero vector stays (near) zero instead of NaN."""
    n = xp.sqrt(xp.sum(v * v, axis=-1, keepdims=True))
    return v / (n + eps)


__all__ = ["array_namespace", "is_jax_array", "safe_normalize"]
