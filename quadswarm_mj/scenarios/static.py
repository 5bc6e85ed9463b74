"""Static scenarios: one shared goal, or a fixed random formation (SPEC §10)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from quadswarm_mj.scenarios.base import Scenario, ScenarioState, clip_goals, empty_state
from quadswarm_mj.scenarios.formations import NUM_FORMATION_UNIFORMS, random_formation
from quadswarm_mj.scenarios.registry import register


@dataclass(frozen=True)
class StaticSameGoal(Scenario):
    """Every quad flies to the formation centre and stays there."""

    name: str = "static_same_goal"

    def init(self, cfg: Any, u: Any) -> ScenarioState:
        s = empty_state(cfg, u)
        return s._replace(goals=clip_goals(cfg, s.goals))


@dataclass(frozen=True)
class StaticDiffGoal(Scenario):
    """A fixed random formation (type, spacing 0.25-0.5 m) around the formation centre."""

    name: str = "static_diff_goal"
    spacing: tuple[float, float] = (0.25, 0.5)

    def num_uniforms(self, num_quads: int) -> int:
        return NUM_FORMATION_UNIFORMS + num_quads

    def init(self, cfg: Any, u: Any) -> ScenarioState:
        s = empty_state(cfg, u)
        offsets = random_formation(cfg.num_quads, u, self.spacing)
        goals = clip_goals(cfg, s.goals + offsets)
        return s._replace(goals=goals, offsets=offsets)


STATIC_SAME_GOAL = register(StaticSameGoal())
STATIC_DIFF_GOAL = register(StaticDiffGoal())
