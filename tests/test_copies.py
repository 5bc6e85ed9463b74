"""Copies are copies (issue 32 item 4): ``copy.deepcopy`` and ``pickle`` of every front end give an
independent env that steps exactly like the original from that point (50 steps, identical
observations and rewards), or a clear TypeError where a copy cannot be honest (worker processes,
the "batch" back end)."""

from __future__ import annotations

import copy
import pickle

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, QuadSwarmEnv, QuadSwarmParallelEnv, QuadSwarmVectorEnv

STEPS = 50


def _deepcopy(env):
    return copy.deepcopy(env)


def _pickle(env):
    return pickle.loads(pickle.dumps(env))


COPIERS = [pytest.param(_deepcopy, id="deepcopy"), pytest.param(_pickle, id="pickle")]


def _actions(shape: tuple[int, ...], seed: int = 3) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1.0, 1.0, size=(STEPS,) + shape).astype(np.float32)


def _run_pair(env, twin, actions) -> None:
    """Step ``env`` and its copy alternately with the same actions: every output must agree (a shared
    state would advance twice per pair, a cut-loose one not at all)."""
    for a in actions:
        o1, r1, _, t1, i1 = env.step(a)
        o2, r2, _, t2, i2 = twin.step(a)
        np.testing.assert_array_equal(o1, o2)
        np.testing.assert_array_equal(r1, r2)
        np.testing.assert_array_equal(t1, t2)
        np.testing.assert_array_equal(i1["state"]["pos"], i2["state"]["pos"])
        if np.ndim(t1) == 0 and t1:
            env.reset()
            twin.reset()


def _moved(env_infos_pos_before: np.ndarray, pos_after: np.ndarray) -> None:
    assert np.abs(pos_after - env_infos_pos_before).max() > 1e-3, "the quads did not move"


# ------------------------------------------------------------------ MuJoCo engine
@pytest.mark.parametrize("copier", COPIERS)
@pytest.mark.parametrize("collision_model", ["paper", "mujoco"])
def test_single_env_copy_steps_like_original(copier, collision_model):
    env = QuadSwarmEnv(num_quads=3, collision_model=collision_model, episode_seconds=0.3)
    env.reset(seed=7)
    for a in _actions((3, 4), seed=1)[:5]:
        env.step(a)
    twin = copier(env)
    assert twin.core.data is not env.core.data
    pos0 = env.core.kinematics()[0].copy()
    _run_pair(env, twin, _actions((3, 4)))
    _moved(pos0, twin.core.kinematics()[0])


@pytest.mark.parametrize("copier", COPIERS)
def test_gym_make_env_copy_steps_like_original(copier):
    """What users copy: the wrapped env ``gym.make`` returns (order enforcing, passive checker)."""
    import gymnasium as gym

    env = gym.make("QuadSwarm-v0", num_quads=3)
    env.reset(seed=7)
    twin = copier(env)
    assert twin.unwrapped.core.data is not env.unwrapped.core.data
    pos0 = env.unwrapped.core.kinematics()[0].copy()
    _run_pair(env, twin, _actions((3, 4)))
    _moved(pos0, twin.unwrapped.core.kinematics()[0])


@pytest.mark.parametrize("copier", COPIERS)
def test_single_env_copy_before_reset_and_with_renderer_state(copier):
    env = QuadSwarmEnv(num_quads=2)
    twin = copier(env)  # never reset: both must start the same from the same seed
    o1, _ = env.reset(seed=5)
    o2, _ = twin.reset(seed=5)
    np.testing.assert_array_equal(o1, o2)
    _run_pair(env, twin, _actions((2, 4))[:10])


@pytest.mark.parametrize("copier", COPIERS)
def test_parallel_env_copy_steps_like_original(copier):
    env = QuadSwarmParallelEnv(num_quads=2)
    env.reset(seed=11)
    twin = copier(env)
    for a in _actions((2, 4)):
        acts = {f"quad_{i}": a[i] for i in range(2)}
        o1, r1, _, _, _ = env.step(acts)
        o2, r2, _, _, _ = twin.step(acts)
        for k in o1:
            np.testing.assert_array_equal(o1[k], o2[k])
        assert r1 == r2
    np.testing.assert_array_equal(env.state(), twin.state())


@pytest.mark.parametrize("copier", COPIERS)
def test_vector_env_copy_steps_like_original(copier):
    # episodes of 20 steps: the 50 steps include two same-step auto-resets (drawn from the copied generators)
    env = QuadSwarmVectorEnv(EnvConfig(num_quads=2, episode_seconds=0.2), num_envs=3, num_shards=1)
    try:
        env.reset(seed=2)
        env.step(_actions((3, 2, 4))[0])
        twin = copier(env)
        try:
            pos0 = env._a["state/pos"].copy()
            _run_pair(env, twin, _actions((3, 2, 4)))
            _moved(pos0, twin._a["state/pos"])
            m1, m2 = env.episode_metrics(), twin.episode_metrics()
            for k in m1:
                np.testing.assert_array_equal(m1[k], m2[k])
        finally:
            twin.close()
        env.step(_actions((3, 2, 4))[1])  # the original still works after its copy is closed
    finally:
        env.close()


@pytest.mark.parametrize("copier", COPIERS)
def test_vector_env_with_workers_copy_steps_like_original(copier):
    env = QuadSwarmVectorEnv(EnvConfig(num_quads=2, episode_seconds=0.2), num_envs=3, num_shards=2)
    try:
        env.reset(seed=5)
        env.step(_actions((3, 2, 4))[0])
        twin = copier(env)
        try:
            assert {w.proc.pid for w in twin._res.workers}.isdisjoint(w.proc.pid for w in env._res.workers)
            _run_pair(env, twin, _actions((3, 2, 4)))
            m1, m2 = env.episode_metrics(), twin.episode_metrics()
            for k in m1:
                np.testing.assert_array_equal(m1[k], m2[k])
        finally:
            twin.close()
        env.step(_actions((3, 2, 4))[1])
    finally:
        env.close()


def test_batch_backend_and_closed_env_refuse_copy():
    env = QuadSwarmVectorEnv(EnvConfig(num_quads=1), num_envs=4, num_shards=2, backend="batch", chunk_worlds=1)
    try:
        env.reset(seed=0)
        with pytest.raises(TypeError, match="batch"):
            copy.deepcopy(env)
        env.step(np.zeros((4, 1, 4)))  # the refused copy changed nothing
    finally:
        env.close()
    with pytest.raises(TypeError, match="closed"):
        copy.deepcopy(env)


# ------------------------------------------------------------------ JAX engine
@pytest.fixture(scope="module")
def jax_single():
    env = QuadSwarmEnv(num_quads=2, engine="jax")
    env.reset(seed=4)
    yield env
    env.close()


@pytest.mark.parametrize("copier", COPIERS)
def test_jax_single_env_copy_steps_like_original(jax_single, copier):
    env = jax_single
    env.reset(seed=4)
    env.step(_actions((2, 4))[0])
    twin = copier(env)
    _run_pair(env, twin, _actions((2, 4)))


@pytest.mark.parametrize("copier", COPIERS)
def test_jax_vector_env_copy_steps_like_original(copier):
    env = QuadSwarmVectorEnv(EnvConfig(num_quads=2, episode_seconds=0.2), num_envs=2, num_shards=1, engine="jax")
    try:
        env.reset(seed=9)
        twin = copier(env)
        try:
            _run_pair(env, twin, _actions((2, 2, 4)))
        finally:
            twin.close()
    finally:
        env.close()


def test_jax_vector_env_with_workers_refuses_copy():
    env = QuadSwarmVectorEnv(EnvConfig(num_quads=1), num_envs=2, num_shards=2, engine="jax")
    try:
        for copier in (copy.deepcopy, pickle.dumps):
            with pytest.raises(TypeError, match="worker processes"):
                copier(env)
    finally:
        env.close()


def test_failed_vector_env_copies_to_an_env_that_needs_reset():
    env = QuadSwarmVectorEnv(EnvConfig(num_quads=1), num_envs=2, num_shards=2)
    try:
        env.reset(seed=0)
        env._res.workers[0].proc.kill()
        env._res.workers[0].proc.join()
        with pytest.raises(RuntimeError):
            env.step(np.zeros((2, 1, 4)))
        twin = copy.deepcopy(env)
        try:
            with pytest.raises(RuntimeError, match="reset"):
                twin.step(np.zeros((2, 1, 4)))
            o1, _ = twin.reset(seed=3)
            o2, _ = env.reset(seed=3)
            np.testing.assert_array_equal(o1, o2)
        finally:
            twin.close()
    finally:
        env.close()


def test_copy_keeps_the_instability_check_on_its_own_data():
    """The copy's instability check reads its own MjData (the warning counters and accelerations are views)."""
    from quadswarm_mj.envs.cpu_core import PhysicsInstabilityError

    env = QuadSwarmEnv(num_quads=2)
    env.reset(seed=0)
    twin = copy.deepcopy(env)
    phys = twin.unwrapped.core.phys
    assert np.shares_memory(phys._bad_counts, phys.data.warning.number)
    assert np.shares_memory(phys._qacc, phys.data.qacc)
    phys.qvel[0, 1, 3:] = 1e12  # bypasses validation: MuJoCo must flag it on the copy's data
    with pytest.raises(PhysicsInstabilityError, match="world 0, quad 1"):
        twin.step(np.zeros((2, 4)))
    env.step(np.zeros((2, 4)))  # the original is untouched
