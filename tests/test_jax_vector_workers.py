"""QuadSwarmVectorEnv(engine="jax", num_shards=k >= 2): the worlds in k worker processes (one
single-device JAX program per CPU core). Same seeds, same results as the in-process engine (bit for
bit at 8 quads and an even number of worlds per worker); the returned arrays are the caller's (no
later step writes into them) while the output blocks are reused once dropped; a dead worker is
reported and the env rebuilt by reset()."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytest.importorskip("mujoco.mjx")

from quadswarm_mj import EnvConfig, QuadSwarmVectorEnv  # noqa: E402
from quadswarm_mj.envs.jax_engine import MAX_OUTPUT_BLOCKS, MIN_WORLDS_PER_WORKER, WorkerWorlds  # noqa: E402
from quadswarm_mj.envs.vector_env import WorkerError, _default_jax_shards  # noqa: E402

B = 4
CFG = EnvConfig(num_quads=8, episode_seconds=0.2, randomize=True)  # all noise on, 20-step episodes
STEPS = 45  # two episode ends


@pytest.fixture(scope="module")
def envs():
    local = QuadSwarmVectorEnv(CFG, num_envs=B, engine="jax", num_shards=1)
    workers = QuadSwarmVectorEnv(CFG, num_envs=B, engine="jax", num_shards=2)
    yield local, workers
    local.close()
    workers.close()


def _leaves(x):
    return jax.tree.leaves(x)


def _assert_same(a, b):
    la, lb = _leaves(a), _leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb):
        np.testing.assert_array_equal(x, y)


def test_workers_equal_in_process_bit_for_bit(envs):
    local, workers = envs
    assert isinstance(workers._jax._worlds, WorkerWorlds) and workers.num_shards == 2
    rng = np.random.default_rng(0)
    _assert_same(local.reset(seed=5), workers.reset(seed=5))
    ends = 0
    for _ in range(STEPS):
        a = rng.uniform(-1, 1, (B, CFG.num_quads, 4)).astype(np.float32)
        out_l, out_w = local.step(a), workers.step(a)
        _assert_same(out_l, out_w)
        ends += "final_obs" in out_w[4]
    assert ends == 2
    _assert_same(local.episode_metrics(), workers.episode_metrics())
    # a partial reset from a given state, then steps
    mask = np.array([True, False, False, True])
    state = {"pos": np.tile([0.0, 0.0, 1.0], (B, CFG.num_quads, 1)) + rng.normal(0, 0.3, (B, CFG.num_quads, 3)),
             "motors": "hover"}
    _assert_same(local.reset(options={"reset_mask": mask, "state": state}),
                 workers.reset(options={"reset_mask": mask, "state": state}))
    for _ in range(5):
        a = rng.uniform(-1, 1, (B, CFG.num_quads, 4)).astype(np.float32)
        _assert_same(local.step(a), workers.step(a))


def test_returned_arrays_are_kept_and_blocks_reused(envs):
    _, env = envs
    worlds = env._jax._worlds
    env.reset(seed=1)
    hover = np.full((B, CFG.num_quads, 4), CFG.quad.hover_action, np.float32)
    kept = []
    for _ in range(MAX_OUTPUT_BLOCKS + 4):  # more live steps than output blocks: the rest are copied
        obs, reward, _, _, info = env.step(hover)
        kept.append((obs, info["state"]["pos"], obs.copy(), info["state"]["pos"].copy()))
    for obs, pos, obs0, pos0 in kept:  # no later step wrote into an earlier step's arrays
        np.testing.assert_array_equal(obs, obs0)
        np.testing.assert_array_equal(pos, pos0)
    assert len(worlds.blocks) == MAX_OUTPUT_BLOCKS + 1  # + the scratch block
    kept.clear()
    for _ in range(50):  # dropped outputs free their blocks: no new ones
        env.step(hover)
    assert len(worlds.blocks) == MAX_OUTPUT_BLOCKS + 1
    assert sum(worlds.free) >= MAX_OUTPUT_BLOCKS - 2


def test_default_split():
    assert _default_jax_shards(B) == 1  # few worlds: in this process
    cores = len(os.sched_getaffinity(0))
    assert _default_jax_shards(2 * MIN_WORLDS_PER_WORKER) == (2 if cores >= 2 else 1)
    with pytest.raises(ValueError, match="num_shards"):
        QuadSwarmVectorEnv(CFG, num_envs=B, engine="jax", num_shards=0)


def test_dead_worker_reported_then_rebuilt_by_reset():
    env = QuadSwarmVectorEnv(CFG, num_envs=2, engine="jax", num_shards=2)
    try:
        hover = np.full((2, CFG.num_quads, 4), CFG.quad.hover_action, np.float32)
        obs0, _ = env.reset(seed=3)
        env.step(hover)
        proc = env._jax._worlds.res.workers[1].proc
        os.kill(proc.pid, signal.SIGKILL)
        proc.join(5)
        with pytest.raises(WorkerError, match=r"worker 1 .* was killed by signal SIGKILL during (step|map)"):
            env.step(hover)
        with pytest.raises(RuntimeError, match="must be reset"):
            env.step(hover)
        obs1, _ = env.reset(seed=3)  # new workers, same seed: the same first observation
        np.testing.assert_array_equal(obs0, obs1)
        env.step(hover)
        worlds = env._jax._worlds
        procs = [w.proc for w in worlds.res.workers]
        names = [b.name.lstrip("/") for b in worlds.blocks]
        assert len(names) >= 2
        for name in names:  # every block unlinked once the workers mapped it: nothing left in /dev/shm
            assert not os.path.exists(os.path.join("/dev/shm", name))
    finally:
        env.close()
    assert all(p.exitcode is not None for p in procs)  # close() ended the workers
