"""``swap_goals`` (SPEC §10): a random formation (spacing 0.4-0.8 m) whose goals are permuted
among the quads every U(4, 6) s.

The permutation is drawn uniformly and replaced by a cyclic shift when it is the identity, so
every event moves goals (N >= 2). The goal set itself never changes (goal velocity 0).
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
)
from quadswarm_mj.scenarios.formations import NUM_FORMATION_UNIFORMS, random_formation
from quadswarm_mj.scenarios.registry import register


def non_identity_permutation(u: Any) -> Any:
    """Permutation (..., N) int sorting ``u`` (..., N); the identity is replaced by a shift by one."""
    xp = array_namespace(u)
    n = u.shape[-1]
    ar = xp.arange(n)
    perm = xp.argsort(u, axis=-1)
    is_id = xp.all(perm == ar, axis=-1, keepdims=True)
    return xp.where(is_id, (ar + 1) % n, perm)


@dataclass(frozen=True)
class SwapGoals(Scenario):
    """Goals of a fixed formation permuted among quads every U(4, 6) s.

    Uniforms: init [type, spacing, N shuffle, period]; step [N permutation, .., period].
    """

    name: str = "swap_goals"
    spacing: tuple[float, float] = (0.4, 0.8)

    def num_uniforms(self, num_quads: int) -> int:
        return NUM_FORMATION_UNIFORMS + num_quads + 1

    def init(self, cfg: Any, u: Any) -> ScenarioState:
        s = empty_state(cfg, u)
        offsets = random_formation(cfg.num_quads, u, self.spacing)
        goals, _ = place_formation(cfg, s.goals[..., 0, :], offsets)
        return s._replace(goals=goals, offsets=offsets, next_event=event_period(u[..., -1]))

    def step(self, cfg: Any, state: ScenarioState, t: Any, pos: Any, u: Any) -> ScenarioState:
        xp = array_namespace(u)

        def swap() -> ScenarioState:
            perm = non_identity_permutation(u[..., :cfg.num_quads])[..., None]
            return state._replace(goals=xp.take_along_axis(state.goals, perm, axis=-2),
                                  offsets=xp.take_along_axis(state.offsets, perm, axis=-2),
                                  next_event=t + event_period(u[..., -1]))

        return on_event(due(t, state.next_event), swap, state)


SWAP_GOALS = register(SwapGoals())
