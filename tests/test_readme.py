"""The README stays true: its Quick start has exactly two commands and its Python examples run."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

README = (Path(__file__).parent.parent / "README.md").read_text()


def python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README, flags=re.S)


def test_quick_start_has_two_commands_and_ci_runs_the_second():
    section = README.split("## Quick start", 1)[1]
    block = re.search(r"```bash\n(.*?)```", section, flags=re.S).group(1)
    commands = [line for line in block.splitlines() if line.strip()]
    assert len(commands) == 2
    assert "render_rollout.py" in commands[0] and "pytest" in commands[1]
    ci = (Path(__file__).parent.parent / ".ci" / "run").read_text()
    assert commands[1].strip() in ci


def test_api_tour_runs():
    code = next(b for b in python_blocks() if "QuadSwarmEnv(cfg)" in b)
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300, capture_output=True)


@pytest.mark.slow
def test_mjx_example_runs():
    code = next(b for b in python_blocks() if "MjxQuadSwarmEnv" in b)
    code = code.replace("64", "4").replace("range(100)", "range(5)")  # same code path, smaller
    out = subprocess.run([sys.executable, "-c", code], check=True, timeout=600, capture_output=True, text=True)
    assert "(4, 8, 54) (4, 8)" in out.stdout
