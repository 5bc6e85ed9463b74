"""The deck sensors' observation part for XLA:CPU (the JAX engine): the model's
:func:`quadswarm_mj.sensors.deck_part` with the engine's same-values forms (the float32 erfinv of
:mod:`quadswarm_mj.perf.fused_draws`, the depth hitbox test of :mod:`quadswarm_mj.perf.depth_xla`,
:func:`axis_hits`) and, with the depth camera, closed by a kernel boundary: the same bits
(``tests/test_sensors_speed.py``).

Why: the step reads the deck part twice, in the observation's concatenation and in the info readings
(``sensors.deck_info`` of the observation). XLA:CPU fuses the depth readings' cheap elementwise chain
(the rays' minima over the room's planes, the VL53L1x noise, clip and select) into both consumers and
computes it twice, a second pass over the N x H x W rays of every world (in the profile of
``quadswarm-profile-jax --sensors depth=8x8``: ``clamp_concatenate_fusion`` f32[512,8,118] for the
observation and ``clamp_bitcast_fusion`` f32[512,8,8,8] for ``info["depth"]``, each about as long as the
other). Divided by a run-time array of ones (XLA does not duplicate a division into its consumers and
cannot fold it away), the part is computed once and both read it (the measured gain: BENCHMARKS.md, "The
deck sensors' cost"). The multi-ranger and flow decks' part (15 numbers per quad) is already one buffer.

:func:`axis_hits` (the multi-ranger's and flow deck's caster) closes the hitbox test's pair arrays (the
offsets' |o|^2 - r^2 and body-frame components, N x N per world) the same way: XLA:CPU recomputed them
from the positions in each of the 4 square-root kernels that read them.
"""

from __future__ import annotations

from typing import Any

from quadswarm_mj import sensor_rays, sensors


def divided_by_ones(x: Any) -> Any:
    """``x`` (the same values: x / 1.0 is exact) divided by an array of ones that XLA cannot tell from
    other data (1 - (x < -1e30), one where x >= -1e30 or NaN: every deck reading is >= -10)."""
    one = 1.0 - (x < -1e30).astype(x.dtype)
    return x / one


def deck_part(cfg: Any, pos: Any, vel: Any, R: Any, omega: Any, obstacles: Any = None,
              draws: dict[str, Any] | None = None) -> Any:
    """:func:`quadswarm_mj.sensors.deck_part` (same arguments, the same values) of JAX arrays with the JAX
    engine's erfinv and depth hitbox forms; with the depth camera computed once into its own buffer (see
    the module doc)."""
    from quadswarm_mj.perf.depth_xla import sphere_pixel_hits
    from quadswarm_mj.perf.fused_draws import erf_inv_f32

    part = sensors.deck_part(cfg, pos, vel, R, omega, obstacles, draws, erf_inv=erf_inv_f32,
                             pixel_spheres=sphere_pixel_hits, axis_caster=axis_hits)
    return divided_by_ones(part) if cfg.sensors.depth is not None else part


def axis_hits(pos: Any, R: Any, room_low: Any, room_high: Any, columns: Any = None,
              quad_radius: float | None = None) -> Any:
    """:func:`quadswarm_mj.sensor_rays.axis_hits` under JAX (the same operations, the same values) with
    the hitbox test's pair arrays computed once (see the module doc)."""
    return sensor_rays.axis_hits(pos, R, room_low, room_high, columns, quad_radius, share=divided_by_ones)
