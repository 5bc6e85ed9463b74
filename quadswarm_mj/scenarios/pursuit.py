"""Evader pursuit (SPEC §10): every quad chases one shared goal moving along a curve.

* ``ep_lissajous3D``: the closed-form 3D Lissajous curve of :func:`trajectories.lissajous3d`,
  t in s from the episode start; goal_vel is its analytic derivative. In a room too small for the
  curve around (-2, 0, 2) the centre is moved (per axis) just enough for the curve to fit, and
  what still does not fit is clipped (goal_vel 0 on clipped axes).
* ``ep_rand_bezier``: quadratic Bezier segments, a new one every 5 s from the episode start.
  Segment k runs from the end of segment k - 1 (the formation centre for k = 0) to a random end
  point 5-10 m away (the first of ``end_tries`` uniform candidates in the room at such a
  distance, else the candidate closest to that range, e.g. in a small room) through a uniformly
  random control point in the room; the whole segment stays in the room (convex hull property).
  goal_vel = B'(tau) / 5 s.

``aux`` layout of ``ep_rand_bezier``: [0:3] start, [3:6] control, [6:9] end point (m), [9] t0 (s).
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
    on_event,
    room_bounds,
    uniform_point,
)
from quadswarm_mj.scenarios.registry import register
from quadswarm_mj.scenarios.trajectories import LISSAJOUS_AMPLITUDE, LISSAJOUS_CENTER, bezier2, lissajous3d


def _shared(xp: Any, point: Any, n: int) -> Any:
    """Broadcast a point (..., 3) to every quad (..., N, 3)."""
    return xp.broadcast_to(point[..., None, :], point.shape[:-1] + (n, 3))


@dataclass(frozen=True)
class EpLissajous3D(Scenario):
    """Shared goal on the closed-form 3D Lissajous curve. Uses no uniforms."""

    name: str = "ep_lissajous3D"

    def num_uniforms(self, num_quads: int) -> int:
        return 1

    @staticmethod
    def center(cfg: Any) -> tuple[float, ...]:
        """Curve centre (m): (-2, 0, 2), moved per axis just enough for the curve to fit the room."""
        low, high = room_bounds(cfg)
        return tuple(min(max(c, lo + a), hi - a) if lo + a <= hi - a else 0.5 * (lo + hi)
                     for c, a, lo, hi in zip(LISSAJOUS_CENTER, LISSAJOUS_AMPLITUDE, low, high))

    def _at(self, cfg: Any, s: ScenarioState, t: Any) -> ScenarioState:
        xp = array_namespace(s.goals)
        raw, vel = lissajous3d(xp.asarray(t, dtype=s.goals.dtype), self.center(cfg))
        goal = clip_goals(cfg, raw)
        vel = xp.where(xp.abs(goal - raw) > 1e-9, 0.0, vel)
        n = cfg.num_quads
        return s._replace(goals=_shared(xp, goal, n) + 0.0, goal_vel=_shared(xp, vel, n) + 0.0)

    def init(self, cfg: Any, u: Any) -> ScenarioState:
        xp = array_namespace(u)
        return self._at(cfg, empty_state(cfg, u), xp.zeros(u.shape[:-1], dtype=u.dtype))

    def step(self, cfg: Any, state: ScenarioState, t: Any, pos: Any, u: Any) -> ScenarioState:
        return self._at(cfg, state, t)


@dataclass(frozen=True)
class EpRandBezier(Scenario):
    """Shared goal on random quadratic Bezier segments, a new one every ``period`` s.

    Uniforms (init and step): [``end_tries`` x end point (3), control point (3)].
    """

    name: str = "ep_rand_bezier"
    period: float = 5.0  # s
    distance: tuple[float, float] = (5.0, 10.0)  # m, start to end of a segment
    end_tries: int = 16

    def num_uniforms(self, num_quads: int) -> int:
        return 3 * self.end_tries + 3

    def _segment(self, cfg: Any, start: Any, u: Any) -> tuple[Any, Any]:
        """Control and end point (..., 3) of a new segment from ``start``."""
        xp = array_namespace(u)
        k = self.end_tries
        cand = uniform_point(cfg, u[..., :3 * k].reshape(u.shape[:-1] + (k, 3)))
        d = xp.linalg.norm(cand - start[..., None, :], axis=-1)
        miss = xp.maximum(self.distance[0] - d, 0.0) + xp.maximum(d - self.distance[1], 0.0)
        idx = xp.argmin(miss, axis=-1)
        end = xp.take_along_axis(cand, idx[..., None, None], axis=-2)[..., 0, :]
        control = uniform_point(cfg, u[..., 3 * k:3 * k + 3])
        return control, end

    def _at(self, cfg: Any, s: ScenarioState, t: Any) -> ScenarioState:
        xp = array_namespace(s.aux)
        a = s.aux
        tau = xp.clip((t - a[..., 9]) / self.period, 0.0, 1.0)
        pos, dpos = bezier2(a[..., 0:3], a[..., 3:6], a[..., 6:9], tau)
        n = cfg.num_quads
        return s._replace(goals=_shared(xp, clip_goals(cfg, pos), n) + 0.0,
                          goal_vel=_shared(xp, dpos / self.period, n) + 0.0)

    def init(self, cfg: Any, u: Any) -> ScenarioState:
        xp = array_namespace(u)
        s = empty_state(cfg, u)
        start = clip_goals(cfg, s.goals[..., 0, :])
        control, end = self._segment(cfg, start, u)
        t0 = xp.zeros(u.shape[:-1] + (1,), dtype=u.dtype)
        aux = xp.concatenate([start, control, end, t0, s.aux[..., 10:]], axis=-1)
        s = s._replace(aux=aux, next_event=t0[..., 0] + self.period)
        return self._at(cfg, s, t0[..., 0])

    def step(self, cfg: Any, state: ScenarioState, t: Any, pos: Any, u: Any) -> ScenarioState:
        xp = array_namespace(u)

        def new_segment() -> ScenarioState:
            a = state.aux
            start = a[..., 6:9]
            control, end = self._segment(cfg, start, u)
            aux = xp.concatenate([start, control, end, state.next_event[..., None], a[..., 10:]], axis=-1)
            return state._replace(aux=aux, next_event=state.next_event + self.period)

        return self._at(cfg, on_event(due(t, state.next_event), new_segment, state), t)


EP_LISSAJOUS3D = register(EpLissajous3D())
EP_RAND_BEZIER = register(EpRandBezier())
