"""``SensorConfig``: the Crazyflie deck sensors as observation components (all off by default).

Frozen and validated like the rest of :mod:`quadswarm_mj.config` (every error a ``ValueError`` naming
the field and its allowed range). The models, their constants and sources are in
:mod:`quadswarm_mj.sensors` and ``docs/sensors.md``. No import of :mod:`quadswarm_mj.config` here
(``config`` imports this module).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any

#: the largest depth image (pixels per side)
MAX_DEPTH_SIDE = 32


def _real(x: Any) -> bool:
    return isinstance(x, numbers.Real) and not isinstance(x, bool) and type(x).__name__ != "bool_"


def _check(name: str, value: Any, lo: float, hi: float, lo_open: bool = False) -> float:
    ok = _real(value) and math.isfinite(value) and (value > lo if lo_open else value >= lo) and value <= hi
    if not ok:
        raise ValueError(f"sensors.{name} must be a finite number {'>' if lo_open else '>='} {lo} and <= {hi}, "
                         f"got {value!r}")
    return float(value)


@dataclass(frozen=True)
class SensorConfig:
    """Which deck sensors a quad carries, appended to its observation in this order (see
    :func:`quadswarm_mj.sensors.deck_layout`): multi-ranger, flow deck, depth camera.

    * ``multiranger``: Multi-ranger deck, 5 VL53L1x ranges (front = body +x, back, left = body +y,
      right, up = body +z) and their 5 validity flags;
    * ``flow``: Flow deck v2, the downward VL53L1x range, the PMW3901 flow x, y (pixels per 10 ms
      frame) and 2 validity flags (range, flow);
    * ``depth``: None or (H, W), a forward depth image of ranges along the pixel rays (m), H, W in
      [1, 32], field of view ``depth_fov`` (deg, horizontal, vertical), ranges beyond
      ``depth_max_range`` read ``depth_max_range``;
    * ``noise``: the sensors' noise and dropout (``EnvConfig.without_noise()`` turns it off);
    * ``range_limit`` (m): the VL53L1x reading limit (4 m, datasheet), readings beyond are clipped to it
      and flagged invalid; ``dropout``: probability that a ToF reading is lost (flagged invalid, reads
      ``range_limit``);
    * ``light_lux``: the room's illumination; the PMW3901 flow is invalid below its low-light limit.
    """

    multiranger: bool = False
    flow: bool = False
    depth: tuple[int, int] | None = None
    noise: bool = True
    range_limit: float = 4.0  # m
    dropout: float = 0.01
    depth_fov: tuple[float, float] = (45.0, 45.0)  # deg
    depth_max_range: float = 4.0  # m
    light_lux: float = 500.0

    def __post_init__(self) -> None:
        for n in ("multiranger", "flow", "noise"):
            if not isinstance(getattr(self, n), bool):
                raise ValueError(f"sensors.{n} must be a bool, got {getattr(self, n)!r}")
        if self.depth is not None:
            d = self.depth
            try:
                if isinstance(d, (str, bytes)):
                    raise TypeError
                items = tuple(d)
            except TypeError:
                items = ()
            if (len(items) != 2 or not all(isinstance(x, numbers.Integral) and _real(x) for x in items)
                    or not all(1 <= x <= MAX_DEPTH_SIDE for x in items)):
                raise ValueError(f"sensors.depth must be None or (H, W), two ints in [1, {MAX_DEPTH_SIDE}], got {d!r}")
            object.__setattr__(self, "depth", (int(items[0]), int(items[1])))
        object.__setattr__(self, "range_limit", _check("range_limit", self.range_limit, 0.0, 100.0, lo_open=True))
        object.__setattr__(self, "dropout", _check("dropout", self.dropout, 0.0, 1.0))
        object.__setattr__(self, "depth_max_range",
                           _check("depth_max_range", self.depth_max_range, 0.0, 100.0, lo_open=True))
        object.__setattr__(self, "light_lux", _check("light_lux", self.light_lux, 0.0, 1e6))
        try:
            fov = tuple(self.depth_fov)
        except TypeError:
            fov = ()
        if len(fov) != 2:
            raise ValueError(f"sensors.depth_fov must be 2 numbers (deg, horizontal, vertical), got {self.depth_fov!r}")
        object.__setattr__(self, "depth_fov", tuple(_check(f"depth_fov[{i}]", f, 0.0, 170.0, lo_open=True)
                                                    for i, f in enumerate(fov)))

    @property
    def any(self) -> bool:
        """True if any deck sensor is on."""
        return self.multiranger or self.flow or self.depth is not None

    @property
    def num_rays(self) -> int:
        """Rays cast per quad: 5 (multi-ranger) + 1 (flow deck, down) + H W (depth)."""
        h, w = self.depth or (0, 0)
        return 5 * self.multiranger + 1 * self.flow + h * w

    @property
    def obs_dim(self) -> int:
        """Observation components per quad: 10 (multi-ranger) + 5 (flow deck) + H W (depth)."""
        h, w = self.depth or (0, 0)
        return 10 * self.multiranger + 5 * self.flow + h * w
