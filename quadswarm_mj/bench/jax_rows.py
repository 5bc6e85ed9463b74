"""The JAX engine's rows (batched rollouts, ablations, obstacles, the single and vector env), crazyflow's,
and the ratios between them, all measured in one run: a markdown table."""

from __future__ import annotations

import functools
from typing import Any

from quadswarm_mj import EnvConfig
from quadswarm_mj.bench.ceiling import ceiling_rollout
from quadswarm_mj.bench.common import fmt, num_devices
from quadswarm_mj.bench.envs import bench_jax_batch, bench_single, bench_single_jax, bench_vector, obstacle_cost
from quadswarm_mj.bench.peers import _peer_tag, alternating_floor_ratio, alternating_peer_ratio, crazyflow_best


def jax_rows(rows: set[str], args: Any, seconds: float, repeat: int, steps: int) -> str:
    """The JAX engine's rows (batched rollouts, the single env, the vector env), crazyflow's and the
    ratios between them, all measured in this run; a markdown table ('' if none asked)."""
    out: list[tuple[str, float | None, str, str]] = []  # label, samples/s, compile, ratio note
    peers: dict[int, dict[str, float] | None] = {}
    ndev = num_devices()
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
    if "draws" in rows:
        out += draws_rows([int(x) for x in args.draws_worlds.split(",")], args.draws_rounds, steps)
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


def alternating_draws(worlds: int, sensors: bool, rounds: int, steps: int) -> dict[str, Any] | None:
    """The JAX engine's jitted rollout (``benchmark_mjx``, paper defaults, ``worlds`` x 8 on one device;
    ``sensors``: the multi-ranger and flow decks on) with ``draws="fused"`` against ``draws="jax"``
    (:class:`~quadswarm_mj.envs.mjx_env.MjxQuadSwarmEnv`) in ``rounds`` alternating rounds of fresh
    processes (fused, then jax). Returns the per-round samples/s of each (wall: ``fused``, ``jax``; CPU
    time: ``fused_cpu``, ``jax_cpu``) and the per-round ratios fused / jax (``ratios``, ``cpu_ratios``),
    or None when a round failed (JAX missing)."""
    from quadswarm_mj.bench.peers import _fresh_process

    cfg = ("EnvConfig(num_quads=8, sensors=SensorConfig(multiranger=True, flow=True))" if sensors
           else "EnvConfig(num_quads=8)")
    out: dict[str, list[float]] = {"fused": [], "jax": [], "fused_cpu": [], "jax_cpu": [], "ratios": [],
                                   "cpu_ratios": []}
    for r in range(rounds):
        for draws in ("fused", "jax"):
            code = ("import json; from quadswarm_mj.devices import tune_jax_cpu, use_cpu_cores; tune_jax_cpu(); "
                    "use_cpu_cores(1, strict=False); from quadswarm_mj import EnvConfig, SensorConfig; "
                    "from quadswarm_mj.envs.mjx_env import benchmark_mjx; "
                    f"print('RESULT', json.dumps(benchmark_mjx({cfg}, {worlds}, {steps}, devices=1, draws='{draws}')))")
            res = _fresh_process(code, {})
            if not res:
                return None
            out[draws].append(res["samples_per_s"])
            out[f"{draws}_cpu"].append(res["cpu_samples_per_s"])
        out["ratios"].append(out["fused"][-1] / out["jax"][-1])
        out["cpu_ratios"].append(out["fused_cpu"][-1] / out["jax_cpu"][-1])
        print(f"  draws {worlds} x 8{' + decks' if sensors else ''}, round {r + 1}/{rounds}: fused "
              f"{fmt(out['fused'][-1])} (CPU {fmt(out['fused_cpu'][-1])}), jax {fmt(out['jax'][-1])} (CPU "
              f"{fmt(out['jax_cpu'][-1])}), ratio {out['ratios'][-1]:.2f} (CPU {out['cpu_ratios'][-1]:.2f})",
              flush=True)
    return out


def draws_rows(worlds: list[int], rounds: int, steps: int) -> list[tuple[str, float | None, str, str]]:
    """Rows of :func:`alternating_draws` at each of ``worlds`` (``steps`` x 512 / worlds control steps per
    rollout, at least ``steps``), decks off and on: the jax form's median samples/s and the ratios."""
    import statistics

    out = []
    for W in worlds:
        for sensors in (False, True):
            res = alternating_draws(W, sensors, rounds, max(steps, steps * 512 // W))
            if res is None:
                print("  draws rows skipped (JAX not available)", flush=True)
                return out
            med = statistics.median
            out.append((f"JAX engine, {W} x 8, paper defaults{', multiranger + flow' if sensors else ''}, 1 device, "
                        f"draws='jax' ({rounds} alternating rounds of fresh processes with draws='fused')",
                        med(res["jax"]), "",
                        f"fused / jax: median {med(res['ratios']):.2f}x (range {min(res['ratios']):.2f} to "
                        f"{max(res['ratios']):.2f}), CPU time {med(res['cpu_ratios']):.2f}x (range "
                        f"{min(res['cpu_ratios']):.2f} to {max(res['cpu_ratios']):.2f}); fused median "
                        f"{fmt(med(res['fused']))}"))
    return out
