"""``swarm_vs_swarm`` (SPEC §10): two half swarms at two centres swap places every U(4, 6) s.

Quads 0 .. N//2 - 1 form group A, the others group B. Each group flies a formation of the same
random type and spacing (0.25-0.5 m) around its own centre. At every event the two centres are
swapped and a new formation type, spacing and assignment (within each group) are drawn, so each
group crosses the other on its way. Centres are uniform in the goal region shrunk by 1 m on every side,
at least ``min_separation`` m apart when one of ``centre_tries`` candidates allows it (else the
farthest candidate); each group's formation is moved as little as needed to fit in the room.

``aux`` layout: [0:3] centre of group A (m), [3:6] centre of group B (m).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from quadswarm_mj._xp import array_namespace
from quadswarm_mj.scenarios.base import (
    Scenario,
    ScenarioState,
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
class SwarmVsSwarm(Scenario):
    """Two half swarms swapping centres with new formations every U(4, 6) s.

    Uniforms (init and step): [type, spacing, N shuffle, period, centre A (3),
    ``centre_tries`` x centre B (3)]; ``step`` ignores the centre draws.
    """

    name: str = "swarm_vs_swarm"
    spacing: tuple[float, float] = (0.25, 0.5)
    min_separation: float = 2.0  # m
    centre_tries: int = 4
    centre_inset: float = 1.0  # m, centres keep this much more room than goals

    def num_uniforms(self, num_quads: int) -> int:
        return NUM_FORMATION_UNIFORMS + num_quads + 1 + 3 * (1 + self.centre_tries)

    @staticmethod
    def groups(num_quads: int) -> tuple[int, int]:
        return num_quads // 2, num_quads - num_quads // 2

    def _goals(self, cfg: Any, ca: Any, cb: Any, u: Any) -> tuple[Any, Any]:
        xp = array_namespace(u)
        n = cfg.num_quads
        na, nb = self.groups(n)
        offsets = random_formation(n, u, self.spacing, groups=(na, nb) if na else None)
        parts = []
        if na:
            parts.append(place_formation(cfg, ca, offsets[..., :na, :])[0])
        parts.append(place_formation(cfg, cb, offsets[..., na:, :])[0])
        return xp.concatenate(parts, axis=-2), offsets

    def init(self, cfg: Any, u: Any) -> ScenarioState:
        xp = array_namespace(u)
        k = NUM_FORMATION_UNIFORMS + cfg.num_quads + 1
        s = empty_state(cfg, u)
        ca = uniform_point(cfg, u[..., k:k + 3], self.centre_inset)
        cand = uniform_point(cfg, u[..., k + 3:k + 3 + 3 * self.centre_tries].reshape(
            u.shape[:-1] + (self.centre_tries, 3)), self.centre_inset)
        d = xp.linalg.norm(cand - ca[..., None, :], axis=-1)
        ok = d >= self.min_separation
        first_ok = xp.argmax(ok, axis=-1)
        farthest = xp.argmax(d, axis=-1)
        idx = xp.where(xp.any(ok, axis=-1), first_ok, farthest)
        cb = xp.take_along_axis(cand, idx[..., None, None], axis=-2)[..., 0, :]
        goals, offsets = self._goals(cfg, ca, cb, u)
        aux = xp.concatenate([ca, cb, s.aux[..., 6:]], axis=-1)
        return s._replace(goals=goals, offsets=offsets, aux=aux, next_event=event_period(u[..., k - 1]))

    def step(self, cfg: Any, state: ScenarioState, t: Any, pos: Any, u: Any) -> ScenarioState:
        xp = array_namespace(u)
        k = NUM_FORMATION_UNIFORMS + cfg.num_quads + 1

        def swap_sides() -> ScenarioState:
            a = state.aux
            ca, cb = a[..., 3:6], a[..., 0:3]  # swapped
            goals, offsets = self._goals(cfg, ca, cb, u)
            aux = xp.concatenate([ca, cb, a[..., 6:]], axis=-1)
            return state._replace(goals=goals, offsets=offsets, aux=aux, next_event=t + event_period(u[..., k - 1]))

        return on_event(due(t, state.next_event), swap_sides, state)


SWARM_VS_SWARM = register(SwarmVsSwarm())
