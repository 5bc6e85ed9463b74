"""The default Gymnasium env against gymnasium's own ``Hopper-v5``, and the time to the first step.

``gym_rates`` measures env steps/s (one ``step`` call = one env step, whatever the number of quads) of
``Hopper-v5`` and of ``gym.make("QuadSwarm-v0", ...)`` variants in one process, with random actions
(pre-drawn uniform in the action space, so drawing them is not timed) and the resets included in the
timed loop. The rows are measured in ``rounds`` alternating rounds (Hopper first in every round) and each
figure is the best of its rounds, so every ratio is of figures of the same run; ``cpu_ratio`` is the ratio of
steps per second of process CPU time (all threads; steadier than wall time when other jobs share the cores,
and for the single-threaded MuJoCo engine and Hopper-v5 the same ratio on a quiet machine). The benchmark runs it in a
fresh process with JAX's defaults (no ``tune_jax_cpu``): what a user who just calls ``gym.make`` gets.
``first_step_seconds`` is the time from ``gym.make`` to the first ``step``'s return in a fresh process
(``import`` timed separately). ``Hopper-v5`` needs gymnasium's MuJoCo extra (``imageio``).
"""

from __future__ import annotations

import json
import time
from typing import Any

import numpy as np

# (label, gym.make keyword arguments); the first is the reference every ratio is of
GYM_ROWS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("Hopper-v5 (gymnasium)", {}),
    ("QuadSwarm-v0, num_quads=1, defaults", {"num_quads": 1}),
    ("QuadSwarm-v0, num_quads=8, defaults", {"num_quads": 8}),
    ("QuadSwarm-v0, num_quads=1, engine='mujoco'", {"num_quads": 1, "engine": "mujoco"}),
    ("QuadSwarm-v0, num_quads=8, engine='mujoco'", {"num_quads": 8, "engine": "mujoco"}),
    ("QuadSwarm-v0, num_quads=1, engine='jax'", {"num_quads": 1, "engine": "jax"}),
    ("QuadSwarm-v0, num_quads=8, engine='jax'", {"num_quads": 8, "engine": "jax"}),
)


def _make(kwargs: dict[str, Any]) -> Any:
    import gymnasium as gym

    import quadswarm_mj  # noqa: F401  (registers QuadSwarm-v0)

    return gym.make("Hopper-v5") if not kwargs else gym.make("QuadSwarm-v0", **kwargs)


def _runner(env: Any, seed: int = 0) -> Any:
    """``run(k)``: k timed random-action steps, resets included; returns their wall time and the process's
    CPU time (all its threads)."""
    env.reset(seed=seed)
    env.action_space.seed(seed)
    pool = [np.asarray(env.action_space.sample()) for _ in range(64)]
    box = {"i": 0}

    def run(k: int) -> tuple[float, float]:
        t, c = time.perf_counter(), time.process_time()
        i = box["i"]
        for _ in range(k):
            _, _, term, trunc, _ = env.step(pool[i % 64])
            i += 1
            if term or trunc:
                env.reset()
        box["i"] = i
        return time.perf_counter() - t, time.process_time() - c

    run(20)  # warm up (the JAX engine compiles on its first step)
    return run


def gym_rates(seconds: float = 2.0, rounds: int = 3, rows: tuple[tuple[str, dict[str, Any]], ...] = GYM_ROWS
              ) -> list[dict[str, Any]]:
    """Env steps/s of each row (best of ``rounds`` alternating windows of ``seconds``) and its ratio to the
    first row; a row that cannot be made (e.g. Hopper without ``imageio``) has ``rate`` None and ``error``."""
    envs, out = [], []
    for label, kw in rows:
        try:
            env = _make(kw)
            envs.append((env, _runner(env)))
            out.append({"label": label, "kwargs": kw, "rate": 0.0, "cpu_rate": 0.0})
        except Exception as e:  # noqa: BLE001
            envs.append((None, None))
            out.append({"label": label, "kwargs": kw, "rate": None, "error": repr(e)[:200]})
    try:
        for _ in range(max(rounds, 1)):
            for (_env, run), r in zip(envs, out):
                if run is None:
                    continue
                k, t, c = 0, 0.0, 0.0
                while t < seconds:
                    n = max(10, k // 4 or 10)
                    dt, dc = run(n)
                    t, c, k = t + dt, c + dc, k + n
                r["rate"] = max(r["rate"], k / t)
                r["cpu_rate"] = max(r["cpu_rate"], k / max(c, 1e-9))
    finally:
        for env, _ in envs:
            if env is not None:
                env.close()
    ref, cpu_ref = out[0]["rate"], out[0].get("cpu_rate")
    for r in out:
        r["ratio"] = r["rate"] / ref if ref and r["rate"] else None
        r["cpu_ratio"] = r["cpu_rate"] / cpu_ref if cpu_ref and r.get("cpu_rate") else None
    return out


FIRST_STEP_CODE = """
import json, time
t0 = time.perf_counter()
import gymnasium as gym
import quadswarm_mj
t1 = time.perf_counter()
env = gym.make("QuadSwarm-v0", **{kwargs})
env.reset(seed=0)
env.step(env.action_space.sample())
t2 = time.perf_counter()
print("RESULT", json.dumps({{"import_s": t1 - t0, "first_step_s": t2 - t1}}))
"""


def first_step_code(kwargs: dict[str, Any]) -> str:
    """Python code that prints ``RESULT {"import_s": ..., "first_step_s": ...}`` (``gym.make`` to the first
    ``step``'s return, reset included) for ``gym.make("QuadSwarm-v0", **kwargs)``."""
    return FIRST_STEP_CODE.format(kwargs=json.dumps(kwargs))
