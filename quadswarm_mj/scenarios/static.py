"""Static scenarios: one shared goal, or a fixed random formation (SPEC §10).

Both keep their goals for the whole episode (``next_event`` = inf, goal velocity 0); ``step`` never
recomputes them, so goals set by the front end at reset are kept.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from quadswarm_mj.scenarios.base import Scenario, ScenarioState, clip_goals, empty_state, place_formation
from quadswarm_mj.scenarios.formations import NUM_FORMATION_UNIFORMS, random_formation
from quadswarm_mj.scenarios.registry import register


@dataclass(frozen=True)
class StaticSameGoal(Scenario):
    """Every quad flies to the formation centre (``cfg.formation_center``, m) and stays there."""

    name: str = "static_same_goal"

    def init(self, cfg: Any, u: Any) -> ScenarioState:
        s = empty_state(cfg, u)
        return s._replace(goals=clip_goals(cfg, s.goals))


@dataclass(frozen=True)
class StaticDiffGoal(Scenario):
    """A fixed random formation (type, spacing 0.25-0.5 m, shuffled) around the formation centre,
    moved as little as needed to fit in the room. Uniforms: [type, spacing, N shuffle]."""

    name: str = "static_diff_goal"
    spacing: tuple[float, float] = (0.25, 0.5)

    def num_uniforms(self, num_quads: int) -> int:
        return NUM_FORMATION_UNIFORMS + num_quads

    def init(self, cfg: Any, u: Any) -> ScenarioState:
        s = empty_state(cfg, u)
        offsets = random_formation(cfg.num_quads, u, self.spacing)
        goals, _ = place_formation(cfg, s.goals[..., 0, :], offsets)
        return s._replace(goals=goals, offsets=offsets)


STATIC_SAME_GOAL = register(StaticSameGoal())
STATIC_DIFF_GOAL = register(StaticDiffGoal())
