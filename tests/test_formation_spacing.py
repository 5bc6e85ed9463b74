"""scripts/formation_spacing.py: the closest pair of each world (the figure TRAINING.md quotes)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "formation_spacing.py"


def test_closest_pair_per_world():
    spec = importlib.util.spec_from_file_location("formation_spacing", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    worlds = np.array([[[0, 0, 0], [3, 0, 0], [0, 0.5, 0]], [[1, 1, 1], [1, 1, 3], [1, 4, 1]]], float)
    np.testing.assert_allclose(mod.closest_pair(worlds), [0.5, 2.0])
