"""``mix`` (SPEC §10): at every reset, one sub-scenario drawn uniformly per world.

Candidates: :data:`MIX_CHOICES` (nine scenarios); with one quad only the first five
(:data:`MIX_CHOICES_SINGLE`). ``ScenarioState.kind`` holds the index of the drawn scenario in
``MIX_CHOICES``. All scenarios share one fixed-shape state, so ``mix`` runs every candidate's
``init``/``step`` and keeps, per world, the result of the drawn one (a fixed-shape select that
works under ``jax.jit``/``jax.vmap``); each candidate gets the leading uniforms it needs after the
one that picks the scenario.

With obstacles (``cfg.obstacles`` set) the candidates are :data:`OBSTACLE_MIX_CHOICES` (``kind``
indexes that tuple), the column map comes in as ``obstacles=`` and the uniform count is
``num_uniforms(N, with_obstacles=True)`` (see :mod:`quadswarm_mj.scenarios.obstacle_scenarios`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from quadswarm_mj.scenarios.base import Scenario, ScenarioState, on_event, select_state, uniform_int
from quadswarm_mj.scenarios.registry import get_scenario, register

MIX_CHOICES = ("static_same_goal", "static_diff_goal", "ep_lissajous3D", "ep_rand_bezier", "dynamic_same_goal",
               "dynamic_diff_goal", "dynamic_formations", "swap_goals", "swarm_vs_swarm")
MIX_CHOICES_SINGLE = MIX_CHOICES[:5]
#: with obstacles (SPEC_obstacles A.5): o_random and o_static_same_goal; o_random only for N = 1
OBSTACLE_MIX_CHOICES = ("o_random", "o_static_same_goal")
OBSTACLE_MIX_CHOICES_SINGLE = OBSTACLE_MIX_CHOICES[:1]


@dataclass(frozen=True)
class Mix(Scenario):
    """Uniform draw per reset among ``MIX_CHOICES`` (``MIX_CHOICES_SINGLE`` for N = 1).

    Uniforms: [choice, then the candidates' own uniforms (the longest list)].
    """

    name: str = "mix"
    accepts_obstacles: ClassVar[bool] = True

    @staticmethod
    def choices(num_quads: int, with_obstacles: bool = False) -> tuple[Scenario, ...]:
        if with_obstacles:
            names = OBSTACLE_MIX_CHOICES_SINGLE if num_quads == 1 else OBSTACLE_MIX_CHOICES
        else:
            names = MIX_CHOICES_SINGLE if num_quads == 1 else MIX_CHOICES
        return tuple(get_scenario(n) for n in names)

    def num_uniforms(self, num_quads: int, with_obstacles: bool = False) -> int:
        return 1 + max(c.num_uniforms(num_quads) for c in self.choices(num_quads, with_obstacles))

    def init(self, cfg: Any, u: Any, obstacles: Any = None) -> ScenarioState:
        obst = cfg.obstacles is not None
        cands = self.choices(cfg.num_quads, obst)
        kind = uniform_int(u[..., 0], len(cands))
        out = None
        for i, c in enumerate(cands):
            ui = u[..., 1:1 + c.num_uniforms(cfg.num_quads)]
            s = c.init(cfg, ui, obstacles=obstacles) if obst else c.init(cfg, ui)
            out = s if out is None else select_state(kind == i, s, out)
        return out._replace(kind=kind)

    def step(self, cfg: Any, state: ScenarioState, t: Any, pos: Any, u: Any, obstacles: Any = None) -> ScenarioState:
        obst = cfg.obstacles is not None
        out = state
        for i, c in enumerate(self.choices(cfg.num_quads, obst)):
            ui = u[..., 1:1 + c.num_uniforms(cfg.num_quads)]
            if obst:
                def fn(c: Scenario = c, ui: Any = ui) -> ScenarioState:
                    return c.step(cfg, state, t, pos, ui, obstacles=obstacles)  # type: ignore[call-arg]
            else:
                def fn(c: Scenario = c, ui: Any = ui) -> ScenarioState:
                    return c.step(cfg, state, t, pos, ui)
            out = on_event(state.kind == i, fn, out)
        return out._replace(kind=state.kind)


MIX = register(Mix())
