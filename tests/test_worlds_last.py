"""quadswarm_mj.perf.xla_cpu.worlds_last: JAX-only layouts (the vmapped worlds axis moved last) for the neighbour
ranks and the pair distances (the kernels the JAX engine's ops hand to the model) give the same values as
the model's plain forms, also under nested vmap and autodiff."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quadswarm_mj.collisions import pairwise_contacts
from quadswarm_mj.observations import _nearest_one_hot, _sorted_position_rows_first
from quadswarm_mj.perf.xla_cpu import _sorted_position_bits, neighbor_rank, pair_distances, worlds_last
from quadswarm_mj.spatial import norm_last


def _stable_ranks(key: np.ndarray, k: int) -> np.ndarray:
    """Reference: the one-hot of a stable argsort's first k (NaNs last)."""
    order = np.argsort(np.where(np.isnan(key), np.inf, key), axis=-1, kind="stable")
    nan_last = np.argsort(np.isnan(np.take_along_axis(key, order, -1)), axis=-1, kind="stable")
    order = np.take_along_axis(order, nan_last, -1)[..., :k]  # (..., N, k)
    return order[..., :, :, None] == np.arange(key.shape[-1])


def _keys() -> np.ndarray:
    rng = np.random.default_rng(0)
    key = rng.integers(0, 4, (3, 5, 8, 8)).astype(np.float32)  # many ties
    key[0, 1, 2, 3] = np.nan
    key[1, 2, 4, :] = np.nan
    key[..., np.arange(8), np.arange(8)] = np.inf
    return key


@pytest.mark.parametrize("kernel", [False, True])
def test_ranks_match_a_stable_argsort_everywhere(kernel):
    """The model's plain ranks and the JAX engine's worlds-last kernel (``rank_fn``)."""
    key = _keys()
    want = _stable_ranks(key, 6)
    k = jnp.asarray(key)
    rank_fn = neighbor_rank() if kernel else None
    one = jax.jit(lambda x: _nearest_one_hot(jnp, x, 6, rank_fn))
    np.testing.assert_array_equal(np.asarray(one(k[1, 2])), want[1, 2])  # one world, no vmap
    np.testing.assert_array_equal(np.asarray(jax.jit(jax.vmap(one))(k[0])), want[0])  # worlds last
    np.testing.assert_array_equal(np.asarray(jax.jit(jax.vmap(jax.vmap(one)))(k)), want)  # nested
    np.testing.assert_array_equal(np.asarray(_nearest_one_hot(jnp, k, 6)), want)  # batched array
    np.testing.assert_array_equal(_nearest_one_hot(np, key, 6), want)  # NumPy


def test_integer_sort_keys_give_the_float_comparisons_ranks():
    """The JAX ranks on integer sort keys equal the float comparison form on keys with negative
    values, -0.0 and +0.0 (equal), +-inf, NaNs of both signs and payloads (equal, last) and ties."""
    rng = np.random.default_rng(3)
    vals = np.array([-2.5, -1.0, -0.0, 0.0, 0.5, 1.0, 1.0, 3.0, np.inf, -np.inf], np.float32)
    key = rng.choice(vals, size=(8, 8, 400)).astype(np.float32)
    bits = key.view(np.uint32)
    nan_at = rng.random(key.shape) < 0.08
    nans = rng.choice(np.array([0x7FC00000, 0xFFC00000, 0x7F800001, 0xFFFFFFFF], np.uint32), size=key.shape)
    key = np.where(nan_at, nans, bits).view(np.float32)
    want = _sorted_position_rows_first(np, key)
    got = jax.jit(_sorted_position_bits)(jnp.asarray(key))
    np.testing.assert_array_equal(np.asarray(got), want)
    # a permutation of 0..N-1 in every row (a stable sort's positions)
    np.testing.assert_array_equal(np.sort(want, axis=1), np.broadcast_to(np.arange(8)[None, :, None], want.shape))


@pytest.mark.parametrize("kernel", [False, True])
def test_pair_distances_values_and_gradient(kernel):
    """The model's plain distances and the JAX engine's worlds-last kernel (``pair_dist``): the same
    values (bits, against each other), and a finite gradient."""
    pos = jnp.asarray(np.random.default_rng(1).normal(size=(6, 8, 3)).astype(np.float32))
    pair_dist = pair_distances() if kernel else None
    want = np.asarray(norm_last(pos[..., :, None, :] - pos[..., None, :, :]))
    got = jax.jit(jax.vmap(lambda p: pairwise_contacts(p, 0.5, pair_dist)[1]))(pos)
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-6)
    other = jax.jit(jax.vmap(lambda p: pairwise_contacts(p, 0.5, None if kernel else pair_distances())[1]))(pos)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(other))
    np.testing.assert_allclose(np.asarray(pairwise_contacts(pos[0], 0.5, pair_dist)[1]), want[0], rtol=1e-6)

    def loss(p: jax.Array) -> jax.Array:
        return jnp.sum(jax.vmap(lambda q: pairwise_contacts(q, 0.5, pair_dist)[1] ** 2)(p))

    g = np.asarray(jax.grad(loss)(pos))
    rel = np.asarray(pos)[:, :, None, :] - np.asarray(pos)[:, None, :, :]
    np.testing.assert_allclose(g, 4.0 * rel.sum(axis=2), rtol=1e-4, atol=1e-4)  # d/dp_i sum_ij |p_i - p_j|^2
    assert np.isfinite(g).all()


def test_worlds_last_mixed_arguments():
    f = worlds_last(lambda a, b: a * 2.0 + b)  # rows first: works with trailing batch axes
    a = jnp.arange(12.0).reshape(4, 3)
    b = jnp.arange(3.0)
    out = jax.vmap(f, in_axes=(0, None))(a, b)
    np.testing.assert_array_equal(np.asarray(out), np.asarray(a) * 2.0 + np.asarray(b))
    np.testing.assert_array_equal(np.asarray(f(a[0], b)), np.asarray(a[0]) * 2.0 + np.asarray(b))
