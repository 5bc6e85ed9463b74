"""All random numbers of one JAX reset or step from ONE threefry hash (speed code for XLA:CPU).

:class:`FusedJaxSampler` is a :class:`~quadswarm_mj.random_draws.JaxSampler` that draws a whole spec
from one threefry call (sliced per entry) instead of one call per entry, with uniforms and normals made
from the words as ``jax.random.uniform`` / ``jax.random.normal`` make them (the same distributions).
:func:`step_key_and_numbers` makes the next step's numbers in one pass over an unrolled threefry
(:func:`threefry_2x32_unrolled`, bit-identical to ``jax.extend.random.threefry_2x32``) with its own
float32 ``erf_inv`` (:func:`erf_inv_f32`) and the results packed two per complex64; the JAX engine
with ``draws="fused"`` (opt-in; the default is ``jax.random``) carries them in ``info["step_numbers"]``.
Why each trick pays on XLA:CPU is said where it is made;
``tests/test_jax_draws.py`` checks the same values (bits, or the distributions) as the plain forms.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quadswarm_mj.random_draws import DrawSpec, JaxSampler, Normal, Uniform

_ROTATIONS = ((13, 15, 26, 6), (17, 29, 16, 24))


def _threefry_rounds(x0: jax.Array, x1: jax.Array, ks: tuple[jax.Array, ...]) -> tuple[jax.Array, jax.Array]:
    """Threefry-2x32's 20 rounds and key injections on the keyed block words (x0, x1)."""
    for group in range(5):
        for r in _ROTATIONS[group % 2]:
            x0 = x0 + x1
            x1 = (x1 << jnp.uint32(r)) | (x1 >> jnp.uint32(32 - r))
            x1 = x1 ^ x0
        x0 = x0 + ks[(group + 1) % 3]
        x1 = x1 + ks[(group + 2) % 3] + jnp.uint32(group + 1)
    return x0, x1


def threefry_2x32_unrolled(key_data: jax.Array, count: jax.Array) -> jax.Array:
    """``jax.extend.random.threefry_2x32(key_data, count)`` (same words) as straight-line code.

    ``key_data`` (2,) uint32, ``count`` (2 M,) uint32 hashed as the pairs (count[:M], count[M:]).
    On CPU, JAX lowers threefry to a rolled loop of 5 iterations (small compiles), which XLA runs as
    ~40 small kernels; unrolled it is one elementwise kernel that XLA fuses with its consumer."""
    k0, k1 = key_data[0], key_data[1]
    ks = (k0, k1, k0 ^ k1 ^ jnp.uint32(0x1BD11BDA))
    half = count.shape[0] // 2
    x0, x1 = count[:half] + ks[0], count[half:] + ks[1]
    x0, x1 = _threefry_rounds(x0, x1, ks)
    return jnp.concatenate([x0, x1])


#: Counter offset of the step's words (the pairs (2^31 + i, 2^31 + M + i)): never the small counters
#: of ``jax.random.split`` / ``fold_in`` of the same key, so the streams stay disjoint.
_COUNTER_BASE = np.uint32(2**31)


def step_words(key: jax.Array, total: int) -> tuple[jax.Array, jax.Array]:
    """(next key, ``total`` uint32 words) from a threefry key with ONE hash: the next key's data are
    words 0-1, the draws the rest (counter mode; replaces ``split`` + ``split`` + ``bits``)."""
    n = total + 2
    n += n % 2
    words = threefry_2x32_unrolled(jax.random.key_data(key), jnp.arange(n, dtype=jnp.uint32) + _COUNTER_BASE)
    if not jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key):  # a raw (legacy uint32) key stays raw
        return words[:2], words[2:2 + total]
    return jax.random.wrap_key_data(words[:2], impl=jax.random.key_impl(key)), words[2:2 + total]


def _unit_numbers(words: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(U[0, 1), N(0, 1)) from uint32 words as ``jax.random.uniform`` (23 mantissa bits, the same
    floats) and ``jax.random.normal`` (sqrt(2) erfinv of a uniform on [nextafter(-1, 0), 1); the erfinv
    is :func:`erf_inv_f32`, within a few float32 ulp of ``jax.lax.erf_inv``) make them."""
    u01 = jax.lax.bitcast_convert_type((words >> 9) | jnp.uint32(0x3F800000), jnp.float32) - 1.0
    lo_n = np.nextafter(np.float32(-1.0), np.float32(0.0))
    return u01, np.sqrt(2.0).astype(np.float32) * erf_inv_f32(jnp.maximum(lo_n, lo_n + (1.0 - lo_n) * u01))


def step_key_and_numbers(key: jax.Array, normal_mask: np.ndarray, tof_mask: np.ndarray | None = None,
                         dropout: float = 0.0) -> tuple[jax.Array, jax.Array]:
    """(next key, float32 unit numbers) equal to ``step_words`` followed by
    :meth:`FusedJaxSampler.unit_numbers` (the same bits), in ONE pass over the threefry rounds.

    An elementwise XLA:CPU kernel makes one output per element, so the block words x0 and x1 of
    :func:`threefry_2x32_unrolled` come out of two kernels that each run all 20 rounds. Here each
    block's two results (its two unit numbers, or the next key's raw words) leave the kernel as the
    two halves of one complex64 (bit casts and selects only: no arithmetic on the carried bits),
    made in a two-trip loop over halves of the blocks (a loop's result is a buffer XLA cannot fuse
    back into its consumers; a one-trip loop would be inlined). ``normal_mask`` (total,) bool: the
    positions of normals (N(0, 1)); the others are U[0, 1).

    ``tof_mask`` (total,) bool (or None): positions whose uniform u is a deck ray's (the VL53L1x model
    of :mod:`quadswarm_mj.sensors`, reading lost where u < ``dropout``): they hold :func:`tof_numbers`
    of u instead (the ray's standard normal noise, NaN where the reading is lost), from the same
    erf_inv as the normals (the kernel computes one erf_inv per word either way)."""
    total = int(normal_mask.shape[0])
    n = total + 2
    n += n % 2
    half = n // 2
    q = (half + 1) // 2  # blocks per trip
    # block m: x0 is word m, x1 is word half + m (threefry_2x32 pairs the counter's two halves)
    full = np.zeros(2 * half, bool)
    full[2:2 + total] = normal_mask
    count = np.arange(2 * half, dtype=np.uint32) + _COUNTER_BASE

    def padded(x: np.ndarray) -> np.ndarray:
        return np.concatenate([x, np.zeros(2 * q - x.shape[0], x.dtype)])

    count0, count1 = padded(count[:half]), padded(count[half:])
    normal0, normal1 = padded(full[:half]), padded(full[half:])
    tof_full = np.zeros(2 * half, bool)
    if tof_mask is not None:
        tof_full[2:2 + total] = tof_mask
    tof0, tof1 = padded(tof_full[:half]), padded(tof_full[half:])
    has_tof = bool(tof_full.any())
    is_key = padded(np.arange(half) < 2)
    kd = jax.random.key_data(key)
    k0, k1 = kd[0], kd[1]
    ks = (k0, k1, k0 ^ k1 ^ jnp.uint32(0x1BD11BDA))

    def body(i: jax.Array, acc: jax.Array) -> jax.Array:
        def pick(c: np.ndarray) -> jax.Array:
            return jnp.where(i == 0, c[:q], c[q:])

        x0, x1 = pick(count0) + ks[0], pick(count1) + ks[1]
        x0, x1 = _threefry_rounds(x0, x1, ks)
        if has_tof:
            v0 = _numbers_with_tof(x0, pick(normal0), pick(tof0), dropout)
            v1 = _numbers_with_tof(x1, pick(normal1), pick(tof1), dropout)
            v0 = jnp.where(pick(is_key), jax.lax.bitcast_convert_type(x0, jnp.float32), v0)
        else:
            u0, n0 = _unit_numbers(x0)
            u1, n1 = _unit_numbers(x1)
            v0 = jnp.where(pick(is_key), jax.lax.bitcast_convert_type(x0, jnp.float32),
                           jnp.where(pick(normal0), n0, u0))
            v1 = jnp.where(pick(normal1), n1, u1)
        return jax.lax.dynamic_update_slice(acc, jax.lax.complex(v0, v1), (i * q,))

    pairs = jax.lax.fori_loop(0, 2, body, jnp.zeros((2 * q,), jnp.complex64))[:half]
    flat = jnp.concatenate([jnp.real(pairs), jnp.imag(pairs)])
    key_words = jax.lax.bitcast_convert_type(flat[:2], jnp.uint32)
    if jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key):
        key_words = jax.random.wrap_key_data(key_words, impl=jax.random.key_impl(key))
    return key_words, flat[2:2 + total]


def _tof_argument(u01: jax.Array, dropout: float) -> jax.Array:
    """2 w - 1 of :func:`quadswarm_mj.sensors.tof_normal` (float32): w = max((u - dropout) / (1 - dropout),
    2^-24), whose ``sqrt(2) erf_inv_f32`` is the ray's standard normal noise."""
    scale = 1.0 / (1.0 - dropout) if dropout < 1.0 else 0.0
    return 2.0 * jnp.maximum((u01 - dropout) * scale, 2.0 ** -24) - 1.0


def tof_numbers(u: jax.Array, dropout: float) -> jax.Array:
    """float32 ``tof_normal(u, dropout)`` where ``u >= dropout`` (the reading is kept), NaN where it is
    lost: what :func:`step_key_and_numbers` carries at its ``tof_mask`` positions, and what
    :func:`quadswarm_mj.sensors.deck_part` takes as ``draws["range_z"]`` instead of ``range_u``."""
    z = np.sqrt(2.0).astype(np.float32) * erf_inv_f32(_tof_argument(u, dropout))
    return jnp.where(u >= dropout, z, jnp.nan)


def _numbers_with_tof(words: jax.Array, normal: jax.Array, tof: jax.Array, dropout: float) -> jax.Array:
    """:func:`_unit_numbers` of ``words`` chosen by ``normal`` (N(0, 1)) or not (U[0, 1)), and
    :func:`tof_numbers` of the uniform where ``tof``: ONE erf_inv per word, of the normal's or the
    ToF noise's argument."""
    u01 = jax.lax.bitcast_convert_type((words >> 9) | jnp.uint32(0x3F800000), jnp.float32) - 1.0
    lo_n = np.nextafter(np.float32(-1.0), np.float32(0.0))
    arg = jnp.where(tof, _tof_argument(u01, dropout), jnp.maximum(lo_n, lo_n + (1.0 - lo_n) * u01))
    z = np.sqrt(2.0).astype(np.float32) * erf_inv_f32(arg)
    return jnp.where(tof, jnp.where(u01 >= dropout, z, jnp.nan), jnp.where(normal, z, u01))


_ERF_INV_SMALL = np.array([2.81022636e-08, 3.43273939e-07, -3.5233877e-06, -4.39150654e-06, 0.00021858087,
                           -0.00125372503, -0.00417768164, 0.246640727, 1.50140941], np.float32)
_ERF_INV_LARGE = np.array([-0.000200214257, 0.000100950558, 0.00134934322, -0.00367342844, 0.00573950773,
                           -0.0076224613, 0.00943887047, 1.00167406, 2.83297682], np.float32)


def erf_inv_f32(x: jax.Array) -> jax.Array:
    """erf^-1 of float32 ``x`` in (-1, 1): XLA's single-precision approximation (M. Giles, the same
    two polynomials as ``jax.lax.erf_inv``) with w = -log((1 - x)(1 + x)) instead of -log1p(-x^2)
    (XLA:CPU's log1p is the slower function: the step's numbers ~140 -> ~90 us for 512 worlds). (1 - x)
    is exact for |x| >= 1/2, so the tails are more accurate too: within ~3 float32 ulp of the exact
    erfinv over the uniforms' range, where ``jax.lax.erf_inv`` (log1p of a rounded x^2) is up to ~64
    ulp off. ``x`` in (-1, 1) (the normals' uniforms never reach +-1)."""
    w = -jnp.log((1.0 - x) * (1.0 + x))
    small = w < 5.0
    w = jnp.where(small, w - 2.5, jnp.sqrt(w) - 3.0)
    p = jnp.where(small, _ERF_INV_SMALL[0], _ERF_INV_LARGE[0])
    for a, b in zip(_ERF_INV_SMALL[1:], _ERF_INV_LARGE[1:]):
        p = jnp.where(small, a, b) + p * w
    return p * x


def _materialized_numbers(words: jax.Array, normals: bool) -> tuple[jax.Array, jax.Array | None]:
    """:func:`_unit_numbers` of flat ``words``, computed once into buffers.

    XLA:CPU otherwise fuses the erf_inv polynomial (log, two branches of 9 coefficients) into every
    consumer of every slice and recomputes it there (the observation, the collision scatters),
    which cost more than all the draws themselves (``jax.lax.optimization_barrier`` does not stop
    it on CPU). The numbers are computed in a loop of two chunks (a loop body cannot be fused into
    its consumers; trip counts of 1 are inlined by XLA), which makes them ordinary buffers."""
    if not normals:
        return _unit_numbers(words)[0], None
    total = words.shape[0]
    half = (total + 1) // 2
    padded = jnp.concatenate([words, jnp.zeros((2 * half - total,), words.dtype)]) if 2 * half != total else words
    first, second = padded[:half], padded[half:]

    def chunk(i: jax.Array, acc: tuple[jax.Array, ...]) -> tuple[jax.Array, ...]:
        u, n = _unit_numbers(jnp.where(i == 0, first, second))
        return (jnp.where(i == 0, u, acc[0]), jnp.where(i == 0, n, acc[1]),
                jnp.where(i == 1, u, acc[2]), jnp.where(i == 1, n, acc[3]))

    zeros = jnp.zeros((half,), jnp.float32)
    ua, na, ub, nb = jax.lax.fori_loop(0, 2, chunk, (zeros, zeros, zeros, zeros))
    return jnp.concatenate([ua, ub])[:total], jnp.concatenate([na, nb])[:total]


class FusedJaxSampler(JaxSampler):
    """A :class:`~quadswarm_mj.random_draws.JaxSampler` that draws a whole spec from ONE
    ``jax.random.bits`` call (sliced per entry) instead of one call per entry: far less to compile
    (each threefry call is a large graph on XLA:CPU) and fewer small kernels to run. The bits are
    hashed with ``jax.extend.random.threefry_2x32`` on a counter, so one threefry block feeds two
    numbers (with ``jax_threefry_partitionable``, ``jax.random.bits`` hashes one block per number). Uniforms and normals
    are made from the words as ``jax.random.uniform`` / ``jax.random.normal`` make them
    (23 mantissa bits; normal = sqrt(2) erfinv(U(-1, 1)), :func:`erf_inv_f32`): the same distributions. Used under
    ``jit`` only (float32 and threefry keys; otherwise one uniform and one normal call)."""

    @staticmethod
    def fused(key: jax.Array, dtype: Any) -> bool:
        """Whether the fused path applies (float32 numbers from a threefry key)."""
        threefry = jax.random.key_impl(key) == jax.random.key_impl(jax.random.key(0, impl="threefry2x32"))
        return jnp.dtype(dtype) == jnp.float32 and threefry

    @staticmethod
    def num_words(spec: DrawSpec, batch_shape: tuple[int, ...] = ()) -> int:
        return sum(int(np.prod(tuple(batch_shape) + tuple(d.shape))) for d in spec.values())

    def draw(self, spec: DrawSpec, batch_shape: tuple[int, ...] = ()) -> dict[str, Any]:
        if not spec or not self.fused(self.key, self.dtype):
            return super().draw(spec, batch_shape)
        from jax.extend.random import threefry_2x32

        self.key, k = jax.random.split(self.key)
        total = self.num_words(spec, batch_shape)
        # threefry_2x32 hashes the counter array's two halves as (x0, x1) pairs: 2 words per block
        words = threefry_2x32(jax.random.key_data(k), jnp.arange(total + total % 2, dtype=jnp.uint32))[:total]
        return self.from_words(spec, words, batch_shape)

    @staticmethod
    def from_words(spec: DrawSpec, words: jax.Array, batch_shape: tuple[int, ...] = ()) -> dict[str, Any]:
        """The draws of ``spec`` from ``num_words(spec)`` uint32 ``words`` (float32)."""
        u01, std_normal = _materialized_numbers(words, any(isinstance(d, Normal) for d in spec.values()))
        return FusedJaxSampler._scaled(spec, u01, std_normal, batch_shape)

    @staticmethod
    def normal_mask(spec: DrawSpec, batch_shape: tuple[int, ...] = ()) -> np.ndarray:
        """(num_words,) bool: the positions of the spec's normal draws."""
        return np.concatenate([np.full(int(np.prod(tuple(batch_shape) + tuple(d.shape))), isinstance(d, Normal))
                               for d in spec.values()])

    @staticmethod
    def entry_mask(spec: DrawSpec, name: str) -> np.ndarray:
        """(num_words,) bool: the positions of the entry ``name`` of ``spec`` (all False without it)."""
        return np.concatenate([np.full(int(np.prod(tuple(d.shape))), k == name) for k, d in spec.items()])

    @staticmethod
    def raw_entry(spec: DrawSpec, numbers: jax.Array, name: str) -> jax.Array:
        """The numbers at the positions of the entry ``name`` of ``spec``, unscaled, in its shape."""
        start = 0
        for k, d in spec.items():
            size = int(np.prod(tuple(d.shape)))
            if k == name:
                return numbers[start:start + size].reshape(tuple(d.shape))
            start += size
        raise KeyError(name)

    @staticmethod
    def unit_numbers(spec: DrawSpec, words: jax.Array) -> jax.Array:
        """(num_words,) float32: U[0, 1) at the spec's uniform positions, N(0, 1) at its normal ones."""
        u01, std_normal = _unit_numbers(words)
        return jnp.where(FusedJaxSampler.normal_mask(spec), std_normal, u01)

    @staticmethod
    def from_numbers(spec: DrawSpec, numbers: jax.Array) -> dict[str, Any]:
        """The draws of ``spec`` from its :meth:`unit_numbers`."""
        return FusedJaxSampler._scaled(spec, numbers, numbers)

    @staticmethod
    def _scaled(spec: DrawSpec, u01: jax.Array, std_normal: jax.Array | None,
                batch_shape: tuple[int, ...] = ()) -> dict[str, Any]:
        items = [(name, d, tuple(batch_shape) + tuple(d.shape)) for name, d in spec.items()]
        sizes = [int(np.prod(shape)) for _, _, shape in items]
        out: dict[str, Any] = {}
        start = 0
        for (name, d, shape), size in zip(items, sizes):
            if isinstance(d, Uniform):
                x = u01[start:start + size].reshape(shape)
                out[name] = jnp.maximum(d.low, d.low + (d.high - d.low) * x)
            else:  # jax.random.normal: uniform on [nextafter(-1, 0), 1), then sqrt(2) erfinv
                out[name] = d.mean + d.std * std_normal[start:start + size].reshape(shape)
            start += size
        return out
