"""Env rows: the single env and the vector env on both engines, the JAX engine's jitted rollout, and the
step-time cost of obstacles."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from quadswarm_mj import EnvConfig, QuadSwarmEnv, QuadSwarmVectorEnv
from quadswarm_mj.bench.common import hover_like, timed
from quadswarm_mj.controllers import PositionController


def _workload_rate(env: Any, cfg: EnvConfig, workload: str, seconds: float, repeat: int, pool_size: int,
                   reset_on_truncation: bool) -> float:
    """Best ``step`` calls/s of ``env`` under ``workload`` (only ``step``, and the resets it needs, timed)."""
    _, info = env.reset(seed=0)
    rng = np.random.default_rng(0)
    shape = env.action_space.shape
    pool = [rng.uniform(-1, 1, shape).astype(np.float32) for _ in range(pool_size)]
    hover = hover_like(shape)
    ctrl = PositionController(cfg) if workload == "controller" else None
    state = {"info": info}

    def run(steps: int) -> float:
        total = 0.0
        for i in range(steps):
            if workload == "hover":
                a = hover
            elif workload == "random":
                a = pool[i % pool_size]
            else:
                inf = state["info"]
                a = np.asarray(ctrl(inf["state"], inf["goals"], inf["goal_vel"], inf["params"]),
                               np.float32).reshape(shape)
            t = time.perf_counter()
            _, _, _, trunc, inf = env.step(a)
            if reset_on_truncation and trunc:
                _, inf = env.reset()
            total += time.perf_counter() - t
            state["info"] = inf
        return total

    return timed(run, seconds, repeat)


def bench_single(n: int, workload: str, seconds: float, repeat: int) -> float:
    cfg = EnvConfig(num_quads=n)
    env = QuadSwarmEnv(cfg)
    try:
        return n * _workload_rate(env, cfg, workload, seconds, repeat, 64, True)
    finally:
        env.close()


def bench_vector(B: int, n: int, workload: str, seconds: float, repeat: int, **kw: Any) -> float:
    cfg = EnvConfig(num_quads=n)
    env = QuadSwarmVectorEnv(cfg, num_envs=B, **kw)
    try:
        return B * n * _workload_rate(env, cfg, workload, seconds, repeat, 8, False)
    finally:
        env.close()


def bench_jax_batch(cfg: EnvConfig, worlds: int, steps: int, **kw: Any) -> dict[str, float] | None:
    """The JAX engine as a jitted rollout (``benchmark_mjx``: auto-reset, hover actions, lax.scan)."""
    try:
        from quadswarm_mj.envs.mjx_env import benchmark_mjx
    except Exception as e:  # noqa: BLE001
        print(f"  JAX engine not available ({e!r}); skipped", flush=True)
        return None
    return benchmark_mjx(cfg, worlds, steps, **kw)


def bench_single_jax(n: int, seconds: float, repeat: int, cfg: EnvConfig | None = None) -> float:
    """``QuadSwarmEnv(engine="jax")``: one world, one Python ``step`` per control step, hover actions."""
    return _bench_single_cfg(cfg or EnvConfig(num_quads=n), seconds, repeat, "jax")

def _bench_single_cfg(cfg: EnvConfig, seconds: float, repeat: int, engine: str = "mujoco") -> float:
    env = QuadSwarmEnv(cfg, engine=engine) if engine != "mujoco" else QuadSwarmEnv(cfg)
    env.reset(seed=0)
    a = hover_like(env.action_space.shape)
    for _ in range(3):  # compile (JAX engine) and warm up
        env.step(a)

    def run(steps: int) -> float:
        t = time.perf_counter()
        for _ in range(steps):
            _, _, _, trunc, _ = env.step(a)
            if trunc:
                env.reset()
        return time.perf_counter() - t

    try:
        return cfg.num_quads * timed(run, seconds, repeat)
    finally:
        env.close()


def obstacle_cost(plain: EnvConfig, obst: EnvConfig, engine: str, worlds: int, steps: int, seconds: float,
                  rounds: int) -> dict[str, float] | None:
    """Step-time cost of obstacles, measured robustly on a shared machine: both envs are built (and
    compiled) first, then timed in alternation (plain, obstacles, plain, ...) for ``rounds`` rounds;
    ``cost`` is the median over rounds of t_obst / t_plain - 1 (``cost_min``/``cost_max`` the range),
    ``with``/``without`` the median samples/s. ``engine``: "jax" (jitted rollout of ``worlds``
    worlds, ``steps`` control steps per timing; wall time) or "mujoco" (QuadSwarmEnv, 1 world,
    ~``seconds`` s per timing; the process's CPU time, which other jobs on a shared machine do not
    inflate, as they inflate a ~100 us Python step's wall time)."""
    if engine == "jax":
        try:
            import jax
            import jax.numpy as jnp

            from quadswarm_mj.envs.mjx_env import AutoResetWrapper, MjxQuadSwarmEnv
        except Exception as e:  # noqa: BLE001
            print(f"  JAX engine not available ({e!r}); skipped", flush=True)
            return None

        def runner(cfg: EnvConfig) -> Callable[[], float]:
            env = AutoResetWrapper(MjxQuadSwarmEnv(cfg))
            hover = jnp.full((worlds, cfg.num_quads, 4), cfg.quad.hover_action, jnp.float32)

            def rollout(st: Any) -> Any:
                return jax.lax.scan(lambda x, _: (env.vstep(x, hover), None), st, None, length=steps)[0]

            box = [jax.block_until_ready(jax.jit(jax.vmap(env.reset))(
                jax.random.split(jax.random.key(0), worlds)))]
            run = jax.jit(rollout).lower(box[0]).compile()
            box[0] = jax.block_until_ready(run(box[0]))  # warm up

            def timed_run() -> float:
                t = time.perf_counter()
                box[0] = jax.block_until_ready(run(box[0]))
                return time.perf_counter() - t

            return timed_run

        samples = worlds * plain.num_quads * steps
    else:
        n_steps = max(50, int(seconds * 800))  # about `seconds` s at ~800 control steps/s (1 x 8)

        def runner(cfg: EnvConfig) -> Callable[[], float]:
            env = QuadSwarmEnv(cfg)
            env.reset(seed=0)
            a = hover_like(env.action_space.shape)
            for _ in range(3):
                env.step(a)

            def timed_run() -> float:  # CPU time of this (single-threaded) process: blind to other load
                t = time.process_time()
                for _ in range(n_steps):
                    if env.step(a)[3]:
                        env.reset()
                return time.process_time() - t

            return timed_run

        samples = plain.num_quads * n_steps
    run_a, run_b = runner(plain), runner(obst)
    ta, tb = [], []
    for _ in range(rounds):
        ta.append(run_a())
        tb.append(run_b())
    ratio = np.asarray(tb) / np.asarray(ta)
    return {"cost": float(np.median(ratio) - 1), "cost_min": float(ratio.min() - 1),
            "cost_max": float(ratio.max() - 1), "without": samples / float(np.median(ta)),
            "with": samples / float(np.median(tb))}
