"""``run_away`` (SPEC §10): a random formation (spacing 0.25-0.5 m); every 1 s two random quads
leave their goal for the formation goal of a random other quad.

The formation goals (m, world frame) are kept in ``offsets`` and each quad's current formation
slot in ``slots``; at every event two distinct quads a, b each move to a slot other than their
current one (uniform among the N - 1 others), so both goals change (N >= 2) and goals become
shared, as in the original where quads 0 and 1 copy the goals of random others. The other quads
keep their goals. Events at t = 1, 2, 3, ... s (the next multiple of 1 s after each event).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from quadswarm_mj._xp import array_namespace
from quadswarm_mj.scenarios.base import (
    EVENT_EPS,
    Scenario,
    ScenarioState,
    due,
    empty_state,
    on_event,
    place_formation,
    uniform_int,
)
from quadswarm_mj.scenarios.formations import NUM_FORMATION_UNIFORMS, random_formation
from quadswarm_mj.scenarios.registry import register


@dataclass(frozen=True)
class RunAway(Scenario):
    """Two quads take the formation goals of random others every ``period`` s.

    Uniforms: init [type, spacing, N shuffle]; step [quad a, quad b, slot of a, slot of b].
    """

    name: str = "run_away"
    spacing: tuple[float, float] = (0.25, 0.5)
    period: float = 1.0  # s

    def num_uniforms(self, num_quads: int) -> int:
        return max(NUM_FORMATION_UNIFORMS + num_quads, 4)

    def init(self, cfg: Any, u: Any) -> ScenarioState:
        xp = array_namespace(u)
        s = empty_state(cfg, u)
        offsets = random_formation(cfg.num_quads, u, self.spacing)
        goals, _ = place_formation(cfg, s.goals[..., 0, :], offsets)
        return s._replace(goals=goals, offsets=goals, next_event=xp.full_like(s.next_event, self.period))

    def step(self, cfg: Any, state: ScenarioState, t: Any, pos: Any, u: Any) -> ScenarioState:
        return on_event(due(t, state.next_event), lambda: self._run(cfg, state, t, u), state)

    def _run(self, cfg: Any, state: ScenarioState, t: Any, u: Any) -> ScenarioState:
        xp = array_namespace(u)
        n = cfg.num_quads
        ar = xp.arange(n, dtype=xp.int32)
        qa = uniform_int(u[..., 0], n)
        qb = (qa + 1 + uniform_int(u[..., 1], n - 1)) % n
        slot_a = xp.take_along_axis(state.slots, qa[..., None], axis=-1)[..., 0]
        slot_b = xp.take_along_axis(state.slots, qb[..., None], axis=-1)[..., 0]
        new_a = (slot_a + 1 + uniform_int(u[..., 2], n - 1)) % n
        new_b = (slot_b + 1 + uniform_int(u[..., 3], n - 1)) % n
        is_a = ar == qa[..., None]
        is_b = ar == qb[..., None]
        slots = xp.where(is_a, new_a[..., None], xp.where(is_b, new_b[..., None], state.slots)).astype(xp.int32)
        moved = (is_a | is_b)[..., None]
        goals = xp.where(moved, xp.take_along_axis(state.offsets, slots[..., None], axis=-2), state.goals)
        return state._replace(goals=goals, slots=slots,
                              next_event=(xp.floor((t + EVENT_EPS) / self.period) + 1.0) * self.period)


RUN_AWAY = register(RunAway())
