"""Scenario machinery: fixed-shape state, the Scenario base class, spawning.

A scenario is a small frozen object with two pure functions over a fixed-shape
:class:`ScenarioState` (leading batch dims allowed, NumPy or ``jax.numpy``):

* ``init(cfg, u) -> ScenarioState``: ``u`` is a (..., num_uniforms) array of U(0, 1) draws,
* ``step(cfg, state, t, pos, u) -> ScenarioState``: called once per control step *after* the
  physics with the time ``t`` (s, since the episode start, of the state just reached), the quad
  positions (..., N, 3) and fresh uniforms; returns the state holding the goals for that time.

All randomness enters as uniforms in [0, 1) that the scenario maps to its ranges, so a front end
makes a single draw per step. Goals are in the world frame (m) and always inside the room.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

from quadswarm_mj._xp import array_namespace

#: Length of the float scratch vector ``ScenarioState.aux``.
AUX_SIZE = 24
#: Goals keep this distance (m) from walls and ceiling, and at least this height.
GOAL_MARGIN = 0.5
MIN_GOAL_Z = 0.25


class ScenarioState(NamedTuple):
    """Fixed-shape scenario state shared by every scenario (so ``mix`` can switch among them)."""

    goals: Any  # (..., N, 3) m, world frame
    goal_vel: Any  # (..., N, 3) m/s
    offsets: Any  # (..., N, 3) formation offsets or stored goals, scenario-specific
    aux: Any  # (..., AUX_SIZE) scratch floats, scenario-specific
    next_event: Any  # (...,) s, time of the next scheduled goal change (inf if none)
    kind: Any  # (...,) int, index into MIX_CHOICES of the active sub-scenario (mix), else -1


@dataclass(frozen=True)
class Scenario:
    """Base class; subclasses override ``num_uniforms``, ``init`` and ``step``."""

    name: str = "base"

    def num_uniforms(self, num_quads: int) -> int:
        """How many U(0, 1) draws one call of ``init`` or ``step`` consumes."""
        return 4

    def init(self, cfg: Any, u: Any) -> ScenarioState:  # pragma: no cover - abstract
        raise NotImplementedError

    def step(self, cfg: Any, state: ScenarioState, t: Any, pos: Any, u: Any) -> ScenarioState:
        return state


def empty_state(cfg: Any, u: Any) -> ScenarioState:
    """A state with all goals at the formation centre, zero velocity and no events."""
    xp = array_namespace(u)
    batch = u.shape[:-1]
    n = cfg.num_quads
    center = xp.asarray(cfg.formation_center, dtype=u.dtype)
    goals = xp.zeros(batch + (n, 3), dtype=u.dtype) + center
    return ScenarioState(goals=goals, goal_vel=xp.zeros_like(goals), offsets=xp.zeros_like(goals),
                         aux=xp.zeros(batch + (AUX_SIZE,), dtype=u.dtype),
                         next_event=xp.full(batch, float("inf"), dtype=u.dtype),
                         kind=xp.full(batch, -1, dtype=xp.int32))


def room_bounds(cfg: Any, margin: float = GOAL_MARGIN) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(low, high) corners of the region goals may occupy (m)."""
    lo, hi = cfg.room_low, cfg.room_high
    low = (lo[0] + margin, lo[1] + margin, max(MIN_GOAL_Z, lo[2] + MIN_GOAL_Z))
    high = (hi[0] - margin, hi[1] - margin, hi[2] - margin)
    return low, high


def clip_goals(cfg: Any, goals: Any) -> Any:
    """Clip goals (..., 3) into the room with the goal margin."""
    xp = array_namespace(goals)
    low, high = room_bounds(cfg)
    return xp.clip(goals, xp.asarray(low, dtype=goals.dtype), xp.asarray(high, dtype=goals.dtype))


def uniform_point(cfg: Any, u3: Any, margin: float = GOAL_MARGIN) -> Any:
    """Map (..., 3) uniforms to a point inside the room (with margin)."""
    xp = array_namespace(u3)
    low, high = room_bounds(cfg, margin)
    lo = xp.asarray(low, dtype=u3.dtype)
    hi = xp.asarray(high, dtype=u3.dtype)
    return lo + u3 * (hi - lo)


def spawn_num_uniforms(num_quads: int) -> int:
    return 4 * num_quads


def spawn_state(cfg: Any, goals: Any, u: Any) -> dict[str, Any]:
    """Start state near the goals (SPEC §9): goal + U(-2, 2)^3, z >= 0.75, inside the room,
    at rest, yaw facing within 60 degrees of the room centre.

    ``u`` is (..., 4 N) uniforms. Returns ``pos`` (..., N, 3) and ``yaw`` (..., N) in rad.
    """
    xp = array_namespace(u)
    n = cfg.num_quads
    uu = u.reshape(u.shape[:-1] + (n, 4))
    pos = goals + (uu[..., :3] * 4.0 - 2.0)
    lo, hi = cfg.room_low, cfg.room_high
    m = 0.5
    low = xp.asarray((lo[0] + m, lo[1] + m, max(0.75, lo[2])), dtype=u.dtype)
    high = xp.asarray((hi[0] - m, hi[1] - m, max(0.75, hi[2] - m)), dtype=u.dtype)
    pos = xp.clip(pos, low, high)
    to_center = xp.arctan2(-pos[..., 1], -pos[..., 0])
    yaw = to_center + (uu[..., 3] * 2.0 - 1.0) * (xp.pi / 3.0)
    return {"pos": pos, "yaw": yaw}
