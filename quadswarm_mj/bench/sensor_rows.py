"""The deck sensors' cost: samples/s with and without them, on both engines, in alternating rounds.

* JAX engine: ``worlds`` x 8 quads, a jitted ``lax.scan`` of ``AutoResetWrapper.vstep`` with hover
  actions, worlds sharded over the JAX devices as ``benchmark_mjx`` does; compiled once per sensor set,
  then timed in rounds;
* ``QuadSwarmEnv`` (MuJoCo engine): one world of 8 quads stepped from Python with hover actions.

Every round times each sensor set once, in turn (the machine may be shared: its speed drifts between
rounds, hardly within one); a set's ratio is its rate over the no-sensor rate of the same round, and the
row gives the median over the rounds, of samples per wall second and of samples per CPU second of this
process (``time.process_time``, all its threads: steadier on a loaded machine). Paper defaults otherwise
(noise on, static_same_goal). Rows: ``python scripts/benchmark.py --rows sensors`` (BENCHMARKS.md) or
``python scripts/sensor_benchmark.py`` (print only).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np

#: (label, SensorConfig keyword arguments); the first is the reference of every ratio
SENSOR_SETS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("off", {}),
    ("multiranger + flow", {"multiranger": True, "flow": True}),
    ("depth 8 x 8", {"depth": (8, 8)}),
    ("multiranger + flow + depth 8 x 8", {"multiranger": True, "flow": True, "depth": (8, 8)}),
)
NOISE_OFF_SETS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("multiranger + flow, noise off", {"multiranger": True, "flow": True, "noise": False}),
    ("depth 8 x 8, noise off", {"depth": (8, 8), "noise": False}),
)
#: the issue's targets: the least ratio to "off" a set may reach (multi-ranger + flow: 25 % loss, depth: 2x)
TARGETS = {"multiranger + flow": 0.75, "depth 8 x 8": 0.5}

Runner = Callable[[], tuple[float, float]]


def _cfg(sensors: dict[str, Any], n: int) -> Any:
    from quadswarm_mj import EnvConfig, SensorConfig

    return EnvConfig(num_quads=n, sensors=SensorConfig(**sensors))


def jax_runner(sensors: dict[str, Any], worlds: int, steps: int, n: int = 8) -> Runner:
    """``once()``: one compiled rollout of ``steps`` steps -> (samples per wall s, samples per CPU s)."""
    import jax
    import jax.numpy as jnp

    from quadswarm_mj.envs.mjx_env import AutoResetWrapper, MjxQuadSwarmEnv
    from quadswarm_mj.envs.sharding import WorldSharding, world_devices

    cfg = _cfg(sensors, n)
    env = AutoResetWrapper(MjxQuadSwarmEnv(cfg))
    shard = WorldSharding(worlds, world_devices(worlds, jax.devices()))
    hover = jnp.full((worlds, n, 4), cfg.quad.hover_action, jnp.float32)

    def rollout(state: Any) -> Any:
        return jax.lax.scan(lambda s, _: (shard.map_batched(env.vstep)(s, hover), None), state, None,
                            length=steps)[0]

    reset = jax.jit(shard.vmap_reset(env), in_shardings=shard.sharding, out_shardings=shard.sharding)
    keys = jax.device_put(jax.random.split(jax.random.key(0), worlds), shard.sharding)
    state = jax.block_until_ready(reset(keys))
    run = jax.jit(rollout, in_shardings=shard.sharding, out_shardings=shard.sharding).lower(state).compile()
    box = [jax.block_until_ready(run(state))]

    def once() -> tuple[float, float]:
        t0, c0 = time.perf_counter(), time.process_time()
        box[0] = jax.block_until_ready(run(box[0]))
        samples = worlds * n * steps
        return samples / (time.perf_counter() - t0), samples / max(time.process_time() - c0, 1e-9)

    return once


def cpu_runner(sensors: dict[str, Any], seconds: float, n: int = 8) -> Runner:
    """``once()``: ``QuadSwarmEnv`` steps for ``seconds`` -> (samples per wall s, samples per CPU s)."""
    from quadswarm_mj import QuadSwarmEnv

    env = QuadSwarmEnv(_cfg(sensors, n))
    env.reset(seed=0)
    a = np.full((n, 4), env.cfg.quad.hover_action)

    def once() -> tuple[float, float]:
        steps, t0, c0 = 0, time.perf_counter(), time.process_time()
        while time.perf_counter() - t0 < seconds:
            for _ in range(50):
                if env.step(a)[3]:
                    env.reset()
            steps += 50
        return n * steps / (time.perf_counter() - t0), n * steps / max(time.process_time() - c0, 1e-9)

    return once


def measure(runners: dict[str, Runner], rounds: int) -> dict[str, dict[str, Any]]:
    """Alternating rounds over ``runners`` (the first is the reference): per runner the best wall rate
    and the median (and range) over the rounds of its wall and CPU-time ratios to the reference."""
    names = list(runners)
    per: dict[str, list[tuple[float, float]]] = {k: [] for k in names}
    for _ in range(max(rounds, 1)):
        for k in names:
            per[k].append(runners[k]())
    ref = per[names[0]]
    out = {}
    for k in names:
        wall = [x[0] / r[0] for x, r in zip(per[k], ref)]
        cpu = [x[1] / r[1] for x, r in zip(per[k], ref)]
        out[k] = {"rate": max(x[0] for x in per[k]), "ratio": statistics.median(wall), "ratio_range": (min(wall),
                  max(wall)), "cpu_ratio": statistics.median(cpu), "cpu_range": (min(cpu), max(cpu))}
    return out


def sensor_rows(worlds: int = 512, steps: int = 50, seconds: float = 2.0, rounds: int = 5,
                engines: tuple[str, ...] = ("jax", "cpu"), noise_off: bool = False) -> list[dict[str, Any]]:
    """The rows (engine label, sensor set, best samples/s, median ratios to "off") of both engines."""
    sets = SENSOR_SETS + (NOISE_OFF_SETS if noise_off else ())
    rows = []
    for eng in engines:
        if eng == "jax":
            label = f"JAX engine, jitted rollout, {worlds} x 8"
            runners = {name: jax_runner(s, worlds, steps) for name, s in sets}
        elif eng == "cpu":
            label = "QuadSwarmEnv (MuJoCo engine), 1 x 8"
            runners = {name: cpu_runner(s, seconds) for name, s in sets}
        else:
            raise ValueError(f"unknown engine {eng!r}; known: 'jax', 'cpu'")
        res = measure(runners, rounds)
        for name, _ in sets:
            rows.append({"engine": label, "sensors": name, "rounds": rounds, **res[name]})
        print(label, res, flush=True)
    return rows


def sensor_table(rows: list[dict[str, Any]]) -> str:
    """Markdown table of :func:`sensor_rows` ('' if none)."""
    if not rows:
        return ""
    from quadswarm_mj.bench.common import fmt

    lines = ["| configuration | deck sensors | samples/s | vs off, wall (median, range) | vs off, CPU time "
             "(median, range) | target |", "|---|---|---:|---:|---:|---:|"]
    for r in rows:
        target = TARGETS.get(r["sensors"])
        target_s = f">= {target:.2f}x" if target else ""
        lines.append(f"| {r['engine']} | {r['sensors']} | {fmt(r['rate'])} | {r['ratio']:.2f}x "
                     f"({r['ratio_range'][0]:.2f} to {r['ratio_range'][1]:.2f}) | {r['cpu_ratio']:.2f}x "
                     f"({r['cpu_range'][0]:.2f} to {r['cpu_range'][1]:.2f}) | "
                     f"{target_s} |")
    return "\n".join(lines)


def _scene(worlds: int, n: int = 8, seed: int = 0) -> tuple[np.ndarray, ...]:
    """Random quads in the default room: pos, vel, R (body -> world), omega of ``worlds`` x ``n``."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform([-2.5, -2.5, 0.3], [2.5, 2.5, 2.7], (worlds, n, 3))
    q = rng.normal(size=(worlds, n, 4))
    w, x, y, z = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    R = np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                  np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                  np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)
    return pos, rng.normal(size=(worlds, n, 3)), R, rng.normal(size=(worlds, n, 3))


def part_timings(worlds: int = 512, reps: int = 30, jax_rows: bool = True) -> list[tuple[str, float]]:
    """(label, microseconds) of the deck part alone: NumPy (one world of 8 quads, best of 5 x ``reps``
    calls, wall time) and ``jax.jit(jax.vmap(...))`` over ``worlds`` worlds (CPU time of this process per
    call, best of 5 x ``reps``), for the deck part with noise and for the casters against the reference
    caster (``cast_rays`` of ``world_rays``); NumPy also the MuJoCo engine's forms (``perf.numpy_deck``, with
    the depth camera ``perf.numpy_depth``), JAX
    the JAX engine's forms (``core.ops.jax_deck_part``). ``jax_rows=False``: the NumPy rows only."""
    import timeit

    from quadswarm_mj.perf import numpy_deck
    from quadswarm_mj.random_draws import NumpySampler
    from quadswarm_mj.sensor_rays import AXIS_DIRS, axis_hits, cast_rays, depth_directions, depth_hits, world_rays
    from quadswarm_mj.sensors import deck_draw_spec, deck_part

    out = []
    sets = (("multiranger + flow", {"multiranger": True, "flow": True}), ("depth 8 x 8", {"depth": (8, 8)}))
    axis_dirs, pix_dirs = np.asarray(AXIS_DIRS), depth_directions((8, 8), (45.0, 45.0)).reshape(-1, 3)

    def casters(cfg: Any, pixel_spheres: Any = None) -> dict[str, Callable[..., Any]]:
        lo, hi, hb = cfg.room_low, cfg.room_high, cfg.hitbox
        def ref(dirs: np.ndarray) -> Callable[..., Any]:
            return lambda p, r: cast_rays(p, world_rays(r, dirs), lo, hi, None, hb)

        return {"reference caster, 6 body-axis rays": ref(axis_dirs),
                "axis_hits": lambda p, r: axis_hits(p, r, lo, hi, None, hb),
                "reference caster, 8 x 8 pixel rays": ref(pix_dirs),
                "depth_hits 8 x 8": lambda p, r: depth_hits(p, r, (8, 8), (45.0, 45.0), lo, hi, None, hb,
                                                            pixel_spheres)}

    pos, vel, R, om = _scene(1)
    for name, s in sets:
        cfg = _cfg(s, 8)
        draws = NumpySampler(np.random.default_rng(1)).draw(deck_draw_spec(cfg), (1,))
        f = lambda: deck_part(cfg, pos, vel, R, om, None, draws)  # noqa: B023,E731
        out.append((f"NumPy, 1 x 8, deck part, {name}", min(timeit.repeat(f, number=reps, repeat=5)) / reps * 1e6))
        # the MuJoCo engine's form (core.ops.NumpyOps; the depth camera's part: perf.numpy_depth)
        f = lambda: numpy_deck.deck_part(cfg, pos, vel, R, om, None, draws)  # noqa: B023,E731
        form = "perf.numpy_deck" if cfg.sensors.depth is None else "perf.numpy_depth"
        us = min(timeit.repeat(f, number=reps, repeat=5)) / reps * 1e6
        out.append((f"NumPy, 1 x 8, deck part ({form}), {name}", us))
    for label, g in casters(_cfg({}, 8)).items():
        f = lambda: g(pos, R)  # noqa: B023,E731
        out.append((f"NumPy, 1 x 8, {label}", min(timeit.repeat(f, number=reps, repeat=5)) / reps * 1e6))
    if not jax_rows:
        return out
    import jax
    import jax.numpy as jnp

    from quadswarm_mj.core.ops import jax_deck_part
    from quadswarm_mj.perf.depth_xla import sphere_pixel_hits

    pos, vel, R, om = (jnp.asarray(x, jnp.float32) for x in _scene(worlds))

    def cpu_time(fn: Callable[..., Any], *args: Any) -> float:
        g = jax.jit(jax.vmap(fn))
        jax.block_until_ready(g(*args))
        best = float("inf")
        for _ in range(5):
            c0 = time.process_time()
            for _ in range(reps):
                r = g(*args)
            jax.block_until_ready(r)
            best = min(best, (time.process_time() - c0) / reps * 1e6)
        return best

    for name, s in sets:
        cfg = _cfg(s, 8)
        k = cfg.sensors.num_rays
        rng = np.random.default_rng(1)
        draws = {"range_u": jnp.asarray(rng.uniform(size=(worlds, 8, k)), jnp.float32)}
        if cfg.sensors.flow:
            draws["flow_noise"] = jnp.asarray(rng.normal(size=(worlds, 8, 2)), jnp.float32)
        t = cpu_time(lambda p, v, r, o, d: jax_deck_part()(cfg, p, v, r, o, None, d), pos, vel, R, om, draws)  # noqa: B023
        out.append((f"JAX jit(vmap), {worlds} x 8, deck part, {name} (CPU time)", t))
    for label, g in casters(_cfg({}, 8), sphere_pixel_hits).items():  # the JAX engine's depth form
        out.append((f"JAX jit(vmap), {worlds} x 8, {label} (CPU time)", cpu_time(g, pos, R)))
    return out
