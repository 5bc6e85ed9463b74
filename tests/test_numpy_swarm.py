"""quadswarm_mj.perf.numpy_swarm (the one-world sub-step loop on work arrays made once) gives the bits of
``perf.numpy_loop.SmallLoop`` and of the per-sub-step ops over whole seeded runs of single envs of
several quads with random actions (floor hits, staying on the floor, lift-offs, collisions), and the
env steps on as before after a deep copy (the cached views of MuJoCo's arrays are made again)."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from episode_record import record_random_run

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.envs.gym_env import QuadSwarmEnv
from quadswarm_mj.perf import numpy_loop, numpy_swarm
from quadswarm_mj.perf.numpy_swarm import SwarmLoop


def _same(a, b):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape and a.dtype == b.dtype
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(np.signbit(a), np.signbit(b))


def _episode(swarm: bool, small: bool, seed: int, **kw) -> list:
    numpy_swarm.ENABLED, numpy_loop.ENABLED = swarm, small
    try:
        env = QuadSwarmEnv(EnvConfig(episode_seconds=3.0, **kw))
        assert isinstance(env.core._ops.fused_loop, SwarmLoop) == swarm
        return record_random_run(env, seed, 500, lambda obs, r, info: [
            obs, r, info["on_floor"], info["rewards"], *info["state"].values()])
    finally:
        numpy_swarm.ENABLED = numpy_loop.ENABLED = True


@pytest.mark.parametrize("kw", [{"num_quads": 8}, {"num_quads": 3, "randomize": True, "downwash": True},
                                {"num_quads": 8, "noise": {"stochastic_collisions": False}, "sim_hz": 300},
                                {"num_quads": 2, "motor_start": "hover"}])
def test_single_env_episodes_are_the_small_loop_and_per_substep_ops_bitwise(kw):
    got = _episode(True, True, 3, **kw)
    floor = np.concatenate([np.ravel(x) for x in got if np.asarray(x).dtype == bool])
    assert floor.any() and not floor.all()  # quads on the floor and in the air
    for ref in (_episode(False, True, 3, **kw), _episode(False, False, 3, **kw)):
        assert len(got) == len(ref)
        for a, b in zip(got, ref):
            _same(a, b)


def test_deep_copy_steps_as_the_original():
    env = QuadSwarmEnv(EnvConfig(num_quads=4))
    env.reset(seed=1)
    rng = np.random.default_rng(2)
    for _ in range(30):
        env.step(rng.uniform(-1, 1, (4, 4)))
    twin = copy.deepcopy(env)
    actions = rng.uniform(-1, 1, (40, 4, 4))
    for a in actions:
        o1, r1, *_ = env.step(a)
        o2, r2, *_ = twin.step(a)
        _same(o1, o2)
        assert r1 == r2
    assert not np.shares_memory(env.core.qpos, twin.core.qpos)
