"""Layouts and kernel boundaries aimed at XLA:CPU (same values as the plain JAX forms).

* :func:`worlds_last`: a function's ``jax.vmap`` with the mapped (worlds) axis moved last, so that
  comparisons and reductions over the short quad and component axes run along contiguous worlds
  (the pair distances and events of :mod:`quadswarm_mj.collisions`, the neighbour ranks of
  :mod:`quadswarm_mj.observations`); ``tests/test_worlds_last.py``.
* :func:`kernel_boundary`: an exact identity that XLA:CPU computes in its own kernel, so that a value
  read by many consumers is computed once (the JAX engine's sub-step loop); ``tests/test_components.py``.

On a GPU neither is expected to pay; both are exact (same bits), so they can be dropped there.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


def kernel_boundary(parts: tuple[Any, ...], one: Any) -> tuple[Any, ...]:
    """``parts`` unchanged (each divided by ``one``, a traced scalar equal to 1.0, which is exact),
    computed by XLA:CPU in their own kernels. XLA fuses cheap elementwise producers into every consumer,
    recomputing them there, but does not duplicate a division (an "expensive" op); a value read by many
    consumers is thus computed once and read back. ``one`` must be a run-time value (e.g. ``1 + 0 * i``
    with the loop index ``i``), or XLA folds the division away."""
    return tuple(p / one for p in parts)


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
