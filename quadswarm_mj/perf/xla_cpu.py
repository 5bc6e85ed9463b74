"""Layouts and kernel boundaries aimed at XLA:CPU (same values as the plain JAX forms).

* :func:`worlds_last`: a function's ``jax.vmap`` with the mapped (worlds) axis moved last, so that
  comparisons and reductions over the short quad and component axes run along contiguous worlds
  (the pair distances and events of :mod:`quadswarm_mj.collisions`, the neighbour ranks of
  :mod:`quadswarm_mj.observations`); ``tests/test_worlds_last.py``.
* :func:`pair_distances`, :func:`pair_events`, :func:`neighbor_rank`: the model's JAX kernels of one
  world with the worlds axis last (the neighbour ranks on integer sort keys), which the JAX engine's
  ops (:class:`quadswarm_mj.core.ops.JaxOps`) hand to the model functions; the model computes the same
  values without them.
* :func:`kernel_boundary`: an exact identity that XLA:CPU computes in its own kernel, so that a value
  read by many consumers is computed once (the JAX engine's sub-step loop); ``tests/test_components.py``.

On a GPU neither is expected to pay; both are exact (same bits), so they can be dropped there.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np


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


@functools.cache
def pair_distances() -> Callable[[Any], Any]:
    """``collisions._pair_distances_rows_first`` of one world's (N, 3) ``pos`` (JAX), vmapped with the
    worlds axis last: the 3-component sums run along contiguous worlds (``collisions.pairwise_contacts``'
    ``pair_dist``; the same values)."""
    import jax.numpy as jnp

    from quadswarm_mj.collisions import _pair_distances_rows_first

    return worlds_last(functools.partial(_pair_distances_rows_first, jnp))


@functools.lru_cache(maxsize=16)
def _pair_events(slots: int) -> Callable[..., Any]:
    import jax.numpy as jnp

    from quadswarm_mj.collisions import _pair_events_rows_first

    return worlds_last(lambda pos, prev, hitbox: _pair_events_rows_first(jnp, pos, prev, hitbox, slots))


def pair_events(pos: Any, prev_contact: Any, hitbox: Any, slots: int) -> tuple[Any, ...]:
    """``collisions._pair_events_rows_first`` of one world's (N, 3) ``pos``, (N, N) ``prev_contact`` and
    the hitbox (a scalar array, m) under JAX, vmapped with the worlds axis last
    (``collisions.quad_collisions_budgeted``' ``pair_events``; the same values)."""
    return _pair_events(slots)(pos, prev_contact, hitbox)


def _sorted_position_bits(key: Any) -> Any:
    """``observations._sorted_position_rows_first`` (the same integers) for a float ``key`` under JAX, on
    integer sort keys: the float bits mapped to integers of the same order (negative floats' magnitude
    bits flipped, then moved up by one so that -0.0 and +0.0 are both 0), every NaN to one value just
    above +inf. A stable sort's "l before j" is then ``key[l] < key[j] + (l < j)`` (an add and a compare
    per pair, no NaN logic)."""
    import jax
    import jax.numpy as jnp

    n = key.shape[0]
    itype = jnp.int32 if key.dtype == jnp.float32 else jnp.int64
    bits = jax.lax.bitcast_convert_type(key, itype)
    negative = bits >> (8 * jnp.dtype(itype).itemsize - 1)  # -1 where the sign bit is set, else 0
    inf_bits = jax.lax.bitcast_convert_type(jnp.asarray(np.inf, key.dtype), itype)
    order = jnp.where(jnp.isnan(key), inf_bits + 1, (bits ^ (negative & jnp.iinfo(itype).max)) - negative)
    tail = (1,) * (key.ndim - 2)
    before = (np.arange(n)[None, :] < np.arange(n)[:, None]).reshape((1, n, n) + tail)  # [j, l] = l < j
    kl, kj = order[:, None, :], order[:, :, None]  # [i, j, l] = key[i, l], key[i, j]
    return jnp.sum((kl < kj + before.astype(itype)).astype(jnp.int32), axis=2)


@functools.cache
def neighbor_rank() -> Callable[[Any], Any]:
    """``observations._sorted_position_rows_first`` of one world's (N, N) ``key`` under JAX, vmapped
    with the worlds axis last (the N^3 comparisons and the sum run along contiguous worlds: the rank
    kernel of a 512-world step 318 -> ~55 us, BENCHMARKS.md; the same integers), on integer sort keys
    (:func:`_sorted_position_bits`); ``observations.neighbor_obs``' ``rank_fn``."""
    return worlds_last(_sorted_position_bits)


def jax_kernels() -> dict[str, Any]:
    """The kernels above by the model's keyword names (``pair_dist``, ``pair_events``, ``rank_fn``)."""
    return {"pair_dist": pair_distances(), "pair_events": pair_events, "rank_fn": neighbor_rank()}
