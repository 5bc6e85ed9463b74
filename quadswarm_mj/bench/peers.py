"""The peer (crazyflow's ``Sim``) at the same protocol, fresh-process measurements, and the alternating
rounds (JAX engine vs crazyflow's scan; the JAX-engine vector env vs the bare-MuJoCo floor)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from quadswarm_mj import EnvConfig, QuadSwarmVectorEnv
from quadswarm_mj.bench.ceiling import ceiling_rollout
from quadswarm_mj.bench.common import fmt, hover_like, timed
from quadswarm_mj.devices import LOOP_KERNEL_FLAG


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
            f"from quadswarm_mj.bench.peers import crazyflow_rates; print('RESULT', json.dumps({call}))")
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
                 f"use_cpu_cores({devices}, strict=False); from quadswarm_mj.bench.peers import crazyflow_rates; "
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

