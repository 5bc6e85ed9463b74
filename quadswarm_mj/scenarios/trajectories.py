"""Closed-form goal trajectories for the evader-pursuit scenarios (SPEC §10).

Pure functions over arrays (NumPy or ``jax.numpy``); positions in m (world frame), times in s,
velocities in m/s.
"""

from __future__ import annotations

import math
from typing import Any

from quadswarm_mj._xp import array_namespace

#: Centre (m), amplitudes (m), angular frequencies (rad/s) and phases (rad) of the 3D Lissajous
#: curve: (-2, 0, 2) + (1.0 sin(0.4 t), 0.6 sin(0.8 t + pi/2), 0.3 cos(0.8 t + pi/2)).
LISSAJOUS_CENTER = (-2.0, 0.0, 2.0)
LISSAJOUS_AMPLITUDE = (1.0, 0.6, 0.3)
LISSAJOUS_FREQ = (0.4, 0.8, 0.8)
LISSAJOUS_PHASE = (0.0, math.pi / 2, math.pi / 2)


def lissajous3d(t: Any, center: Any = LISSAJOUS_CENTER) -> tuple[Any, Any]:
    """Position and velocity (..., 3) of the 3D Lissajous curve at time ``t`` (...) s.

    p(t) = c + (A_x sin(w_x t), A_y sin(w_y t + phi_y), A_z cos(w_z t + phi_z)),
    v(t) = dp/dt = (A_x w_x cos(w_x t), A_y w_y cos(w_y t + phi_y), -A_z w_z sin(w_z t + phi_z)).
    """
    xp = array_namespace(t)
    (ax, ay, az), (wx, wy, wz), (_, py, pz) = LISSAJOUS_AMPLITUDE, LISSAJOUS_FREQ, LISSAJOUS_PHASE
    c = xp.asarray(center, dtype=t.dtype)
    pos = xp.stack([ax * xp.sin(wx * t), ay * xp.sin(wy * t + py), az * xp.cos(wz * t + pz)], axis=-1)
    vel = xp.stack([ax * wx * xp.cos(wx * t), ay * wy * xp.cos(wy * t + py), -az * wz * xp.sin(wz * t + pz)],
                   axis=-1)
    return c + pos, vel


def bezier2(p0: Any, p1: Any, p2: Any, tau: Any) -> tuple[Any, Any]:
    """Quadratic Bezier point and its derivative d/dtau at ``tau`` (...) in [0, 1].

    ``p0``, ``p1``, ``p2`` (..., 3) are the start, control and end points;
    B(tau) = (1 - tau)^2 p0 + 2 (1 - tau) tau p1 + tau^2 p2,
    B'(tau) = 2 (1 - tau) (p1 - p0) + 2 tau (p2 - p1).
    """
    s = tau[..., None]
    pos = (1 - s) ** 2 * p0 + 2 * (1 - s) * s * p1 + s**2 * p2
    dpos = 2 * (1 - s) * (p1 - p0) + 2 * s * (p2 - p1)
    return pos, dpos
