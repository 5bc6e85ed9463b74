"""Probe: the JAX engine's one-world step in a dedicated worker process that applies ``tune_jax_cpu()`` to
itself only (the caller's process unchanged), seen from the caller through a pipe, against Hopper-v5.

What it measures, in one caller process (``python scripts/worker_probe.py --quads 1``):

* ``pipe_round_trip_us``: a one-byte round trip to a spawned process (the transport's floor);
* ``first_step_s``: from starting the worker to the first step's return in the caller (spawn, imports, JAX
  start, compiles, reset);
* ``worker_step_us``: the worker's own time per ``JaxSingleBackend.step`` (info included), as it ran for
  the caller's steps, and ``worker_step_alone_us`` when the worker steps by itself, back to back;
* ``rate`` / ``hopper_rate`` / ``ratio``: env steps/s the caller gets (step = send the action, receive the
  pickled ``(obs, reward, truncated, info)``), and Hopper-v5's in the same process, alternating
  (best of ``--rounds`` windows of ``--steps`` steps each).

A probe, not a front end: the default env does not run this way (see BENCHMARKS.md, "The default
Gymnasium env and Hopper-v5").
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from typing import Any

import numpy as np


def _worker(conn: Any, num_quads: int, alone_steps: int) -> None:
    import quadswarm_mj

    quadswarm_mj.tune_jax_cpu()  # this worker process only
    from quadswarm_mj.config import EnvConfig
    from quadswarm_mj.envs.jax_single import JaxSingleBackend

    b = JaxSingleBackend(EnvConfig(num_quads=num_quads))
    spent, count = 0.0, 0
    while True:
        msg = conn.recv()
        if msg[0] == "step":
            t = time.perf_counter()
            out = b.step(msg[1])
            spent, count = spent + time.perf_counter() - t, count + 1
            conn.send(out)
        elif msg[0] == "reset":
            if msg[1] is not None:
                b.seed(msg[1])
            conn.send(b.reset(None))
        elif msg[0] == "ping":  # (after the first step: its compile is not counted)
            spent, count = 0.0, 0
            conn.send_bytes(b"k")
        else:  # "stop": report, then time the step back to back
            a = np.zeros((num_quads, 4), np.float32)
            t = time.perf_counter()
            for _ in range(alone_steps):
                if b.step(a)[2]:
                    b.reset(None)
            alone = (time.perf_counter() - t) / alone_steps
            conn.send({"worker_step_us": 1e6 * spent / max(count, 1), "worker_step_alone_us": 1e6 * alone})
            return


def probe(num_quads: int = 1, steps: int = 2000, rounds: int = 3) -> dict[str, Any]:
    """Run the probe (module doc); returns its figures."""
    import gymnasium as gym

    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    t0 = time.perf_counter()
    proc = ctx.Process(target=_worker, args=(child, num_quads, steps), daemon=True)
    proc.start()
    parent.send(("reset", 0))
    parent.recv()
    act = np.zeros((num_quads, 4), np.float32)
    parent.send(("step", act))
    parent.recv()
    out: dict[str, Any] = {"num_quads": num_quads, "first_step_s": time.perf_counter() - t0}
    t = time.perf_counter()
    for _ in range(steps):
        parent.send(("ping",))
        parent.recv_bytes()
    out["pipe_round_trip_us"] = 1e6 * (time.perf_counter() - t) / steps
    hopper = gym.make("Hopper-v5")
    hopper.reset(seed=0)
    ha = hopper.action_space.sample()
    rate = hrate = 0.0
    for _ in range(rounds):
        t = time.perf_counter()
        for _ in range(steps):
            parent.send(("step", act))
            if parent.recv()[2]:
                parent.send(("reset", None))
                parent.recv()
        rate = max(rate, steps / (time.perf_counter() - t))
        t = time.perf_counter()
        for _ in range(steps):
            _, _, term, trunc, _ = hopper.step(ha)
            if term or trunc:
                hopper.reset()
        hrate = max(hrate, steps / (time.perf_counter() - t))
    parent.send(("stop",))
    out.update(parent.recv())
    proc.join(timeout=30)
    hopper.close()
    out.update(rate=rate, hopper_rate=hrate, ratio=rate / hrate)
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quads", type=int, default=1)
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--rounds", type=int, default=3)
    a = p.parse_args(argv)
    print(json.dumps(probe(a.quads, a.steps, a.rounds), indent=1))


if __name__ == "__main__":
    main()
