"""Where the time goes (cProfile groups of the single and vector env) and the design measurements behind
the vector env (physics back ends, threads vs processes)."""

from __future__ import annotations

import cProfile
import pstats
import time
from collections.abc import Callable

import numpy as np

from quadswarm_mj import EnvConfig, QuadSwarmEnv, QuadSwarmVectorEnv
from quadswarm_mj.bench.ceiling import ceiling_one_core
from quadswarm_mj.bench.common import fmt, hover_like, timed
from quadswarm_mj.bench.envs import bench_vector

PROFILE_GROUPS = [  # (label, [(file suffix, function name)]); builtins have file "~" and match by substring
    ("MuJoCo physics step (C)", [("~", "mj_step"), ("~", "_batch.step")]),
    # the CPU engine calls the model through its ops (core/ops.py's NumpyOps: the model's functions, the
    # fewest-NumPy-calls forms of perf/numpy_small.py, the sub-step loop of perf/numpy_loop.py, or for one quad
    # perf/one_quad_step.py's float forms on perf/one_quad.py's bodies; several quads in one world: the loop and
    # stages of perf/numpy_swarm.py and the task half of perf/numpy_swarm_task.py)
    ("actuation: command, motor noise, lag, thrusts, wrench", [("numpy_small.py", "substep_wrench"),
                                                               ("numpy_loop.py", "substep_wrench"),
                                                               ("one_quad.py", "wrench_floats"),
                                                               ("numpy_swarm.py", "_wrench"),
                                                               ("ops.py", "motor_noise"), ("ops.py", "command")]),
    ("rotation matrices from quaternions", [("numpy_small.py", "quat_to_rotmat"),
                                            ("numpy_small.py", "quat_to_rotmat_qpos"),
                                            ("one_quad.py", "quat_to_rotmat"), ("one_quad.py", "rotmat_floats"),
                                            ("numpy_swarm.py", "rotmat")]),
    ("floor model (friction wrench + impact)", [("ops.py", "floor_wrench"), ("ops.py", "floor_impact"),
                                                ("numpy_loop.py", "floor_wrench"),
                                                ("one_quad.py", "floor_wrench_floats"),
                                                ("one_quad.py", "floor_impact_qv"),
                                                ("numpy_swarm.py", "_floor_wrench"), ("numpy_swarm.py", "_landing")]),
    ("walls, ceiling, quad-quad response", [("collisions.py", "wall_collisions"),
                                            ("collisions.py", "quad_collisions")]),
    ("pairwise distances and contacts", [("ops.py", "pairwise_contacts"),
                                         ("numpy_swarm.py", "stages")]),  # (with the event-free wall test)
    ("reward terms and total", [("ops.py", "reward_terms"), ("ops.py", "total_reward"),
                                ("one_quad.py", "reward_values"), ("numpy_swarm_task.py", "_rewards")]),
    ("episode metrics", [("ops.py", "metrics_update"), ("metrics.py", "goal_jump"), ("one_quad.py", "metrics_floats"),
                         ("numpy_swarm_task.py", "_metrics")]),
    ("observations (own state, K nearest)", [("ops.py", "obs"), ("one_quad.py", "obs_values"),
                                             ("numpy_swarm_task.py", "_obs")]),
    ("scenario goals", [("scenarios/static.py", "step"), ("scenarios/base.py", "step")]),
    ("env wrapper: action check, info / output arrays", [("validation.py", "check_action"), ("gym_env.py", "_info"),
                                                         ("vector_env.py", "_info"),
                                                         ("vector_env.py", "_write_info")]),
]


def profile_breakdown(fn: Callable[[], None]) -> tuple[float, list[tuple[str, float]]]:
    """Run ``fn`` under cProfile; return its total time and the cumulative time of each group (the
    groups are disjoint calls, except that the floor model computes rotations too; a group's function
    called by another of the same group is counted once)."""
    pr = cProfile.Profile()
    pr.enable()
    fn()
    pr.disable()
    st = pstats.Stats(pr)
    total = max(v[3] for v in st.stats.values())
    out = []
    for label, keys in PROFILE_GROUPS:
        def match(func: tuple, keys: list = keys) -> bool:
            file, _line, name = func
            return any((suffix == "~" and file == "~" and fname in name) or (
                suffix != "~" and file.endswith(suffix) and name == fname) for suffix, fname in keys)

        t = 0.0
        for func, (_cc, _nc, _tt, ct, callers) in st.stats.items():
            if match(func):  # its time, less what a matched caller of the same group already counts
                t += ct - sum(edge[3] for caller, edge in callers.items() if match(caller))
        out.append((label, t))
    return total, out


def _profile_table(total: float, groups: list[tuple[str, float]]) -> list[str]:
    lines = ["| stage | share of step time |", "|---|---:|"]
    for label, t in groups:
        if t > 0:
            lines.append(f"| {label} | {100 * t / total:.1f} % |")
    rest = total - sum(t for label, t in groups if "rotation" not in label)
    lines.append(f"| everything else (engine glue, Python overhead) | {100 * max(rest, 0.0) / total:.1f} % |")
    return lines


def gym_profile(steps: int = 3000) -> list[str]:
    """The default Gymnasium env with one quad as the gym rows run it (``gym.make``, random actions from a
    pool, resets included), ``steps`` steps under cProfile: a table of stage shares."""
    import gymnasium as gym

    import quadswarm_mj  # noqa: F401  (registers QuadSwarm-v0)

    env = gym.make("QuadSwarm-v0", num_quads=1)
    env.reset(seed=0)
    env.action_space.seed(0)
    pool = [np.asarray(env.action_space.sample()) for _ in range(64)]

    def run() -> None:
        for i in range(steps):
            _, _, term, trunc, _ = env.step(pool[i % 64])
            if term or trunc:
                env.reset()

    run()  # warm up
    total, groups = profile_breakdown(run)
    env.close()
    lines = ["gym.make('QuadSwarm-v0', num_quads=1), random actions (the quad lies on the floor most of the time; "
             f"perf/one_quad_step.py's float forms run), {steps} steps under cProfile: "
             f"{total / steps * 1e6:.0f} us/step profiled:", ""]
    return lines + _profile_table(total, groups)


def run_profile() -> str:
    cfg = EnvConfig(num_quads=8)
    env = QuadSwarmEnv(cfg)
    env.reset(seed=0)
    a = hover_like(env.action_space.shape)

    def single() -> None:
        for _ in range(1500):
            _, _, _, tr, _ = env.step(a)
            if tr:
                env.reset()

    total, groups = profile_breakdown(single)
    env.close()
    lines = gym_profile() + [""]
    lines += ["QuadSwarmEnv, 8 quads, hover workload (quads crash after ~1 s, so the floor model runs), one "
             f"1500-step episode under cProfile: {total / 1500 * 1e6:.0f} us/step profiled (cProfile adds"
             " overhead per Python call, so Python-heavy stages look larger than they are):", ""]
    lines += _profile_table(total, groups)
    venv = QuadSwarmVectorEnv(cfg, num_envs=512, num_shards=1)
    venv.reset(seed=0)
    act = hover_like(venv.action_space.shape)

    def vector() -> None:
        for _ in range(100):
            venv.step(act)

    total, groups = profile_breakdown(vector)
    venv.close()
    lines += ["", "QuadSwarmVectorEnv with one shard of 512 worlds x 8 quads (what each of the two processes runs "
              f"at B = 1024), hover workload, 100 steps under cProfile: {total / 100 * 1e3:.2f} ms/step profiled:", ""]
    lines += _profile_table(total, groups)
    return "\n".join(lines)


# ------------------------------------------------------------------------------- design choices
def compare_engines(B: int, seconds: float, repeat: int) -> str:
    """The measurements behind the vector env's design: physics back ends, threads vs processes."""
    import threading

    from quadswarm_mj.envs.cpu_core import CpuSwarm

    cfg = EnvConfig(num_quads=8)
    act = np.full((B, 8, 4), cfg.quad.hover_action)
    rows = []

    def physics_rate(core: CpuSwarm) -> float:
        core.seed(0)
        core.reset()

        def run(steps: int) -> float:
            t = time.perf_counter()
            for _ in range(steps):
                core.phys.step(cfg.quad.max_omega)
            return time.perf_counter() - t

        return B * 8 * timed(run, seconds, repeat) / 2.0

    for label, kw in [(f"one MjData, {B} worlds, visual geoms", {"backend": "mjdata", "visual": True}),
                      (f"one MjData, {B} worlds, no visual geoms", {"backend": "mjdata", "visual": False}),
                      (f"mujoco.batch, {B} one-world simulations", {"backend": "batch", "chunk_worlds": 1}),
                      (f"mujoco.batch, {B // 64} simulations of 64 worlds (+ copies)",
                       {"backend": "batch", "chunk_worlds": 64})]:
        t0 = time.perf_counter()
        core = CpuSwarm(cfg, B, **kw)
        build = time.perf_counter() - t0
        rows.append((f"physics only: {label}", physics_rate(core), f"model built in {build:.1f} s"))
    rows.append((f"bare-MuJoCo ceiling, {8 * B} free bodies, 1 core", ceiling_one_core(8 * B, seconds, repeat), ""))

    def step_rate(cores: list[CpuSwarm], threads: bool) -> float:
        for k, c in enumerate(cores):
            c.seed(k)
            c.reset()
        a = act[: cores[0].B]

        def one(c: CpuSwarm, steps: int) -> None:
            for _ in range(steps):
                c.step(a)

        def run(steps: int) -> float:
            t = time.perf_counter()
            if threads:
                th = [threading.Thread(target=one, args=(c, steps)) for c in cores]
                for x in th:
                    x.start()
                for x in th:
                    x.join()
            else:
                for c in cores:
                    one(c, steps)
            return time.perf_counter() - t

        return B * 8 * timed(run, seconds, repeat)

    half = [CpuSwarm(cfg, B // 2, backend="batch") for _ in range(2)]
    rows.append((f"engine step, {B} worlds in 1 process (2 shards one after the other)", step_rate(half, False), ""))
    rows.append((f"engine step, {B} worlds, 2 shards in 2 threads", step_rate(half, True), ""))
    rows.append((f"QuadSwarmVectorEnv, {B} worlds, 2 shards in 2 processes",
                 bench_vector(B, 8, "hover", seconds, repeat, num_shards=2), "whole env step, info included"))
    rows.append((f"QuadSwarmVectorEnv, {B} worlds, 1 process",
                 bench_vector(B, 8, "hover", seconds, repeat, num_shards=1), "whole env step, info included"))
    out = ["| measurement (hover workload) | samples/s | note |", "|---|---:|---|"]
    out += [f"| {a} | {fmt(b)} | {c} |" for a, b, c in rows]
    return "\n".join(out)

