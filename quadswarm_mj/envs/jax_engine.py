"""The JAX engine behind the NumPy front ends (``engine="jax"`` of ``QuadSwarmEnv``,
``QuadSwarmParallelEnv`` and ``QuadSwarmVectorEnv``).

:class:`JaxSingleBackend` runs one world, :class:`JaxVectorBackend` B worlds, of
:class:`~quadswarm_mj.envs.mjx_env.MjxQuadSwarmEnv`, with NumPy in and out and the MuJoCo engine's
spaces, ``info`` keys, seeding and auto-reset contracts. Only the MJX env's public API is used:
``MjxQuadSwarmEnv(cfg)``, ``reset(key, init_state)``, ``step(state, action)``, the ``State`` fields
and the ``info`` keys of its docstring.

Speed: a step is ONE jitted call with the state donated (one world: one XLA:CPU kernel, see
:func:`quadswarm_mj.devices.loop_once`). The state (with the free-body physics only
the changing fields of ``mjx.Data``: qpos, qvel, time, mocap_pos; the rest is rebuilt from constants
inside the jit) is kept between calls as one flat uint32 buffer (float32 and int32 leaves as their
bits, bools as 0/1, PRNG keys as their key data), so a call passes one array instead of ~150 leaves;
everything the host needs (observations, rewards, reward terms, state, goals, parameters, episode
metrics, flags) is packed inside the jit into one flat float array per world and split on the host
with NumPy views. Compiled programs are cached per (config, number of worlds), so envs of the same
config share compiles.
B worlds are sharded over every device whose count divides B (``shard_map``: each device steps its
own worlds; :func:`quadswarm_mj.use_cpu_cores` gives JAX one CPU device per core), with results
bit-identical to one device when each device's worlds x quads fill XLA:CPU's vector loops (a multiple
of 16 elements, e.g. 8 quads and an even number of worlds per device; otherwise XLA:CPU may contract
a multiply-add into an FMA differently in a loop's scalar remainder, and the runs agree within
float32 round-off: ``tests/test_devices.py``); ``final_obs`` is a separate output, read only after an
episode ended.

Seeding: ``reset(seed=s)`` derives the JAX keys from ``np.random.SeedSequence(s)`` (any int), so
seeded runs are bit-identical; later unseeded resets continue that stream. Random streams differ
from the MuJoCo engine's; noise-free runs agree within the MJX parity tolerance (float32).
"""

from __future__ import annotations

import functools
import os
import types
import weakref
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.devices import check_mjx_batch, loop_once
from quadswarm_mj.envs.mjx_env import AutoResetWrapper, MjxQuadSwarmEnv, State
from quadswarm_mj.envs.sharding import WorldSharding
from quadswarm_mj.envs.workers import (
    DEFAULT_WORKER_TIMEOUT_S,
    STEP_INTO,
    Resources,
    SharedBlock,
    Worker,
    check_not_forked_from_jax,
    layout_bytes,
    map_arrays,
    run_on_workers,
    wait_started,
)
from quadswarm_mj.metrics import METRIC_KEYS, OBSTACLE_METRIC_KEYS, metric_keys
from quadswarm_mj.rewards import OBSTACLE_TERMS, TERMS, env_terms

STATE_KEYS = ("pos", "vel", "rot", "omega", "thrust")
VECTOR_INFO_KEYS = ("rewards", "reward_terms", "state", "goals", "goal_vel", "params", "on_floor",
                    "new_collisions", "time")


def _key_shape() -> tuple[int, ...]:
    return tuple(jax.random.key_data(jax.random.key(0)).shape)


def _wrap_keys(data: jax.Array) -> jax.Array:
    return jax.random.wrap_key_data(data)


class KeyStream:
    """Host-side stream of JAX key data from a seed (``np.random.SeedSequence``, any int)."""

    def __init__(self, seed: int):
        self.rng = np.random.default_rng(np.random.SeedSequence(int(seed)))
        self.shape = _key_shape()

    def draw(self, lead: tuple[int, ...] = ()) -> np.ndarray:
        """Key data (*lead, *key_shape) uint32."""
        return self.rng.integers(0, 2**32, size=tuple(lead) + self.shape, dtype=np.uint32)


# ------------------------------------------------------------------------------- state packing
class StatePacker:
    """Flatten a state pytree with leading axes ``lead`` into one uint32 buffer and back: float32 and
    int32 leaves as their bits, bools as 0/1, PRNG keys as their key data (a leaf of another width,
    e.g. float64 under ``jax_enable_x64``, gets a buffer of its own dtype). Under jit the bit casts,
    slices and the concatenation are cheap XLA ops; the host passes one array per call instead of
    one per leaf (~70) or per dtype (4: measured ~3 us more per call of one world)."""

    WORD = np.dtype(np.uint32)

    def __init__(self, struct: Any, lead: tuple[int, ...]):
        leaves, self.treedef = jax.tree.flatten(struct)
        self.lead = tuple(lead)
        # (group dtype name, start, size, shape, leaf dtype, is_key)
        self.entries: list[tuple[str, int, int, tuple[int, ...], Any, bool]] = []
        sizes: dict[str, int] = {}
        for leaf in leaves:
            is_key = jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key)
            shape = tuple(leaf.shape[len(self.lead):])
            dt = self.WORD if is_key else np.dtype(leaf.dtype)
            if is_key:
                shape = shape + _key_shape()
            g = self.WORD.name if dt.itemsize <= 4 else dt.name
            size = int(np.prod(shape))
            self.entries.append((g, sizes.get(g, 0), size, shape, dt, is_key))
            sizes[g] = sizes.get(g, 0) + size
        self.groups = tuple(sorted(sizes))
        self.sizes = sizes

    def _to_group(self, x: jax.Array, g: str) -> jax.Array:
        if g != self.WORD.name or x.dtype == self.WORD:
            return x
        if x.dtype.itemsize == 4:
            return jax.lax.bitcast_convert_type(x, self.WORD)
        return x.astype(self.WORD)  # bool, 8/16-bit integers: by value

    def _from_group(self, x: jax.Array, dt: np.dtype) -> jax.Array:
        if x.dtype == dt:
            return x
        if dt.itemsize == 4:
            return jax.lax.bitcast_convert_type(x, dt)
        return x.astype(dt)

    def pack(self, state: Any) -> tuple[jax.Array, ...]:
        leaves = jax.tree.leaves(state)
        parts: dict[str, list[jax.Array]] = {g: [] for g in self.groups}
        for leaf, (g, _, _, _, _, is_key) in zip(leaves, self.entries):
            x = jax.random.key_data(leaf) if is_key else leaf
            x = jnp.reshape(x, x.shape[:len(self.lead)] + (-1,))  # local lead under shard_map
            parts[g].append(self._to_group(x, g))
        return tuple(jnp.concatenate(parts[g], axis=-1) for g in self.groups)

    def unpack(self, bufs: tuple[jax.Array, ...]) -> Any:
        by_group = dict(zip(self.groups, bufs))
        leaves = []
        for g, start, size, shape, dt, is_key in self.entries:
            buf = by_group[g]
            x = self._from_group(buf[..., start:start + size], dt).reshape(buf.shape[:-1] + shape)
            leaves.append(_wrap_keys(x) if is_key else x)
        return jax.tree.unflatten(self.treedef, leaves)


class LeafPacker:
    """A state pytree as the tuple of its leaves (PRNG keys as their key data) and back: the state of
    B worlds stays on the devices as ~70 arrays between calls. (For B worlds, :class:`StatePacker`'s
    flat buffers cost more than they save: XLA:CPU's slices of the rows of a (B, 1473) buffer into
    (B, 8, 3, 3) and similar shapes ran at scalar speed, ~0.7 ms of a 1024-world step.)"""

    def __init__(self, struct: Any):
        leaves, self.treedef = jax.tree.flatten(struct)
        self.is_key = tuple(jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) for x in leaves)

    def pack(self, state: Any) -> tuple[jax.Array, ...]:
        return tuple(jax.random.key_data(x) if k else x for x, k in zip(jax.tree.leaves(state), self.is_key))

    def unpack(self, bufs: tuple[jax.Array, ...]) -> Any:
        return jax.tree.unflatten(self.treedef, [_wrap_keys(x) if k else x for x, k in zip(bufs, self.is_key)])


# ------------------------------------------------------------------------------- output packing
def _outputs(s: State, new_collisions: jax.Array, extra: dict[str, jax.Array]) -> dict[str, jax.Array]:
    """Everything the host reads after a reset or step of one world (unbatched)."""
    info = s.info
    terms = [k for k in TERMS + OBSTACLE_TERMS if f"reward/{k}" in s.metrics]  # = env_terms(cfg)
    out = {"obs": s.obs, "reward": jnp.mean(s.reward), "rewards": s.reward,
           "terms": jnp.stack([s.metrics[f"reward/{k}"] for k in terms])}
    out.update({f"state/{k}": info["state"][k] for k in STATE_KEYS})
    out.update({"goals": info["goals"], "goal_vel": info["goal_vel"]})
    out.update({f"params/{k}": v for k, v in info["params"].items()})
    mkeys = [k for k in METRIC_KEYS + OBSTACLE_METRIC_KEYS if k in info["episode_metrics"]]  # = metric_keys(cfg)
    out["metrics"] = jnp.stack([jnp.asarray(info["episode_metrics"][k], s.reward.dtype) for k in mkeys])
    if "obstacles" in info:  # the (M_max, 2) column centres and their validity
        out.update({"obstacles": info["obstacles"], "obstacles_valid": info["obstacles_valid"]})
    out.update({"time": info["time"], "on_floor": info["on_floor"], "new_collisions": new_collisions,
                "done": s.done})
    out.update(extra)
    return out


def _episode_key(name: str) -> bool:
    """Outputs fixed for an episode (dynamics parameters, column map): B worlds return them only from
    resets and renewals, not from every step."""
    return name.startswith("params/") or name in ("obstacles", "obstacles_valid")


class OutputLayout:
    """Names, shapes and offsets of the packed per-world output (one float array)."""

    #: outputs the host reads as float32 (observations), packed first: the rest is converted to float64
    FLOAT32 = ("obs",)

    def __init__(self, struct: dict[str, Any]):
        self.names = tuple(k for k in self.FLOAT32 if k in struct) + tuple(k for k in struct if k not in self.FLOAT32)
        self.shapes = {k: tuple(v.shape) for k, v in struct.items()}
        self.slices: dict[str, slice] = {}
        off = 0
        for k in self.names:
            n = int(np.prod(self.shapes[k]))
            self.slices[k] = slice(off, off + n)
            off += n
        self.size = off
        #: start of the float64 part (everything after the observations)
        self.f64_start = sum(int(np.prod(self.shapes[k])) for k in self.FLOAT32 if k in self.shapes)
        self.items = [(k, self.slices[k], self.shapes[k]) for k in self.names]
        self.params = tuple(k for k in self.names if k.startswith("params/"))
        # the float64 part as one structured record: its fields are the outputs' views (one view per
        # field instead of a slice and a reshape each: ~18 -> ~6 us per step of one world)
        rest = [(k, sl, shape) for k, sl, shape in self.items if k not in self.FLOAT32]
        self._rec64 = np.dtype({"names": [k for k, _, _ in rest],
                                "formats": [(np.float64, shape) if shape else np.float64 for _, _, shape in rest],
                                "offsets": [8 * (sl.start - self.f64_start) for _, sl, _ in rest],
                                "itemsize": 8 * (self.size - self.f64_start)})

    def pack(self, out: dict[str, jax.Array], dtype: Any) -> jax.Array:
        return jnp.concatenate([jnp.ravel(out[k]).astype(dtype) for k in self.names])

    def split64(self, flat32: np.ndarray, lead: tuple[int, ...] = ()) -> dict[str, np.ndarray]:
        """Float64 views (*lead, *shape) of the non-observation outputs of a packed float32 array
        (only that part is converted)."""
        return self.views64(flat32[..., self.f64_start:].astype(np.float64), lead)

    def views64(self, rest: np.ndarray, lead: tuple[int, ...] = ()) -> dict[str, np.ndarray]:
        """The views of :meth:`split64` from the float64 non-observation part ``rest`` (*lead, size - f64_start)."""
        rest = np.ascontiguousarray(rest).reshape(lead + (-1,))
        rec = rest.view(self._rec64).reshape(lead)  # lead-shaped record array (0-d for one world: fields are arrays)
        return {k: rec[k] for k in self._rec64.names}


def _init_variant(state: dict[str, Any] | None) -> tuple[tuple[str, ...], str | None]:
    """Static part of a reset: the array keys given and the motors string (or None)."""
    if state is None:
        return (), None
    motors = state.get("motors")
    keys = tuple(sorted(k for k, v in state.items() if v is not None and not isinstance(v, str)))
    return keys, motors if isinstance(motors, str) else None


def _select(pred: jax.Array, a: Any, b: Any) -> Any:
    """``where(pred, a, b)`` broadcast from the leading axis, also for typed PRNG keys."""
    def one(x: jax.Array, y: jax.Array) -> jax.Array:
        if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            return _wrap_keys(one(jax.random.key_data(x), jax.random.key_data(y)))
        p = jnp.reshape(pred, pred.shape + (1,) * (x.ndim - pred.ndim))
        return jnp.where(p, x, y)

    return jax.tree.map(one, a, b)


# ------------------------------------------------------------------------------- programs
class _Program:
    """Jitted reset/step of B worlds (``batch=None``: one unbatched world) of one config.

    One world: ``step(bufs, action) -> (bufs, out)`` with everything the host reads in one packed
    float array (:attr:`step_layout`; resets return :attr:`layout`, which adds the episode constants:
    parameters, column map). B worlds: ``step(leaves, actions) -> (leaves, rest)`` WITHOUT
    the auto-reset (the stepped observation, i.e. the final one where an episode ended, is the leaf
    ``leaves[obs_leaf]``; ``rest`` the per-step outputs of :attr:`step_layout`), and
    ``renew(leaves) -> (leaves, obs, rest, episode)``, which the host calls only after a step that
    ended an episode: the fresh episodes of the finished worlds
    (:meth:`AutoResetWrapper.renew_finished`, the same function as inside ``vstep``); ``episode``
    holds the outputs fixed for an episode (:attr:`episode_layout`: parameters, column map), which
    B worlds return only from resets and renewals."""

    def __init__(self, cfg: EnvConfig, batch: int | None):
        self.cfg, self.batch = cfg, batch
        self.env = MjxQuadSwarmEnv(cfg)
        check_mjx_batch(self.env.physics, batch or 1)  # a clear error where jax >= 0.10 would hang (devices.py)
        self.auto = AutoResetWrapper(self.env)
        self.lead = () if batch is None else (batch,)
        key0 = jax.random.key(0)
        one = jax.eval_shape(self.env.reset, key0)
        self.float = one.obs.dtype
        if batch is None:
            struct = one
        else:
            struct = jax.eval_shape(jax.vmap(self.env.reset), jax.random.split(key0, batch))
        # With the free-body physics only qpos, qvel, time and mocap_pos of mjx.Data change (the rest is
        # the model's initial data): the carried state keeps those four and the rest is rebuilt from
        # constants inside the jit (no 2 x 48 x 48 mass matrix and factor per world in and out).
        self._small_data = self.env.physics == "freebody"
        struct = self._shrink(struct)
        outs = jax.eval_shape(lambda s: self._outs(s, s), one)
        if batch is None:
            # one world: the state as one flat uint32 buffer (one array instead of ~70 leaves: measured
            # ~4x faster per call), all outputs in one packed array (one transfer)
            self.packer: StatePacker | LeafPacker = StatePacker(struct, self.lead)
            self.layout = OutputLayout(outs)  # resets: everything
            # steps: without the episode constants (parameters, column map), which the host keeps from the reset
            self.step_layout = OutputLayout({k: v for k, v in outs.items() if not _episode_key(k)})
        else:
            self.packer = LeafPacker(struct)
            self.step_layout = OutputLayout({k: v for k, v in outs.items() if k != "obs" and not _episode_key(k)})
            self.episode_layout = OutputLayout({k: v for k, v in outs.items() if _episode_key(k)})
        # B worlds: sharded over every CPU/accelerator device whose count divides B (each device steps
        # its own worlds, no communication; quadswarm_mj.use_cpu_cores() gives JAX one device per core)
        self.worlds = None if batch is None else WorldSharding(batch)
        # one world: the step as one XLA:CPU kernel (devices.loop_once; ~185 -> ~40 us per call). B worlds
        # keep XLA's default runtime: the same wrapping measured 0.63x at 1024 worlds.
        step = loop_once(self._step_impl) if batch is None else self._step_impl
        self._step = self._jit(step, donate=True)
        if batch is not None:
            # B worlds: the host reads the stepped observations from the state's obs leaf (a separate
            # output would be an XLA copy of it), and the carried random numbers of the next step are
            # not donated: they are rewritten at the end of a step whose every stage still reads the
            # old ones, so an aliased buffer costs XLA two copies of them (~20 % of a 512-world step
            # on one core, BENCHMARKS.md; the other leaves stay donated)
            paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(struct)[0]]
            self.obs_leaf = paths.index(".obs")
            self._kept = tuple(i for i, q in enumerate(paths) if q == ".info['step_numbers']")
            self._step = self._jit(self._split_step_impl, donate=True)
        self._renew = None if batch is None else self._jit(self._renew_impl, donate=True)
        self._resets: dict[Any, Any] = {}

    def _jit(self, impl: Any, donate: bool) -> Any:
        """``jax.jit(impl)`` (first argument donated if ``donate``); with B worlds on several devices
        run per device on its slice of worlds (every argument and result has the leading worlds axis)."""
        kw = {"donate_argnums": 0} if donate else {}
        ws = self.worlds
        if ws is None or ws.num_devices == 1:
            return jax.jit(impl, **kw)
        return jax.jit(ws.map_batched(impl), in_shardings=ws.sharding, out_shardings=ws.sharding, **kw)

    def _shrink(self, s: State) -> State:
        """The carried form of a state (free-body physics: only the changing fields of Data)."""
        if not self._small_data:
            return s
        d = s.data
        return s.replace(data={"qpos": d.qpos, "qvel": d.qvel, "time": d.time, "mocap_pos": d.mocap_pos})

    def _grow(self, s: State) -> State:
        """The full state from its carried form."""
        if not self._small_data:
            return s
        d0 = self.env._data0
        if self.lead:  # the local number of worlds (a device's slice under shard_map)
            lead = s.data["qpos"].shape[:len(self.lead)]
            d0 = jax.tree.map(lambda x: jnp.broadcast_to(x, lead + x.shape), d0)
        return s.replace(data=d0.replace(**s.data))

    def _pack(self, s: State) -> Any:
        return self.packer.pack(self._shrink(s))

    def _unpack(self, bufs: Any) -> State:
        return self._grow(self.packer.unpack(bufs))

    def _outs(self, s: State, prev: State) -> dict[str, jax.Array]:
        """One world's outputs; ``new_collisions`` are the contacts of ``s`` not in ``prev``."""
        new = jnp.any(s.info["contact"] & ~prev.info["contact"], axis=-1)
        extra = {"qpos": s.data.qpos} if self.batch is None else {}
        return _outputs(s, new, extra)

    def _batch_outs(self, s: State, prev: State, episode: bool) -> tuple[jax.Array, ...]:
        """B worlds: (obs, per-step outputs) and with ``episode`` the episode outputs, packed per world."""
        def one(a: State, b: State) -> tuple[jax.Array, ...]:
            out = self._outs(a, b)
            packed = (self.step_layout.pack(out, self.float),)
            return packed + ((self.episode_layout.pack(out, self.float),) if episode else ())

        return (s.obs,) + jax.vmap(one)(s, prev)

    # ---------------------------------------------------------------- reset
    def reset_fn(self, variant: tuple[tuple[str, ...], str | None], masked: bool) -> Any:
        """The jitted reset for this static variant (cached): one world ``(bufs, out)``; B worlds
        ``(leaves, obs, rest, episode)``."""
        key = (variant, masked)
        if key not in self._resets:
            motors = variant[1]

            def one_reset(k: jax.Array, arrays: dict[str, jax.Array]) -> State:
                init = dict(arrays)
                if motors is not None:
                    init["motors"] = motors
                return self.env.reset(_wrap_keys(k), init or None)

            if self.batch is None:
                def impl(key_data: jax.Array, arrays: dict[str, jax.Array]) -> tuple:
                    s = one_reset(key_data, arrays)
                    return self._pack(s), self.layout.pack(self._outs(s, s), self.float)
                self._resets[key] = jax.jit(impl)
            elif not masked:
                def impl(key_data: jax.Array, arrays: dict[str, jax.Array]) -> tuple:
                    s = jax.vmap(one_reset)(key_data, arrays)
                    return (self._pack(s),) + self._batch_outs(s, s, episode=True)
                self._resets[key] = self._jit(impl, donate=False)
            else:
                def impl(bufs: tuple, key_data: jax.Array, arrays: dict[str, jax.Array], mask: jax.Array) -> tuple:
                    old = self._unpack(bufs)
                    fresh = jax.vmap(one_reset)(key_data, arrays)
                    fresh = fresh.replace(info={**fresh.info, "total_steps": old.info["total_steps"]})
                    s = _select(mask, fresh, old)
                    return (self._pack(s),) + self._batch_outs(s, s, episode=True)
                self._resets[key] = self._jit(impl, donate=True)
        return self._resets[key]

    # ---------------------------------------------------------------- step
    def _step_impl(self, bufs: tuple, action: jax.Array) -> tuple:
        prev = self._unpack(bufs)
        if self.batch is None:
            s = self.env.step(prev, action)
            return self._pack(s), self.step_layout.pack(self._outs(s, prev), self.float)
        s = jax.vmap(self.env.step)(prev, action)
        return (self._pack(s),) + self._batch_outs(s, prev, episode=False)[1:]  # obs: the state's leaf

    def _split_step_impl(self, donated: tuple, kept: tuple, action: jax.Array) -> tuple:
        """B worlds: :meth:`_step_impl` with the state's leaves split into donated and kept ones."""
        d, k = iter(donated), iter(kept)
        n = len(donated) + len(kept)
        return self._step_impl(tuple(next(k) if i in self._kept else next(d) for i in range(n)), action)

    def _renew_impl(self, bufs: tuple) -> tuple:
        s = self.auto.renew_finished(self._unpack(bufs))  # the rules of AutoResetWrapper (where done)
        return (self._pack(s),) + self._batch_outs(s, s, episode=True)

    def step(self, bufs: tuple, action: np.ndarray) -> tuple:
        """One world: (state buffers, packed outputs); B worlds: (state leaves, per-step outputs
        (B, step_layout.size)) before any auto-reset, the stepped observations (B, N, obs_dim) being
        the leaf ``leaves[obs_leaf]``. ``bufs`` are donated (B worlds: except the carried random
        numbers)."""
        if self.batch is None:
            return self._step(bufs, action)
        return self._step(tuple(b for i, b in enumerate(bufs) if i not in self._kept),
                          tuple(bufs[i] for i in self._kept), action)

    def renew(self, bufs: tuple) -> tuple:
        """B worlds after a step that ended an episode: (state leaves, obs, per-step outputs, episode
        outputs) with the finished worlds in fresh episodes. ``bufs`` are donated."""
        return self._renew(bufs)


@functools.lru_cache(maxsize=8)
def _program(cfg: EnvConfig, batch: int | None) -> _Program:
    return _Program(cfg, batch)


def _init_arrays(state: dict[str, Any] | None, dtype: Any) -> dict[str, np.ndarray]:
    if state is None:
        return {}
    return {k: np.asarray(v, dtype) for k, v in state.items() if v is not None and not isinstance(v, str)}


def _host_rows(x: jax.Array) -> list[np.ndarray]:
    """The host views of a batched array's device shards, in world order (read-only; CPU: no copy)."""
    shards = x.addressable_shards
    if len(shards) == 1:
        return [np.asarray(x)]
    return [np.asarray(sh.data) for sh in sorted(shards, key=lambda sh: sh.index[0].start or 0)]


# ------------------------------------------------------------------------------- single world
class JaxSingleBackend:
    """One world on the JAX engine with ``QuadSwarmEnv``'s ``info`` (NumPy in and out).

    ``reset(seed, state) -> (obs_flat (N, obs_dim) float32, info)`` and
    ``step(action (N, 4)) -> (obs, rewards (N,), truncated, info)``; the caller validates inputs.

    JAX starts only at the first seed, reset or step, in the process that runs them: an env built in
    one process (e.g. gymnasium's ``AsyncVectorEnv`` builds one to read the spaces) and stepped in a
    forked one works; in a process forked from one where JAX already ran, every call raises
    RuntimeError (JAX is not fork-safe; use a "spawn" or "forkserver" context). ``copy.deepcopy``
    and ``pickle`` give an independent backend in the same state (the state buffers as host arrays)."""

    def __init__(self, cfg: EnvConfig):
        self.cfg = cfg
        self._prog: _Program | None = None
        self._keys: KeyStream | None = None
        self._bufs: tuple | None = None
        self._last: dict[str, np.ndarray] | None = None
        # the episode's constants, from the reset (steps do not return them; each info gets copies, as
        # Gymnasium's checker requires that no two calls return shared objects)
        self._params: dict[str, np.ndarray] = {}
        self._obstacles: np.ndarray | None = None
        self._renderer: Any = None

    @property
    def prog(self) -> _Program:
        """The compiled programs of this config (JAX starts here, in the calling process)."""
        check_not_forked_from_jax()
        if self._prog is None:
            self._prog = _program(self.cfg, None)
        return self._prog

    def __getstate__(self) -> dict[str, Any]:
        d = {k: v for k, v in self.__dict__.items() if k not in ("_prog", "_renderer")}
        d["_bufs"] = None if self._bufs is None else tuple(np.asarray(b) for b in self._bufs)
        return d

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._prog, self._renderer = None, None

    @property
    def seeded(self) -> bool:
        return self._keys is not None

    def seed(self, seed: int) -> None:
        check_not_forked_from_jax()
        self._keys = KeyStream(seed)

    def _info(self, v: dict[str, np.ndarray]) -> dict[str, Any]:
        info = {"state": {"pos": v["state/pos"], "vel": v["state/vel"], "rot": v["state/rot"],
                          "omega": v["state/omega"], "thrust": v["state/thrust"]},
                "goals": v["goals"], "goal_vel": v["goal_vel"],
                "params": {k: x.copy() for k, x in self._params.items()},
                "on_floor": v["on_floor"] > 0.5, "time": float(v["time"])}
        if self._obstacles is not None:
            info["obstacles"] = self._obstacles.copy()
        return info

    def _split(self, out: jax.Array, layout: OutputLayout) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        o = np.array(out)  # one transfer, writable
        v = layout.split64(o)
        self._last = v
        return o[layout.slices["obs"]].reshape(layout.shapes["obs"]), v

    def reset(self, state: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        if self._keys is None:
            raise RuntimeError("seed() before reset()")
        variant = _init_variant(state)
        fn = self.prog.reset_fn(variant, masked=False)
        self._bufs, out = fn(self._keys.draw(), _init_arrays(state, self.prog.float))
        obs, v = self._split(out, self.prog.layout)
        if self._renderer is not None:
            self._renderer.reset()
        # the dynamics parameters and the column map are fixed for the episode: kept from here
        self._params = {k[len("params/"):]: v[k].copy() for k in self.prog.layout.params}
        self._obstacles = v["obstacles"][v["obstacles_valid"] > 0.5] if "obstacles" in v else None
        return obs, self._info(v)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, dict[str, Any]]:
        """One control step; returns (obs, team reward (mean over quads), truncated, info)."""
        prog = self.prog
        if self._bufs is not None and isinstance(self._bufs[0], np.ndarray):  # a copy's host buffers
            self._bufs = tuple(jax.device_put(b) for b in self._bufs)
        self._bufs, out = prog.step(self._bufs, action.astype(prog.float))
        obs, v = self._split(out, prog.step_layout)
        info = self._info(v)
        info["rewards"] = v["rewards"]
        info["reward_terms"] = dict(zip(env_terms(self.cfg), v["terms"]))
        info["new_collisions"] = v["new_collisions"] > 0.5
        truncated = bool(v["done"] > 0.5)
        if truncated:
            info["episode_metrics"] = dict(zip(metric_keys(self.cfg), v["metrics"].tolist()))
        return obs, float(v["reward"]), truncated, info

    def render(self) -> np.ndarray:
        """An RGB frame of the current state: the state's ``qpos`` copied into the renderer's
        ``MjData`` (:class:`quadswarm_mj.render.SwarmRenderer` on ``build_arena(cfg, 1)``)."""
        from quadswarm_mj.arena import build_arena
        from quadswarm_mj.render import SwarmRenderer

        if self._last is None:
            raise RuntimeError("call reset() before render()")
        if self._renderer is None:
            arena = build_arena(self.cfg, 1)
            self._renderer = SwarmRenderer(types.SimpleNamespace(arena=arena, model=arena.model))
        v = self._last
        return self._renderer.render(qpos=v["qpos"], goals=v["goals"], obstacles=self._obstacles)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


# ------------------------------------------------------------------------------- B worlds
#: per-step outputs replaced by those of the fresh episodes after a renewal
RENEWED = ("goals", "goal_vel", "on_floor", "time") + tuple(f"state/{k}" for k in STATE_KEYS)
#: on CPU the JAX engine's vector env runs in worker processes (one core each) from this many worlds per
#: worker (measured on 2 cores: 1024 worlds 1.04-1.24x the in-process engine, 256 worlds 0.86-1.36x)
MIN_WORLDS_PER_WORKER = 256


def _copy_rows(dst: np.ndarray, x: jax.Array) -> None:
    """Copy a batched device array into the host array ``dst`` (converting dtype), each device's rows
    read in place (no gather copy)."""
    lo = 0
    for part in _host_rows(x):
        hi = lo + part.shape[0]
        np.copyto(dst[lo:hi], part, casting="same_kind")
        lo = hi


class LocalWorlds:
    """B worlds on this process's JAX devices, their outputs read into host arrays.

    ``out`` arrays (given by the caller: fresh ones, or a worker's rows of the shared block):
    ``obs`` (B, N, obs_dim) float32, ``final_obs`` (B, N, obs_dim) float32, ``rest`` (B, S) float64
    (the per-step outputs of :attr:`_Program.step_layout`) and ``episode`` (B, E) float64 (the episode
    constants of :attr:`_Program.episode_layout`)."""

    def __init__(self, cfg: EnvConfig, num_worlds: int):
        self.cfg, self.B = cfg, int(num_worlds)
        self.prog = _program(cfg, self.B)
        self.bufs: tuple | None = None
        lay = self.prog.step_layout
        self._done = lay.slices["done"].start
        self._renewed = [lay.slices[k] for k in RENEWED]

    def reset(self, keys: np.ndarray, mask: np.ndarray | None, state: dict[str, Any] | None,
              out: dict[str, np.ndarray]) -> None:
        """Reset every world (or those in ``mask``) from the key data ``keys`` (B, *key_shape) uint32;
        writes ``obs``, ``rest`` and ``episode``."""
        variant = _init_variant(state)
        arrays = _init_arrays(state, self.prog.float)
        if mask is None or self.bufs is None:
            self.bufs, obs, rest, episode = self.prog.reset_fn(variant, masked=False)(keys, arrays)
        else:
            self.bufs, obs, rest, episode = self.prog.reset_fn(variant, masked=True)(self.bufs, keys, arrays,
                                                                                     np.asarray(mask))
        for name, x in (("obs", obs), ("rest", rest), ("episode", episode)):
            _copy_rows(out[name], x)

    def step(self, actions: np.ndarray, out: dict[str, np.ndarray]) -> bool:
        """One control step; writes ``obs`` and ``rest``. Where an episode ended, also ``final_obs``
        (the stepped observations), the fresh episodes' ``obs``, their :data:`RENEWED` columns of
        ``rest`` and ``episode``; returns whether that happened (SAME_STEP auto-reset)."""
        self.bufs, rest = self.prog.step(self.bufs, actions.astype(self.prog.float, copy=False))
        obs = self.bufs[self.prog.obs_leaf]  # read (copied out) before the next call donates it
        _copy_rows(out["rest"], rest)
        if not (out["rest"][:, self._done] > 0.5).any():
            _copy_rows(out["obs"], obs)
            return False
        _copy_rows(out["final_obs"], obs)
        self.bufs, obs, rest, episode = self.prog.renew(self.bufs)
        _copy_rows(out["obs"], obs)
        _copy_rows(out["episode"], episode)
        fresh = np.concatenate(_host_rows(rest))
        for sl in self._renewed:
            out["rest"][:, sl] = fresh[:, sl]
        return True

    def close(self) -> None:
        self.bufs = None

    def __getstate__(self) -> dict[str, Any]:
        """For copy/pickle: the state leaves as host arrays (put back on the devices by :meth:`__setstate__`)."""
        d = {k: v for k, v in self.__dict__.items() if k != "prog"}
        d["bufs"] = None if self.bufs is None else tuple(np.array(b) for b in self.bufs)
        return d

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.prog = _program(self.cfg, self.B)
        ws = self.prog.worlds
        put = (lambda x: jax.device_put(x)) if ws is None or ws.num_devices == 1 else (
            lambda x: jax.device_put(x, ws.sharding))
        if self.bufs is not None:
            self.bufs = tuple(put(b) for b in self.bufs)


#: output blocks a worker-process vector env hands out before it falls back to copying (see WorkerWorlds)
MAX_OUTPUT_BLOCKS = 8


class WorkerShard:
    """Worlds [lo, hi) of a worker process (the ``factory`` :func:`jax_shard`): a :class:`LocalWorlds`
    on the worker's one CPU core, writing its rows of the shared arrays: ``obs`` and ``rest`` into the
    output block the step names, the rest into the control block."""

    def __init__(self, init: dict[str, Any], arrays: dict[str, np.ndarray]):
        self.lo, self.hi = init["lo"], init["hi"]
        self.index, self.out_layout = init["index"], init["out_layout"]
        self.worlds = LocalWorlds(init["cfg"], self.hi - self.lo)
        self.ctrl = {k: v[self.lo:self.hi] for k, v in arrays.items() if k != "renewed"}
        self.renewed = arrays["renewed"]
        self.blocks: dict[int, tuple[Any, dict[str, np.ndarray]]] = {}

    def _out(self, block: int) -> dict[str, np.ndarray]:
        rows = self.blocks[block][1]
        return {"obs": rows["obs"], "rest": rows["rest"], "final_obs": self.ctrl["final_obs"],
                "episode": self.ctrl["episode"]}

    def step_into(self, block: int) -> None:
        self.renewed[self.index] = self.worlds.step(self.ctrl["actions"], self._out(block))

    def handle(self, msg: tuple) -> Any:
        """("map", block, name), ("reset", keys, mask, state, block) or ("call", fn, *args) (a test
        hook: fn(shard, *args))."""
        if msg[0] == "map":  # a new output block of the env
            shm = SharedBlock(name=msg[2])
            arrays = map_arrays(shm.buf, self.out_layout)
            self.blocks[msg[1]] = (shm, {k: v[self.lo:self.hi] for k, v in arrays.items()})
            return None
        if msg[0] == "reset":
            self.worlds.reset(msg[1], msg[2], msg[3], self._out(msg[4]))
            return None
        if msg[0] == "call":
            return msg[1](self, *msg[2:])
        raise ValueError(f"unknown command {msg[0]!r}")


def jax_shard(init: dict[str, Any], arrays: dict[str, np.ndarray]) -> WorkerShard:
    """A worker's JAX-engine shard (the ``factory`` of :func:`quadswarm_mj.envs.workers.worker_main`)."""
    return WorkerShard(init, arrays)


def worker_environ() -> dict[str, str | None]:
    """The environment of a JAX-engine worker: JAX on CPU with ONE device (the parent's device count,
    e.g. from :func:`quadswarm_mj.use_cpu_cores` or ``--xla_force_host_platform_device_count``, is
    not inherited)."""
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split()
             if not f.startswith("--xla_force_host_platform_device_count")]
    return {"JAX_PLATFORMS": "cpu", "JAX_NUM_CPU_DEVICES": "1", "XLA_FLAGS": " ".join(flags) or None}


class WorkerWorlds:
    """B worlds split over ``num_workers`` worker processes, each a single-device JAX program pinned
    to one CPU core (worker k to the k-th core this process may run on, cyclically).

    Why: on CPU one program per core in its own process measured ~1.8x the same worlds as one program
    sharded over the cores' devices in one process (1024 x 8 in a loop: ~4 ms against ~7.4 ms per
    step, BENCHMARKS.md): a lone call of a sharded XLA:CPU program starts its second device's work
    late and shares the cores' threads.

    Transport (:mod:`quadswarm_mj.envs.workers`): a control block (actions, final observations,
    episode constants, flags) and output blocks of shared memory. Each step's observations and
    per-step outputs are written by the workers straight into an output block that nothing refers
    to any more, and the env returns views of it: no copy in this process. A block is free again when
    every array viewing it is gone (``weakref.finalize`` on the step's carrier array); at most
    :data:`MAX_OUTPUT_BLOCKS` exist, and if a caller keeps all of them alive the step goes through a
    scratch block and is copied out."""

    def __init__(self, cfg: EnvConfig, num_worlds: int, num_workers: int,
                 timeout: float | None = DEFAULT_WORKER_TIMEOUT_S):
        self.cfg, self.B, self.n = cfg, int(num_worlds), int(num_workers)
        prog = _program(cfg, self.B)  # layouts only (traced, not compiled, in this process)
        N, D = cfg.num_quads, cfg.obs_dim
        self.layout = [("actions", (self.B, N, 4), np.float32), ("final_obs", (self.B, N, D), np.float32),
                       ("episode", (self.B, prog.episode_layout.size), np.float64), ("renewed", (self.n,), np.bool_)]
        self.out_layout = [("obs", (self.B, N, D), np.float32), ("rest", (self.B, prog.step_layout.size), np.float64)]
        self._out_bytes = layout_bytes(self.out_layout)
        edges = np.linspace(0, self.B, self.n + 1).round().astype(int)
        self.bounds = [(int(edges[k]), int(edges[k + 1])) for k in range(self.n)]
        cores = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else [None]
        self.res = res = Resources()
        self.blocks: list[Any] = []  # output blocks; 0 is the scratch block (copied out, never handed out)
        self.free: list[bool] = []
        try:
            self.a = map_arrays(res.create_block(layout_bytes(self.layout)).buf, self.layout)
            env = worker_environ()
            for k, (lo, hi) in enumerate(self.bounds):
                init = {"factory": "quadswarm_mj.envs.jax_engine:jax_shard", "shm": res.shm.name,
                        "layout": self.layout, "out_layout": self.out_layout, "cfg": cfg, "lo": lo, "hi": hi,
                        "index": k, "cpu": cores[k % len(cores)], "timeout": timeout}
                res.workers.append(Worker(k, lo, hi, init, environ=env))
            wait_started(res.workers)
            res.unlink()  # every worker has mapped the block: its name can go
            self._new_block()  # the scratch block
        except BaseException:
            self.close()
            raise

    def _run(self, what: str, msg_for: Any) -> None:
        run_on_workers(self.res.workers, what, msg_for, self.n)

    def _new_block(self) -> int:
        block = SharedBlock(create=True, size=self._out_bytes)
        try:
            k = len(self.blocks)
            self._run("map", lambda _: ("map", k, block.name))
        finally:
            block.unlink()  # mapped by every worker (or failed): the name can go
        self.blocks.append(block)
        self.free.append(k != 0)
        return k

    def _acquire(self) -> int:
        """A free output block (a new one while fewer than MAX_OUTPUT_BLOCKS exist), else 0 (scratch)."""
        for k in range(1, len(self.blocks)):
            if self.free[k]:
                return k
        if len(self.blocks) <= MAX_OUTPUT_BLOCKS:
            return self._new_block()
        return 0

    def _outputs(self, k: int) -> dict[str, np.ndarray]:
        """``obs`` and ``rest`` of block k as new arrays (scratch) or views that free the block when gone."""
        carrier = np.frombuffer(self.blocks[k].buf, np.uint8, count=self._out_bytes)
        out = map_arrays(carrier, self.out_layout)
        if k == 0:
            return {name: x.copy() for name, x in out.items()}
        self.free[k] = False
        weakref.finalize(carrier, self.free.__setitem__, k, True)
        return out

    def _episode_outputs(self, out: dict[str, np.ndarray], renewed: np.ndarray | None) -> dict[str, np.ndarray]:
        a = self.a
        out["episode"] = a["episode"].copy()
        if renewed is not None:
            final = a["final_obs"].copy()
            for k, (lo, hi) in enumerate(self.bounds):  # no episode ended there: stepped = current observation
                if not renewed[k]:
                    final[lo:hi] = out["obs"][lo:hi]
            out["final_obs"] = final
        return out

    def reset(self, keys: np.ndarray, mask: np.ndarray | None, state: dict[str, Any] | None
              ) -> dict[str, np.ndarray]:
        """Reset every world (or those in ``mask``); returns ``obs``, ``rest`` and ``episode``."""
        def rows(x: Any, k: int) -> Any:
            lo, hi = self.bounds[k]
            return None if x is None else x[lo:hi]

        block = self._acquire()

        def msg(k: int) -> tuple:
            sub = None if state is None else {key: (v if isinstance(v, str) or v is None else rows(v, k))
                                              for key, v in state.items()}
            return ("reset", rows(keys, k), rows(mask, k), sub, block)

        self._run("reset", msg)
        return self._episode_outputs(self._outputs(block), None)

    def step(self, actions: np.ndarray) -> tuple[dict[str, np.ndarray], bool]:
        """Step every worker: (``obs`` and ``rest``, with ``final_obs`` and ``episode`` if an episode
        ended anywhere; every world's stepped observation in ``final_obs``), and whether one ended."""
        a = self.a
        np.copyto(a["actions"], actions, casting="same_kind")
        block = self._acquire()
        msg = STEP_INTO + block.to_bytes(2, "little")
        self._run("step", lambda _: msg)
        out = self._outputs(block)
        renewed = a["renewed"]
        if not renewed.any():
            return out, False
        return self._episode_outputs(out, renewed.copy()), True

    def close(self) -> None:
        self.res.release()
        for block in self.blocks:
            block.close()
        self.blocks, self.free = [], []


class JaxVectorBackend:
    """B worlds on the JAX engine with ``QuadSwarmVectorEnv``'s outputs (NumPy in and out,
    SAME_STEP auto-reset, ``final_obs`` and ``episode_metrics`` with masks).

    A step is one jitted call without the auto-reset; only after a step that ended an episode a
    second call renews the finished worlds (the fresh episodes of :class:`AutoResetWrapper`), whose
    observation, state, goals, time, floor flags and episode constants are then returned, with the
    step's rewards, reward terms, new collisions, done flags and episode metrics (as the MuJoCo
    engine's vector env). The episode constants (parameters, column map) are read only after resets
    and renewals and kept on the host.

    ``num_workers`` 0: the worlds run in this process (sharded over its devices); k >= 1: in k worker
    processes (:class:`WorkerWorlds`). Either way every returned array is the caller's: no later
    call writes into it (``copy`` does not apply). The reset keys are drawn here for all B worlds, so
    a seed gives the same worlds whatever the split (bit-identical where each part's worlds x quads
    is a multiple of 16, see the module doc)."""

    RENEWED = RENEWED

    def __init__(self, cfg: EnvConfig, num_envs: int, info_keys: tuple[str, ...] = VECTOR_INFO_KEYS,
                 copy: bool = True, num_workers: int = 0, worker_timeout: float | None = DEFAULT_WORKER_TIMEOUT_S):
        check_not_forked_from_jax()
        self.cfg, self.B = cfg, int(num_envs)
        self.info_keys, self.copy = tuple(info_keys), bool(copy)
        self.num_workers = int(num_workers)
        self.worker_timeout = worker_timeout
        self.prog = _program(cfg, self.B)
        self._keys: KeyStream | None = None
        self._v: dict[str, np.ndarray] | None = None
        self._episode: dict[str, np.ndarray] = {}
        self._worlds: LocalWorlds | WorkerWorlds | None = None
        self.start()

    def start(self) -> None:
        """(Re)build the worlds (their state is gone: reset every world next)."""
        self.close()
        self._worlds = (WorkerWorlds(self.cfg, self.B, self.num_workers, self.worker_timeout) if self.num_workers
                        else LocalWorlds(self.cfg, self.B))

    def __getstate__(self) -> dict[str, Any]:
        """For copy/pickle (in-process worlds only: TypeError with worker processes)."""
        if self.num_workers:
            raise TypeError(f"a JAX-engine vector env with worker processes (num_shards={self.num_workers}) cannot be "
                            f"copied or pickled: its worlds live in other processes. Build a new env with the same "
                            f"arguments (num_shards=1 envs can be copied)")
        d = {k: v for k, v in self.__dict__.items() if k != "prog"}
        return d

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.prog = _program(self.cfg, self.B)

    def seed(self, seed: int) -> None:
        self._keys = KeyStream(seed)

    def _new_outputs(self) -> dict[str, np.ndarray]:
        N, D = self.cfg.num_quads, self.cfg.obs_dim
        return {"obs": np.empty((self.B, N, D), np.float32), "final_obs": np.empty((self.B, N, D), np.float32),
                "rest": np.empty((self.B, self.prog.step_layout.size)),
                "episode": np.empty((self.B, self.prog.episode_layout.size))}

    def _read(self, out: dict[str, np.ndarray], episode: bool, final: bool = False
              ) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray | None]:
        """(obs (B, N, obs_dim) float32, float64 views of the per-step outputs, final_obs or None)
        from arrays no one else writes; updates the episode constants with ``episode``."""
        v = self.prog.step_layout.views64(out["rest"], (self.B,))
        if episode:  # new read-only arrays at every reset and renewal, shared by the infos until then
            ep = self.prog.episode_layout.views64(out["episode"], (self.B,))
            for x in ep.values():
                x.flags.writeable = False
            self._episode = ep
        return out["obs"], v, (out["final_obs"] if final else None)

    def _info(self, v: dict[str, np.ndarray], step: bool) -> dict[str, Any]:
        keys, out, ep = self.info_keys, {}, self._episode
        if step and "rewards" in keys:
            out["rewards"] = v["rewards"]
        if step and "reward_terms" in keys:
            out["reward_terms"] = {k: v["terms"][:, i] for i, k in enumerate(env_terms(self.cfg))}
        if "state" in keys:
            out["state"] = {k: v[f"state/{k}"] for k in STATE_KEYS}
        for k in ("goals", "goal_vel"):
            if k in keys:
                out[k] = v[k]
        if "params" in keys:
            out["params"] = {k[len("params/"):]: x for k, x in ep.items() if k.startswith("params/")}
        if "on_floor" in keys:
            out["on_floor"] = v["on_floor"] > 0.5
        if step and "new_collisions" in keys:
            out["new_collisions"] = v["new_collisions"] > 0.5
        if "time" in keys:
            out["time"] = v["time"]
        if "obstacles" in ep:  # (B, M_max, 2) centres, NaN in unused slots
            out["obstacles"] = np.where(ep["obstacles_valid"][..., None] > 0.5, ep["obstacles"], np.nan)
        return out

    def reset(self, mask: np.ndarray | None, state: dict[str, Any] | None) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every world, or those in ``mask`` (B,) bool (the first reset must reset all)."""
        if self._keys is None:
            raise RuntimeError("seed() before reset()")
        keys = self._keys.draw((self.B,))
        w = self._worlds
        if isinstance(w, WorkerWorlds):
            out = w.reset(keys, mask, state)
        else:
            out = self._new_outputs()
            w.reset(keys, mask, state, out)
        obs, self._v, _ = self._read(out, episode=True)
        return obs, self._info(self._v, step=False)

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        w = self._worlds
        if isinstance(w, WorkerWorlds):
            out, renewed = w.step(actions)
        else:
            out = self._new_outputs()
            renewed = w.step(actions, out)
        obs, v, final_obs = self._read(out, episode=renewed, final=renewed)
        done = v["done"] > 0.5
        self._v = v
        info = self._info(v, step=True)
        if final_obs is not None:
            info["episode_metrics"] = {k: np.where(done, v["metrics"][:, i], np.nan)
                                       for i, k in enumerate(metric_keys(self.cfg))}
            info["_episode_metrics"] = done.copy()
            info["final_obs"] = final_obs  # (B, N, obs_dim) float32, the stepped observations
            info["_final_obs"] = done.copy()
        return obs, v["rewards"].mean(axis=-1), np.zeros(self.B, dtype=np.bool_), done, info

    def episode_metrics(self) -> dict[str, np.ndarray]:
        """Episode metrics (B,) of the running episodes so far (as of the last reset or step)."""
        if self._v is None:
            raise RuntimeError("call reset() first")
        return {k: self._v["metrics"][:, i].copy() for i, k in enumerate(metric_keys(self.cfg))}

    def close(self) -> None:
        if self._worlds is not None:
            self._worlds.close()
            self._worlds = None
