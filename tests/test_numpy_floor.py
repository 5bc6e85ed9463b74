"""``quadswarm_mj.perf.numpy_floor`` (the CPU engine's fewest-calls floor model) against the model's
plain form (:mod:`quadswarm_mj.collisions`): bit-identical, signs of zero included, on random inputs
with signed zeros, quads exactly at rest or without horizontal force, grounded and airborne mixes."""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from quadswarm_mj import collisions
from quadswarm_mj.perf import numpy_floor
from quadswarm_mj.perf import numpy_small as small


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
    rng = np.random.default_rng(zlib.crc32(repr((lead, grounded, mass_shape)).encode()))  # not hash(): salted
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


@pytest.mark.parametrize("lead", [(1, 1), (1, 8), (3, 8)])
@pytest.mark.parametrize("offsets", ["zero", "per_world"])
def test_floor_impact_rows_is_the_model_bitwise(lead, offsets):
    """In-place rows (MuJoCo's frame) = the model's angle path, with quads below, exactly at, just above
    (within the tolerance) and above the floor, grounded and airborne, upside down, signed zeros."""
    rng = np.random.default_rng(zlib.crc32(repr((lead, offsets)).encode()))  # not hash(): salted per process
    arm = 0.046
    off = (np.zeros((1, 1, 3)) if offsets == "zero"
           else np.concatenate([rng.uniform(-20, 20, lead[:1] + (1, 2)), np.zeros(lead[:1] + (1, 1))], axis=-1))
    pos = _signed_zeros(rng, rng.uniform(-1, 1, lead + (3,)), 0.2)
    pos[..., 2] = rng.choice([arm - 0.01, arm, arm + 5e-7, arm + 0.01, 1.0], size=lead)
    quat = rng.normal(size=lead + (4,))
    quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
    quat.reshape(-1, 4)[:4] = np.eye(4)[:min(4, quat.size // 4)] * rng.choice([-1.0, 1.0])  # exact zeros
    on_floor = rng.uniform(size=lead) < 0.5
    v = _signed_zeros(rng, rng.normal(size=lead + (6,)), 0.2)
    yaw_draw = rng.uniform(-np.pi, np.pi, lead)
    R = small.quat_to_rotmat(quat)
    u = rng.uniform(size=lead + (4,))
    ref = collisions.floor_impact(pos, v[..., :3], v[..., 3:], quat, R, u, on_floor, arm, yaw_draw)
    q = np.concatenate([pos if offsets == "zero" else pos + off, quat], axis=-1)  # (keeps -0.0 there)
    vv = v.copy()
    hit, grounded, any_hit = numpy_floor.floor_impact_rows(q, vv, on_floor, arm, None if offsets == "zero" else off,
                                                           yaw_draw)
    _same(q[..., :3], ref["pos"] + off)  # the engine's frame round trip (model position + offset)
    _same(q[..., 3:7], ref["quat"])
    _same(vv[..., :3], ref["vel"])
    _same(vv[..., 3:], ref["omega"])
    np.testing.assert_array_equal(hit, ref["hit_floor"])
    np.testing.assert_array_equal(grounded, ref["on_floor"])
    assert any_hit == bool(ref["hit_floor"].any())
    if lead == (3, 8):  # the mix covers upside-down landings and quads staying on the floor
        assert (hit & (R[..., 2, 2] < 0)).any() and (grounded & ~hit).any()


@pytest.mark.parametrize("lead", [(1, 2), (1, 8), (3, 8)])
def test_qpos_row_rotations_are_the_quaternion_forms_bitwise(lead):
    """``quat_to_rotmat_qpos`` / ``yaw_entries_qpos`` on qpos rows = the forms on the quaternion view,
    signs of zero included (exact zeros of both signs in the quaternions)."""
    rng = np.random.default_rng(sum(lead))
    quat = rng.normal(size=lead + (4,))
    quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
    flat = quat.reshape(-1, 4)
    flat[:min(4, len(flat))] = np.eye(4)[:min(4, len(flat))]
    flat[-1] = [-0.0, 0.0, -1.0, -0.0]
    qpos = np.concatenate([rng.normal(size=lead + (3,)), quat], axis=-1)
    _same(small.quat_to_rotmat_qpos(qpos), small.quat_to_rotmat(qpos[..., 3:7]))
    R = small.quat_to_rotmat(qpos[..., 3:7])
    _same(small.yaw_entries_qpos(qpos), np.stack([R[..., 1, 0], R[..., 0, 0], R[..., 2, 2]], axis=-1))
