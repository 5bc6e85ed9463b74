"""Goal formations for N quads (SPEC §10), as offsets from the formation centre.

Eight formation types; each is computed for unit neighbour spacing once per N (NumPy constant)
and scaled by the spacing ``s`` (m) at run time, so sampling a random formation is a few
fixed-shape array ops that run on NumPy and under ``jax.jit``.

* circle (horizontal / vertical xz / vertical yz): at most 8 per layer on a circle of radius
  0.5 s / sin(pi / 8); layers stacked along the circle's normal, s apart, centred.
* grid (horizontal / vertical xz / vertical yz): columns = the largest divisor of N not above
  sqrt(N), spacing s, centred.
* sphere: Fibonacci spiral points on a sphere of radius s * sqrt(N / (4 pi)) (about s between
  neighbours).
* cube: floor(cbrt(N))^2 lattice per layer, layers stacked along z (the original stacks along x,
  a bug not copied), spacing s, centred.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from quadswarm_mj._xp import array_namespace

FORMATIONS = ("circle_horizontal", "circle_vertical_xz", "circle_vertical_yz", "grid_horizontal",
              "grid_vertical_xz", "grid_vertical_yz", "sphere", "cube")
#: uniforms used by :func:`random_formation` before the N shuffle uniforms: type, spacing.
NUM_FORMATION_UNIFORMS = 2

# Axes (u, v, normal) of each planar formation.
_PLANES = {"horizontal": (0, 1, 2), "vertical_xz": (0, 2, 1), "vertical_yz": (1, 2, 0)}


def _circle(n: int, plane: str) -> np.ndarray:
    a, b, c = _PLANES[plane]
    radius = 0.5 / math.sin(math.pi / 8)
    out = np.zeros((n, 3))
    layers = (n + 7) // 8
    for i in range(n):
        layer, k = divmod(i, 8)
        in_layer = min(8, n - 8 * layer)
        ang = 2 * math.pi * k / in_layer
        out[i, a] = radius * math.cos(ang)
        out[i, b] = radius * math.sin(ang)
        out[i, c] = layer - (layers - 1) / 2
    return out


def _grid(n: int, plane: str) -> np.ndarray:
    a, b, _ = _PLANES[plane]
    cols = max(d for d in range(1, int(math.isqrt(n)) + 1) if n % d == 0)
    rows = n // cols
    out = np.zeros((n, 3))
    for i in range(n):
        r, c = divmod(i, cols)
        out[i, a] = c - (cols - 1) / 2
        out[i, b] = r - (rows - 1) / 2
    return out


def _sphere(n: int) -> np.ndarray:
    if n == 1:
        return np.zeros((1, 3))
    radius = math.sqrt(n / (4 * math.pi))
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = math.pi * (1 + 5**0.5) * i
    return radius * np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], -1)


def _cube(n: int) -> np.ndarray:
    k = max(1, int(math.floor(round(n ** (1 / 3), 9))))
    per = k * k
    layers = (n + per - 1) // per
    out = np.zeros((n, 3))
    for i in range(n):
        layer, j = divmod(i, per)
        r, c = divmod(j, k)
        out[i] = (c - (k - 1) / 2, r - (k - 1) / 2, layer - (layers - 1) / 2)
    return out


@functools.lru_cache(maxsize=64)
def unit_formations(n: int) -> np.ndarray:
    """(8, N, 3) offsets of every formation type at unit spacing (order of ``FORMATIONS``)."""
    return np.stack([
        _circle(n, "horizontal"), _circle(n, "vertical_xz"), _circle(n, "vertical_yz"),
        _grid(n, "horizontal"), _grid(n, "vertical_xz"), _grid(n, "vertical_yz"),
        _sphere(n), _cube(n),
    ])


def formation_offsets(n: int, kind: Any, spacing: Any) -> Any:
    """Offsets (..., N, 3) of formation ``kind`` (int array, index into FORMATIONS) at ``spacing`` m."""
    xp = array_namespace(kind, spacing)
    table = xp.asarray(unit_formations(n))
    return table[kind] * spacing[..., None, None]


def shuffle(goals: Any, u: Any) -> Any:
    """Permute goals (..., N, 3) among quads with the permutation that sorts ``u`` (..., N)."""
    xp = array_namespace(goals, u)
    perm = xp.argsort(u, axis=-1)
    return xp.take_along_axis(goals, perm[..., None], axis=-2)


def random_formation(n: int, u: Any, spacing_range: tuple[float, float]) -> Any:
    """A random formation type and spacing, shuffled among quads.

    ``u`` (..., >= 2 + N) uniforms: [type, spacing, N shuffle draws, ...].
    """
    xp = array_namespace(u)
    kind = xp.minimum((u[..., 0] * len(FORMATIONS)).astype(xp.int32), len(FORMATIONS) - 1)
    spacing = spacing_range[0] + u[..., 1] * (spacing_range[1] - spacing_range[0])
    offsets = formation_offsets(n, kind, spacing).astype(u.dtype)
    return shuffle(offsets, u[..., NUM_FORMATION_UNIFORMS:NUM_FORMATION_UNIFORMS + n])
