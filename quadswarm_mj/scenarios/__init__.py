"""Scenarios (SPEC §10): small frozen objects with pure ``init``/``step``, found by name."""

from quadswarm_mj.scenarios import static  # noqa: F401  (registers the scenarios)
from quadswarm_mj.scenarios.base import Scenario, ScenarioState
from quadswarm_mj.scenarios.registry import get_scenario, list_scenarios, register

__all__ = ["Scenario", "ScenarioState", "get_scenario", "list_scenarios", "register"]
