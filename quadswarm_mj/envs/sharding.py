"""Shard MJX worlds over all JAX devices along a mesh axis named ``"worlds"``.

Worlds never interact, so each device simulates its own slice of them: the vmapped ``reset`` and
``step`` run inside ``jax.shard_map`` (no cross-device communication) on a 1-D ``Mesh`` of the
devices, and every leaf of a batched state is laid out with
``NamedSharding(mesh, PartitionSpec("worlds"))`` (leading axis = worlds). On a CPU-only machine
:func:`quadswarm_mj.use_cpu_cores` (or ``JAX_NUM_CPU_DEVICES=K``) exposes one device per core, which
is also the fastest way to use the cores (BENCHMARKS.md)::

    env = ShardedEnv(MjxQuadSwarmEnv(cfg), num_worlds=512)   # all devices, 512 / D worlds each
    state = env.reset(jax.random.key(0))
    state = env.step(state, actions)                          # actions (512, N, 4)
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

AXIS = "worlds"


def world_devices(num_worlds: int, devices: Sequence[Any] | None = None) -> list[Any]:
    """The largest prefix of ``devices`` (default: all) whose length divides ``num_worlds``."""
    devices = list(jax.devices() if devices is None else devices)
    k = max(d for d in range(1, len(devices) + 1) if num_worlds % d == 0)
    return devices[:k]


class WorldSharding:
    """A 1-D device mesh over worlds and helpers to run vmapped env functions on it.

    ``num_worlds`` must be a multiple of the number of devices (ValueError otherwise).
    """

    def __init__(self, num_worlds: int, devices: Sequence[Any] | None = None):
        if not isinstance(num_worlds, int) or num_worlds < 1:
            raise ValueError(f"num_worlds must be an int >= 1, got {num_worlds!r}")
        devices = list(world_devices(num_worlds) if devices is None else devices)
        if num_worlds % len(devices) != 0:
            raise ValueError(f"num_worlds ({num_worlds}) must be a multiple of the number of devices "
                             f"({len(devices)})")
        self.num_worlds = num_worlds
        self.devices = devices
        self.mesh = Mesh(np.asarray(devices), (AXIS,))
        self.spec = PartitionSpec(AXIS)
        self.sharding = NamedSharding(self.mesh, self.spec)

    @property
    def num_devices(self) -> int:
        return len(self.devices)

    def shard(self, tree: Any) -> Any:
        """Place a batched pytree (leading axis = worlds) on the mesh."""
        return jax.device_put(tree, self.sharding)

    def map(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        """``jax.vmap(fn)`` run per device on its slice of worlds (every argument and result is
        batched along the worlds axis)."""
        # check_vma=False: the worlds never communicate, and MJX's lax.scan carries would otherwise
        # need per-leaf pcast annotations (replicated model constants mixed with per-world data).
        return jax.shard_map(jax.vmap(fn), mesh=self.mesh, in_specs=self.spec, out_specs=self.spec, check_vma=False)

    def map_batched(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        """A function of batched arguments (leading axis = worlds) run per device on its slice."""
        return jax.shard_map(fn, mesh=self.mesh, in_specs=self.spec, out_specs=self.spec, check_vma=False)

    def vmap_reset(self, env: Any) -> Callable[[jax.Array], Any]:
        """keys (W,) -> batched State."""
        return self.map(lambda k: env.reset(k))

    def vmap_step(self, env: Any) -> Callable[[Any, jax.Array], Any]:
        """(batched State, actions (W, N, 4)) -> batched State; uses the env's batched ``vstep``
        when it has one (:class:`~quadswarm_mj.envs.mjx_env.AutoResetWrapper`)."""
        vstep = getattr(env, "vstep", None)
        return self.map_batched(vstep) if vstep is not None else self.map(env.step)


class ShardedEnv:
    """``num_worlds`` copies of an MJX env (``MjxQuadSwarmEnv`` or a wrapper of it), jitted and
    sharded over devices. ``reset(key, init_state=None)`` splits ``key`` into one key per world;
    ``init_state`` (optional) holds the CPU env's state keys with a leading worlds axis
    (``motors`` may be the string "zero"/"hover", applied to every world)."""

    def __init__(self, env: Any, num_worlds: int, devices: Sequence[Any] | None = None):
        self.env = env
        self.num_worlds = num_worlds
        self.ws = WorldSharding(num_worlds, list(jax.devices()) if devices is None else devices)
        s = self.ws.sharding
        self._step = jax.jit(self.ws.vmap_step(env), in_shardings=(s, s), out_shardings=s)
        self._resets: dict[Any, Callable[..., Any]] = {}

    @property
    def sharding(self) -> NamedSharding:
        return self.ws.sharding

    def _reset_fn(self, motors: str | None, keys: tuple[str, ...]) -> Callable[..., Any]:
        sig = (motors, keys)
        if sig not in self._resets:
            def one(key: jax.Array, arrays: dict[str, Any]) -> Any:
                init = dict(arrays)
                if motors is not None:
                    init["motors"] = motors
                return self.env.reset(key, init or None)

            s = self.ws.sharding
            self._resets[sig] = jax.jit(self.ws.map(one), in_shardings=(s, s), out_shardings=s)
        return self._resets[sig]

    def reset(self, key: jax.Array, init_state: dict[str, Any] | None = None) -> Any:
        init_state = dict(init_state or {})
        motors = init_state.pop("motors", None)
        if motors is not None and not isinstance(motors, str):
            init_state["motors"] = motors
            motors = None
        for k, v in init_state.items():
            if np.shape(v)[:1] != (self.num_worlds,):
                raise ValueError(f"init_state['{k}'] must have a leading worlds axis of {self.num_worlds}, "
                                 f"got shape {np.shape(v)}")
        keys = jax.random.split(key, self.num_worlds)
        fn = self._reset_fn(motors, tuple(sorted(init_state)))
        return fn(self.ws.shard(keys), self.ws.shard(init_state))

    def step(self, state: Any, action: jax.Array) -> Any:
        """Actions (num_worlds, N, 4)."""
        return self._step(state, action)
