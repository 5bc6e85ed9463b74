"""A seeded random-action run of a Gymnasium env recorded as a flat list of arrays, for bitwise
comparisons of two code paths (the perf forms against the plain ones)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np


def record_random_run(env: Any, seed: int, steps: int, outputs: Callable[[Any, float, dict], list]) -> list:
    """``steps`` steps of random actions (full thrust for 30 of every 100: falls, floor hits, lift-offs),
    resetting at episode ends; ``outputs(obs, reward, info)`` lists what each step records."""
    env.action_space.seed(seed)
    obs, info = env.reset(seed=seed)
    out = [obs]
    for t in range(steps):
        a = env.action_space.sample() if t % 100 < 70 else np.ones(env.action_space.shape, np.float32)
        obs, r, term, trunc, info = env.step(a)
        out += outputs(obs, np.float64(r), info)
        if trunc:
            out += list(info["episode_metrics"].values())
            obs, info = env.reset()
            out.append(obs)
    return out


def record_three_world_run(core: Any, outputs: Callable[[Any, dict], list], steps: int = 300) -> list:
    """A seeded run of a 3-world, 4-quad ``CpuSwarm`` (Gaussian actions around hover, world 1 reset alone
    halfway); ``outputs(core, step_output)`` lists what each step records."""
    core.seed(5)
    core.reset()
    rng = np.random.default_rng(6)
    run = []
    for t in range(steps):
        o = core.step(np.clip(-0.2 + 0.8 * rng.standard_normal((3, 4, 4)), -1, 1))
        run += outputs(core, o)
        if t == steps // 2:
            core.reset(mask=np.array([False, True, False]))
    return run
