"""``mix`` (SPEC §10): at every reset, one sub-scenario drawn uniformly per world.

Candidates: :data:`MIX_CHOICES` (nine scenarios); with one quad only the first five
(:data:`MIX_CHOICES_SINGLE`). ``ScenarioState.kind`` holds the index of the drawn scenario in
``MIX_CHOICES``. All scenarios share one fixed-shape state, so ``mix`` runs every candidate's
``init``/``step`` and keeps, per world, the result of the drawn one (a fixed-shape select that
works under ``jax.jit``/``jax.vmap``); each candidate gets the leading uniforms it needs after the
one that picks the scenario.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from quadswarm_mj.scenarios.base import Scenario, ScenarioState, on_event, select_state, uniform_int
from quadswarm_mj.scenarios.registry import get_scenario, register

MIX_CHOICES = ("static_same_goal", "static_diff_goal", "ep_lissajous3D", "ep_rand_bezier", "dynamic_same_goal",
               "dynamic_diff_goal", "dynamic_formations", "swap_goals", "swarm_vs_swarm")
MIX_CHOICES_SINGLE = MIX_CHOICES[:5]


@dataclass(frozen=True)
class Mix(Scenario):
    """Uniform draw per reset among ``MIX_CHOICES`` (``MIX_CHOICES_SINGLE`` for N = 1).

    Uniforms: [choice, then the candidates' own uniforms (the longest list)].
    """

    name: str = "mix"

    @staticmethod
    def choices(num_quads: int) -> tuple[Scenario, ...]:
        names = MIX_CHOICES_SINGLE if num_quads == 1 else MIX_CHOICES
        return tuple(get_scenario(n) for n in names)

    def num_uniforms(self, num_quads: int) -> int:
        return 1 + max(c.num_uniforms(num_quads) for c in self.choices(num_quads))

    def init(self, cfg: Any, u: Any) -> ScenarioState:
        cands = self.choices(cfg.num_quads)
        kind = uniform_int(u[..., 0], len(cands))
        out = None
        for i, c in enumerate(cands):
            s = c.init(cfg, u[..., 1:1 + c.num_uniforms(cfg.num_quads)])
            out = s if out is None else select_state(kind == i, s, out)
        return out._replace(kind=kind)

    def step(self, cfg: Any, state: ScenarioState, t: Any, pos: Any, u: Any) -> ScenarioState:
        out = state
        for i, c in enumerate(self.choices(cfg.num_quads)):
            ui = u[..., 1:1 + c.num_uniforms(cfg.num_quads)]
            out = on_event(state.kind == i, lambda c=c, ui=ui: c.step(cfg, state, t, pos, ui), out)
        return out._replace(kind=state.kind)


MIX = register(Mix())
