"""The bare-MuJoCo ceiling: free bodies with the Crazyflie's inertia, contacts off, Euler, 2 sub-steps per
sample; ``mj_step`` on one core and ``mujoco.rollout`` over equal models on 2 threads."""

from __future__ import annotations

import time

import mujoco
import mujoco.rollout
import numpy as np

from quadswarm_mj.bench.common import timed


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

