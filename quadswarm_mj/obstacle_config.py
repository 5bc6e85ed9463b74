"""``ObstacleConfig``: columns from floor to ceiling on the cells of a spawn area (SPEC_obstacles A.1,
A.6). Re-exported by :mod:`quadswarm_mj.config`; :mod:`quadswarm_mj.obstacles` builds the maps from it."""

from __future__ import annotations

import numbers
from dataclasses import dataclass

from quadswarm_mj.config_checks import MAX_REWARD_SCALE, _check_range, _is_real

OBSTACLE_DENSITY_VALUES = (0.05, 0.10, 0.15, 0.20)  # SPEC_obstacles A.6: np.arange(0.05, 0.2, 0.05) incl. 0.2
OBSTACLE_SIZE_VALUES = (0.3, 0.4, 0.5)  # SPEC_obstacles A.6: np.arange(0.3, 0.6, 0.1), 0.6 excluded
FEATURE_FORMS = ("grid", "slopes", "near")


@dataclass(frozen=True)
class ObstacleConfig:
    """Columns from floor to ceiling on the cells of a spawn area (SPEC_obstacles A.1, A.6).

    ``size`` is the column *diameter* (m); ``area`` (m, along x and y) is centred on the room and
    split into ``cell``-sized cells; ``int(cells_x * cells_y * density)`` cells get a column at
    every reset. ``density_random`` / ``size_random`` draw density and size per reset uniformly
    from ``density_values`` / ``size_values``. ``max_columns`` (None: the most any reset can
    place) fixes the number of column slots per world (static shapes). ``collision_reward`` is
    the penalty per new obstacle contact (not scaled by dt; SPEC_obstacles A.4). ``proximity_reward``
    (default 0: off, as the original) adds the shaping term ``obstacle_proximity``: per control step
    ``-control_dt * proximity_reward * max(1 - d / proximity_falloff, 0)`` with ``d`` the distance (m)
    from the quad's centre to the nearest column surface in xy (negative inside a column).
    ``approach_reward`` (default 0: off) adds the shaping term ``obstacle_approach``: per control step
    ``-control_dt * approach_reward * max(-v . grad d, 0) * max(1 - d / proximity_falloff, 0)``, the speed
    (m/s) towards the nearest column within the falloff (motion around a column costs nothing).
    ``pos_around_columns`` (default False: the straight distance, as the original) makes the reward's
    ``pos`` cost the path length around the nearest column when it blocks the way to the goal
    (:func:`quadswarm_mj.obstacles.around_distance`); the metrics keep the straight distance.
    ``observe_features`` (default True) appends the 9 privileged column-distance features
    (SPEC_obstacles A.2, from the true column map) to every observation; False keeps the columns in
    the world (physics, collisions, the deck sensors' rays) but leaves these 9 features out of the
    observation, so a policy must sense the columns, e.g. with ``SensorConfig(multiranger=True)``.
    ``feature_form`` is how the 9 features are observed: ``"grid"`` (default, the original's 3 x 3
    distances) or ``"slopes"`` (the centre distance and the 8 others' differences from it per
    0.1 m: the same information, decorrelated) or ``"near"`` (the slopes form made local and bounded: a
    proximity 0 beyond ``near_range`` (m, default 1) of a column's surface and 1 at it, the slopes scaled by it;
    all 0 in open space; :func:`quadswarm_mj.obstacles.observed_features`). ``near_speed_reach`` (s, default 0)
    lengthens that reach by the quad's closing speed (m/s) towards the nearest column times this: a fast approach
    is seen from further off, a hover beside a column not at all.
    """

    density: float = 0.2
    size: float = 0.6  # m, diameter
    area: tuple[float, float] = (8.0, 8.0)  # m
    cell: float = 1.0  # m
    density_random: bool = False
    size_random: bool = False
    density_values: tuple[float, ...] = OBSTACLE_DENSITY_VALUES
    size_values: tuple[float, ...] = OBSTACLE_SIZE_VALUES
    max_columns: int | None = None
    collision_reward: float = 5.0
    observe_features: bool = True
    proximity_reward: float = 0.0
    proximity_falloff: float = 0.5  # m
    approach_reward: float = 0.0
    pos_around_columns: bool = False
    feature_form: str = "grid"
    near_range: float = 1.0  # m
    near_speed_reach: float = 0.0  # s

    def __post_init__(self) -> None:
        _check_range("obstacles.density", self.density, 0.0, 1.0)
        _check_range("obstacles.cell", self.cell, 0.0, lo_open=True)
        _check_range("obstacles.size", self.size, 0.0, lo_open=True)
        if not self.size < self.cell:
            raise ValueError(f"obstacles.size (diameter, m) must be smaller than obstacles.cell = {self.cell}, "
                             f"got {self.size!r}")
        try:
            area = tuple(float(x) for x in self.area)
        except Exception as e:  # noqa: BLE001
            raise ValueError(f"obstacles.area must be 2 numbers (m, x and y), got {self.area!r}") from e
        if len(area) != 2:
            raise ValueError(f"obstacles.area must be 2 numbers (m, x and y), got {self.area!r}")
        for i, a in enumerate(area):
            _check_range(f"obstacles.area[{i}]", a, self.cell)
        object.__setattr__(self, "area", area)
        for n, vals in (("density_values", self.density_values), ("size_values", self.size_values)):
            try:
                vals = tuple(float(x) for x in vals)
            except Exception as e:  # noqa: BLE001
                raise ValueError(f"obstacles.{n} must be a non-empty tuple of numbers, got {vals!r}") from e
            if not vals:
                raise ValueError(f"obstacles.{n} must be a non-empty tuple of numbers, got {vals!r}")
            object.__setattr__(self, n, vals)
        for i, d in enumerate(self.density_values):
            _check_range(f"obstacles.density_values[{i}]", d, 0.0, 1.0)
        for i, d in enumerate(self.size_values):
            _check_range(f"obstacles.size_values[{i}]", d, 0.0, lo_open=True)
            if not d < self.cell:
                raise ValueError(f"obstacles.size_values[{i}] must be smaller than obstacles.cell = {self.cell}, "
                                 f"got {d!r}")
        for n in ("density_random", "size_random", "observe_features", "pos_around_columns"):
            if not isinstance(getattr(self, n), bool):
                raise ValueError(f"obstacles.{n} must be a bool, got {getattr(self, n)!r}")
        _check_range("obstacles.collision_reward", self.collision_reward, 0.0, MAX_REWARD_SCALE)
        _check_range("obstacles.proximity_reward", self.proximity_reward, 0.0, MAX_REWARD_SCALE)
        _check_range("obstacles.proximity_falloff", self.proximity_falloff, 0.0, 10.0, lo_open=True)
        _check_range("obstacles.approach_reward", self.approach_reward, 0.0, MAX_REWARD_SCALE)
        if self.feature_form not in FEATURE_FORMS:
            raise ValueError(f"obstacles.feature_form must be one of {FEATURE_FORMS}, got {self.feature_form!r}")
        _check_range("obstacles.near_range", self.near_range, 0.0, 10.0, lo_open=True)
        _check_range("obstacles.near_speed_reach", self.near_speed_reach, 0.0, 5.0)
        need = self.columns_needed
        if self.max_columns is not None:
            m = self.max_columns
            if isinstance(m, numbers.Integral) and _is_real(m):
                m = int(m)
                object.__setattr__(self, "max_columns", m)
            if not isinstance(m, int) or isinstance(m, bool) or m < max(need, 1) or m > self.num_cells:
                raise ValueError(f"obstacles.max_columns must be an int in [{max(need, 1)}, {self.num_cells}] "
                                 f"(the most columns a reset places .. the number of cells), got {m!r}")

    @property
    def grid(self) -> tuple[int, int]:
        """(cells along x, cells along y)."""
        return tuple(int(a / self.cell + 1e-9) for a in self.area)  # type: ignore[return-value]

    @property
    def num_cells(self) -> int:
        gx, gy = self.grid
        return gx * gy

    def num_columns(self, density: float | None = None) -> int:
        """Columns placed at ``density`` (default: ``self.density``): int(cells * density), as the original."""
        return int(self.num_cells * (self.density if density is None else density))

    @property
    def columns_needed(self) -> int:
        """The most columns one reset can place (over the density values when randomized)."""
        ds = self.density_values if self.density_random else (self.density,)
        return max(self.num_columns(d) for d in ds)

    @property
    def slots(self) -> int:
        """M_max: column slots per world (>= 1 so arrays never have a zero-size axis)."""
        return self.max_columns if self.max_columns is not None else max(self.columns_needed, 1)

    @property
    def feature_dim(self) -> int:
        """Observation components of the column features: 9 when ``observe_features``, else 0."""
        return 9 if self.observe_features else 0

    @property
    def max_size(self) -> float:
        """Largest column diameter any reset can draw (m)."""
        return max(self.size_values) if self.size_random else self.size
