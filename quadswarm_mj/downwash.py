"""The paper's downwash model (SPEC §6), once per control step.

Quad ``j`` is in the downwash of quad ``i`` when it sits in the cylinder below ``i`` along ``i``'s
body z axis: ``-0.7 < (p_j - p_i) . z_i < 0`` and radial distance < 0.1 m. It then gets a
velocity change along ``-z_i`` (noisy) and a small random angular-velocity change. Effects of
several quads above are summed. Pure, any leading batch dims, NumPy or ``jax.numpy``.
"""

from __future__ import annotations

from typing import Any

from quadswarm_mj._xp import array_namespace, safe_normalize
from quadswarm_mj.random_draws import DrawSpec, Normal, Uniform

DOWNWASH_DEPTH = 0.7  # m below the quad
DOWNWASH_RADIUS = 0.1  # m around its z axis


def downwash_draw_spec(num_quads: int) -> DrawSpec:
    n = num_quads
    return {
        "acc": Uniform(-0.1, 0.1, (n, n)),
        "z_dir": Uniform(-0.1, 0.1, (n, n, 3)),
        "omega_mag": Uniform(-0.01, 0.01, (n, n)),
        "omega_dir": Normal(0.0, 1.0, (n, n, 3)),
    }


def downwash_mask(pos: Any, R: Any) -> tuple[Any, Any]:
    """(..., N, N) mask [i, j] = j is in i's downwash, and the distances d[i, j] = ||p_j - p_i||."""
    xp = array_namespace(pos, R)
    rel = pos[..., None, :, :] - pos[..., :, None, :]  # [i, j] = p_j - p_i
    dist = xp.sqrt(xp.sum(rel * rel, axis=-1))
    z_axis = R[..., :, 2]  # body z of i in the world frame, (..., N, 3)
    rz = xp.sum(rel * z_axis[..., :, None, :], axis=-1)
    radial = xp.sqrt(xp.maximum(dist * dist - rz * rz, 0.0))
    n = pos.shape[-2]
    mask = (rz > -DOWNWASH_DEPTH) & (rz < 0.0) & (radial < DOWNWASH_RADIUS) & ~xp.eye(n, dtype=bool)
    return mask, dist


def apply_downwash(pos: Any, vel: Any, omega: Any, R: Any, dt: float, draws: dict[str, Any]) -> tuple[Any, Any]:
    """Return (vel, omega) after one control step of downwash (dt in s).

    vel_j += acc * (-z_noisy) * dt with acc = max(1e-6, (6/17)(7 - 10 d) + U(-0.1, 0.1)) m/s^2;
    omega_j += max(1e-6, 0.3 (d - 1)^2 + U(-0.01, 0.01)) * unit(random) * dt.
    """
    xp = array_namespace(pos, vel)
    mask, dist = downwash_mask(pos, R)
    acc = xp.maximum(1e-6, (6.0 / 17.0) * (7.0 - 10.0 * dist) + draws["acc"])
    z_noisy = safe_normalize(xp, R[..., :, None, :, 2] + draws["z_dir"], eps=1e-12)
    dv = xp.where(mask[..., None], acc[..., None] * (-z_noisy) * dt, 0.0)
    w_mag = xp.maximum(1e-6, 0.3 * (dist - 1.0) ** 2 + draws["omega_mag"])
    dw = xp.where(mask[..., None], w_mag[..., None] * safe_normalize(xp, draws["omega_dir"]) * dt, 0.0)
    return vel + xp.sum(dv, axis=-3), omega + xp.sum(dw, axis=-3)


#: Downwash pairs (i above j) per step and world that get their own draws on the JAX engine.
DOWNWASH_BUDGET = 4


def downwash_slot_spec(slots: int) -> DrawSpec:
    """Per-slot draws of :func:`downwash_draw_spec` (one downwash pair per slot)."""
    return {
        "acc": Uniform(-0.1, 0.1, (slots,)),
        "z_dir": Uniform(-0.1, 0.1, (slots, 3)),
        "omega_mag": Uniform(-0.01, 0.01, (slots,)),
        "omega_dir": Normal(0.0, 1.0, (slots, 3)),
    }


def expand_downwash_draws(mask: Any, slots: dict[str, Any]) -> dict[str, Any]:
    """Dense (N, N, ...) draws of :func:`apply_downwash` (one world) from per-slot draws; pairs
    [i, j] in ``mask`` (from :func:`downwash_mask`) ranked in row-major order, slot = rank mod S."""
    from quadswarm_mj.random_draws import event_slots, spread

    xp = array_namespace(mask, slots["acc"])
    n = mask.shape[-1]
    hot = event_slots(xp, mask.reshape(n * n), slots["acc"].shape[0])
    return {k: spread(xp, hot, v).reshape((n, n) + tuple(v.shape[1:])) for k, v in slots.items()}
