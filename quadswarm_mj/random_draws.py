"""Random draws for the pure model functions.

Every stochastic model function (collisions, downwash, actuation noise, scenarios,
randomization) declares the draws it needs as a *draw spec*: a dict mapping a name to
:class:`Uniform` or :class:`Normal` with a per-item shape. A front end turns a spec into
arrays with one of three samplers:

* :class:`NumpySampler` – a seeded ``numpy.random.Generator`` (CPU envs),
* :class:`JaxSampler` – a ``jax.random`` key, one call per distribution (JAX engine, under ``jit``),
* :class:`MeanSampler` – every draw replaced by its mean (``EnvConfig.without_noise()``).

The model functions themselves only ever see arrays, so they are pure and identical
on both backends.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Uniform:
    """U(low, high) with per-item ``shape`` (appended to the batch shape)."""

    low: float
    high: float
    shape: tuple[int, ...] = ()

    @property
    def mean(self) -> float:
        return 0.5 * (self.low + self.high)


@dataclass(frozen=True)
class Normal:
    """N(mean, std^2) with per-item ``shape``."""

    mean: float = 0.0
    std: float = 1.0
    shape: tuple[int, ...] = ()


Dist = Uniform | Normal
DrawSpec = dict[str, Dist]


class NumpySampler:
    """Draw a spec with a NumPy Generator (float64). Deterministic for a seeded Generator."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng

    def draw(self, spec: DrawSpec, batch_shape: tuple[int, ...] = ()) -> dict[str, np.ndarray]:
        out = {}
        for name, d in spec.items():
            shape = tuple(batch_shape) + tuple(d.shape)
            if isinstance(d, Uniform):
                out[name] = self.rng.uniform(d.low, d.high, size=shape)
            else:
                out[name] = self.rng.normal(d.mean, d.std, size=shape)
        return out


class MeanSampler:
    """Every draw takes its mean: the noise-free model of SPEC §5-6."""

    def __init__(self, dtype: Any = np.float64, xp: Any = np):
        self.dtype = dtype
        self.xp = xp

    def draw(self, spec: DrawSpec, batch_shape: tuple[int, ...] = ()) -> dict[str, Any]:
        out = {}
        for name, d in spec.items():
            shape = tuple(batch_shape) + tuple(d.shape)
            out[name] = self.xp.full(shape, d.mean, dtype=self.dtype)
        return out


class JaxSampler:
    """Draw a spec from a ``jax.random`` key: one ``jax.random.uniform`` call for all its uniform
    entries and one ``jax.random.normal`` call for all its normal ones (sliced per entry).

    Use inside ``jit``: the Python object only lives at trace time.
    """

    def __init__(self, key: Any, dtype: Any = None):
        import jax.numpy as jnp

        self.key = key
        self.dtype = dtype or jnp.float32

    def draw(self, spec: DrawSpec, batch_shape: tuple[int, ...] = ()) -> dict[str, Any]:
        import jax

        self.key, k_u, k_n = jax.random.split(self.key, 3)
        out: dict[str, Any] = {}
        for kind, key in ((Uniform, k_u), (Normal, k_n)):
            items = [(name, d, tuple(batch_shape) + tuple(d.shape)) for name, d in spec.items() if isinstance(d, kind)]
            if not items:
                continue
            sizes = [int(np.prod(shape)) for _, _, shape in items]
            flat = (jax.random.uniform if kind is Uniform else jax.random.normal)(key, (sum(sizes),), self.dtype)
            start = 0
            for (name, d, shape), size in zip(items, sizes):
                x = flat[start:start + size].reshape(shape)
                start += size
                out[name] = d.low + (d.high - d.low) * x if kind is Uniform else d.mean + d.std * x
        return {name: out[name] for name in spec}


def jax_unit_numbers(key: Any, normal_mask: np.ndarray, dtype: Any = None, own_mask: np.ndarray | None = None,
                     own: Callable[[Any], Any] | None = None, own_words: int = 0) -> tuple[Any, Any]:
    """(next key, numbers (len(normal_mask),)) from a ``jax.random`` key: N(0, 1) where ``normal_mask``,
    U[0, 1) elsewhere, from one ``jax.random.normal`` and one ``jax.random.bits`` call (use under ``jit``);
    where ``own_mask``, ``own(words)`` of ``own_words`` more uint32 words of that call (the JAX engine's
    deck rays: :func:`quadswarm_mj.sensors.tof_from_words`). The uniforms are ``jax.random.uniform``'s
    (the float in [1, 2) of the word's high bits, minus 1). The JAX engine makes a step's numbers this way
    at the end of the previous step. Assembled from the masks' runs by slices and one concatenation
    (XLA:CPU's scatter of the same positions took ~3x the normals' own time)."""
    import jax
    import jax.numpy as jnp

    dtype = jnp.dtype(dtype or jnp.float32)
    normal_mask = np.asarray(normal_mask, bool)
    kind = normal_mask.astype(np.int8)  # 0 uniform, 1 normal, 2 own
    if own_mask is not None:
        kind[np.asarray(own_mask, bool)] = 2
    counts = np.bincount(kind, minlength=3)
    k_next, k_u, k_n = jax.random.split(key, 3)
    made = [None, jax.random.normal(k_n, (int(counts[1]),), dtype), None]
    if dtype == jnp.float32:
        words = jax.random.bits(k_u, (int(counts[0]) + (own_words if counts[2] else 0),), jnp.uint32)
        unit = (words[:counts[0]] >> 9) | jnp.uint32(0x3F800000)  # jax.random.uniform's float32 bits
        made[0] = jax.lax.bitcast_convert_type(unit, jnp.float32) - 1.0
        own_in = words[counts[0]:]
    else:
        made[0] = jax.random.uniform(k_u, (int(counts[0]),), dtype)
        own_in = jax.random.bits(jax.random.fold_in(k_u, 1), (own_words,), jnp.uint32)
    if counts[2]:
        made[2] = jnp.asarray(own(own_in), dtype)
    if kind.size == 0:
        return k_next, jnp.zeros(0, dtype)
    used = [0, 0, 0]
    edges = np.flatnonzero(kind[1:] != kind[:-1]) + 1
    pieces = []
    for start, stop in zip(np.r_[0, edges], np.r_[edges, kind.size]):
        k = int(kind[start])
        pieces.append(made[k][used[k]:used[k] + stop - start])
        used[k] += stop - start
    return k_next, jnp.concatenate(pieces) if len(pieces) > 1 else pieces[0]


# ------------------------------------------------------------------------------- draw budgets
# The JAX engine draws the noise of rare events (a new contact, a wall hit) for a fixed number of
# *slots* per step instead of for every possible event. The events of one step are ranked in a fixed
# order (flattened index order of their mask); event r takes the draws of slot r mod S. So every
# event's draws have exactly the distribution of its dense draw spec; only when more than S events
# happen at once in one world do some share (repeat) the draws of an earlier event of that step.


def event_slots(xp: Any, mask: Any, num_slots: int) -> Any:
    """(..., E, S) float one-hot: event e (mask[..., e] True) -> its slot (rank of e among the
    events, in index order, modulo S); all zeros where the mask is False."""
    rank = xp.cumsum(mask.astype(xp.int32), axis=-1) - 1
    slot = rank % num_slots
    hot = (slot[..., None] == xp.arange(num_slots)) & mask[..., None]
    return hot.astype(xp.float32 if xp is not np else np.float64)


def spread(xp: Any, hot: Any, slot_draws: Any) -> Any:
    """Per-event draws (..., E, *shape) from per-slot draws (..., S, *shape) and a one-hot (..., E, S)
    (zero where no event)."""
    shape = slot_draws.shape[hot.ndim - 1:]
    flat = slot_draws.reshape(slot_draws.shape[:hot.ndim - 2] + (hot.shape[-1], -1))
    out = xp.matmul(hot.astype(flat.dtype), flat)
    return out.reshape(out.shape[:-1] + tuple(shape))
