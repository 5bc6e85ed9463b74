"""State and output packing at the JAX engine's host boundary (``engine="jax"``).

A jitted call's host cost grows with the number of arrays passed in and out, so the one-world
step passes its ~70-leaf state as ONE flat uint32 buffer (:class:`StatePacker`: float32 and int32
leaves as their bits, bools as 0/1, PRNG keys as their key data; measured ~4x faster per call than
the leaves) and returns everything the host reads as ONE flat float array per world
(:class:`OutputLayout`, split on the host with NumPy views). :class:`LeafPacker` is the plain
default (the state as the tuple of its leaves), kept for B worlds, where flat buffers cost more than
they save. ``jax.flatten_util.ravel_pytree`` does not serve as the default: it converts every leaf
to one dtype (int32 counters beside float32 become float32, which loses bits) and takes no typed
PRNG keys. Same values: ``tests/test_perf_packing.py`` (pack then unpack is the identity, bit for
bit).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["LeafPacker", "OutputLayout", "StatePacker", "key_shape", "wrap_keys"]


def key_shape() -> tuple[int, ...]:
    """The shape of one PRNG key's key data (uint32) under the current default implementation."""
    return tuple(jax.random.key_data(jax.random.key(0)).shape)


def wrap_keys(data: jax.Array) -> jax.Array:
    """Typed PRNG keys from key data (*lead, *key_shape) uint32."""
    return jax.random.wrap_key_data(data)


class StatePacker:
    """Flatten a state pytree with leading axes ``lead`` into one uint32 buffer and back: float32 and
    int32 leaves as their bits, bools as 0/1, PRNG keys as their key data (a leaf of another width,
    e.g. float64 under ``jax_enable_x64``, gets a buffer of its own dtype). Under jit the bit casts,
    slices and the concatenation are cheap XLA ops; the host passes one array per call instead of
    one per leaf (~70) or per dtype (4: measured ~3 us more per call of one world)."""

    WORD = np.dtype(np.uint32)

    def __init__(self, struct: Any, lead: tuple[int, ...]):
        leaves, self.treedef = jax.tree.flatten(struct)
        self.lead = tuple(lead)
        # (group dtype name, start, size, shape, leaf dtype, is_key)
        self.entries: list[tuple[str, int, int, tuple[int, ...], Any, bool]] = []
        sizes: dict[str, int] = {}
        for leaf in leaves:
            is_key = jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key)
            shape = tuple(leaf.shape[len(self.lead):])
            dt = self.WORD if is_key else np.dtype(leaf.dtype)
            if is_key:
                shape = shape + key_shape()
            g = self.WORD.name if dt.itemsize <= 4 else dt.name
            size = int(np.prod(shape))
            self.entries.append((g, sizes.get(g, 0), size, shape, dt, is_key))
            sizes[g] = sizes.get(g, 0) + size
        self.groups = tuple(sorted(sizes))
        self.sizes = sizes

    def _to_group(self, x: jax.Array, g: str) -> jax.Array:
        if g != self.WORD.name or x.dtype == self.WORD:
            return x
        if x.dtype.itemsize == 4:
            return jax.lax.bitcast_convert_type(x, self.WORD)
        return x.astype(self.WORD)  # bool, 8/16-bit integers: by value

    def _from_group(self, x: jax.Array, dt: np.dtype) -> jax.Array:
        if x.dtype == dt:
            return x
        if dt.itemsize == 4:
            return jax.lax.bitcast_convert_type(x, dt)
        return x.astype(dt)

    def pack(self, state: Any) -> tuple[jax.Array, ...]:
        leaves = jax.tree.leaves(state)
        parts: dict[str, list[jax.Array]] = {g: [] for g in self.groups}
        for leaf, (g, _, _, _, _, is_key) in zip(leaves, self.entries):
            x = jax.random.key_data(leaf) if is_key else leaf
            x = jnp.reshape(x, x.shape[:len(self.lead)] + (-1,))  # local lead under shard_map
            parts[g].append(self._to_group(x, g))
        return tuple(jnp.concatenate(parts[g], axis=-1) for g in self.groups)

    def unpack(self, bufs: tuple[jax.Array, ...]) -> Any:
        by_group = dict(zip(self.groups, bufs))
        leaves = []
        for g, start, size, shape, dt, is_key in self.entries:
            buf = by_group[g]
            x = self._from_group(buf[..., start:start + size], dt).reshape(buf.shape[:-1] + shape)
            leaves.append(wrap_keys(x) if is_key else x)
        return jax.tree.unflatten(self.treedef, leaves)


class LeafPacker:
    """A state pytree as the tuple of its leaves (PRNG keys as their key data) and back: the state of
    B worlds stays on the devices as ~70 arrays between calls. (For B worlds, :class:`StatePacker`'s
    flat buffers cost more than they save: XLA:CPU's slices of the rows of a (B, 1473) buffer into
    (B, 8, 3, 3) and similar shapes ran at scalar speed, ~0.7 ms of a 1024-world step.)"""

    def __init__(self, struct: Any):
        leaves, self.treedef = jax.tree.flatten(struct)
        self.is_key = tuple(jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) for x in leaves)

    def pack(self, state: Any) -> tuple[jax.Array, ...]:
        return tuple(jax.random.key_data(x) if k else x for x, k in zip(jax.tree.leaves(state), self.is_key))

    def unpack(self, bufs: tuple[jax.Array, ...]) -> Any:
        return jax.tree.unflatten(self.treedef, [wrap_keys(x) if k else x for x, k in zip(bufs, self.is_key)])


class OutputLayout:
    """Names, shapes and offsets of the packed per-world output (one float array)."""

    #: outputs the host reads as float32 (observations), packed first: the rest is converted to float64
    FLOAT32 = ("obs",)

    def __init__(self, struct: dict[str, Any]):
        self.names = tuple(k for k in self.FLOAT32 if k in struct) + tuple(k for k in struct if k not in self.FLOAT32)
        self.shapes = {k: tuple(v.shape) for k, v in struct.items()}
        self.slices: dict[str, slice] = {}
        off = 0
        for k in self.names:
            n = int(np.prod(self.shapes[k]))
            self.slices[k] = slice(off, off + n)
            off += n
        self.size = off
        #: start of the float64 part (everything after the observations)
        self.f64_start = sum(int(np.prod(self.shapes[k])) for k in self.FLOAT32 if k in self.shapes)
        self.items = [(k, self.slices[k], self.shapes[k]) for k in self.names]
        self.params = tuple(k for k in self.names if k.startswith("params/"))
        # the float64 part as one structured record: its fields are the outputs' views (one view per
        # field instead of a slice and a reshape each: ~18 -> ~6 us per step of one world)
        rest = [(k, sl, shape) for k, sl, shape in self.items if k not in self.FLOAT32]
        self._rec64 = np.dtype({"names": [k for k, _, _ in rest],
                                "formats": [(np.float64, shape) if shape else np.float64 for _, _, shape in rest],
                                "offsets": [8 * (sl.start - self.f64_start) for _, sl, _ in rest],
                                "itemsize": 8 * (self.size - self.f64_start)})

    def pack(self, out: dict[str, jax.Array], dtype: Any) -> jax.Array:
        return jnp.concatenate([jnp.ravel(out[k]).astype(dtype) for k in self.names])

    def split64(self, flat32: np.ndarray, lead: tuple[int, ...] = ()) -> dict[str, np.ndarray]:
        """Float64 views (*lead, *shape) of the non-observation outputs of a packed float32 array
        (only that part is converted)."""
        return self.views64(flat32[..., self.f64_start:].astype(np.float64), lead)

    def views64(self, rest: np.ndarray, lead: tuple[int, ...] = ()) -> dict[str, np.ndarray]:
        """The views of :meth:`split64` from the float64 non-observation part ``rest`` (*lead, size - f64_start)."""
        rest = np.ascontiguousarray(rest).reshape(lead + (-1,))
        rec = rest.view(self._rec64).reshape(lead)  # lead-shaped record array (0-d for one world: fields are arrays)
        return {k: rec[k] for k in self._rec64.names}
