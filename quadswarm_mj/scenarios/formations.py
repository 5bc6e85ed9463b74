"""Goal formations for N quads (SPEC §10), as offsets (m, world frame) from the formation centre.

Eight types (circle, grid: horizontal / vertical xz / vertical yz; sphere; cube), each computed for unit
spacing once per N (a cached NumPy constant) and scaled by the spacing ``s`` (m) at run time, so sampling a
random formation is a few fixed-shape array ops (NumPy or under ``jax.jit``). Every formation is centred;
for N >= 2 its closest pair is s apart. The geometry of each type: docs/model.md ("Episodes, resets,
scenarios, randomization").
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
#: goals per circle layer
CIRCLE_PER_LAYER = 8

# Axes (u, v, normal) of each planar formation.
_PLANES = {"horizontal": (0, 1, 2), "vertical_xz": (0, 2, 1), "vertical_yz": (1, 2, 0)}


def circle_radius(spacing: float = 1.0) -> float:
    """Radius (m) of a circle layer whose 8 goals are ``spacing`` m apart."""
    return 0.5 * spacing / math.sin(math.pi / CIRCLE_PER_LAYER)


def grid_columns(n: int) -> int:
    """Largest divisor of ``n`` not above sqrt(n) (1 for a prime)."""
    return max(d for d in range(1, math.isqrt(n) + 1) if n % d == 0)


def cube_side(n: int) -> int:
    """floor(cbrt(n)), exact for perfect cubes."""
    k = int(round(n ** (1 / 3)))
    while k**3 > n:
        k -= 1
    while (k + 1) ** 3 <= n:
        k += 1
    return max(1, k)


def _circle(n: int, plane: str) -> np.ndarray:
    a, b, c = _PLANES[plane]
    radius = circle_radius()
    out = np.zeros((n, 3))
    layers = -(-n // CIRCLE_PER_LAYER)
    for i in range(n):
        layer, k = divmod(i, CIRCLE_PER_LAYER)
        in_layer = min(CIRCLE_PER_LAYER, n - CIRCLE_PER_LAYER * layer)
        r = radius if in_layer > 1 else 0.0
        ang = 2 * math.pi * k / in_layer
        out[i, a] = r * math.cos(ang)
        out[i, b] = r * math.sin(ang)
        out[i, c] = layer - (layers - 1) / 2
    return out


def _grid(n: int, plane: str) -> np.ndarray:
    a, b, _ = _PLANES[plane]
    cols = grid_columns(n)
    out = np.zeros((n, 3))
    for i in range(n):
        r, c = divmod(i, cols)
        out[i, a] = c
        out[i, b] = r
    return out


def _sphere(n: int) -> np.ndarray:
    if n == 1:
        return np.zeros((1, 3))
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = math.pi * (1 + 5**0.5) * i
    pts = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], -1)
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    d[np.eye(n, dtype=bool)] = np.inf
    return pts / d.min()  # closest pair exactly 1 apart


def _cube(n: int) -> np.ndarray:
    k = cube_side(n)
    per = k * k
    out = np.zeros((n, 3))
    for i in range(n):
        layer, j = divmod(i, per)
        r, c = divmod(j, k)
        out[i] = (c, r, layer)
    return out


@functools.lru_cache(maxsize=128)
def unit_formations(n: int) -> np.ndarray:
    """(8, N, 3) centred offsets of every formation type at unit spacing (order of ``FORMATIONS``).

    N = 0 gives an (8, 0, 3) array.
    """
    if n == 0:
        return np.zeros((len(FORMATIONS), 0, 3))
    table = np.stack([
        _circle(n, "horizontal"), _circle(n, "vertical_xz"), _circle(n, "vertical_yz"),
        _grid(n, "horizontal"), _grid(n, "vertical_xz"), _grid(n, "vertical_yz"),
        _sphere(n), _cube(n),
    ])
    table = table - table.mean(axis=1, keepdims=True)
    table.setflags(write=False)
    return table


@functools.lru_cache(maxsize=128)
def group_unit_formations(sizes: tuple[int, ...]) -> np.ndarray:
    """(8, sum(sizes), 3): each group's own centred unit formation, concatenated along the quads."""
    table = np.concatenate([unit_formations(s) for s in sizes], axis=1)
    table.setflags(write=False)
    return table


def formation_offsets(n: int, kind: Any, spacing: Any, table: np.ndarray | None = None) -> Any:
    """Offsets (..., N, 3) (m) of formation ``kind`` (int array, index into FORMATIONS) at ``spacing`` m.

    ``table`` (8, N, 3) defaults to :func:`unit_formations` (n).
    """
    xp = array_namespace(kind, spacing)
    table = unit_formations(n) if table is None else table
    return xp.asarray(table)[kind] * spacing[..., None, None]


def shuffle(goals: Any, u: Any, groups: Any = None) -> Any:
    """Permute goals (..., N, 3) among quads with the permutation that sorts ``u`` (..., N) in [0, 1).

    With ``groups`` (N ints, a static NumPy array) goals are only permuted within each group
    (sorting ``u + 2 * group`` keeps the groups in place).
    """
    xp = array_namespace(goals, u)
    if groups is not None:
        u = u + 2.0 * xp.asarray(np.asarray(groups), dtype=u.dtype)
    perm = xp.argsort(u, axis=-1)
    return xp.take_along_axis(goals, perm[..., None], axis=-2)


def formation_kind(u: Any) -> Any:
    """Map U(0, 1) draws (...,) to a formation index (int32) uniformly."""
    xp = array_namespace(u)
    return xp.minimum((u * len(FORMATIONS)).astype(xp.int32), len(FORMATIONS) - 1)


def random_formation(n: int, u: Any, spacing_range: tuple[float, float], groups: tuple[int, ...] | None = None) -> Any:
    """Offsets (..., N, 3) (m) of a random formation type and spacing, shuffled among quads.

    ``u`` (..., >= 2 + N) uniforms: [type, spacing, N shuffle draws, ...]; the spacing is uniform
    in ``spacing_range`` (m). With ``groups`` (group sizes summing to N) each group gets its own
    centred formation of the same type and spacing, and goals are shuffled within groups only.
    """
    kind = formation_kind(u[..., 0])
    spacing = spacing_range[0] + u[..., 1] * (spacing_range[1] - spacing_range[0])
    table = None if groups is None else group_unit_formations(tuple(groups))
    offsets = formation_offsets(n, kind, spacing, table).astype(u.dtype)
    gid = None if groups is None else np.repeat(np.arange(len(groups)), groups)
    return shuffle(offsets, u[..., NUM_FORMATION_UNIFORMS:NUM_FORMATION_UNIFORMS + n], gid)
