"""The JAX engine's compiled programs: jitted reset, step and renewal of one world or B worlds of
one config (:class:`Program`, cached per (config, number of worlds) by :func:`program`), the
host-side key stream, and the outputs the host reads.

A step is ONE jitted call with the state donated (one world: one XLA:CPU kernel,
:func:`quadswarm_mj.devices.loop_once`). With the free-body physics the carried state keeps only
the changing fields of ``mjx.Data`` (qpos, qvel, time, mocap_pos); the rest is rebuilt from
constants inside the jit. The state and outputs cross the host boundary packed
(:mod:`quadswarm_mj.perf.packing`). B worlds are sharded over every device whose count divides B
(:class:`~quadswarm_mj.envs.sharding.WorldSharding`).
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.devices import check_mjx_batch, loop_once
from quadswarm_mj.envs.mjx_env import AutoResetWrapper, MjxQuadSwarmEnv, State
from quadswarm_mj.envs.sharding import WorldSharding
from quadswarm_mj.metrics import METRIC_KEYS, OBSTACLE_METRIC_KEYS
from quadswarm_mj.perf.packing import LeafPacker, OutputLayout, StatePacker, key_shape, wrap_keys
from quadswarm_mj.perf.xla_options import one_world_options
from quadswarm_mj.rewards import OBSTACLE_TERMS, TERMS

STATE_KEYS = ("pos", "vel", "rot", "omega", "thrust")


class KeyStream:
    """Host-side stream of JAX key data from a seed (``np.random.SeedSequence``, any int)."""

    def __init__(self, seed: int):
        self.rng = np.random.default_rng(np.random.SeedSequence(int(seed)))
        self.shape = key_shape()

    def draw(self, lead: tuple[int, ...] = ()) -> np.ndarray:
        """Key data (*lead, *key_shape) uint32."""
        return self.rng.integers(0, 2**32, size=tuple(lead) + self.shape, dtype=np.uint32)


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


def init_variant(state: dict[str, Any] | None) -> tuple[tuple[str, ...], str | None]:
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
            return wrap_keys(one(jax.random.key_data(x), jax.random.key_data(y)))
        p = jnp.reshape(pred, pred.shape + (1,) * (x.ndim - pred.ndim))
        return jnp.where(p, x, y)

    return jax.tree.map(one, a, b)


# ------------------------------------------------------------------------------- programs
class Program:
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

    def __init__(self, cfg: EnvConfig, batch: int | None, compiler_options: dict[str, Any] | None = None):
        self.cfg, self.batch = cfg, batch
        #: XLA compile options of the one-world programs (default: quadswarm_mj.perf.xla_options)
        self.compiler_options = one_world_options() if compiler_options is None else dict(compiler_options)
        # one world: the fused random numbers (perf.fused_draws): 2.2-2.5x the steps/s of jax.random's many small
        # kernels per step (QuadSwarmEnv(engine='jax'), 8 quads, tune_jax_cpu); B worlds: jax.random (the
        # fused form 1.07-1.25x at 512 worlds per worker, below issue 33's 1.3x; docs/engines.md)
        self.env = MjxQuadSwarmEnv(cfg, draws="fused" if batch is None else "jax")
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
        kw: dict[str, Any] = {"donate_argnums": 0} if donate else {}
        if self.batch is None and self.compiler_options:
            kw["compiler_options"] = self.compiler_options
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
                return self.env.reset(wrap_keys(k), init or None)

            if self.batch is None:
                def impl(key_data: jax.Array, arrays: dict[str, jax.Array]) -> tuple:
                    s = one_reset(key_data, arrays)
                    return self._pack(s), self.layout.pack(self._outs(s, s), self.float)
                self._resets[key] = self._jit(impl, donate=False)
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
def program(cfg: EnvConfig, batch: int | None) -> Program:
    """The programs of ``cfg`` for ``batch`` worlds (None: one unbatched world), shared by every env of that config."""
    return Program(cfg, batch)


def init_arrays(state: dict[str, Any] | None, dtype: Any) -> dict[str, np.ndarray]:
    """The array entries of a reset's ``state`` as ``dtype`` (strings and Nones are static: :func:`init_variant`)."""
    if state is None:
        return {}
    return {k: np.asarray(v, dtype) for k, v in state.items() if v is not None and not isinstance(v, str)}


def host_rows(x: jax.Array) -> list[np.ndarray]:
    """The host views of a batched array's device shards, in world order (read-only; CPU: no copy)."""
    shards = x.addressable_shards
    if len(shards) == 1:
        return [np.asarray(x)]
    return [np.asarray(sh.data) for sh in sorted(shards, key=lambda sh: sh.index[0].start or 0)]
