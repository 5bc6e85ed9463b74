"""Collision replay buffer (quadswarm_mj.training.replay) on batched env states.

The buffer functions only read ``done``, ``reward``, ``metrics`` and a few ``info`` keys of the env's
``State`` pytree, so these tests drive them with a hand-made batch of ``State``\\ s (a small ``data``
leaf that encodes the step at which it was taken) instead of compiling the MJX env; the trainer's
tests run them inside the jitted loop on ``MjxQuadSwarmEnv``."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("brax")

from quadswarm_mj.envs.mjx_env import State  # noqa: E402
from quadswarm_mj.training.replay import (  # noqa: E402
    CARRIED_INFO,
    ReplayConfig,
    init_replay,
    record,
    restart,
)

W, N, DT = 3, 2, 0.01
# snapshot every 2 steps, write the snapshot 2 snapshots before the hit, no grace time, no cooldown
RC = ReplayConfig(prob=1.0, buffer_size=4, snapshot_s=0.02, snapshots_back=2, max_replays=2, cooldown_s=0.0,
                  min_time_s=0.0)


def _state(step: np.ndarray, contact: np.ndarray | None = None, done: np.ndarray | None = None) -> State:
    """A batch of W fake world states at per-world control ``step``; ``data``/``obs`` encode world and step."""
    step = np.asarray(step, np.int32)
    tag = (np.arange(W)[:, None] * 1000 + step[:, None]).astype(np.float32)
    c = np.zeros((W, N, N), bool) if contact is None else contact
    obs = np.repeat(tag[:, None], N, 1).repeat(5, -1)
    return State(data={"qpos": jnp.asarray(np.repeat(tag, 7 * N, axis=1))}, obs=jnp.asarray(obs),
                 reward=jnp.full((W, N), -0.5, jnp.float32),
                 done=jnp.asarray(np.zeros(W, bool) if done is None else done),
                 metrics={"reward/quad_collision": jnp.zeros((W, N), jnp.float32)},
                 info={"contact": jnp.asarray(c), "time": jnp.asarray(step * DT, jnp.float32),
                       "step": jnp.asarray(step),
                       "total_steps": jnp.asarray(step + 10_000), "episode_metrics": {"success": jnp.zeros(W)},
                       "truncation": jnp.zeros(W), "rng": jnp.asarray(np.tile(np.arange(2, dtype=np.uint32), (W, 1)))})


_record = jax.jit(lambda rs, prev, s, key: record(rs, prev, s, RC, DT, key))
_restart = jax.jit(lambda rs, s, key: restart(rs, s, RC, key))


def _run(steps: int, hits: dict[int, list[int]]) -> tuple:
    """Advance all worlds ``steps`` steps; at step k the worlds in ``hits[k]`` get a new contact."""
    prev = _state(np.zeros(W))
    rs = init_replay(prev, RC)
    key = jax.random.PRNGKey(0)
    for k in range(1, steps + 1):
        c = np.zeros((W, N, N), bool)
        for w in hits.get(k, []):
            c[w, 0, 1] = c[w, 1, 0] = True
        s = _state(np.full(W, k), c)
        key, sub = jax.random.split(key)
        rs = _record(rs, prev, s, sub)
        prev = s
    return rs, prev


def test_collision_writes_the_snapshot_from_before_the_hit():
    # snapshots at steps 2, 4, 6, ...; a hit at step 7 in world 1 writes the snapshot 2 snapshots before the
    # latest (6): the one of step 4
    rs, _ = _run(8, {7: [1]})
    assert int(rs.added) == 1 and np.asarray(rs.valid).tolist() == [True, False, False, False]
    entry = jax.tree.map(lambda b: b[0], rs.buf)
    assert float(entry.data["qpos"][0]) == 1000 * 1 + 4 and int(entry.info["step"]) == 4
    # an ongoing contact (no new pair) does not write again
    assert int(rs.ptr) == 1


def test_buffer_fills_on_forced_collisions_and_wraps():
    hits = {5: [0], 7: [1, 2], 9: [2], 11: [0], 13: [1]}  # 6 triggering world-steps, one write per step
    rs, _ = _run(14, hits)
    assert int(rs.added) == 5  # step 7 had two triggering worlds: one written
    assert np.asarray(rs.valid).all() and int(rs.ptr) == 5 % RC.buffer_size
    steps = sorted(int(x) for x in np.asarray(rs.buf.info["step"]))
    # the ring of 4 holds the last 4 writes: hits at 7, 9, 11, 13 -> snapshots of steps 4, 6, 8, 10
    assert steps == [4, 6, 8, 10]


def test_no_write_before_enough_snapshots_or_in_grace_time():
    rs, _ = _run(3, {3: [0]})  # only one snapshot taken (step 2): fewer than snapshots_back
    assert int(rs.added) == 0
    rc = ReplayConfig(prob=1.0, buffer_size=4, snapshot_s=0.02, snapshots_back=2, cooldown_s=0.0, min_time_s=1.0)
    prev = _state(np.zeros(W))
    rs = init_replay(prev, rc)
    for k in range(1, 10):
        c = np.zeros((W, N, N), bool)
        c[0, 0, 1] = k == 9
        s = _state(np.full(W, k), c)
        rs = record(rs, prev, s, rc, DT, jax.random.PRNGKey(k))
        prev = s
    assert int(rs.added) == 0  # t = 0.09 s < min_time_s


def test_replayed_world_state_equals_the_saved_state():
    rs, prev = _run(8, {7: [1]})
    saved = jax.tree.map(lambda b: b[0], rs.buf)
    # world 0's episode ends at the next step: its state is a fresh episode (step 0), done True
    s = _state(np.array([0, 9, 9]), done=np.array([True, False, False]))
    rs = _record(rs, prev, s, jax.random.PRNGKey(1))
    out, rs2, mask = _restart(rs, s, jax.random.PRNGKey(2))
    assert np.asarray(mask).tolist() == [True, False, False]
    w0 = jax.tree.map(lambda x: x[0], out)
    np.testing.assert_array_equal(w0.data["qpos"], saved.data["qpos"])
    np.testing.assert_array_equal(w0.obs, saved.obs)
    for k, v in saved.info.items():
        if k not in CARRIED_INFO:
            for a, b in zip(jax.tree.leaves(w0.info[k]), jax.tree.leaves(v)):
                np.testing.assert_array_equal(a, b)
    # carried from the step: the annealing clock, done, reward; the other worlds are untouched
    assert int(w0.info["total_steps"]) == 10_000 and bool(w0.done) and float(w0.reward[0]) == -0.5
    for a, b in zip(jax.tree.leaves(jax.tree.map(lambda x: x[1:], out)), jax.tree.leaves(jax.tree.map(lambda x: x[1:],
                                                                                                       s))):
        np.testing.assert_array_equal(a, b)
    assert int(rs2.count[0]) == 1 and bool(rs2.replaying[0]) and int(rs2.replayed) == 1
    # a replay episode takes no snapshots and triggers no write
    c = np.zeros((W, N, N), bool)
    c[0, 0, 1] = c[0, 1, 0] = True
    s2 = _state(np.array([6, 10, 10]), c)
    rs3 = _record(rs2, out, s2, jax.random.PRNGKey(3))
    assert int(rs3.added) == int(rs2.added) and int(rs3.n_snap[0]) == 0


def test_entries_replayed_max_times_are_dropped_and_prob_zero_never_replays():
    rs, prev = _run(8, {7: [1]})
    s = _state(np.zeros(W), done=np.ones(W, bool))  # all three worlds end: 3 replays of the only entry >= 2
    rs = _record(rs, prev, s, jax.random.PRNGKey(1))
    out, rs2, mask = _restart(rs, s, jax.random.PRNGKey(2))
    assert np.asarray(mask).all() and int(rs2.count[0]) == 3 and not bool(rs2.valid[0])
    out, rs3, mask = _restart(rs2, s, jax.random.PRNGKey(3))  # empty buffer: fresh episodes
    assert not np.asarray(mask).any()
    rc0 = ReplayConfig(prob=0.0)
    assert not rc0.enabled
    _, _, mask = restart(rs, s, ReplayConfig(prob=0.0, buffer_size=4), jax.random.PRNGKey(4))
    assert not np.asarray(mask).any()


def test_replay_config_validation():
    with pytest.raises(ValueError, match="replay.prob"):
        ReplayConfig(prob=1.5)
    with pytest.raises(ValueError, match="replay.buffer_size"):
        ReplayConfig(buffer_size=0)
    with pytest.raises(ValueError, match="replay.snapshot_s"):
        ReplayConfig(snapshot_s=0.0)


@pytest.mark.slow
def test_buffer_fills_on_a_forced_head_on_collision_in_the_jax_engine():
    """MjxQuadSwarmEnv: two quads flying head-on collide; the buffer receives the snapshot taken before the
    hit (equal to the state the env had then), and a world restarted from it steps on from there."""
    from quadswarm_mj.config import EnvConfig
    from quadswarm_mj.envs.mjx_env import AutoResetWrapper, MjxQuadSwarmEnv

    cfg = EnvConfig(num_quads=2, scenario="static_diff_goal", episode_seconds=1.0, motor_start="hover").without_noise()
    env = AutoResetWrapper(MjxQuadSwarmEnv(cfg))
    init = {"pos": np.array([[-0.25, 0.0, 2.0], [0.25, 0.0, 2.0]]), "vel": np.array([[2.0, 0, 0], [-2.0, 0, 0]])}
    rc = ReplayConfig(prob=1.0, buffer_size=4, snapshot_s=0.02, snapshots_back=2, cooldown_s=0.0, min_time_s=0.0)
    reset = jax.jit(jax.vmap(lambda k: env.reset(k, init)))
    step = jax.jit(env.vstep)
    rec = jax.jit(lambda rs, p, s, k: record(rs, p, s, rc, cfg.control_dt, k))
    s = reset(jax.random.split(jax.random.PRNGKey(0), 2))
    rs = init_replay(s, rc)
    hover = jnp.full((2, 2, 4), cfg.quad.hover_action)
    qpos = {0: np.asarray(s.data.qpos)}
    for k in range(1, 25):
        prev, s = s, step(s, hover)
        qpos[k] = np.asarray(s.data.qpos)
        rs = rec(rs, prev, s, jax.random.PRNGKey(k))
        if int(rs.added):
            break
    assert int(rs.added) >= 1, "the head-on quads never collided"
    hit = k
    entry = jax.tree.map(lambda b: b[0], rs.buf)
    snap_step = int(entry.info["step"])
    assert snap_step % 2 == 0 and hit - 6 <= snap_step < hit  # 2 snapshots (0.02 s apart) before the last one
    w = int(np.argmax([np.array_equal(np.asarray(entry.data.qpos), qpos[snap_step][i]) for i in range(2)]))
    np.testing.assert_array_equal(np.asarray(entry.data.qpos), qpos[snap_step][w])
    # restart world 0 from the entry and step on
    s_done = s.replace(done=jnp.array([True, False]))
    out, _, mask = restart(rs, s_done, rc, jax.random.PRNGKey(99))
    assert bool(mask[0])
    np.testing.assert_array_equal(np.asarray(out.data.qpos[0]), np.asarray(entry.data.qpos))
    nxt = step(out, hover)
    assert int(nxt.info["step"][0]) == snap_step + 1 and np.isfinite(np.asarray(nxt.obs)).all()
