"""Shared helpers of the benchmark: the machine line, load, best-of timing, hover actions, number format."""

from __future__ import annotations

import os
import platform
from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np

from quadswarm_mj import EnvConfig

WORKLOADS = ("hover", "random", "controller")


def machine() -> str:
    cpu = platform.processor() or "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} logical cores, {platform.system()} {platform.release()}, " \
           f"Python {platform.python_version()}, numpy {np.__version__}, mujoco {mujoco.__version__}"


def load() -> str:
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def timed(run: Callable[[int], float], seconds: float, repeat: int, min_steps: int = 3) -> float:
    """Best rate (units/s) over ``repeat`` runs; ``run(n)`` does n steps and returns their time."""
    n = min_steps
    while True:  # calibrate n to about `seconds`
        dt = run(n)
        if dt >= 0.2 * seconds or n >= 1_000_000:
            break
        n *= 4
    n = max(min_steps, int(n * seconds / max(dt, 1e-9)))
    best = 0.0
    for _ in range(repeat):
        best = max(best, n / run(n))
    return best


def hover_like(shape: tuple[int, ...]) -> np.ndarray:
    return np.full(shape, EnvConfig().quad.hover_action, dtype=np.float32)


def fmt(x: float | None) -> str:
    if x is None:
        return "-"
    if x >= 1e6:
        return f"{x / 1e6:.2f} M"
    if x >= 1e3:
        return f"{x / 1e3:.1f} k"
    return f"{x:.0f}"


def num_devices() -> int:
    """JAX's devices in this process (1 if JAX is missing)."""
    try:
        import jax

        return len(jax.devices())
    except Exception:  # noqa: BLE001
        return 1
