"""Throughput of quadswarm_mj on this machine, with the bare-MuJoCo ceiling measured in the same run.

samples/s = quad-steps per second (one quad advanced one 100 Hz control step = 2 physics sub-steps of
200 Hz), paper defaults (collisions, noise, K = 6 neighbours, static_same_goal). Row families
(``--rows``): ``single`` and ``vector`` (the MuJoCo engine's envs), ``jax`` (``benchmark_mjx``'s jitted
rollout; ``--ablations`` switches stages on or off), ``jaxsingle`` and ``jaxvector`` (the envs with
``engine="jax"``), ``peers`` (crazyflow's ``Sim``), ``obstacles`` (the cost of 12 columns), ``gym``
(against Hopper-v5), ``sensors`` (the decks' cost) and ``draws`` (``draws="fused"`` vs ``"jax"``).
Env rows have the bare-MuJoCo ceiling (free bodies, no contacts, ``mj_step`` or ``mujoco.rollout``).
Each figure is the best of ``--repeat`` runs of ``--seconds``; every ratio is of figures of the same run,
and ``--alternate R`` measures the peer and floor ratios in R alternating rounds (medians).

Also the console command ``quadswarm-benchmark`` (same options)::

    python scripts/benchmark.py                  # full table -> BENCHMARKS.md (above its notes marker)
    python scripts/benchmark.py --quick --skip-mjx --no-write
    python scripts/benchmark.py --rows single,vector --profile --no-write

Measuring lives in :mod:`quadswarm_mj.bench` (one module per row family), report writing in
:mod:`quadswarm_mj.bench.report`; this module is the command line. Reading the table: BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import datetime
import sys

from quadswarm_mj import EnvConfig  # noqa: F401  (re-exported)
from quadswarm_mj.bench.ceiling import ceiling
from quadswarm_mj.bench.common import WORKLOADS, load, machine, num_devices
from quadswarm_mj.bench.envs import bench_single, bench_vector
from quadswarm_mj.bench.gym_rows import first_step_code
from quadswarm_mj.bench.jax_rows import jax_rows
from quadswarm_mj.bench.peers import (  # noqa: F401  (the ratios re-exported)
    _fresh_process,
    _jax_defaults_env,
    alternating_floor_ratio,
    alternating_peer_ratio,
)
from quadswarm_mj.bench.profile import compare_engines, run_profile
from quadswarm_mj.bench.report import (  # noqa: F401  (NOTES_MARKER re-exported)
    NOTES_MARKER,
    check_report_target,
    document,
    env_table,
    gym_table,
    vector_summary,
    write_report,
)

_jax_rows = jax_rows
_num_devices = num_devices
FIRST_STEP_ROWS = (("gym.make('QuadSwarm-v0', num_quads=1)", {"num_quads": 1}),
                   ("gym.make('QuadSwarm-v0', num_quads=8)", {"num_quads": 8}),
                   ("gym.make('QuadSwarm-v0', num_quads=1, engine='mujoco')", {"num_quads": 1, "engine": "mujoco"}),
                   ("gym.make('QuadSwarm-v0', num_quads=1, engine='jax')", {"num_quads": 1, "engine": "jax"}),
                   ("gym.make('QuadSwarm-v0', num_quads=8, engine='jax')", {"num_quads": 8, "engine": "jax"}))


def gym_rows(seconds: float, repeat: int) -> str:
    """The Gymnasium rows: rates vs Hopper-v5 in a fresh process with JAX's defaults (what a user gets), the
    JAX engine's again in a fresh process with the opt-in ``tune_jax_cpu()`` (Hopper measured there too), and
    the first-step times in fresh processes with JAX's defaults."""
    call = f"gym_rates({seconds}, {max(repeat, 1)}"
    code = f"import json; from quadswarm_mj.bench.gym_rows import gym_rates; print('RESULT', json.dumps({call})))"
    rates = _fresh_process(code, _jax_defaults_env())
    tuned_code = ("import json, quadswarm_mj; quadswarm_mj.tune_jax_cpu(); "
                  "from quadswarm_mj.bench.gym_rows import GYM_ROWS, gym_rates; "
                  f"rows = [GYM_ROWS[0]] + [r for r in GYM_ROWS if r[1].get('engine') == 'jax']; "
                  f"print('RESULT', json.dumps({call}, rows=rows)))")
    tuned = _fresh_process(tuned_code, {"QUADSWARM_MJ_TUNE_JAX": "1"})
    if rates is None or tuned is None:
        print("  gym rows failed in a fresh process", flush=True)
    for r in tuned or []:
        r["label"] += ", with tune_jax_cpu()"
    first = [(label, _fresh_process(first_step_code(kw), _jax_defaults_env())) for label, kw in FIRST_STEP_ROWS]
    print("gym", rates, tuned, first, flush=True)
    return gym_table((rates or []) + (tuned or []), first)


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # run as a command: the opt-in XLA:CPU tuning (quadswarm_mj.tune_jax_cpu), before JAX starts
        from quadswarm_mj.devices import tune_jax_cpu

        tune_jax_cpu()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="short runs (0.5 s, 1 repeat, hover workload only)")
    p.add_argument("--rows", default="single,vector,jax,jaxsingle,jaxvector,peers,gym",
                   help="comma list of single, vector, jax (mjx is an alias), jaxsingle, jaxvector, peers, obstacles, "
                        "gym (gym.make('QuadSwarm-v0') vs gymnasium's Hopper-v5, first-step time), sensors (the deck "
                        "sensors' cost, both engines), draws (draws='fused' vs 'jax', alternating fresh processes)")
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
    p.add_argument("--sensor-worlds", type=int, default=512, help="worlds of the JAX engine's sensor rows ('sensors')")
    p.add_argument("--sensor-rounds", type=int, default=5,
                   help="alternating rounds of the sensor rows ('sensors'; median ratios to no sensors)")
    p.add_argument("--draws-worlds", default="512,16", help="worlds of the 'draws' rows (1 device; default 512,16)")
    p.add_argument("--draws-rounds", type=int, default=5, help="alternating rounds of the 'draws' rows (default 5)")
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
        rows -= {"mjx", "jax", "jaxsingle", "jaxvector", "peers", "obstacles", "gym", "draws"}
    command = "python scripts/benchmark.py " + " ".join(sys.argv[1:] if argv is None else argv)
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
    jax_table = jax_rows(rows, args, seconds, repeat, jax_steps)
    gym = gym_rows(seconds, repeat) if "gym" in rows else ""
    sensors = ""
    if "sensors" in rows:
        from quadswarm_mj.bench.sensor_rows import sensor_rows, sensor_table

        sensors = sensor_table(sensor_rows(args.sensor_worlds, jax_steps // 4 if not args.quick else jax_steps,
                                           seconds, args.sensor_rounds,
                                           ("cpu",) if args.skip_mjx else ("jax", "cpu")))
    prof = run_profile() if args.profile else None
    comp = compare_engines(args.compare, seconds, repeat) if args.compare else None
    load1 = load()
    tab = env_table(table, workloads)
    for extra in (tab, jax_table, gym, sensors):
        if extra:
            print("\n" + extra)
    if args.no_write:
        for extra in (prof, comp):
            if extra:
                print("\n" + extra)
        return 0
    doc = document(command, started, load0, load1, repeat, seconds, tab, vector_summary(table, workloads),
                   jax_table, gym, prof, comp, sensors=sensors)
    return write_report(args.out, doc)


if __name__ == "__main__":
    raise SystemExit(main())
