"""Throughput of quadswarm_mj on this machine, with the bare-MuJoCo ceiling measured in the same run.

samples/s = quad-steps per second (one quad advanced one 100 Hz control step = 2 physics sub-steps
of 200 Hz), paper defaults (collisions, noise, K = 6 neighbours, static_same_goal). Rows:

* ``QuadSwarmEnv`` (one world) at N = 1, 8, 32, 128 quads;
* ``QuadSwarmVectorEnv`` at B = 64, 256, 1024 worlds x 8 quads (auto-reset);
* the JAX engine (``quadswarm_mj.envs.mjx_env.benchmark_mjx``: a jitted ``lax.scan`` rollout with
  auto-reset) at 1, 64, 512, 2048 worlds x 8 quads, paper defaults and ``without_noise()``; the
  single env and the vector env on the JAX engine (``engine="jax"``) beside the MuJoCo engine; with
  ``--ablations`` the JAX engine at 512 x 8 with stages switched on or off (where the time goes);
  ``obstacles`` rows: the cost of 12 columns on each engine (``--skip-mjx`` leaves the JAX rows out);
* the peer, crazyflow's ``Sim`` (first-principles dynamics, per-rotor control, 200 Hz physics, 2
  physics steps per 100 Hz sample) when ``crazyflow`` is installed (``pip install crazyflow``; the
  rows are skipped with a note otherwise): jitted scan (as ``benchmark_mjx``) and Python loop (as a
  Gymnasium env), so every ratio to it is of figures of the same run; with ``--alternate R`` also the
  JAX engine against crazyflow's scan in R alternating rounds of fresh processes, and the JAX-engine
  vector env against the bare-MuJoCo floor in R alternating windows (the medians of the per-round
  ratios: robust on a machine whose speed drifts within a run);
* for every row, the bare-MuJoCo ceiling for the same number of bodies: free bodies with the
  Crazyflie's inertia, contacts off, Euler, 2 sub-steps per control step; ``1 core`` steps one model
  holding all bodies with ``mj_step``, ``rollout`` steps them split in equal models on both cores
  with ``mujoco.rollout`` (long rollouts, no Python in the loop). The ceiling is the faster of the two.

Workloads (actions): ``hover`` = the hover command on every rotor (the quads drift and many crash
after ~1 s: the floor model then runs every sub-step, as in early RL training); ``random`` =
uniform in [-1, 1]; ``controller`` = the baseline position controller flying to the goals (only
the env's ``step`` is timed, not the controller). Each figure is the best of ``--repeat`` runs of
``--seconds`` each (the machine is shared: best-of is the least noisy estimate), and every ratio is
of figures measured in the same run.

Also installed as the console command ``quadswarm-benchmark`` (same options)::

    /work/venv/bin/python scripts/benchmark.py                 # full table -> BENCHMARKS.md
    /work/venv/bin/python scripts/benchmark.py --quick --skip-mjx --no-write
    /work/venv/bin/python scripts/benchmark.py --rows single,ceiling --single-n 8 --profile
"""

from __future__ import annotations

import argparse
import cProfile
import datetime
import functools
import json
import os
import platform
import pstats
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import mujoco
import mujoco.rollout
import numpy as np

from quadswarm_mj import EnvConfig, QuadSwarmEnv, QuadSwarmVectorEnv
from quadswarm_mj.controllers import PositionController
from quadswarm_mj.devices import LOOP_KERNEL_FLAG
from quadswarm_mj.outfiles import atomic_write_text, check_writable

WORKLOADS = ("hover", "random", "controller")
NOTES_MARKER = "<!-- notes: kept by scripts/benchmark.py -->"


# ---------------------------------------------------------------------------------------- helpers
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


# ------------------------------------------------------------------------------------ env rows
def bench_single(n: int, workload: str, seconds: float, repeat: int) -> float:
    cfg = EnvConfig(num_quads=n)
    env = QuadSwarmEnv(cfg)
    _, info = env.reset(seed=0)
    rng = np.random.default_rng(0)
    shape = env.action_space.shape
    pool = [rng.uniform(-1, 1, shape).astype(np.float32) for _ in range(64)]
    hover = hover_like(shape)
    ctrl = PositionController(cfg) if workload == "controller" else None
    state = {"info": info}

    def run(steps: int) -> float:
        total = 0.0
        for i in range(steps):
            if workload == "hover":
                a = hover
            elif workload == "random":
                a = pool[i % 64]
            else:
                inf = state["info"]
                a = np.asarray(ctrl(inf["state"], inf["goals"], inf["goal_vel"], inf["params"]),
                               np.float32).reshape(shape)
            t = time.perf_counter()
            _, _, _, trunc, inf = env.step(a)
            if trunc:
                _, inf = env.reset()
            total += time.perf_counter() - t
            state["info"] = inf
        return total

    try:
        return n * timed(run, seconds, repeat)
    finally:
        env.close()


def bench_vector(B: int, n: int, workload: str, seconds: float, repeat: int, **kw: Any) -> float:
    cfg = EnvConfig(num_quads=n)
    env = QuadSwarmVectorEnv(cfg, num_envs=B, **kw)
    try:
        _, info = env.reset(seed=0)
        rng = np.random.default_rng(0)
        shape = env.action_space.shape
        pool = [rng.uniform(-1, 1, shape).astype(np.float32) for _ in range(8)]
        hover = hover_like(shape)
        ctrl = PositionController(cfg) if workload == "controller" else None
        state = {"info": info}

        def run(steps: int) -> float:
            total = 0.0
            for i in range(steps):
                if workload == "hover":
                    a = hover
                elif workload == "random":
                    a = pool[i % 8]
                else:
                    inf = state["info"]
                    a = np.asarray(ctrl(inf["state"], inf["goals"], inf["goal_vel"], inf["params"]), np.float32)
                t = time.perf_counter()
                _, _, _, _, inf = env.step(a)
                total += time.perf_counter() - t
                state["info"] = inf
            return total

        return B * n * timed(run, seconds, repeat)
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


def crazyflow_rates(worlds: int, n: int, steps: int, seconds: float, repeat: int,
                    devices: int = 1, scan_only: bool = False) -> dict[str, float] | None:
    """crazyflow's ``Sim`` (first-principles dynamics, per-rotor ``rotor_vel`` control) at the same
    protocol: 200 Hz physics, one control step = 2 physics steps, samples = drone-steps at 100 Hz.
    ``scan``: a jitted ``lax.scan`` of (control, 2 physics steps), as ``benchmark_mjx``; ``loop``: one
    Python call pair (``rotor_vel_control``, ``step(2)``) per control step, never waiting for the
    results (JAX's async dispatch pipelines the calls); ``loop_read``: the same loop reading the drones'
    state (pos, vel, quat, ang_vel) to NumPy after every step, as a Gymnasium env must return its
    observation. With ``devices`` > 1 (and dividing ``worlds``) also ``scan_sharded``: the same scan
    with the worlds sharded over that many JAX devices (crazyflow's arrays have the worlds axis first;
    jit partitions its step along it), the peer of the JAX engine's sharded rows. ``scan_only``: the scans
    only (no Python loops)."""
    try:
        import contextlib
        import io

        import jax
        import jax.numpy as jnp
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            import crazyflow.sim.functional as cf_functional
            from crazyflow.sim import Sim
    except Exception as e:  # noqa: BLE001
        print(f"  crazyflow not installed ({e!r}); peer rows skipped (pip install crazyflow)", flush=True)
        return None
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sim = Sim(n_worlds=worlds, n_drones=n, control="rotor_vel", freq=200)
    sim.reset()
    rpm = jnp.full((worlds, n, 4), 15000.0)  # a constant per-rotor command
    step_fn = sim._step

    def rollout(data: Any) -> Any:
        def body(d: Any, _: Any) -> tuple[Any, None]:
            return step_fn(cf_functional.rotor_vel_control(d, rpm), n_steps=2), None

        return jax.lax.scan(body, data, None, length=steps)[0]

    t0 = time.perf_counter()
    run_c = jax.jit(rollout).lower(sim.data).compile()
    compile_s = time.perf_counter() - t0
    data = jax.block_until_ready(run_c(sim.data))
    times = []
    for _ in range(max(repeat, 3)):
        t = time.perf_counter()
        data = jax.block_until_ready(run_c(data))
        times.append(time.perf_counter() - t)
    scan = worlds * n * steps / float(np.min(times))
    sharded = None
    if devices > 1 and worlds % devices == 0:
        from jax.sharding import Mesh, NamedSharding, PartitionSpec

        mesh = Mesh(np.asarray(jax.devices()[:devices]), ("worlds",))

        def put(x: Any) -> Any:
            if not hasattr(x, "shape"):
                return x
            spec = PartitionSpec("worlds") if x.ndim >= 1 and x.shape[0] == worlds else PartitionSpec()
            return jax.device_put(x, NamedSharding(mesh, spec))

        d_sh, rpm_sh = jax.tree.map(put, data), put(rpm)
        run_sh = jax.jit(lambda d, r: jax.lax.scan(
            lambda c, _: (step_fn(cf_functional.rotor_vel_control(c, r), n_steps=2), None), d, None,
            length=steps)[0]).lower(d_sh, rpm_sh).compile()
        d_sh = jax.block_until_ready(run_sh(d_sh, rpm_sh))
        times = []
        for _ in range(max(repeat, 3)):
            t = time.perf_counter()
            d_sh = jax.block_until_ready(run_sh(d_sh, rpm_sh))
            times.append(time.perf_counter() - t)
        sharded = worlds * n * steps / float(np.min(times))
    if scan_only:
        out = {"scan": scan, "compile_s": compile_s}
        if sharded is not None:
            out["scan_sharded"] = sharded
        return out

    def loop(k: int) -> float:
        t = time.perf_counter()
        for _ in range(k):
            sim.rotor_vel_control(rpm)
            sim.step(2)
        jax.block_until_ready(sim.data)
        return time.perf_counter() - t

    def loop_read(k: int) -> float:  # as a Gymnasium env must: the state on the host after every step
        t = time.perf_counter()
        for _ in range(k):
            sim.rotor_vel_control(rpm)
            sim.step(2)
            st = sim.data.states
            np.asarray(st.pos), np.asarray(st.vel), np.asarray(st.quat), np.asarray(st.ang_vel)
        return time.perf_counter() - t

    loop(3)
    looped = worlds * n * timed(loop, seconds, repeat)
    loop_read(3)
    read = worlds * n * timed(loop_read, seconds, repeat)
    out = {"scan": scan, "loop": looped, "loop_read": read, "compile_s": compile_s}
    if sharded is not None:
        out["scan_sharded"] = sharded
    return out


def _peer_tag(setup: dict[str, str], key: str) -> str:
    return f"peer ({setup.get(key, 'tuned')})"


def _fresh_process(code: str, env: dict[str, str]) -> Any:
    """The JSON after ``RESULT`` printed by ``python -c code`` in a fresh process (None on failure); the
    package is importable there as here (an installed wheel or this checkout)."""
    import quadswarm_mj

    root = str(Path(quadswarm_mj.__file__).resolve().parent.parent)
    env = {**os.environ, **env}
    env["PYTHONPATH"] = os.pathsep.join([root] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    try:
        res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=1800)
        line = [x for x in res.stdout.splitlines() if x.startswith("RESULT ")]
        return json.loads(line[-1][len("RESULT "):]) if line else None
    except (OSError, subprocess.SubprocessError, ValueError):
        return None


def _jax_defaults_env() -> dict[str, str]:
    """Environment of a fresh process with JAX's own defaults (no ``tune_jax_cpu``; the user's XLA flags kept)."""
    flags = os.environ.get("XLA_FLAGS", "").replace(LOOP_KERNEL_FLAG, "").strip()  # the user's own flags only
    return {"QUADSWARM_MJ_TUNE_JAX": "0", "SCIPY_ARRAY_API": "1", "XLA_FLAGS": flags}


def crazyflow_best(worlds: int, n: int, steps: int, seconds: float, repeat: int,
                   devices: int = 1) -> dict[str, float] | None:
    """:func:`crazyflow_rates` at the better of two JAX set-ups, per figure: in this process (the XLA:CPU
    options of ``quadswarm_mj.devices.tune_jax_cpu``, which the JAX engine's rows run with) and in a
    fresh process with JAX's defaults (``QUADSWARM_MJ_TUNE_JAX=0``: asynchronous dispatch, XLA's loop
    limits), so the peer is never measured below its own best. ``"setup"`` says which won each figure."""
    here = crazyflow_rates(worlds, n, steps, seconds, repeat, devices=devices)
    if here is None:
        return None
    call = f"crazyflow_rates({worlds}, {n}, {steps}, {seconds}, {repeat}, devices={devices})"
    code = (f"import json; from quadswarm_mj.devices import tune_jax_cpu, use_cpu_cores; tune_jax_cpu(); "
            f"use_cpu_cores({devices}, strict=False); "
            f"from quadswarm_mj.cli.benchmark import crazyflow_rates; print('RESULT', json.dumps({call}))")
    default = _fresh_process(code, _jax_defaults_env())
    if not default:
        return {**here, "setup": {k: "tuned" for k in here}}
    best, setup = {}, {}
    for k, v in here.items():
        d = default.get(k)
        if k == "compile_s":
            best[k], setup[k] = v, "tuned"
        elif d is not None and d > v:
            best[k], setup[k] = d, "JAX defaults"
        else:
            best[k], setup[k] = v, "tuned"
    best["setup"] = setup
    return best


def alternating_peer_ratio(worlds: int, devices: int, rounds: int, steps: int, repeat: int) -> dict[str, Any] | None:
    """The JAX engine's jitted rollout (``benchmark_mjx``, paper defaults, ``worlds`` x 8) against
    crazyflow's jitted scan on the same ``devices``, in ``rounds`` alternating rounds of fresh processes:
    each round measures the JAX engine (best of ``repeat`` rollouts of ``steps`` control steps, with
    :func:`quadswarm_mj.devices.tune_jax_cpu` in force) and then crazyflow (the better of a tuned
    process and one with JAX's defaults, as :func:`crazyflow_best`). On a shared machine whose speed
    drifts by tens of per cent within minutes, the median of the per-round ratios is the robust figure.
    Returns ``ratios``, ``median``, ``min``, ``max`` and the per-round samples/s (``ours``, ``peer``), or
    None when a side could not be measured (crazyflow or JAX missing)."""
    import statistics

    ours_code = ("import json; from quadswarm_mj.devices import tune_jax_cpu, use_cpu_cores; tune_jax_cpu(); "
                 f"use_cpu_cores({devices}, strict=False); from quadswarm_mj import EnvConfig; "
                 "from quadswarm_mj.envs.mjx_env import benchmark_mjx; "
                 f"r = [benchmark_mjx(EnvConfig(num_quads=8), {worlds}, {steps}, devices={devices})"
                 f"['samples_per_s'] for _ in range({max(repeat, 1)})]; print('RESULT', json.dumps(max(r)))")
    key = "scan_sharded" if devices > 1 else "scan"
    peer_code = ("import json; from quadswarm_mj.devices import tune_jax_cpu, use_cpu_cores; tune_jax_cpu(); "
                 f"use_cpu_cores({devices}, strict=False); from quadswarm_mj.cli.benchmark import crazyflow_rates; "
                 f"r = crazyflow_rates({worlds}, 8, {steps}, 1.0, {max(repeat, 3)}, devices={devices}, "
                 f"scan_only=True); print('RESULT', json.dumps(r and r.get('{key}')))")
    defaults = _jax_defaults_env()
    ours, peer, ratios = [], [], []
    for r in range(rounds):
        a = _fresh_process(ours_code, {})
        b = [x for x in (_fresh_process(peer_code, {}), _fresh_process(peer_code, defaults)) if x]
        if not a or not b:
            return None
        ours.append(float(a))
        peer.append(max(b))
        ratios.append(ours[-1] / peer[-1])
        print(f"  alternating {worlds} x 8, {devices} device(s), round {r + 1}/{rounds}: JAX engine {fmt(ours[-1])}, "
              f"crazyflow {fmt(peer[-1])}, ratio {ratios[-1]:.2f}x", flush=True)
    return {"ratios": ratios, "median": statistics.median(ratios), "min": min(ratios), "max": max(ratios),
            "ours": ours, "peer": peer}


def alternating_floor_ratio(B: int, rounds: int, seconds: float) -> dict[str, Any]:
    """``QuadSwarmVectorEnv(engine="jax")`` (B x 8, hover actions, auto-reset) against the bare-MuJoCo
    floor (:func:`ceiling_rollout`, 2 threads) in ``rounds`` alternating windows of ``seconds`` each, in
    this process. The env is warmed up past its first episode end (which compiles the renewal
    program), and each window times every ``step`` call it makes. On a machine whose speed drifts by
    tens of per cent within seconds, the median of the per-round ratios is the robust figure.
    Returns ``ratios``, ``median``, ``min``, ``max`` and the per-round samples/s (``env``, ``floor``)."""
    import statistics

    cfg = EnvConfig(num_quads=8)
    env = QuadSwarmVectorEnv(cfg, num_envs=B, engine="jax")
    try:
        env.reset(seed=0)
        hover = hover_like(env.action_space.shape)
        for _ in range(cfg.episode_steps + 2):
            env.step(hover)
        rates, floors, ratios = [], [], []
        for r in range(rounds):
            n, busy, t_end = 0, 0.0, time.perf_counter() + seconds
            while time.perf_counter() < t_end:
                t = time.perf_counter()
                env.step(hover)
                busy += time.perf_counter() - t
                n += 1
            rates.append(8 * B * n / busy)
            floors.append(ceiling_rollout(8 * B, seconds, 1))
            ratios.append(rates[-1] / floors[-1])
            print(f"  alternating vector env {B} x 8 vs floor, round {r + 1}/{rounds}: env {fmt(rates[-1])}, "
                  f"floor {fmt(floors[-1])}, ratio {ratios[-1]:.2f}", flush=True)
    finally:
        env.close()
    return {"ratios": ratios, "median": statistics.median(ratios), "min": min(ratios), "max": max(ratios),
            "env": rates, "floor": floors}


# -------------------------------------------------------------------------------------- ceiling
def bare_model(bodies: int) -> mujoco.MjModel:
    """``bodies`` free bodies with the Crazyflie's inertia and no geoms; contacts off, Euler, 5 ms."""
    b = "".join(f"<body pos='{0.3 * (i // 8):.1f} 0 {1 + 0.2 * (i % 8):.1f}'><freejoint/><inertial pos='0 0 0' "
                f"mass='0.028' diaginertia='1.3669e-05 1.4357e-05 2.6562e-05'/></body>" for i in range(bodies))
    size = f"<size memory='{4 + bodies * 60 // 1000}M'/>"
    return mujoco.MjModel.from_xml_string(f"<mujoco>{size}<option timestep='0.005' integrator='Euler'>"
                                          f"<flag contact='disable'/></option><worldbody>{b}</worldbody></mujoco>")


def ceiling_one_core(bodies: int, seconds: float, repeat: int) -> float:
    m = bare_model(bodies)
    d = mujoco.MjData(m)

    def run(steps: int) -> float:
        t = time.perf_counter()
        for _ in range(steps):
            mujoco.mj_step(m, d)
        return time.perf_counter() - t

    return bodies * timed(run, seconds, repeat) / 2.0  # 2 sub-steps per sample


def ceiling_rollout(bodies: int, seconds: float, repeat: int, nthread: int = 2) -> float:
    parts = nthread if bodies % nthread == 0 and bodies >= nthread else 1
    while bodies // parts > 512 and bodies % (2 * parts) == 0:  # equal models of <= 512 bodies
        parts *= 2
    m = bare_model(bodies // parts)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    s0 = np.zeros(mujoco.mj_stateSize(m, spec))
    mujoco.mj_getState(m, d, s0, spec)
    init = np.tile(s0, (parts, 1))
    datas = [mujoco.MjData(m) for _ in range(nthread)]
    with mujoco.rollout.Rollout(nthread=nthread) as r:
        def run(steps: int) -> float:
            t = time.perf_counter()
            r.rollout(m, datas, init, nstep=steps)
            return time.perf_counter() - t

        return bodies * timed(run, seconds, repeat, min_steps=8) / 2.0


def ceiling(bodies: int, seconds: float, repeat: int) -> dict[str, float]:
    one = ceiling_one_core(bodies, seconds, repeat)
    two = ceiling_rollout(bodies, seconds, repeat)
    return {"one_core": one, "rollout": two, "ceiling": max(one, two)}


# -------------------------------------------------------------------------------------- profile
PROFILE_GROUPS = [  # (label, [(file suffix, function name)]); builtins have file "~" and match by substring
    ("MuJoCo physics step (C)", [("~", "mj_step"), ("~", "_batch.step")]),
    ("actuation: command, motor noise, lag, thrusts, wrench", [("actuation.py", "substep_wrench"),
                                                               ("actuation.py", "motor_noise_step"),
                                                               ("actuation.py", "action_to_command")]),
    ("rotation matrices from quaternions", [("spatial.py", "quat_to_rotmat")]),
    ("floor model (friction wrench + impact)", [("collisions.py", "floor_wrench"), ("cpu_core.py", "_floor_impact")]),
    ("walls, ceiling, quad-quad response", [("collisions.py", "wall_collisions"),
                                            ("collisions.py", "quad_collisions")]),
    ("pairwise distances and contacts", [("collisions.py", "pairwise_contacts")]),
    ("reward terms and total", [("rewards.py", "reward_terms"), ("rewards.py", "total_reward")]),
    ("episode metrics", [("metrics.py", "update"), ("metrics.py", "goal_jump")]),
    ("observations (sensor noise, own state, K nearest)", [("cpu_core.py", "observe")]),
    ("scenario goals", [("scenarios/static.py", "step"), ("scenarios/base.py", "step")]),
    ("env wrapper: action check, info / output arrays", [("validation.py", "check_action"), ("gym_env.py", "_info"),
                                                         ("vector_env.py", "_info"),
                                                         ("vector_env.py", "_write_info")]),
]


def profile_breakdown(fn: Callable[[], None]) -> tuple[float, list[tuple[str, float]]]:
    """Run ``fn`` under cProfile; return its total time and the cumulative time of each group (the
    groups are disjoint calls, except that the floor model computes rotations too)."""
    pr = cProfile.Profile()
    pr.enable()
    fn()
    pr.disable()
    st = pstats.Stats(pr)
    total = max(v[3] for v in st.stats.values())
    out = []
    for label, keys in PROFILE_GROUPS:
        t = 0.0
        for (file, _line, name), (_cc, _nc, _tt, ct, _callers) in st.stats.items():
            for suffix, fname in keys:
                if (suffix == "~" and file == "~" and fname in name) or (
                        suffix != "~" and file.endswith(suffix) and name == fname):
                    t += ct
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
    lines = ["QuadSwarmEnv, 8 quads, hover workload (quads crash after ~1 s, so the floor model runs), one "
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


# ----------------------------------------------------------------------------------------- main
def fmt(x: float | None) -> str:
    if x is None:
        return "-"
    if x >= 1e6:
        return f"{x / 1e6:.2f} M"
    if x >= 1e3:
        return f"{x / 1e3:.1f} k"
    return f"{x:.0f}"


def _num_devices() -> int:
    """JAX's devices in this process (1 if JAX is missing)."""
    try:
        import jax

        return len(jax.devices())
    except Exception:  # noqa: BLE001
        return 1


def _jax_rows(rows: set[str], args: Any, seconds: float, repeat: int, steps: int) -> str:
    """The JAX engine's rows (batched rollouts, the single env, the vector env), crazyflow's and the
    ratios between them, all measured in this run; a markdown table ('' if none asked)."""
    out: list[tuple[str, float | None, str, str]] = []  # label, samples/s, compile, ratio note
    peers: dict[int, dict[str, float] | None] = {}
    ndev = _num_devices()
    if "peers" in rows:
        for W in (int(x) for x in args.peer_worlds.split(",")):
            peers[W] = crazyflow_best(W, 8, steps, seconds, repeat, devices=ndev)
            print("crazyflow", W, peers[W], flush=True)
            if peers[W] is None:
                break
    base = EnvConfig(num_quads=8)
    if "jax" in rows:
        for W in (int(x) for x in args.jax_worlds.split(",")):
            # all devices (sharded worlds); and one device at the peer sizes (as JAX runs by default)
            runs = [(ndev, "paper defaults", base), (ndev, "without_noise()", base.without_noise())]
            if ndev > 1 and W > 1 and W % ndev == 0 and W in peers:
                runs.append((1, "paper defaults", base))
            for dev, variant, cfg in runs:
                res = bench_jax_batch(cfg, W, steps, devices=dev)
                if res is None:
                    break
                print("jax", W, variant, dev, res, flush=True)
                peer = peers.get(W)
                used = int(res.get("devices", 1))
                where = "1 device" if used == 1 else f"sharded over {used} CPU devices"
                note = ""
                if peer:
                    key = "scan_sharded" if used > 1 and "scan_sharded" in peer else "scan"
                    note = (f"{res['samples_per_s'] / peer[key]:.2f}x crazyflow scan "
                            f"({'sharded the same way' if key == 'scan_sharded' else '1 device'})")
                out.append((f"JAX engine, jitted rollout, {W} x 8, {variant}, {where}", res["samples_per_s"],
                            f"{res['compile_s']:.1f}", note))
    if getattr(args, "alternate", 0) and "peers" in rows and "jax" in rows:
        import statistics

        for W in (int(x) for x in args.alternate_worlds.split(",")):
            for dev in sorted({1, ndev}):
                res = alternating_peer_ratio(W, dev, args.alternate, steps, repeat)
                if res is None:
                    print(f"  alternating rounds at {W} x 8 skipped (crazyflow or JAX not available)", flush=True)
                    break
                where = "1 device" if dev == 1 else f"sharded over {dev} CPU devices"
                out.append((f"JAX engine vs crazyflow scan, {W} x 8, {where}, {args.alternate} alternating rounds of "
                            f"fresh processes (median of the JAX engine's)", statistics.median(res["ours"]), "",
                            f"median {res['median']:.2f}x crazyflow scan (range {res['min']:.2f}x to "
                            f"{res['max']:.2f}x; crazyflow median {fmt(statistics.median(res['peer']))})"))
    if args.ablations and "jax" in rows:
        W = 512
        for variant, cfg, kw in (
                ("physics='mjx' (generic mjx.step)", base, {"physics": "mjx"}),
                ("downwash on", base.replace(downwash=True), {}),
                ("randomize on", base.replace(randomize=True), {}),
                ("sensor noise off", base.replace(noise={"sensor_pos_std": 0.0, "sensor_vel_std": 0.0,
                                                         "sensor_omega_std": 0.0}), {}),
                ("motor noise off", base.replace(noise={"motor_noise_ratio": 0.0}), {}),
                ("K = 0 neighbours", base.replace(num_neighbors=0), {}),
        ):
            try:
                res = bench_jax_batch(cfg, W, steps, **kw)
            except Exception as e:  # noqa: BLE001
                print(f"  ablation {variant} failed: {e!r}", flush=True)
                continue
            if res is not None:
                print("ablation", variant, res, flush=True)
                out.append((f"JAX engine, {W} x 8, {variant}", res["samples_per_s"], f"{res['compile_s']:.1f}", ""))
    if "obstacles" in rows:  # the same swarm and scenario with and without 12 columns, then o_random
        from quadswarm_mj.config import ObstacleConfig

        ocfg = base.replace(obstacles=ObstacleConfig())
        rcfg = ocfg.replace(scenario="o_random")
        W, rounds = 512, max(5, 2 * repeat + 1)
        for engine in ("jax", "mujoco"):
            for label, c in (("static_same_goal + obstacles (12 columns)", ocfg), ("o_random", rcfg)):
                res = obstacle_cost(base, c, engine, W, steps, seconds, rounds)
                if res is None:
                    continue
                print("obstacles", engine, label, res, flush=True)
                what = f"JAX engine, {W} x 8" if engine == "jax" else "QuadSwarmEnv (MuJoCo engine), 1 x 8"
                out.append((f"{what}, {label}", res["with"], "",
                            f"{100 * res['cost']:+.0f} % step time vs the same swarm without obstacles "
                            f"({fmt(res['without'])}); median of {rounds} alternating rounds, range "
                            f"{100 * res['cost_min']:+.0f} to {100 * res['cost_max']:+.0f} %"))
    if "jaxsingle" in rows:
        rate = bench_single_jax(8, seconds, repeat)
        peer = peers.get(1)
        note = (f"{rate / peer['loop']:.2f}x crazyflow loop, {rate / peer['loop_read']:.2f}x crazyflow loop reading "
                f"the state (1 x 8)") if peer else ""
        ref = bench_single(8, "hover", seconds, repeat)
        out.append(("QuadSwarmEnv(engine='jax'), 1 x 8, one step() per control step", rate, "", note))
        ref_note = f"{ref / peer['loop']:.2f}x crazyflow loop, {ref / peer['loop_read']:.2f}x reading" if peer else ""
        out.append(("QuadSwarmEnv(engine='mujoco'), 1 x 8 (same run)", ref, "", ref_note))
    if "jaxvector" in rows:
        for B in (int(x) for x in args.jax_vector_b.split(",")):
            jx = bench_vector(B, 8, "hover", seconds, repeat, engine="jax")
            mj = bench_vector(B, 8, "hover", seconds, repeat)
            floor = ceiling_rollout(8 * B, seconds, repeat)
            out.append((f"QuadSwarmVectorEnv(engine='jax'), {B} x 8", jx, "",
                        f"{jx / floor:.2f} of the bare-MuJoCo floor (mujoco.rollout, 2 threads: {fmt(floor)})"))
            out.append((f"QuadSwarmVectorEnv(engine='mujoco'), {B} x 8", mj, "", f"{mj / floor:.2f} of the floor"))
            if getattr(args, "alternate", 0):
                import statistics

                res = alternating_floor_ratio(B, args.alternate, seconds)
                out.append((f"QuadSwarmVectorEnv(engine='jax'), {B} x 8, {args.alternate} alternating rounds with the "
                            f"floor (median of the env's)", statistics.median(res["env"]), "",
                            f"median {res['median']:.2f} of the floor (range {res['min']:.2f} to {res['max']:.2f}; "
                            f"floor median {fmt(statistics.median(res['floor']))})"))
    for W, peer in peers.items():
        if peer:
            tag = functools.partial(_peer_tag, peer.get("setup", {}))

            out.append((f"crazyflow 0.4 Sim, {W} x 8, jitted scan", peer["scan"], f"{peer['compile_s']:.1f}",
                        tag("scan")))
            if "scan_sharded" in peer:
                out.append((f"crazyflow 0.4 Sim, {W} x 8, jitted scan, sharded over {ndev} CPU devices",
                            peer["scan_sharded"], "", tag("scan_sharded")))
            out.append((f"crazyflow 0.4 Sim, {W} x 8, Python loop", peer["loop"], "", tag("loop")))
            out.append((f"crazyflow 0.4 Sim, {W} x 8, Python loop reading the state every step", peer["loop_read"], "",
                        tag("loop_read")))
    if not out:
        return ""
    lines = ["| configuration | samples/s | compile (s) | ratio (same run) |", "|---|---:|---:|---|"]
    lines += [f"| {a} | {fmt(b)} | {c} | {d} |" for a, b, c, d in out]
    return "\n".join(lines)


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


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # run as a command: the opt-in XLA:CPU tuning (quadswarm_mj.tune_jax_cpu), before JAX starts
        from quadswarm_mj.devices import tune_jax_cpu

        tune_jax_cpu()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="short runs (0.5 s, 1 repeat, hover workload only)")
    p.add_argument("--rows", default="single,vector,jax,jaxsingle,jaxvector,peers",
                   help="comma list of single, vector, jax (mjx is an alias), jaxsingle, jaxvector, peers, obstacles")
    p.add_argument("--single-n", default="1,8,32,128")
    p.add_argument("--vector-b", default="64,256,1024")
    p.add_argument("--mjx-steps", type=int, default=200)
    p.add_argument("--jax-worlds", default="1,64,512,2048",
                   help="worlds of the JAX-engine rows (rows 'jax': jitted rollouts, paper defaults and without_noise)")
    p.add_argument("--jax-vector-b", default="1024", help="worlds of the JAX-engine vector env rows ('jaxvector')")
    p.add_argument("--peer-worlds", default="1,512,2048", help="worlds of the crazyflow peer rows ('peers')")
    p.add_argument("--alternate", type=int, default=0, metavar="R",
                   help="also measure the JAX engine against crazyflow's scan in R alternating rounds of fresh "
                        "processes (rows 'jax' and 'peers'; 1 device and all devices) and the JAX-engine vector "
                        "env against the floor in R alternating windows (row 'jaxvector'): median ratios, robust "
                        "to a machine whose speed drifts within a run (default 0: off)")
    p.add_argument("--alternate-worlds", default="512", help="worlds of the --alternate rounds (default 512)")
    p.add_argument("--ablations", action="store_true",
                   help="JAX engine at 512 x 8 with stages switched off/on (where the time goes)")
    p.add_argument("--skip-mjx", action="store_true")
    p.add_argument("--workloads", default=None, help=f"comma list of {WORKLOADS} (default: all; --quick: hover)")
    p.add_argument("--seconds", type=float, default=None, help="length of one timed run (default 2, --quick 0.5)")
    p.add_argument("--repeat", type=int, default=None, help="timed runs per figure, best kept (default 3, --quick 1)")
    p.add_argument("--profile", action="store_true", help="add a cProfile breakdown of the single and vector env")
    p.add_argument("--compare", type=int, default=0, metavar="B",
                   help="add the design measurements (physics back ends, threads vs processes) at B worlds")
    p.add_argument("--cpu-devices", default="cores", metavar="N",
                   help="JAX CPU devices: 'cores' (default: one per core, quadswarm_mj.use_cpu_cores(); the JAX "
                        "engine shards its worlds over them and also reports 1-device rows) or an int (1: JAX's "
                        "default single device)")
    p.add_argument("--out", default="BENCHMARKS.md", help="report file (default ./BENCHMARKS.md)")
    p.add_argument("--no-write", action="store_true", help="print only")
    args = p.parse_args(argv)
    from quadswarm_mj.devices import cpu_devices_option, use_cpu_cores

    try:
        cpu_devices = cpu_devices_option(args.cpu_devices)
    except ValueError as e:
        p.error(str(e))
    if args.alternate < 0:
        p.error("--alternate must be >= 0")
    if not args.no_write:  # before the work: a report that cannot be written is known now, not after it
        try:
            check_report_target(args.out)
        except ValueError as e:
            p.error(str(e))
    if not args.skip_mjx:
        try:
            use_cpu_cores(cpu_devices, strict=False)
        except ImportError:  # JAX missing: the JAX rows are skipped with a note
            pass
    seconds = args.seconds or (0.5 if args.quick else 2.0)
    repeat = args.repeat or (1 if args.quick else 3)
    workloads = tuple((args.workloads or ("hover" if args.quick else ",".join(WORKLOADS))).split(","))
    for w in workloads:
        if w not in WORKLOADS:
            p.error(f"unknown workload {w!r}; known: {WORKLOADS}")
    rows = set(args.rows.split(","))
    if "mjx" in rows:
        rows.add("jax")
    if args.skip_mjx:
        rows -= {"mjx", "jax", "jaxsingle", "jaxvector", "peers", "obstacles"}
    command = "/work/venv/bin/python scripts/benchmark.py " + " ".join(sys.argv[1:] if argv is None else argv)
    started = datetime.datetime.now().astimezone()
    load0 = load()
    print(f"{machine()}\nload average at start: {load0}\n", flush=True)

    table = []  # dicts: label, quads, bodies, workloads..., mjx, ceiling...
    if "single" in rows:
        for n in (int(x) for x in args.single_n.split(",")):
            r = {"label": f"QuadSwarmEnv, 1 world x {n}", "bodies": n}
            for w in workloads:
                r[w] = bench_single(n, w, seconds, repeat)
            r.update(ceiling(n, seconds, repeat))
            print(r, flush=True)
            table.append(r)
    if "vector" in rows:
        for B in (int(x) for x in args.vector_b.split(",")):
            r = {"label": f"QuadSwarmVectorEnv, {B} worlds x 8", "bodies": 8 * B, "vector": True}
            for w in workloads:
                r[w] = bench_vector(B, 8, w, seconds, repeat)
            r.update(ceiling(8 * B, seconds, repeat))
            print(r, flush=True)
            table.append(r)
    jax_steps = args.mjx_steps if not args.quick else max(20, args.mjx_steps // 4)
    jax_table = _jax_rows(rows, args, seconds, repeat, jax_steps)
    prof = run_profile() if args.profile else None
    comp = compare_engines(args.compare, seconds, repeat) if args.compare else None
    load1 = load()

    head = "| configuration | " + " | ".join(f"{w} (samples/s)" for w in workloads) + \
           " | ceiling 1 core | ceiling rollout 2 cores | env / ceiling (" + workloads[0] + ") |"
    sep = "|---|" + "---:|" * (len(workloads) + 3)
    lines = [head, sep]
    for r in table:
        vals = [fmt(r.get(w)) for w in workloads]
        label = r["label"]
        ratio = r.get(workloads[0])
        ratio_s = f"{100 * ratio / r['ceiling']:.0f} %" if ratio else "-"
        lines.append(f"| {label} | " + " | ".join(vals)
                     + f" | {fmt(r['one_core'])} | {fmt(r['rollout'])} | {ratio_s} |")
    tab = "\n".join(lines)
    print("\n" + tab)
    if jax_table:
        print("\n" + jax_table)
    vec = [r for r in table if r.get("vector")]
    summary = []
    for r in vec:
        for w in workloads:
            summary.append(f"- {r['label']}, {w}: {fmt(r[w])} samples/s = {100 * r[w] / r['ceiling']:.0f} % of the "
                           f"ceiling ({fmt(r['ceiling'])}, the faster of 1 core {fmt(r['one_core'])} and rollout "
                           f"{fmt(r['rollout'])})")
    if args.no_write:
        for extra in (prof, comp):
            if extra:
                print("\n" + extra)
        return 0
    doc = [
        "# Benchmarks",
        "",
        "The part above the notes marker is generated by `scripts/benchmark.py`; the notes below it are",
        "kept when the script rewrites the file.",
        "",
        f"- command: `{command}`",
        f"- machine: {machine()}",
        f"- date: {started.strftime('%Y-%m-%d %H:%M %Z')}; load average (1, 5, 15 min) at start {load0}, "
        f"at end {load1} "
        "(2 cores shared with other jobs: absolute figures drift with load, ratios are measured in the same run)",
        f"- each figure: best of {repeat} timed runs of {seconds:g} s; samples/s = quad-steps/s at 100 Hz control,"
        " 200 Hz physics, paper defaults (collisions, noise, K = 6, static_same_goal)",
        "- workloads: hover = hover command (quads drift and crash, the floor model runs), random = uniform"
        " actions, controller = baseline position controller (flying; only `step` timed)",
        "- ceiling: bare free bodies (Crazyflie inertia, no geoms, contacts off, Euler, 2 sub-steps per sample);"
        " 1 core = one model, `mj_step` loop; rollout = `mujoco.rollout` on 2 threads over equal models",
        "",
        tab,
        "",
    ]
    if summary:
        doc += ["Vector env / ceiling, measured in this run:", ""] + summary + [""]
    if jax_table:
        doc += ["## The JAX engine and the peer (same run)", "",
                "JAX rows run with `quadswarm_mj.devices.tune_jax_cpu()` in force (loops compiled as single "
                "XLA:CPU kernels, synchronous CPU dispatch). Each crazyflow figure is the better of the same "
                "process (\"tuned\") and a fresh process with JAX's defaults (\"JAX defaults\"), as its row says.",
                "", jax_table, ""]
    if prof:
        doc += ["## Where the time goes", "", prof, ""]
    if comp:
        doc += ["## Design measurements (same run)", "", comp, ""]
    try:
        old = existing_report(args.out)
    except ValueError as e:  # the file changed during the run
        print("\n".join(doc) + "\n", flush=True)
        print(f"error: {e}; the report is printed above", file=sys.stderr)
        return 1
    doc.append(old[old.index(NOTES_MARKER):] if NOTES_MARKER in old else NOTES_MARKER + "\n")
    text = "\n".join(doc)
    try:
        atomic_write_text(args.out, text)
    except OSError as e:  # e.g. the disk filled up or the directory went away during the run
        print(text, flush=True)
        print(f"error: could not write the report to {args.out!r} ({e.strerror or e}); it is printed above",
              file=sys.stderr)
        return 1
    print(f"\nwrote {args.out}")
    return 0


def check_report_target(path: str | os.PathLike) -> str:
    """The text of the benchmark report at ``path`` ('' if there is none yet), after checking that it
    can be rewritten: ``ValueError`` if it cannot be written or if it exists and is not a benchmark
    report (it lacks the notes marker this command writes), so no other file is ever overwritten."""
    check_writable(path, "--out")
    return existing_report(path)


def existing_report(path: str | os.PathLike) -> str:
    """The text of the benchmark report at ``path`` ('' if there is none); ``ValueError`` if the file exists
    and is not one."""
    p = Path(path)
    if not p.is_file():
        return ""  # missing, or a device/pipe (written in place)
    try:
        if p.stat().st_size > (16 << 20):
            raise ValueError("larger than 16 MiB")
        old = p.read_text(encoding="utf-8")
    except (OSError, ValueError) as e:  # incl. UnicodeDecodeError: a binary file
        raise ValueError(f"--out {str(p)!r} exists and is not a benchmark report ({e}); refusing to overwrite it: "
                         "choose another file or remove it") from None
    if old.strip() and NOTES_MARKER not in old:
        raise ValueError(f"--out {str(p)!r} exists and is not a benchmark report (it lacks the line "
                         f"{NOTES_MARKER!r}); refusing to overwrite it: choose another file or remove it")
    return old


if __name__ == "__main__":
    raise SystemExit(main())
