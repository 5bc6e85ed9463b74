"""The paper's floor model in the fewest NumPy calls, for the CPU engine's small arrays.

:func:`quadswarm_mj.collisions.floor_wrench` (the model, component form in
:mod:`quadswarm_mj.components`) changes only the grounded quads' wrench. On a single env's (B, N, .)
arrays NumPy's per-call overhead dominates, so :class:`quadswarm_mj.core.ops.NumpyOps` calls
:func:`floor_wrench_inplace` instead: the grounded quads gathered once by a boolean index, the
model's formulas fused into whole-row expressions with the same rounding (bit-identical, signs of
zero included; ``tests/test_numpy_floor.py``), written back into the (fresh) force and torque arrays.
NumPy only.
"""

from __future__ import annotations

from typing import Any

import numpy as np

# thresholds of (|F_h|, |v_h|): the static ratio divides by |F_h| where it is > 0, the kinetic one by
# the speed where the quad moves (> 1e-9 m/s), as the model
_THRESH = np.array([0.0, 1e-9])


def floor_wrench_inplace(on_floor: np.ndarray, force: np.ndarray, torque: np.ndarray, v: np.ndarray,
                         mass: Any, gravity: Any, friction: float, dt: float) -> None:
    """:func:`quadswarm_mj.collisions.floor_wrench` written into ``force``/``torque`` (..., N, 3)
    (world, N and N m) at the quads flagged in ``on_floor`` (..., N) bool; ``v`` (..., N, >= 2) the
    world velocity (its first two entries horizontal, m/s), ``mass`` (kg) broadcastable to
    ``on_floor``. The other quads' entries are left as they are (the model returns them unchanged)."""
    f = force[on_floor]  # (K, 3) the grounded quads' force
    m = (mass if np.shape(mass) == on_floor.shape else np.broadcast_to(mass, on_floor.shape))[on_floor]
    h = np.concatenate((f[:, :2], v[on_floor][:, :2]), axis=1)  # F_x F_y v_x v_y
    sq = h * h
    mags = np.sqrt(sq[:, 0::2] + sq[:, 1::2])  # |F_h|, speed (sqrt(x x + y y) as norm_last)
    normal = np.maximum(0.0, m * gravity - f[:, 2])
    cap = friction * normal
    num = np.empty_like(mags)  # static: max(0, |F_h| - cap); kinetic: min(cap, m speed / dt)
    np.maximum(0.0, mags[:, 0] - cap, out=num[:, 0])
    np.minimum(cap, m * mags[:, 1] / dt, out=num[:, 1])
    positive = mags > _THRESH  # |F_h| > 0, moving
    ratio = num / np.where(positive, mags, 1.0)
    np.multiply(h[:, :2], ratio[:, :1], out=f[:, :2])  # static friction
    np.subtract(h[:, :2], ratio[:, 1:] * h[:, 2:], out=f[:, :2], where=positive[:, 1:])  # kinetic
    f[:, 2] += normal
    force[on_floor] = f
    torque[..., :2][on_floor] = 0.0  # no roll/pitch torque (+0.0, as the model's zeros)
