"""quadswarm_mj.perf.packing returns the same values as the plain default: a state packed into flat
buffers (StatePacker) or into its leaves (LeafPacker) and unpacked again is the same pytree bit for
bit (NaN payloads, -0.0, integer extremes, PRNG keys included), eagerly and under jit; the packed
outputs (OutputLayout) split on the host give back the values packed. ``ravel_pytree``, the
maintained flattener, is shown not to serve (it loses bits and takes no keys)."""

from __future__ import annotations

import numpy as np
import pytest

jax = pytest.importorskip("jax")
jnp = jax.numpy

from quadswarm_mj.perf.packing import LeafPacker, OutputLayout, StatePacker  # noqa: E402


def _bits(x) -> np.ndarray:
    """An array's raw bits (keys: their key data), for exact comparison (NaN payloads, -0.0)."""
    if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
        x = jax.random.key_data(x)
    a = np.atleast_1d(np.asarray(x))
    return a.view(np.uint8) if a.dtype != np.bool_ else a


def _assert_bit_identical(a, b) -> None:
    la, ta = jax.tree.flatten(a)
    lb, tb = jax.tree.flatten(b)
    assert ta == tb
    for x, y in zip(la, lb):
        assert x.dtype == y.dtype and x.shape == y.shape
        np.testing.assert_array_equal(_bits(x), _bits(y))


def _tree(lead: tuple[int, ...], seed: int = 0) -> dict:
    """A state-like pytree with every leaf kind the engine carries, leading axes ``lead``."""
    rng = np.random.default_rng(seed)
    n = int(np.prod(lead, dtype=int))
    f = rng.standard_normal(lead + (3, 4)).astype(np.float32).reshape(-1)
    special = np.array([np.nan, -0.0, np.inf, -np.inf, 1e-45, np.float32(3.4e38)], np.float32)
    f[: special.size] = special[: f.size]
    f = f.view(np.uint32)
    f[0] |= 0x1234  # a NaN with a payload
    f = f.view(np.float32).reshape(lead + (3, 4))
    ints = rng.integers(-(2**31), 2**31, lead + (5,), dtype=np.int64).astype(np.int32)
    ints.reshape(-1)[:2] = [-(2**31), 2**31 - 1]
    keys = jax.random.split(jax.random.key(seed), max(n, 1) * 2).reshape(lead + (2,))
    return {"pos": jnp.asarray(f), "count": jnp.asarray(ints), "flag": jnp.asarray(rng.random(lead + (2,)) < 0.5),
            "small": jnp.asarray(rng.integers(0, 256, lead + (3,), dtype=np.uint8)),
            "scalar": jnp.asarray(np.float32(0.25) * np.ones(lead, np.float32)),
            "nested": {"key": keys, "step": jnp.asarray(np.full(lead, 7, np.int32))}}


@pytest.mark.parametrize("lead", [(), (3,)])
@pytest.mark.parametrize("packer_cls", [StatePacker, LeafPacker])
def test_pack_then_unpack_is_the_identity_bit_for_bit(lead, packer_cls):
    tree = _tree(lead)
    packer = packer_cls(tree, lead) if packer_cls is StatePacker else packer_cls(tree)
    bufs = packer.pack(tree)
    if packer_cls is StatePacker:
        assert len(bufs) == 1 and bufs[0].dtype == np.uint32  # one flat word buffer per call
    _assert_bit_identical(packer.unpack(bufs), tree)
    _assert_bit_identical(jax.jit(lambda t: packer.unpack(packer.pack(t)))(tree), tree)
    # the buffers cross the host boundary (as a copied env's do) and come back unchanged
    host = tuple(np.asarray(b) for b in jax.jit(packer.pack)(tree))
    _assert_bit_identical(jax.jit(packer.unpack)(tuple(jnp.asarray(b) for b in host)), tree)


def test_state_packer_same_values_as_the_leaves_on_an_engine_state():
    """A real one-world state of the JAX engine (and 2 vmapped worlds): flat buffers and leaves agree."""
    pytest.importorskip("mujoco.mjx")
    from quadswarm_mj import EnvConfig
    from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv

    env = MjxQuadSwarmEnv(EnvConfig(num_quads=2, episode_seconds=0.2))
    one = jax.jit(env.reset)(jax.random.key(3))
    many = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(4), 2))
    for state, lead in ((one, ()), (many, (2,))):
        flat, leaves = StatePacker(state, lead), LeafPacker(state)
        via_flat = jax.jit(lambda s, p=flat: p.unpack(p.pack(s)))(state)
        via_leaves = leaves.unpack(leaves.pack(state))
        _assert_bit_identical(via_flat, state)
        _assert_bit_identical(via_flat, via_leaves)


def test_output_layout_split_returns_the_packed_values():
    rng = np.random.default_rng(1)
    out = {"reward": np.float32(0.5), "metrics": rng.standard_normal(4).astype(np.float32),
           "obs": rng.standard_normal((2, 7)).astype(np.float32),
           "goals": rng.standard_normal((2, 3)).astype(np.float32), "done": np.float32(1.0)}
    layout = OutputLayout({k: jax.ShapeDtypeStruct(np.shape(v), np.float32) for k, v in out.items()})
    assert layout.names[0] == "obs" and layout.size == sum(np.size(v) for v in out.values())
    flat = np.asarray(jax.jit(lambda o: layout.pack(o, jnp.float32))(out))
    np.testing.assert_array_equal(flat[layout.slices["obs"]].reshape(2, 7), out["obs"])
    views = layout.split64(flat)
    assert set(views) == set(out) - {"obs"}
    for k, v in views.items():
        assert v.dtype == np.float64 and v.shape == np.shape(out[k])
        np.testing.assert_array_equal(v, np.asarray(out[k], np.float64))
    # B worlds: the same per row
    rows = np.stack([flat, 2 * flat])
    views = layout.split64(rows, (2,))
    np.testing.assert_array_equal(views["goals"][1], 2 * out["goals"].astype(np.float64))


def test_ravel_pytree_does_not_serve_as_the_default():
    """Why the plain default is the leaves: ``ravel_pytree`` casts int32 beside float32 to float32
    (2**24 + 1 does not survive) and rejects typed PRNG keys. If this fails, JAX changed: reconsider."""
    from jax.flatten_util import ravel_pytree

    flat, unravel = ravel_pytree({"x": jnp.float32(1.5), "n": jnp.int32(2**24 + 1)})
    assert int(unravel(flat)["n"]) != 2**24 + 1
    with pytest.raises(TypeError):
        ravel_pytree({"key": jax.random.key(0)})
