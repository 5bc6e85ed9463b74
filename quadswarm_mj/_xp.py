"""Array-namespace helpers: the model is written once against ``xp`` (NumPy or jax.numpy).

JAX is never imported here; a namespace is chosen from the types of the inputs, so the
CPU path runs without JAX installed.
"""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType
from typing import Any

import numpy as np


def is_jax_array(x: Any) -> bool:
    """True for ``jax.Array`` values and tracers (checked by module name, no import)."""
    return type(x).__module__.startswith(("jax", "jaxlib"))


def array_namespace(*arrays: Any) -> ModuleType:
    """Return ``jax.numpy`` if any input is a JAX array or tracer, else ``numpy``."""
    for a in arrays:
        if is_jax_array(a):
            import jax.numpy as jnp

            return jnp
    return np


def safe_normalize(xp: ModuleType, v: Any, eps: float = 1e-5) -> Any:
    """Normalize along the last axis; a zero vector stays (near) zero instead of NaN."""
    n = xp.sqrt(xp.sum(v * v, axis=-1, keepdims=True))
    return v / (n + eps)


def worlds_last(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` for unbatched JAX arrays, whose ``jax.vmap`` moves the mapped axis of every argument LAST
    and calls ``fn`` on those arrays (``jax.custom_batching.custom_vmap``); the results' last axis is
    moved back to the front. ``fn`` must accept trailing batch axes after its own axes (write it
    "rows first": ``x[:, None] - x[None, :]``, reductions over named leading axes).

    Why: XLA:CPU vectorizes along the last axis; the model's arrays end in short axes (N = 8 quads,
    3 components), so a comparison or reduction over them runs at scalar speed, while with the worlds
    axis last the same operations run along contiguous worlds. Same values (the same operations in
    the same order), different memory layout. Integer or non-differentiated results only (no
    autodiff rule: pass ``jax.lax.stop_gradient`` inputs)."""
    import jax

    @jax.custom_batching.custom_vmap
    def mapped(*args: Any) -> Any:
        return fn(*args)

    @mapped.def_vmap
    def _rule(axis_size: int, in_batched: list[bool], *args: Any) -> tuple[Any, Any]:
        jnp = jax.numpy
        if not any(in_batched):
            out = mapped(*args)
            return out, jax.tree.map(lambda _: False, out)
        moved = [jnp.moveaxis(a, 0, -1) if b else jnp.asarray(a)[..., None] for a, b in zip(args, in_batched)]
        out = jax.tree.map(lambda o: jnp.moveaxis(jnp.broadcast_to(o, o.shape[:-1] + (axis_size,)), -1, 0),
                           fn(*moved))
        return out, jax.tree.map(lambda _: True, out)

    return mapped
