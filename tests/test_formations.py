"""Goal formations (SPEC §10): geometry, spacing, centring, shuffling; NumPy and JAX agree."""

from __future__ import annotations

import math

import numpy as np
import pytest

from quadswarm_mj.scenarios.formations import (
    FORMATIONS,
    circle_radius,
    cube_side,
    formation_offsets,
    grid_columns,
    group_unit_formations,
    random_formation,
    shuffle,
    unit_formations,
)

SIZES = [1, 2, 3, 4, 5, 7, 8, 9, 12, 16, 17, 27, 32, 64]
AXES = {"horizontal": (0, 1, 2), "vertical_xz": (0, 2, 1), "vertical_yz": (1, 2, 0)}


def min_dist(p: np.ndarray) -> float:
    d = np.linalg.norm(p[:, None] - p[None], axis=-1)
    d[np.eye(len(p), dtype=bool)] = np.inf
    return float(d.min())


def test_names_and_table_shape():
    assert FORMATIONS == ("circle_horizontal", "circle_vertical_xz", "circle_vertical_yz", "grid_horizontal",
                          "grid_vertical_xz", "grid_vertical_yz", "sphere", "cube")
    for n in SIZES:
        t = unit_formations(n)
        assert t.shape == (8, n, 3) and np.isfinite(t).all()


@pytest.mark.parametrize("n", SIZES)
def test_centred_distinct_and_unit_spacing(n):
    t = unit_formations(n)
    np.testing.assert_allclose(t.mean(axis=1), 0.0, atol=1e-12)  # centroid = formation centre
    if n == 1:
        np.testing.assert_array_equal(t, 0.0)
        return
    for k, name in enumerate(FORMATIONS):
        d = min_dist(t[k])
        if name.startswith("circle") and n < 8:
            assert d >= 1.0 - 1e-9, (name, n, d)  # partial layer on the same radius: wider spacing
        else:
            assert d == pytest.approx(1.0, abs=1e-9), (name, n, d)


@pytest.mark.parametrize("n", SIZES[1:])
@pytest.mark.parametrize("plane", list(AXES))
def test_circle_layers(n, plane):
    a, b, c = AXES[plane]
    t = unit_formations(n)[FORMATIONS.index(f"circle_{plane}")]
    layer_pos = np.unique(np.round(t[:, c], 9))
    assert len(layer_pos) == math.ceil(n / 8)
    np.testing.assert_allclose(np.diff(layer_pos), 1.0, atol=1e-9)  # layers s apart along the normal
    for z in layer_pos:
        pts = t[np.abs(t[:, c] - z) < 1e-9]
        assert len(pts) <= 8
        centre = pts[:, [a, b]].mean(0)
        r = np.linalg.norm(pts[:, [a, b]] - centre, axis=-1)
        if len(pts) > 1:
            np.testing.assert_allclose(r, circle_radius(), atol=1e-9)  # 0.5 s / sin(pi / 8)
    assert circle_radius(0.5) == pytest.approx(0.25 / math.sin(math.pi / 8))


@pytest.mark.parametrize("n", SIZES[1:])
@pytest.mark.parametrize("plane", list(AXES))
def test_grid_columns_and_plane(n, plane):
    a, b, c = AXES[plane]
    t = unit_formations(n)[FORMATIONS.index(f"grid_{plane}")]
    cols = grid_columns(n)
    assert n % cols == 0 and cols <= math.isqrt(n)
    assert not any(n % d == 0 for d in range(cols + 1, math.isqrt(n) + 1))
    np.testing.assert_allclose(t[:, c], 0.0, atol=1e-12)  # flat in its plane
    assert len(np.unique(np.round(t[:, a], 9))) == cols
    assert len(np.unique(np.round(t[:, b], 9))) == n // cols


@pytest.mark.parametrize("n", SIZES[1:])
def test_sphere_points_on_sphere_with_fitted_radius(n):
    t = unit_formations(n)[FORMATIONS.index("sphere")]
    # every point at one radius around the sphere's centre (fitted by least squares; the spiral's
    # centroid, which the formation is centred on, is close to it), closest pair exactly 1 apart
    if n > 3:
        c = np.linalg.lstsq(np.c_[2 * t, np.ones(n)], (t**2).sum(1), rcond=None)[0][:3]
        r = np.linalg.norm(t - c, axis=-1)
        np.testing.assert_allclose(r, r[0], rtol=1e-9)
        assert np.linalg.norm(c) < 0.2 * r[0]
    assert min_dist(t) == pytest.approx(1.0, abs=1e-9)


@pytest.mark.parametrize("n", SIZES[1:])
def test_cube_layers_stack_along_z(n):
    t = unit_formations(n)[FORMATIONS.index("cube")]
    k = cube_side(n)
    assert k**3 <= n < (k + 1) ** 3
    zs = np.unique(np.round(t[:, 2], 9))
    assert len(zs) == math.ceil(n / k**2)  # floor(cbrt N)^2 per layer, layers along z
    for z in zs:
        layer = t[np.abs(t[:, 2] - z) < 1e-9]
        assert len(layer) <= k * k
        assert np.ptp(layer[:, 0]) <= k - 1 + 1e-9 and np.ptp(layer[:, 1]) <= k - 1 + 1e-9


def test_cube_side_exact_for_cubes():
    assert [cube_side(n) for n in (1, 7, 8, 26, 27, 63, 64, 124, 125)] == [1, 1, 2, 2, 3, 3, 4, 4, 5]


def test_offsets_scale_with_spacing_and_shuffle_is_permutation():
    rng = np.random.default_rng(0)
    kind = np.array([0, 3, 6, 7])
    s = np.array([0.25, 0.5, 1.0, 2.0])
    off = formation_offsets(8, kind, s)
    assert off.shape == (4, 8, 3)
    for i in range(4):
        np.testing.assert_allclose(off[i], unit_formations(8)[kind[i]] * s[i])
    u = rng.uniform(size=(4, 8))
    sh = shuffle(off, u)
    for i in range(4):
        perm = np.argsort(u[i])
        np.testing.assert_array_equal(sh[i], off[i][perm])


def test_random_formation_ranges_and_groups():
    rng = np.random.default_rng(1)
    u = rng.uniform(size=(400, 2 + 8))
    off = random_formation(8, u, (0.25, 0.5))
    d = np.array([min_dist(o) for o in off])
    np.testing.assert_allclose(d, 0.25 + u[:, 1] * 0.25, atol=1e-9)  # N = 8: closest pair = spacing
    kinds = np.minimum((u[:, 0] * 8).astype(int), 7)
    assert set(kinds) == set(range(8))
    # grouped: each group its own centred formation, shuffled only within the group
    g = random_formation(8, u, (0.25, 0.5), groups=(3, 5))
    np.testing.assert_allclose(g[:, :3].mean(1), 0.0, atol=1e-12)
    np.testing.assert_allclose(g[:, 3:].mean(1), 0.0, atol=1e-12)
    table = group_unit_formations((3, 5))
    np.testing.assert_array_equal(table[:, :3], unit_formations(3))
    np.testing.assert_array_equal(table[:, 3:], unit_formations(5))
    spacing = 0.25 + u[:, 1] * 0.25
    for i in range(5):
        a = np.sort((table[kinds[i], 3:] * spacing[i]).round(9), axis=0)
        np.testing.assert_allclose(np.sort(g[i, 3:].round(9), axis=0), a, atol=1e-9)


def test_jax_matches_numpy():
    jnp = pytest.importorskip("jax.numpy")
    rng = np.random.default_rng(2)
    u = rng.uniform(size=(6, 2 + 8)).astype(np.float32)
    ref = random_formation(8, u.astype(np.float64), (0.25, 0.5))
    got = np.asarray(random_formation(8, jnp.asarray(u), (0.25, 0.5)))
    np.testing.assert_allclose(got, ref, atol=1e-5)
