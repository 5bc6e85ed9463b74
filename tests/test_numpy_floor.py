"""``quadswarm_mj.perf.numpy_floor`` (the CPU engine's fewest-calls floor model) against the model's
plain form (:mod:`quadswarm_mj.collisions`): bit-identical, signs of zero included, on random inputs
with signed zeros, quads exactly at rest or without horizontal force, grounded and airborne mixes."""

from __future__ import annotations

import numpy as np
import pytest

from quadswarm_mj import collisions
from quadswarm_mj.perf import numpy_floor


def _same(a: np.ndarray, b: np.ndarray) -> None:
    """Bit-identical, including the sign of zeros."""
    np.testing.assert_array_equal(np.signbit(a), np.signbit(b))
    np.testing.assert_array_equal(a, b)


def _signed_zeros(rng: np.random.Generator, x: np.ndarray, p: float) -> np.ndarray:
    """``x`` with a fraction ``p`` of its entries replaced by +0.0 or -0.0."""
    zero = rng.uniform(size=x.shape) < p
    return np.where(zero, np.where(rng.uniform(size=x.shape) < 0.5, -0.0, 0.0), x)


@pytest.mark.parametrize("lead", [(1, 1), (1, 8), (3, 8), (2, 5)])
@pytest.mark.parametrize("grounded", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("mass_shape", ["per_quad", "per_world", "scalar"])
def test_floor_wrench_inplace_is_the_model_bitwise(lead, grounded, mass_shape):
    rng = np.random.default_rng(hash((lead, grounded, mass_shape)) % 2**32)
    on_floor = rng.uniform(size=lead) < grounded
    force = _signed_zeros(rng, rng.normal(0, 0.3, lead + (3,)), 0.15)
    force[..., 2] = np.where(rng.uniform(size=lead) < 0.3, rng.uniform(0.0, 0.5, lead), force[..., 2])  # lifting
    force[..., :2] *= rng.uniform(size=lead + (1,)) < 0.7  # some without horizontal force (signed zeros)
    torque = _signed_zeros(rng, rng.normal(0, 0.01, lead + (3,)), 0.15)
    v = _signed_zeros(rng, rng.normal(0, 1, lead + (6,)), 0.15)
    v[..., :3] *= rng.uniform(size=lead + (1,)) < 0.5  # half at rest
    v[..., :2] = np.where(rng.uniform(size=lead + (1,)) < 0.2, 1e-10, v[..., :2])  # below the moving speed
    mass = {"per_quad": rng.uniform(0.025, 0.035, lead), "per_world": rng.uniform(0.025, 0.035, lead[:1] + (1,)),
            "scalar": 0.028}[mass_shape]
    ref_f, ref_t = collisions.floor_wrench(on_floor, force, torque, v[..., :3], mass, 9.81, 0.3, 0.005)
    f, t = force.copy(), torque.copy()
    numpy_floor.floor_wrench_inplace(on_floor, f, t, v, mass, 9.81, 0.3, 0.005)
    _same(f, ref_f)
    _same(t, ref_t)
    _same(f[~on_floor], force[~on_floor])  # airborne quads untouched
