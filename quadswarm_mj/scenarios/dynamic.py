"""Dynamic scenarios (SPEC §10): goals that jump, formations that are redrawn, formations that
shrink and expand.

* ``dynamic_same_goal``: one shared goal at the formation centre; every U(4, 6) s it jumps to a
  uniformly random point of the room (goal margin 0.5 m at walls and ceiling, z >= 0.25 m).
* ``dynamic_diff_goal``: a random formation (spacing 0.25-0.5 m) at the formation centre; every
  U(4, 6) s the centre (uniform in the room), type, spacing and goal assignment are redrawn.
* ``dynamic_formations``: a random formation whose spacing moves linearly between 0 and 1.0 m at
  U(0.1, 0.3) m/s; at each limit the direction reverses and the speed is redrawn.

``aux`` layout of ``dynamic_formations``: [0:3] centre (m), [3] spacing s0 (m) at the segment
start, [4] segment start time t0 (s), [5] direction (+1 grow, -1 shrink), [6] speed (m/s).
``offsets`` hold the unit-spacing formation (shuffled), so goals = centre + offsets * s(t).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from quadswarm_mj._xp import array_namespace
from quadswarm_mj.scenarios.base import (
    Scenario,
    ScenarioState,
    clip_goals,
    due,
    empty_state,
    event_period,
    on_event,
    place_formation,
    uniform_point,
)
from quadswarm_mj.scenarios.formations import NUM_FORMATION_UNIFORMS, random_formation
from quadswarm_mj.scenarios.registry import register


@dataclass(frozen=True)
class DynamicSameGoal(Scenario):
    """Shared goal jumping every U(4, 6) s to a random point in the room.

    Uniforms (init and step): [x, y, z, period].
    """

    name: str = "dynamic_same_goal"

    def num_uniforms(self, num_quads: int) -> int:
        return 4

    def init(self, cfg: Any, u: Any) -> ScenarioState:
        s = empty_state(cfg, u)
        return s._replace(goals=clip_goals(cfg, s.goals), next_event=event_period(u[..., 3]))

    def step(self, cfg: Any, state: ScenarioState, t: Any, pos: Any, u: Any) -> ScenarioState:
        xp = array_namespace(u)

        def jump() -> ScenarioState:
            point = uniform_point(cfg, u[..., :3])
            return state._replace(goals=xp.zeros_like(state.goals) + point[..., None, :],
                                  next_event=t + event_period(u[..., 3]))

        return on_event(due(t, state.next_event), jump, state)


@dataclass(frozen=True)
class DynamicDiffGoal(Scenario):
    """Random formation redrawn (centre, type, spacing, assignment) every U(4, 6) s.

    Uniforms (init and step): [centre x, y, z, type, spacing, N shuffle, period]; ``init`` ignores
    the centre draws and starts at the formation centre.
    """

    name: str = "dynamic_diff_goal"
    spacing: tuple[float, float] = (0.25, 0.5)

    def num_uniforms(self, num_quads: int) -> int:
        return 3 + NUM_FORMATION_UNIFORMS + num_quads + 1

    def _formation(self, cfg: Any, center: Any, u: Any) -> tuple[Any, Any]:
        offsets = random_formation(cfg.num_quads, u[..., 3:], self.spacing)
        goals, _ = place_formation(cfg, center, offsets)
        return goals, offsets

    def init(self, cfg: Any, u: Any) -> ScenarioState:
        s = empty_state(cfg, u)
        goals, offsets = self._formation(cfg, s.goals[..., 0, :], u)
        return s._replace(goals=goals, offsets=offsets, next_event=event_period(u[..., -1]))

    def step(self, cfg: Any, state: ScenarioState, t: Any, pos: Any, u: Any) -> ScenarioState:
        def redraw() -> ScenarioState:
            goals, offsets = self._formation(cfg, uniform_point(cfg, u[..., :3]), u)
            return state._replace(goals=goals, offsets=offsets, next_event=t + event_period(u[..., -1]))

        return on_event(due(t, state.next_event), redraw, state)


@dataclass(frozen=True)
class DynamicFormations(Scenario):
    """Shrink & expand: a random formation whose spacing oscillates in ``spacing`` (m) at a speed
    (m/s of spacing) redrawn from ``speed`` at each limit. The centre is placed once so that the
    formation fits in the room at the largest spacing; goal_vel = offsets * ds/dt.

    Uniforms: init [type, s0, N shuffle, direction, speed]; step [.., speed] (last one used).
    """

    name: str = "dynamic_formations"
    spacing: tuple[float, float] = (0.0, 1.0)
    speed: tuple[float, float] = (0.1, 0.3)

    def num_uniforms(self, num_quads: int) -> int:
        return NUM_FORMATION_UNIFORMS + num_quads + 2

    def _speed(self, u: Any) -> Any:
        return self.speed[0] + u * (self.speed[1] - self.speed[0])

    def _goals(self, cfg: Any, s: ScenarioState, t: Any) -> ScenarioState:
        """Goals and goal velocity at time t from the segment parameters in ``aux``."""
        xp = array_namespace(s.aux)
        lo, hi = self.spacing
        a = s.aux
        center, s0, t0, direction, speed = a[..., 0:3], a[..., 3], a[..., 4], a[..., 5], a[..., 6]
        spacing = xp.clip(s0 + direction * speed * (t - t0), lo, hi)
        raw = center[..., None, :] + s.offsets * spacing[..., None, None]
        goals = clip_goals(cfg, raw)
        vel = s.offsets * (direction * speed)[..., None, None]
        vel = xp.where(xp.abs(goals - raw) > 1e-9, 0.0, vel)
        # time at which the spacing reaches the limit it is heading to
        to_go = xp.where(direction > 0, hi - s0, s0 - lo)
        next_event = t0 + to_go / xp.maximum(speed, 1e-6)
        return s._replace(goals=goals, goal_vel=vel, next_event=next_event)

    def init(self, cfg: Any, u: Any) -> ScenarioState:
        xp = array_namespace(u)
        n = cfg.num_quads
        s = empty_state(cfg, u)
        unit = random_formation(n, u, (1.0, 1.0))  # shuffled, unit spacing
        lo, hi = self.spacing
        _, center = place_formation(cfg, s.goals[..., 0, :], unit * hi)
        s0 = lo + u[..., 1] * (hi - lo)
        direction = xp.where(u[..., NUM_FORMATION_UNIFORMS + n] < 0.5, -1.0, 1.0).astype(u.dtype)
        aux = xp.concatenate([center, s0[..., None], xp.zeros_like(s0)[..., None], direction[..., None],
                              self._speed(u[..., -1])[..., None], s.aux[..., 7:]], axis=-1)
        return self._goals(cfg, s._replace(offsets=unit, aux=aux), xp.zeros_like(s0))

    def step(self, cfg: Any, state: ScenarioState, t: Any, pos: Any, u: Any) -> ScenarioState:
        xp = array_namespace(state.aux)
        lo, hi = self.spacing
        a = state.aux
        ev = due(t, state.next_event)
        limit = xp.where(a[..., 5] > 0, hi, lo)
        new_aux = xp.concatenate([a[..., 0:3], limit[..., None], t[..., None] + xp.zeros_like(limit[..., None]),
                                  -a[..., 5:6], self._speed(u[..., -1])[..., None], a[..., 7:]], axis=-1)
        aux = xp.where(ev[..., None], new_aux, a)
        return self._goals(cfg, state._replace(aux=aux), t)


DYNAMIC_SAME_GOAL = register(DynamicSameGoal())
DYNAMIC_DIFF_GOAL = register(DynamicDiffGoal())
DYNAMIC_FORMATIONS = register(DynamicFormations())
