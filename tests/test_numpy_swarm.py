"""quadswarm_mj.perf.numpy_swarm (the one-world sub-step loop on work arrays made once) gives the bits of
``perf.numpy_loop.SmallLoop`` and of the per-sub-step ops over whole seeded runs of single envs of
several quads with random actions (floor hits, staying on the floor, lift-offs, collisions), and the
env steps on as before after a deep copy (the cached views of MuJoCo's arrays are made again)."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from episode_record import record_random_run, record_three_world_run

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.envs.gym_env import QuadSwarmEnv
from quadswarm_mj.perf import numpy_loop, numpy_swarm, numpy_swarm_task
from quadswarm_mj.perf.numpy_swarm import SwarmLoop
from quadswarm_mj.perf.numpy_swarm_task import SwarmTask


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


def _task_episode(enabled: bool, seed: int, **kw) -> list:
    numpy_swarm_task.ENABLED = enabled
    try:
        env = QuadSwarmEnv(EnvConfig(**{"episode_seconds": 2.0, **kw}))
        assert isinstance(env.core._ops.fused_task, SwarmTask) == enabled
        return record_random_run(env, seed, 450, lambda obs, r, info: [
            obs, r, info["rewards"], *info["reward_terms"].values(), info["new_collisions"]])
    finally:
        numpy_swarm_task.ENABLED = True


@pytest.mark.parametrize("kw", [
    {"num_quads": 8},
    {"num_quads": 8, "scenario": "swap_goals", "room_size": (3.0, 3.0, 3.0)},  # goal jumps, collisions
    {"num_quads": 3, "obs_self": "floor", "normalize_obs": True, "num_neighbors": 1, "scenario": "dynamic_same_goal",
     "rewards": {"vel": 0.5, "action_change": 0.2, "yaw": 0.1, "rot": 0.3, "floor_hit": 1.0, "anneal_steps": 300}},
    {"num_quads": 4, "noise": {"sensor_pos_std": 0.0, "sensor_vel_std": 0.0, "sensor_omega_std": 0.0},
     "rewards": {"pos": 0.0, "proximity": 0.0}, "num_neighbors": 0},
    {"num_quads": 6, "room_size": (2.0, 2.0, 2.0)},  # crowded: proximity and collisions
    {"num_quads": 4, "scenario": "run_away", "episode_seconds": 4.0},  # goal jumps (metric segments)
    {"num_quads": 4, "sensors": {"multiranger": True, "flow": True}},  # the decks' part, noise drawn last
    {"num_quads": 3, "room_size": (2.0, 2.0, 2.0), "sensors": {"multiranger": True, "depth": (4, 6), "noise": False}},
])
def test_task_episodes_are_the_model_functions_bitwise(kw):
    got, ref = _task_episode(True, 4, **kw), _task_episode(False, 4, **kw)
    assert len(got) == len(ref)
    for a, b in zip(got, ref):
        _same(a, b)


def test_task_several_worlds_are_the_model_functions_bitwise():
    from quadswarm_mj.envs.cpu_core import CpuSwarm

    out = []
    for enabled in (True, False):
        numpy_swarm_task.ENABLED = enabled
        try:
            core = CpuSwarm(EnvConfig(num_quads=4, scenario="swap_goals"), num_worlds=3, visual=False)
            assert isinstance(core._ops.fused_task, SwarmTask) == enabled
            out.append(record_three_world_run(core, lambda c, o: [o["obs"], o["rewards"], *o["terms"].values(),
                                                                 *c.episode_metrics().values()]))
        finally:
            numpy_swarm_task.ENABLED = True
    for a, b in zip(*out):
        _same(a, b)


def test_action_to_command_is_the_model_form_bitwise():
    from quadswarm_mj.actuation import action_to_command

    rng = np.random.default_rng(0)
    a = np.concatenate([rng.uniform(-3, 3, 400), [-0.0, 0.0, -1.0, 1.0, -1.5, 1.5, 1e-300, -1e-300, np.inf, -np.inf]])
    _same(numpy_swarm.action_to_command(a.reshape(-1, 2, 1)), action_to_command(a.reshape(-1, 2, 1)))


def test_motor_noise_step_is_the_model_form_bitwise():
    from quadswarm_mj.actuation import motor_noise_step

    rng = np.random.default_rng(1)
    eps = np.concatenate([rng.normal(0, 0.1, (5, 3, 4)), np.full((1, 3, 4), -0.0)])
    sigma, normal = rng.uniform(0, 0.2, (6, 3)), rng.standard_normal((6, 3, 4))
    sigma[0, 0], normal[1] = 0.0, -0.0
    _same(numpy_swarm.motor_noise_step(eps, sigma, 0.15, normal), motor_noise_step(eps, sigma, 0.15, normal))


_SPECIAL = np.array([0.0, -0.0, np.nan, np.inf, -np.inf, 1.0, -1.0, 5e-324, -5e-324, 2.5, 1e-9])


def test_clip_forms_are_the_max_min_they_replace_bitwise():
    """perf.numpy_swarm(_task) write max(0, x), min(a, x) and min(max(x, lo), hi) as NumPy's clip ufunc, with
    0-d bounds (floor wrench) or bounds of x's shape (the observation's bounds): the same bits on special
    values, signs of zero and NaN included, in exactly those call forms."""
    from quadswarm_mj.perf.numpy_swarm import _clip

    a, b = (x.ravel() for x in np.meshgrid(_SPECIAL, _SPECIAL))
    zero, inf, ninf = np.zeros(()), np.full((), np.inf), np.full((), -np.inf)
    _same(_clip(a, zero, inf, np.empty_like(a)), np.maximum(0.0, a))  # normal, static friction
    _same(_clip(b, ninf, a, np.empty_like(a)), np.minimum(b, a))  # kinetic friction: min(cap, x)
    for x in _SPECIAL:  # the observation's bounds: lo, hi of the observation's own shape
        _same(_clip(np.full(a.shape, x), a, b), np.minimum(np.maximum(np.full(a.shape, x), a), b))


def test_event_free_stages_are_the_model_stages_bitwise():
    """SwarmLoop.stages (gathered pair rows, left-to-right sums) gives velocity_stages' flags and distances."""
    from quadswarm_mj.core.step import velocity_stages

    env = QuadSwarmEnv(EnvConfig(num_quads=5))
    env.reset(seed=3)
    loop = env.core._ops._swarm_loop
    rng = np.random.default_rng(4)
    pos = rng.uniform(-1.0, 1.0, (1, 5, 3)) + np.array([0.0, 0.0, 2.0])
    pos[0, 1] = pos[0, 0] + [0.0, -0.0, 1e-3]  # a pair in contact
    z = np.zeros((1, 5), bool)
    kin = {"pos": pos, "vel": np.zeros((1, 5, 3)), "omega": np.zeros((1, 5, 3)), "R": np.tile(np.eye(3), (1, 5, 1, 1)),
           "quat": np.tile([1.0, 0, 0, 0], (1, 5, 1)), "u": np.zeros((1, 5, 4)), "on_floor": z, "hit_floor": z}
    prev = {"on_floor": z, "at_wall": z, "at_ceiling": z, "contact": np.zeros((1, 5, 5), bool)}
    assert loop.stages(env.cfg, kin, prev) is None  # a contact starts: the model's response runs
    prev["contact"] = loop.stages(env.cfg, kin, {**prev, "contact": np.ones((1, 5, 5), bool)})["contact"]
    got, ref = loop.stages(env.cfg, kin, prev), velocity_stages(env.cfg, kin, prev, env.core._ops)
    assert got["contact"].any()
    for key in ("contact", "new_contact", "dist", "at_wall", "at_ceiling", "hit_wall", "hit_ceiling"):
        _same(got[key], ref[key])
