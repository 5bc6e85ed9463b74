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
inside the jit) is kept between calls as a few flat buffers, one per dtype (PRNG keys as their key
data), so a call passes a handful of arrays instead of ~150 leaves; everything the host needs
(observations, rewards, reward terms, state, goals, parameters, episode metrics, flags) is packed
inside the jit into one flat float array per world and split on the host with NumPy views. Compiled
programs are cached per (config, number of worlds), so envs of the same config share compiles.
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
import types
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.devices import loop_once, reuse_freed_memory
from quadswarm_mj.envs.mjx_env import AutoResetWrapper, MjxQuadSwarmEnv, State
from quadswarm_mj.envs.sharding import WorldSharding
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
    """Flatten a state pytree with leading axes ``lead`` into one buffer per dtype and back
    (under jit: the slices and the concatenation are cheap XLA ops; the host sees few arrays)."""

    def __init__(self, struct: Any, lead: tuple[int, ...]):
        leaves, self.treedef = jax.tree.flatten(struct)
        self.lead = tuple(lead)
        self.entries: list[tuple[str, int, int, tuple[int, ...], Any, bool]] = []  # group, start, size, shape, dtype
        sizes: dict[str, int] = {}
        self.group_dtype: dict[str, Any] = {}
        for leaf in leaves:
            is_key = jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key)
            shape = tuple(leaf.shape[len(self.lead):])
            if is_key:
                dt = np.dtype(np.uint32)
                shape = shape + _key_shape()
            else:
                dt = np.dtype(leaf.dtype)
            g = dt.name
            size = int(np.prod(shape))
            self.group_dtype[g] = dt
            self.entries.append((g, sizes.get(g, 0), size, shape, dt, is_key))
            sizes[g] = sizes.get(g, 0) + size
        self.groups = tuple(sorted(sizes))
        self.sizes = sizes

    def pack(self, state: Any) -> tuple[jax.Array, ...]:
        leaves = jax.tree.leaves(state)
        parts: dict[str, list[jax.Array]] = {g: [] for g in self.groups}
        for leaf, (g, _, _, _, dt, is_key) in zip(leaves, self.entries):
            x = jax.random.key_data(leaf) if is_key else leaf
            parts[g].append(jnp.reshape(x, x.shape[:len(self.lead)] + (-1,)).astype(dt))  # local lead under shard_map
        return tuple(jnp.concatenate(parts[g], axis=-1) for g in self.groups)

    def unpack(self, bufs: tuple[jax.Array, ...]) -> Any:
        by_group = dict(zip(self.groups, bufs))
        leaves = []
        for g, start, size, shape, _, is_key in self.entries:
            buf = by_group[g]
            x = buf[..., start:start + size].reshape(buf.shape[:-1] + shape)
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
    parameters, column map). B worlds: ``step(leaves, actions) -> (leaves, obs, rest)`` WITHOUT
    the auto-reset (``obs`` is the stepped observation, i.e. the final one where an episode ended;
    ``rest`` the per-step outputs of :attr:`step_layout`), and ``renew(leaves) -> (leaves, obs, rest,
    episode)``, which the host calls only after a step that ended an episode: the fresh episodes of
    the finished worlds (:meth:`AutoResetWrapper.renew_finished`, the same function as inside
    ``vstep``); ``episode`` holds the outputs fixed for an episode (:attr:`episode_layout`:
    parameters, column map), which B worlds return only from resets and renewals."""

    def __init__(self, cfg: EnvConfig, batch: int | None):
        self.cfg, self.batch = cfg, batch
        self.env = MjxQuadSwarmEnv(cfg)
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
            # one world: the state as flat buffers, one per dtype (a handful of arrays instead of ~70
            # leaves: measured ~4x faster per call), all outputs in one packed array (one transfer)
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
        return (self._pack(s),) + self._batch_outs(s, prev, episode=False)

    def _renew_impl(self, bufs: tuple) -> tuple:
        s = self.auto.renew_finished(self._unpack(bufs))  # the rules of AutoResetWrapper (where done)
        return (self._pack(s),) + self._batch_outs(s, s, episode=True)

    def step(self, bufs: tuple, action: np.ndarray) -> tuple:
        """One world: (state buffers, packed outputs); B worlds: (state leaves, obs (B, N, obs_dim),
        per-step outputs (B, step_layout.size)) before any auto-reset. ``bufs`` are donated."""
        return self._step(bufs, action)

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
    ``step(action (N, 4)) -> (obs, rewards (N,), truncated, info)``; the caller validates inputs."""

    def __init__(self, cfg: EnvConfig):
        self.cfg = cfg
        self.prog = _program(cfg, None)
        self._keys: KeyStream | None = None
        self._bufs: tuple | None = None
        self._last: dict[str, np.ndarray] | None = None
        # the episode's constants, from the reset (steps do not return them; each info gets copies, as
        # Gymnasium's checker requires that no two calls return shared objects)
        self._params: dict[str, np.ndarray] = {}
        self._obstacles: np.ndarray | None = None
        self._renderer: Any = None

    @property
    def seeded(self) -> bool:
        return self._keys is not None

    def seed(self, seed: int) -> None:
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
        self._bufs, out = self.prog.step(self._bufs, action.astype(self.prog.float))
        obs, v = self._split(out, self.prog.step_layout)
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
class JaxVectorBackend:
    """B worlds on the JAX engine with ``QuadSwarmVectorEnv``'s outputs (NumPy in and out,
    SAME_STEP auto-reset, ``final_obs`` and ``episode_metrics`` with masks).

    A step is one jitted call without the auto-reset; only after a step that ended an episode a
    second call renews the finished worlds (the fresh episodes of :class:`AutoResetWrapper`), whose
    observation, state, goals, time, floor flags and episode constants are then returned, with the
    step's rewards, reward terms, new collisions, done flags and episode metrics (as the MuJoCo
    engine's vector env). The episode constants (parameters, column map) are read only after resets
    and renewals and kept on the host."""

    #: per-step outputs replaced by those of the fresh episodes after a renewal
    RENEWED = ("goals", "goal_vel", "on_floor", "time") + tuple(f"state/{k}" for k in STATE_KEYS)

    def __init__(self, cfg: EnvConfig, num_envs: int, info_keys: tuple[str, ...] = VECTOR_INFO_KEYS,
                 copy: bool = True):
        self.cfg, self.B = cfg, int(num_envs)
        self.info_keys, self.copy = tuple(info_keys), bool(copy)
        self.prog = _program(cfg, self.B)
        reuse_freed_memory()  # no page faults on the step's megabytes of fresh outputs (see there)
        self._keys: KeyStream | None = None
        self._bufs: tuple | None = None
        self._v: dict[str, np.ndarray] | None = None
        self._episode: dict[str, np.ndarray] = {}

    def seed(self, seed: int) -> None:
        self._keys = KeyStream(seed)

    def _host(self, x: jax.Array, dtype: Any = None) -> np.ndarray:
        """One host array of a batched device array: each device's rows read in place (no gather
        copy) and copied once into a new array (converted to ``dtype`` on the way)."""
        parts = _host_rows(x)
        return np.concatenate(parts, dtype=dtype) if len(parts) > 1 else np.array(parts[0], dtype=dtype)

    def _read(self, obs: jax.Array, rest: jax.Array, episode: jax.Array | None = None
              ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """(obs (B, N, obs_dim) float32, float64 views of the per-step outputs); updates the episode
        constants from ``episode``."""
        v = self.prog.step_layout.views64(self._host(rest, np.float64), (self.B,))
        if episode is not None:  # new read-only arrays at every reset and renewal, shared by the infos until then
            ep = self.prog.episode_layout.views64(self._host(episode, np.float64), (self.B,))
            for x in ep.values():
                x.flags.writeable = False
            self._episode = ep
        return self._host(obs), v

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
        variant = _init_variant(state)
        arrays = _init_arrays(state, self.prog.float)
        keys = self._keys.draw((self.B,))
        if mask is None or self._bufs is None:
            self._bufs, *out = self.prog.reset_fn(variant, masked=False)(keys, arrays)
        else:
            self._bufs, *out = self.prog.reset_fn(variant, masked=True)(self._bufs, keys, arrays, np.asarray(mask))
        obs, self._v = self._read(*out)
        return obs, self._info(self._v, step=False)

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        self._bufs, obs, rest = self.prog.step(self._bufs, actions.astype(self.prog.float))
        obs, v = self._read(obs, rest)
        done = v["done"] > 0.5
        final_obs = None
        if done.any():  # SAME_STEP auto-reset: the finished worlds' fresh episodes
            final_obs = obs
            self._bufs, *out = self.prog.renew(self._bufs)
            obs, fresh = self._read(*out)
            v.update({k: fresh[k] for k in self.RENEWED})
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
        self._bufs = None
