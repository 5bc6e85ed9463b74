# ruff: noqa: I001  (import order = registration order = order of list_scenarios())
"""Scenarios (SPEC §10): small frozen objects with pure ``init``/``step``, found by name.

Importing this package registers all sixteen scenarios (eleven, plus the five ``o_*`` ones that need
obstacles); ``list_scenarios()`` shows their names.
"""

# Order of import = order of ``list_scenarios()``; each module registers its scenarios.
from quadswarm_mj.scenarios import static  # noqa: F401  (registers the scenarios)
from quadswarm_mj.scenarios import dynamic  # noqa: F401
from quadswarm_mj.scenarios import swap  # noqa: F401
from quadswarm_mj.scenarios import swarm_vs_swarm  # noqa: F401
from quadswarm_mj.scenarios import pursuit  # noqa: F401
from quadswarm_mj.scenarios import run_away  # noqa: F401
from quadswarm_mj.scenarios import obstacle_scenarios  # noqa: F401  (the o_* scenarios, SPEC_obstacles A.5)
from quadswarm_mj.scenarios import mix  # noqa: F401  (last: it looks up the others)
from quadswarm_mj.scenarios.base import Scenario, ScenarioState
from quadswarm_mj.scenarios.mix import MIX_CHOICES, MIX_CHOICES_SINGLE
from quadswarm_mj.scenarios.registry import get_scenario, list_scenarios, register

__all__ = ["MIX_CHOICES", "MIX_CHOICES_SINGLE", "Scenario", "ScenarioState", "get_scenario", "list_scenarios",
           "register"]
