"""Name -> scenario registry. ``list_scenarios()`` shows the names."""

from __future__ import annotations

from quadswarm_mj.scenarios.base import Scenario

_REGISTRY: dict[str, Scenario] = {}


def register(scenario: Scenario) -> Scenario:
    """Add a scenario instance under its ``name``."""
    _REGISTRY[scenario.name] = scenario
    return scenario


def list_scenarios() -> list[str]:
    """Names of all registered scenarios, in registration order."""
    return list(_REGISTRY)


def get_scenario(name: str) -> Scenario:
    """Look a scenario up by name; unknown names raise a ValueError listing the known ones."""
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown scenario {name!r}; known scenarios: {', '.join(_REGISTRY)}") from None
