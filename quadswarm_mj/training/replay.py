"""Replay of collision episodes on the JAX engine (SPEC_obstacles C.2, adapted to fixed shapes under ``jit``).

Inside the trainer's jitted loop on W worlds of one :class:`~quadswarm_mj.envs.mjx_env.MjxQuadSwarmEnv`:
every ``snapshot_s`` of episode time each world not in a replay episode saves its ``State`` into its ring
of ``snapshots_back`` slots (``ReplayState.ring``, leaves (W, S, ...)); a new collision after
``min_time_s`` (and ``cooldown_s`` after the world's last write) stores the snapshot from 1-1.5 s before
the hit in a ring of ``buffer_size`` entries (``ReplayState.buf``, leaves (R, ...)); a world whose episode
ended restarts from a stored entry with probability ``prob``; entries replayed ``max_replays`` times are
dropped. The rules in full and the differences from the original: docs/training.md ("Collision replay").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp

#: info keys a restarted world keeps from the step that ended its episode (see the module docstring).
CARRIED_INFO = ("total_steps", "episode_metrics", "truncation", "rng")
#: reward terms whose negative value marks a collision
COLLISION_TERMS = ("reward/quad_collision", "reward/obstacle_collision")


@dataclass(frozen=True)
class ReplayConfig:
    """Collision replay settings (SPEC_obstacles C.2 values as defaults, ``prob`` 0 disables it)."""

    prob: float = 0.75  # probability that an episode end restarts from the buffer
    buffer_size: int = 20  # saved events per batch of worlds
    snapshot_s: float = 0.5  # s of episode time between snapshots
    snapshots_back: int = 3  # the snapshot written is this many snapshots before the hit (3 x 0.5 s = 1.5 s)
    max_replays: int = 10  # an entry replayed this many times is dropped
    cooldown_s: float = 5.0  # s between two writes of one world
    min_time_s: float = 1.5  # s: collisions earlier in the episode do not trigger a write

    def __post_init__(self) -> None:
        if not (isinstance(self.prob, (int, float)) and 0.0 <= self.prob <= 1.0):
            raise ValueError(f"replay.prob must be in [0, 1], got {self.prob!r}")
        for n in ("buffer_size", "snapshots_back", "max_replays"):
            v = getattr(self, n)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"replay.{n} must be an int >= 1, got {v!r}")
        for n in ("snapshot_s", "cooldown_s", "min_time_s"):
            v = getattr(self, n)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"replay.{n} must be a finite number >= 0 (s), got {v!r}")
        if self.snapshot_s <= 0:
            raise ValueError(f"replay.snapshot_s must be > 0 (s), got {self.snapshot_s!r}")

    @property
    def enabled(self) -> bool:
        return self.prob > 0

    def snapshot_steps(self, control_dt: float) -> int:
        """Control steps between snapshots (>= 1)."""
        return max(1, int(round(self.snapshot_s / control_dt)))


@jax.tree_util.register_dataclass
@dataclass
class ReplayState:
    """Replay buffers of W worlds (a pytree; see the module docstring)."""

    ring: Any  # State, leaves (W, S, ...): the last S snapshots of each world
    n_snap: jax.Array  # (W,) int32 snapshots taken in the current episode
    last_add: jax.Array  # (W,) float episode time (s) of the world's last write, -inf if none this episode
    replaying: jax.Array  # (W,) bool: the current episode is a replay
    buf: Any  # State, leaves (R, ...): saved events
    valid: jax.Array  # (R,) bool
    count: jax.Array  # (R,) int32 times replayed
    ptr: jax.Array  # () int32 next buffer slot to write
    added: jax.Array  # () int32 writes so far
    replayed: jax.Array  # () int32 restarts so far


def _is_key(x: Any) -> bool:
    return jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _where(pred: jax.Array, a: jax.Array, b: jax.Array) -> jax.Array:
    """``where(pred, a, b)`` with ``pred`` broadcast over the trailing axes of ``a``; typed keys too."""
    if _is_key(a):
        data = _where(pred, jax.random.key_data(a), jax.random.key_data(b))
        return jax.random.wrap_key_data(data, impl=jax.random.key_impl(a))
    p = jnp.reshape(pred, jnp.shape(pred) + (1,) * (a.ndim - jnp.ndim(pred)))
    return jnp.where(p, a, b)


def tree_where(pred: jax.Array, a: Any, b: Any) -> Any:
    """Leaf-wise :func:`_where` of two pytrees of the same structure."""
    return jax.tree.map(lambda x, y: _where(pred, x, y), a, b)


def init_replay(state: Any, rcfg: ReplayConfig) -> ReplayState:
    """Empty buffers shaped after a batched env ``State`` (leading axis W)."""
    w = state.done.shape[0]
    s, r = rcfg.snapshots_back, rcfg.buffer_size
    ring = jax.tree.map(lambda x: jnp.stack([x] * s, axis=1), state)
    buf = jax.tree.map(lambda x: jnp.concatenate([x[:1]] * r, axis=0), state)
    f = state.info["time"].dtype
    return ReplayState(ring=ring, n_snap=jnp.zeros((w,), jnp.int32), last_add=jnp.full((w,), -jnp.inf, f),
                       replaying=jnp.zeros((w,), bool), buf=buf, valid=jnp.zeros((r,), bool),
                       count=jnp.zeros((r,), jnp.int32), ptr=jnp.zeros((), jnp.int32), added=jnp.zeros((), jnp.int32),
                       replayed=jnp.zeros((), jnp.int32))


def collision_events(prev: Any, state: Any) -> jax.Array:
    """(W,) bool: a new quad-quad contact pair, or a negative collision reward term, at this step."""
    new = jnp.any(state.info["contact"] & ~prev.info["contact"], axis=(-2, -1))
    for name in COLLISION_TERMS:
        if name in state.metrics:
            new = new | jnp.any(state.metrics[name] < 0, axis=-1)
    return new


def record(rs: ReplayState, prev: Any, state: Any, rcfg: ReplayConfig, control_dt: float,
           key: jax.Array) -> ReplayState:
    """After a step ``prev -> state`` (batched, auto-reset already applied): write a triggered event into
    the buffer, take the due snapshots, and clear the per-episode counters of worlds whose episode ended."""
    w = state.done.shape[0]
    s_slots, r_size = rcfg.snapshots_back, rcfg.buffer_size
    t = state.info["time"]
    live = ~state.done & ~rs.replaying
    trig = (live & collision_events(prev, state) & (t > rcfg.min_time_s) & (t - rs.last_add > rcfg.cooldown_s)
            & (rs.n_snap >= s_slots))
    # write: one triggering world, drawn uniformly
    score = jnp.where(trig, jax.random.uniform(key, (w,)), -1.0)
    wi = jnp.argmax(score)
    any_t = jnp.any(trig)
    slot = (rs.n_snap[wi] - s_slots) % s_slots  # the oldest of the ring: snapshots_back snapshots before
    entry = jax.tree.map(lambda r: r[wi, slot], rs.ring)
    ptr = rs.ptr
    buf = jax.tree.map(lambda b, e: jax.lax.dynamic_update_index_in_dim(b, _where(any_t, e, b[ptr]), ptr, 0),
                       rs.buf, entry)
    valid = rs.valid.at[ptr].set(rs.valid[ptr] | any_t)
    count = rs.count.at[ptr].set(jnp.where(any_t, 0, rs.count[ptr]))
    last_add = jnp.where(trig & (jnp.arange(w) == wi), t, rs.last_add)
    # snapshots every snapshot_steps of episode time
    every = rcfg.snapshot_steps(control_dt)
    take = live & (state.info["step"] % every == 0)
    slot_w = rs.n_snap % s_slots

    def put(ring_w: Any, s_w: Any, take_w: jax.Array, sl: jax.Array) -> Any:
        return jax.tree.map(lambda r, x: r.at[sl].set(_where(take_w, x, r[sl])), ring_w, s_w)

    ring = jax.vmap(put)(rs.ring, state, take, slot_w)
    done = state.done
    return ReplayState(ring=ring, n_snap=jnp.where(done, 0, rs.n_snap + take.astype(jnp.int32)),
                       last_add=jnp.where(done, -jnp.inf, last_add), replaying=rs.replaying & ~done, buf=buf,
                       valid=valid, count=count, ptr=(ptr + any_t.astype(jnp.int32)) % r_size,
                       added=rs.added + any_t.astype(jnp.int32), replayed=rs.replayed)


def restored_state(entry: Any, state: Any) -> Any:
    """The saved ``entry`` with the step's ``done``/``reward``/``metrics`` and the :data:`CARRIED_INFO` of
    ``state`` (same batch shape)."""
    info = {**entry.info, **{k: state.info[k] for k in CARRIED_INFO}}
    return entry.replace(done=state.done, reward=state.reward, metrics=state.metrics, info=info)


def restart(rs: ReplayState, state: Any, rcfg: ReplayConfig, key: jax.Array) -> tuple[Any, ReplayState, jax.Array]:
    """At episode ends (``state.done``), restart worlds from the buffer with probability ``rcfg.prob``.

    Returns (state, replay state, (W,) bool mask of the restarted worlds). Call after :func:`record`.
    """
    w = state.done.shape[0]
    k_u, k_i = jax.random.split(key)
    mask = state.done & (jax.random.uniform(k_u, (w,)) < rcfg.prob) & jnp.any(rs.valid)
    idx = jax.random.categorical(k_i, jnp.where(rs.valid, 0.0, -jnp.inf), shape=(w,))
    idx = jnp.clip(idx, 0, rcfg.buffer_size - 1)

    def swap(st: Any) -> Any:
        entry = jax.tree.map(lambda b: b[idx], rs.buf)
        return tree_where(mask, restored_state(entry, st), st)

    state = jax.lax.cond(jnp.any(mask), swap, lambda st: st, state)
    count = rs.count + jnp.zeros_like(rs.count).at[idx].add(mask.astype(jnp.int32))
    valid = rs.valid & (count < rcfg.max_replays)
    rs = ReplayState(ring=rs.ring, n_snap=rs.n_snap, last_add=rs.last_add, replaying=rs.replaying | mask,
                     buf=rs.buf, valid=valid, count=count, ptr=rs.ptr, added=rs.added,
                     replayed=rs.replayed + jnp.sum(mask.astype(jnp.int32)))
    return state, rs, mask
