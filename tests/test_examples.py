"""The examples of examples/ run end to end (``--smoke``: a few hundred steps on 0.5 s episodes, then the
held-out evaluation), each in a subprocess with this checkout's package, and print a finite held-out figure.
Each is skipped when its RL library is absent (the optional extra ``examples``: torch, stable-baselines3,
torchrl, skrl; the JAX example needs optax, in ``dev``)."""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = {  # script -> the modules it needs
    "sb3_ppo_single.py": ("torch", "stable_baselines3"),
    "sb3_ppo_swarm.py": ("torch", "stable_baselines3"),
    "skrl_ppo_pettingzoo.py": ("torch", "skrl"),
    "torchrl_ppo.py": ("torch", "torchrl", "tensordict"),
    "jax_ppo_cleanrl.py": ("optax",),
}


@pytest.mark.timeout(600)
@pytest.mark.parametrize("script", sorted(EXAMPLES))
def test_example_smoke(script):
    for mod in EXAMPLES[script]:
        pytest.importorskip(mod, reason=f"examples/{script} needs {mod} (pip install -e '.[examples]')")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, str(ROOT / "examples" / script), "--smoke", "--seed", "3"], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f"{script} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("held-out")]
    assert line, f"{script} printed no held-out line:\n{proc.stdout[-3000:]}"
    m = re.search(r"mean distance (\S+) m", line[-1])
    assert m and math.isfinite(float(m.group(1))) and float(m.group(1)) >= 0, line[-1]


def test_examples_are_short_and_documented():
    for script in EXAMPLES:
        text = (ROOT / "examples" / script).read_text()
        assert len(text.splitlines()) <= 200, f"examples/{script} is over 200 lines"
        assert "--smoke" in text and "--total-steps" in text and "--seed" in text
        assert f"examples/{script}" in (ROOT / "docs" / "examples.md").read_text(), f"{script} not in docs/examples.md"
