"""The depth camera's hitbox test in the form XLA:CPU runs fastest (same values as the model's plain form
:func:`quadswarm_mj.sensor_rays.sphere_pixel_hits`, ``tests/test_sensors_speed.py``; the JAX engine passes
it to ``depth_hits`` as ``pixel_spheres``, :func:`quadswarm_mj.core.ops.jax_deck_part`).

The plain form materializes an (..., N, N, H W) array of hit distances and reduces it over the
neighbours: XLA:CPU writes it out and reads it back in a separate (YNNPACK) reduction. Here:

* each pair's distance ``beta - sqrt(beta^2 - |e|^2 c)`` is compared as the unsigned integer of its
  bits: a hit ahead is a float >= 0, whose bits order as the floats do; a ray that misses gives NaN
  (the root of a negative) and one that passes behind (beta < 0, outside the sphere: c > 0) a negative
  float, both of whose bit patterns are larger than +inf's as unsigned integers, as is NaN of the own
  sphere (c = inf). An unsigned minimum (one instruction) thus replaces the tests, the select and the
  NaN-aware float minimum (~6 instructions) per pair and pixel;
* the neighbours are taken in two halves by a two-trip loop, whose result is a buffer: XLA:CPU cannot
  fuse the cast into the deck part's later kernels, where it ran along their layouts several times
  slower (a one-trip loop would be inlined). Within a half, the neighbours' axis is put first and
  halved by pairwise minima of slices (log2 N steps, no reduction op), fused with the distances into
  one loop over the pixels.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

_UINT = {jnp.dtype(jnp.float32): jnp.uint32, jnp.dtype(jnp.float64): jnp.uint64}


def _min_leading(x: jax.Array, fill: Any) -> jax.Array:
    """The minimum over the leading axis by halving (pairwise minima of the even and odd slices;
    an odd count is padded with ``fill``)."""
    while x.shape[0] > 1:
        if x.shape[0] % 2:
            x = jnp.concatenate([x, jnp.full((1,) + x.shape[1:], fill, x.dtype)])
        x = jnp.minimum(x[0::2], x[1::2])
    return x[0]


def sphere_pixel_hits(ob: list[Any], c: Any, uk: Any, vk: Any, norm2: Any) -> jax.Array:
    """(..., N, H W) the nearest of the other quads' hitboxes along each pixel ray, as the parameter
    ``beta - sqrt(disc)`` along e = (1, -u_w, v_h) times |e| (divide by |e| for metres; +inf: no hit),
    of the body-frame offsets ``ob`` = 3 arrays (..., N (i), N (j)), ``c`` (..., N, N) = |offset|^2 -
    r^2 (inf on the diagonal) and the pixels' ``uk``, ``vk``, ``norm2`` = |e|^2 (H W,). The hit test is
    the plain form's (beta > 0 and disc >= 0); a pair with c < 0 (inside) is the caller's to override."""
    f = c.dtype
    u = _UINT[jnp.dtype(f)]
    inf_bits = jax.lax.bitcast_convert_type(jnp.asarray(np.inf, f), u)
    n = c.shape[-1]
    half = (n + 1) // 2
    # (4, 2 half (j), ..., N (i)): the neighbours first, padded to an even count with a sphere never hit
    parts = [jnp.moveaxis(a, -1, 0) for a in ob + [c]]
    if 2 * half > n:
        parts = [jnp.concatenate([a, jnp.full((1,) + a.shape[1:], np.inf if k == 3 else 0.0, f)])
                 for k, a in enumerate(parts)]
    stacked = jnp.stack(parts)

    def body(k: jax.Array, best: jax.Array) -> jax.Array:
        x, y, z, cc = jax.lax.dynamic_slice_in_dim(stacked, k * half, half, axis=1)[..., None]
        beta = x + uk * y + vk * z  # (half, ..., N, H W)
        t = beta - jnp.sqrt(beta * beta - norm2 * cc)  # NaN: no hit; < 0: behind (see the module doc)
        return jnp.minimum(best, _min_leading(jax.lax.bitcast_convert_type(t, u), inf_bits))

    best = jax.lax.fori_loop(0, 2, body, jnp.full(c.shape[:-1] + uk.shape, inf_bits, u))
    return jax.lax.bitcast_convert_type(best, f)
