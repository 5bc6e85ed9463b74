"""quadswarm_mj.perf.numpy_loop (the CPU engine's sub-step loop for small arrays, the control step's
constants computed once) gives the bits of the per-sub-step ops over whole seeded runs: single envs of
several quads with random actions (floor hits, staying on the floor, lift-offs, collisions) and a
several-world engine with a partial reset."""

from __future__ import annotations

import numpy as np
import pytest
from episode_record import record_random_run, record_three_world_run

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.envs.cpu_core import CpuSwarm
from quadswarm_mj.envs.gym_env import QuadSwarmEnv
from quadswarm_mj.perf import numpy_loop, numpy_swarm


def _same(a, b):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape and a.dtype == b.dtype
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(np.signbit(a), np.signbit(b))


def _episode(enabled: bool, seed: int, **kw) -> list:
    numpy_loop.ENABLED, numpy_swarm.ENABLED = enabled, False  # SmallLoop (numpy_swarm: tests/test_numpy_swarm.py)
    try:
        env = QuadSwarmEnv(EnvConfig(episode_seconds=3.0, **kw))
        assert (env.core._ops.fused_loop is not None) == enabled
        return record_random_run(env, seed, 500, lambda obs, r, info: [
            obs, r, info["on_floor"], info["rewards"], *info["state"].values()])
    finally:
        numpy_loop.ENABLED = numpy_swarm.ENABLED = True


@pytest.mark.parametrize("kw", [{"num_quads": 8}, {"num_quads": 3, "randomize": True, "downwash": True},
                                {"num_quads": 8, "noise": {"stochastic_collisions": False}, "sim_hz": 300}])
def test_single_env_episodes_are_the_per_substep_ops_bitwise(kw):
    got, ref = _episode(True, 2, **kw), _episode(False, 2, **kw)
    assert len(got) == len(ref)
    floor = np.concatenate([np.ravel(x) for x in got if np.asarray(x).dtype == bool])
    assert floor.any() and not floor.all()  # quads on the floor and in the air
    for a, b in zip(got, ref):
        _same(a, b)


@pytest.mark.parametrize("backend", ["mjdata", "batch"])
def test_several_worlds_are_the_per_substep_ops_bitwise(backend):
    out = []
    for enabled in (True, False):
        numpy_loop.ENABLED = enabled
        try:
            core = CpuSwarm(EnvConfig(num_quads=4, scenario="swap_goals"), num_worlds=3, backend=backend,
                            visual=False)
            out.append(record_three_world_run(core, lambda c, o: [o["obs"], o["rewards"], c.qpos.copy(),
                                                                 c.qvel.copy(), c.on_floor.copy()]))
        finally:
            numpy_loop.ENABLED = True
    for a, b in zip(*out):
        _same(a, b)
