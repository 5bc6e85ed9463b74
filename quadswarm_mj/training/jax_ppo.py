"""PPO on the JAX engine: rollouts and updates in ONE jitted function per iteration.

``JaxPPOTrainer`` runs the project's PPO (the pieces of :mod:`quadswarm_mj.training.ppo`: Brax's loss,
networks or the encoders of :mod:`quadswarm_mj.training.networks`, Brax's normalizer) on
:class:`~quadswarm_mj.envs.mjx_env.MjxQuadSwarmEnv` through ``AutoResetWrapper.vstep``. One ``iteration`` is
a ``lax.scan`` over ``unroll_length`` control steps (policy sampling, ``vstep`` of every scenario's worlds,
first-episode desynchronization, collision replay of :mod:`quadswarm_mj.training.replay`, metric sums),
then the PPO update: no host callback, so it runs unchanged on a GPU. Agent order: scenario, world, quad.
Reward annealing runs inside the env (``info["total_steps"]``); :func:`anneal_steps_for` converts a budget
in agent-steps. Why not Brax's ``ppo.train``: docs/training.md ("Which trainer is faster here, and why").
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from brax.training import types as brax_types
from brax.training.acme import running_statistics

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.metrics import METRIC_KEYS
from quadswarm_mj.training.checkpoints import (
    TRAIN_STATE_FILE,
    load_init,
    load_train_state,
    save_policy_file,
    save_train_state,
)
from quadswarm_mj.training.distributed import broadcast_from_main, gather_worlds, global_array
from quadswarm_mj.training.learner import (
    TrainState,
    check_train_inputs_from,
    correlated_noise,
    init_params,
    make_networks,
    make_noise_policy_step,
    make_optimizer,
    make_policy_step,
    make_update_fn,
    obs_layout,
)
from quadswarm_mj.training.ppo_config import PPOConfig, ppo_meta, run_lr_scale
from quadswarm_mj.training.replay import ReplayConfig, init_replay, record, restart, tree_where
from quadswarm_mj.training.run_logs import plot_curves, start_run, write_logs

AXIS = "worlds"  # the device axis of the data-parallel iteration


def anneal_steps_for(agent_steps: float, num_worlds: int, num_quads: int) -> int:
    """``rewards.anneal_steps`` (control steps per world) for an annealing over ``agent_steps`` agent-steps
    of a run with ``num_worlds`` worlds of ``num_quads`` quads (the original anneals over 3e8 frames)."""
    return max(1, int(round(agent_steps / (num_worlds * num_quads))))


def check_engine_config(env: Any, cfg: EnvConfig) -> None:
    """Raise ValueError if the JAX engine cannot simulate ``cfg`` as configured (its reset fails or its
    observation does not have the config's layout)."""
    try:
        st = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"the JAX engine rejects this configuration (scenario {cfg.scenario!r}): "
                         f"{type(e).__name__}: {e}") from e
    if tuple(st.obs.shape) != (cfg.num_quads, cfg.obs_dim):
        raise ValueError(f"the JAX engine's observation has shape {tuple(st.obs.shape)}, the config needs "
                         f"{(cfg.num_quads, cfg.obs_dim)}")


class JaxPPOTrainer:
    """PPO with rollouts on ``MjxQuadSwarmEnv`` inside one jitted iteration (see the module docstring).

    ``cfgs``: one EnvConfig per scenario (same ``num_quads`` and observation layout); ``weights``: the
    share of the worlds of each (default equal); ``replay``: collision replay (None or ``prob`` 0: off).
    Use :meth:`train`. The same outputs as :class:`~quadswarm_mj.training.ppo.PPOTrainer`.
    """

    def __init__(self, cfgs: list[EnvConfig], ppo: PPOConfig, seed: int = 0, init_from: str | None = None,
                 replay: ReplayConfig | None = None, weights: list[float] | None = None,
                 devices: int | None = None):
        from quadswarm_mj.envs.mjx_env import AutoResetWrapper, MjxQuadSwarmEnv

        if not cfgs:
            raise ValueError("need at least one scenario config")
        n, d = cfgs[0].num_quads, cfgs[0].obs_dim
        for c in cfgs:
            if c.num_quads != n or c.obs_dim != d or obs_layout(c) != obs_layout(cfgs[0]):
                raise ValueError("all training scenarios must share num_quads and the observation layout")
        self.cfgs, self.ppo, self.seed, self.N, self.obs_dim = cfgs, ppo, seed, n, d
        self.worlds = split_worlds(ppo.num_worlds, weights or [1.0] * len(cfgs))
        self.num_agents = sum(self.worlds) * n
        if self.num_agents % ppo.num_minibatches:
            raise ValueError(f"the number of agents ({self.num_agents} = worlds x quads) must be divisible by "
                             f"ppo.num_minibatches={ppo.num_minibatches}")
        self.replay = replay if replay is not None and replay.enabled else None
        self.envs = []
        for c in cfgs:
            try:
                env = AutoResetWrapper(MjxQuadSwarmEnv(c))
            except Exception as e:  # noqa: BLE001
                raise ValueError(f"the JAX engine rejects this configuration (scenario {c.scenario!r}): "
                                 f"{type(e).__name__}: {e}") from e
            check_engine_config(env, c)
            self.envs.append(env)
        check_train_inputs_from(ppo, d, init_from)
        self.layout = obs_layout(cfgs[0])
        self.networks, self.arch = make_networks(ppo, self.layout)
        self.optimizer = make_optimizer(ppo)
        key = jax.random.PRNGKey(seed)
        self.key, kinit, _ = jax.random.split(key, 3)
        params = init_params(self.networks, ppo, self.arch, kinit)
        normalizer = running_statistics.init_state(jax.ShapeDtypeStruct((d,), jnp.float32))
        if init_from is not None:
            params, normalizer = self._load_init(init_from, params, normalizer)
        self.state = TrainState(params=params, opt_state=self.optimizer.init(params), normalizer=normalizer)
        self._policy_step = make_policy_step(self.networks)
        self._noise_policy_step = make_noise_policy_step(self.networks)
        self.num_processes, self.is_main = jax.process_count(), jax.process_index() == 0
        self.num_devices = self._data_parallel_devices(devices)
        self._update = make_update_fn(self.networks, self.optimizer, ppo,
                                      axis_name=AXIS if self.num_devices > 1 else None)
        self._reset = [jax.jit(jax.vmap(e.reset)) for e in self.envs]
        self._iteration = self._jit_iteration()
        self.env_steps = 0
        self.iteration = 0
        self.lr_start = 1.0
        self._lr_scale = 1.0
        self._resume_total_steps: list[np.ndarray] | None = None
        self.compile_s: float | None = None

    def _load_init(self, path: str, params: Any, normalizer: Any) -> tuple[Any, Any]:
        """Warm start from a policy file (MLP: zero weights for new neighbour inputs; encoders: same arch)."""
        return load_init(path, params, normalizer, self.arch, self.layout, self.obs_dim,
                         action_std=self.ppo.warm_start_std, min_std=self.ppo.min_action_std)

    # ------------------------------------------------------------------ rollout state
    def init_worlds(self, key: jax.Array) -> tuple[dict[str, Any], ...]:
        """Fresh worlds of every scenario: env states, first-episode lengths (desync), replay buffers."""
        rng = np.random.default_rng(self.seed + 7919 * self.iteration)
        out = []
        for k, (c, w) in enumerate(zip(self.cfgs, self.worlds)):
            key, kr = jax.random.split(key)
            st = self._reset[k](jax.random.split(kr, w))
            if self._resume_total_steps is not None and self._resume_total_steps[k].shape == (w,):
                st = st.replace(info={**st.info, "total_steps": jnp.asarray(self._resume_total_steps[k],
                                                                            st.info["total_steps"].dtype)})
            steps = c.episode_steps
            first_len = (rng.integers(1, steps + 1, size=w) if self.ppo.desync_episodes
                         else np.full(w, steps + 1))
            wd = {"env": st, "first": jnp.ones((w,), bool), "first_len": jnp.asarray(first_len, jnp.int32),
                  "ep_ret": jnp.zeros((w,), jnp.float32)}
            if self.replay is not None:
                wd["replay"] = init_replay(st, self.replay)
            if self.ppo.noise_correlation > 0:  # each agent's exploration noise (noise_correlation)
                key, kn = jax.random.split(key)
                wd["noise"] = jax.random.normal(kn, (w, self.N, 4), jnp.float32)
            out.append(wd)
        if self.num_processes > 1:  # every process computed all worlds: it places its own devices' slices
            ws, rep = self._world_sharding()
            out = jax.tree.map(lambda x: global_array(x, ws if x.size else rep), out)
        elif self.num_devices > 1:  # every leaf has the leading worlds axis: each device gets its slice
            ws, rep = self._world_sharding()  # (empty arrays come back replicated: place them so, no recompile)
            out = jax.tree.map(lambda x: jax.device_put(x, ws if x.size else rep), out)
        return tuple(out)

    # ------------------------------------------------------------------ the jitted iteration
    def _data_parallel_devices(self, devices: int | None) -> int:
        """The devices the iteration runs on (data parallel): ``devices`` (None: as many of
        ``jax.devices()`` as divide every scenario's worlds and the minibatches; 1 with replay,
        whose buffer is shared by all worlds). Over several processes (``jax.distributed``): every
        device of every process."""
        avail = len(jax.devices())
        if self.num_processes > 1:
            if self.replay is not None:
                raise ValueError("collision replay runs on one device: training over several processes needs "
                                 "replay off (replay prob 0)")
            if devices not in (None, avail):
                raise ValueError(f"over {self.num_processes} processes the iteration runs on all {avail} devices "
                                 f"(jax.devices()), got devices={devices!r}")
            if not all(w % avail == 0 for w in self.worlds) or (self.num_agents // avail) % self.ppo.num_minibatches:
                raise ValueError(f"the {avail} devices of the {self.num_processes} processes must divide every "
                                 f"scenario's worlds {self.worlds} and leave a multiple of "
                                 f"num_minibatches={self.ppo.num_minibatches} agents per device")
            return avail
        if devices is not None:
            if not isinstance(devices, int) or not 1 <= devices <= avail:
                raise ValueError(f"devices must be an int in [1, {avail}] (jax.devices()), got {devices!r}")
        if self.replay is not None:
            if devices not in (None, 1):
                raise ValueError("collision replay runs on one device: use devices=1 (or None)")
            return 1

        def fits(d: int) -> bool:
            return all(w % d == 0 for w in self.worlds) and (self.num_agents // d) % self.ppo.num_minibatches == 0

        if devices is not None:
            if not fits(devices):
                raise ValueError(f"devices={devices} must divide every scenario's worlds {self.worlds} and leave "
                                 f"a multiple of num_minibatches={self.ppo.num_minibatches} agents per device")
            return devices
        return max(d for d in range(1, avail + 1) if fits(d))

    def _world_sharding(self) -> tuple[Any, Any]:
        """(worlds-axis sharding, replicated sharding) on the iteration's devices."""
        from jax.sharding import Mesh, NamedSharding, PartitionSpec

        mesh = Mesh(np.asarray(jax.devices()[:self.num_devices]), (AXIS,))
        return NamedSharding(mesh, PartitionSpec(AXIS)), NamedSharding(mesh, PartitionSpec())

    def _jit_iteration(self) -> Callable:
        """The jitted iteration; on D > 1 devices each runs the rollout of its slice of every scenario's
        worlds and the data-parallel update (:func:`make_update_fn` with ``axis_name``); the train state
        stays replicated, the returned sums are totals over the devices."""
        it = self._make_iteration()
        if self.num_devices == 1:
            return jax.jit(it, donate_argnums=(0,))
        from jax.sharding import PartitionSpec

        rep, wsp = PartitionSpec(), PartitionSpec(AXIS)
        carry_spec = (rep, wsp, rep)
        mapped = jax.shard_map(it, mesh=self._world_sharding()[0].mesh, in_specs=(carry_spec, rep),
                               out_specs=(carry_spec, rep, rep), check_vma=False)
        return jax.jit(mapped, donate_argnums=(0,))

    def _make_iteration(self) -> Callable:
        T, N, D = self.ppo.unroll_length, self.N, self.obs_dim
        envs, rcfg, cfgs = self.envs, self.replay, self.cfgs
        nd = self.num_devices
        worlds = [w // nd for w in self.worlds]  # per device
        axis = AXIS if nd > 1 else None
        policy_step, noise_step, update = self._policy_step, self._noise_policy_step, self._update
        rho = float(self.ppo.noise_correlation)

        def local(key: jax.Array) -> jax.Array:  # a device's own stream (rollout noise, resets, shuffles)
            return key if axis is None else jax.random.fold_in(key, jax.lax.axis_index(axis))

        def cut_first(env: Any, s: Any, cut: jax.Array, key: jax.Array, w: int) -> Any:
            fresh = jax.vmap(env.reset)(jax.random.split(key, w))
            fresh = fresh.replace(info={**fresh.info, "total_steps": s.info["total_steps"]},
                                  done=s.done, reward=s.reward, metrics=s.metrics)
            return tree_where(cut, fresh, s)

        def world_step(k: int, wd: dict[str, Any], a: jax.Array, key: jax.Array) -> tuple[dict, Any, Any, dict]:
            env, w = envs[k], worlds[k]
            k_cut, k_rec, k_rs = jax.random.split(key, 3)
            prev = wd["env"]
            s = env.vstep(prev, a)
            done = s.done
            cut = wd["first"] & ~done & (s.info["step"] >= wd["first_len"])
            s = jax.lax.cond(jnp.any(cut), lambda x: cut_first(env, x, cut, k_cut, w), lambda x: x, s)
            ended = done | cut
            ep_ret = wd["ep_ret"] + jnp.mean(s.reward, axis=-1).astype(jnp.float32)
            was_replay = wd["replay"].replaying if rcfg is not None else jnp.zeros((w,), bool)
            log = done & ~wd["first"] & ~was_replay
            logf = log.astype(jnp.float32)
            em = s.info["episode_metrics"]
            sums = {"episodes": jnp.sum(logf), "return": jnp.sum(jnp.where(log, ep_ret, 0.0))}
            for m in METRIC_KEYS:
                v = em[m].astype(jnp.float32)
                ok = log & jnp.isfinite(v)
                sums[m] = jnp.sum(jnp.where(ok, v, 0.0))
                sums[m + "#n"] = jnp.sum(ok.astype(jnp.float32))
            sums["ended"] = jnp.sum(done.astype(jnp.float32))
            new = {"env": s, "first": wd["first"] & ~ended, "first_len": wd["first_len"],
                   "ep_ret": jnp.where(ended, 0.0, ep_ret)}
            if rcfg is not None:
                # a desync cut ends an episode too: its snapshots must not be written for the next one
                s = s.replace(done=ended)
                rs = record(wd["replay"], prev, s, rcfg, cfgs[k].control_dt, k_rec)
                s, rs, mask = restart(rs, s, rcfg, k_rs)
                new["env"], new["replay"] = s, rs
                sums["replays"] = jnp.sum(mask.astype(jnp.float32))
            return new, s.reward.reshape(-1), jnp.repeat(ended, N).astype(jnp.float32), sums

        def env_step(ts: TrainState, carry: Any, _: Any) -> tuple[Any, Any]:
            wds, key = carry
            key, k_act, *k_w = jax.random.split(key, 2 + len(wds))
            obs = jnp.concatenate([wd["env"].obs.reshape(-1, D) for wd in wds]).astype(jnp.float32)
            if rho > 0:  # AR(1) noise per agent: N(0, 1) at every step, correlated over ~1 / (1 - rho) steps
                prev = jnp.concatenate([wd["noise"].reshape(-1, 4) for wd in wds])
                eps = correlated_noise(prev, k_act, rho)
                act, extras = noise_step(ts.normalizer, ts.params.policy, obs, eps)
            else:
                act, extras = policy_step(ts.normalizer, ts.params.policy, obs, k_act)
            new_wds, rews, truncs, sums = [], [], [], []
            i = 0
            for k, wd in enumerate(wds):
                a = act[i:i + worlds[k] * N].reshape(worlds[k], N, 4)
                nw, r, tr, sm = world_step(k, wd, a, k_w[k])
                if rho > 0:
                    nw["noise"] = eps[i:i + worlds[k] * N].reshape(worlds[k], N, 4)
                i += worlds[k] * N
                new_wds.append(nw)
                rews.append(r)
                truncs.append(tr)
                sums.append(sm)
            nobs = jnp.concatenate([wd["env"].obs.reshape(-1, D) for wd in new_wds]).astype(jnp.float32)
            trunc = jnp.concatenate(truncs)
            tr = brax_types.Transition(observation=obs, action=act, reward=jnp.concatenate(rews).astype(jnp.float32),
                                       discount=jnp.ones_like(trunc), next_observation=nobs,
                                       extras={"policy_extras": extras, "state_extras": {"truncation": trunc}})
            return (tuple(new_wds), key), (tr, tuple(sums))

        def iteration(carry: Any, lr_scale: jax.Array) -> tuple[Any, dict[str, Any], Any]:
            ts, wds, key = carry
            key, k_upd, k_roll = jax.random.split(key, 3)
            (wds, _), (data, sums) = jax.lax.scan(lambda c, x: env_step(ts, c, x), (wds, local(k_roll)), None,
                                                  length=T)
            ts, m = update(ts, data, local(k_upd), lr_scale)
            m["reward_per_step"] = jnp.mean(data.reward)
            sums = jax.tree.map(lambda x: jnp.sum(x, axis=0), sums)
            if axis is not None:  # totals and means over the devices
                m["reward_per_step"] = jax.lax.pmean(m["reward_per_step"], axis)
                sums = jax.lax.psum(sums, axis)
            if rcfg is not None:
                for k, wd in enumerate(wds):
                    rs = wd["replay"]
                    sums[k]["buffer_size"] = jnp.sum(rs.valid.astype(jnp.float32))
                    sums[k]["buffer_added"] = rs.added.astype(jnp.float32)
                    sums[k]["buffer_replayed"] = rs.replayed.astype(jnp.float32)
            return (ts, wds, key), m, sums

        return iteration

    # ------------------------------------------------------------------ save / resume
    def train_meta(self, extra_meta: dict[str, Any] | None = None) -> dict[str, Any]:
        return {"engine": "jax", "scenarios": [c.scenario for c in self.cfgs], "worlds": list(self.worlds),
                "env_steps": int(self.env_steps), "iterations": int(self.iteration), "seed": self.seed,
                "ppo": ppo_meta(self.ppo), "replay": None if self.replay is None else vars(self.replay),
                "processes": self.num_processes, "devices": self.num_devices, **(extra_meta or {})}

    def save(self, path: str | Path, extra_meta: dict[str, Any] | None = None) -> str | None:
        """Write the policy file (MLP format 1 or encoder format 2); returns its SHA-256. Over several
        processes only process 0 writes (the others return None)."""
        if not self.is_main:
            return None
        return save_policy_file(path, self.ppo, self.arch, self.cfgs[0], self.state, self.train_meta(extra_meta))

    def save_state(self, path: str | Path, wds: tuple[dict[str, Any], ...] | None = None) -> None:
        """The resumable learner state, RNG key, counters and the worlds' ``total_steps`` (annealing).
        Over several processes every process must call it (the worlds' clocks are gathered) and process 0
        writes."""
        extra = {}
        if wds is not None:
            for k, wd in enumerate(wds):
                extra[f"total_steps_{k}"] = gather_worlds(wd["env"].info["total_steps"])
        if not self.is_main:
            return
        save_train_state(path, self.state, self.key, {"engine": "jax", "env_steps": int(self.env_steps),
                                                      "iteration": int(self.iteration),
                                                      "lr_scale": float(self._lr_scale)}, extra)

    def resume(self, path: str | Path) -> None:
        """Continue from a :meth:`save_state` file (parameters, Adam state, normalizer, RNG, counters,
        annealing clocks). Worlds start fresh episodes; the replay buffer starts empty."""
        self.state, self.key, sc, extra = load_train_state(path, self.state)
        self.env_steps, self.iteration = int(sc["env_steps"]), int(sc["iteration"])
        self.lr_start = float(sc.get("lr_scale", 1.0))
        self._resume_total_steps = [extra[f"total_steps_{k}"] for k in range(len(self.cfgs))
                                    if f"total_steps_{k}" in extra] or None
        if self._resume_total_steps is not None and len(self._resume_total_steps) != len(self.cfgs):
            self._resume_total_steps = None

    # ------------------------------------------------------------------ training loop
    def train(self, total_steps: int | None = None, seconds: float | None = None, out_dir: str | Path | None = None,
              log_every: int = 1, checkpoint_every_s: float = 300.0, progress: bool = True,
              callback: Callable[[dict[str, Any]], None] | None = None,
              history: list[dict[str, Any]] | None = None) -> list[dict[str, Any]]:
        """Train until this run has done ``total_steps`` agent-steps or ``seconds`` of wall time (the
        compile counts against ``seconds``). Writes ``progress.csv``/``progress.json``, ``curves.png``,
        ``checkpoints/`` (policy files and ``train_state.npz``) and ``final.npz`` into ``out_dir``.

        Over several processes every process calls it with the same arguments; process 0's clock decides
        when to stop and to checkpoint and sets the learning rate (broadcast each iteration), process 0
        alone writes files and shows the progress bar; every process returns the same rows."""
        out, rows, self._wall0, bar = start_run(out_dir if self.is_main else None, history, total_steps, seconds,
                                                progress and self.is_main)
        want_ckpt = out_dir is not None  # every process joins the checkpoint's gather, process 0 writes
        per_iter = self.num_agents * self.ppo.unroll_length
        t0 = time.perf_counter()
        last_ckpt = t0
        self.key, k_env = jax.random.split(self.key)
        carry = (self.state, self.init_worlds(k_env), self.key)
        if self.num_processes > 1:  # host values onto the global mesh (replicated)
            rep = self._world_sharding()[1]
            carry = (jax.tree.map(lambda x: global_array(x, rep), self.state), carry[1], global_array(self.key, rep))
        elif self.num_devices > 1:  # placed as the iteration returns them: no second compile
            rep = self._world_sharding()[1]
            carry = (jax.device_put(self.state, rep), carry[1], jax.device_put(self.key, rep))
        steps0 = self._steps0 = self.env_steps
        if bar is not None:
            bar.steps0 = steps0
        t_first = None
        while True:
            now = time.perf_counter()
            elapsed = now - t0
            stop = ((total_steps is not None and self.env_steps - steps0 >= total_steps)
                    or (seconds is not None and elapsed >= seconds))
            # the learning-rate schedule follows the step budget when there is one (the wall clock then only
            # caps the run, so a run that reaches its budget is reproducible from its seed), else the clock
            frac = (self.env_steps - steps0) / max(total_steps, 1) if total_steps is not None else elapsed / seconds
            lr_scale = run_lr_scale(self.ppo, self.env_steps, frac, self.lr_start)
            ckpt = want_ckpt and now - last_ckpt >= checkpoint_every_s
            stop, ckpt, lr_scale = broadcast_from_main(np.array([stop, ckpt, lr_scale], np.float64))
            if ckpt and not stop:
                self.save(out / "checkpoints" / f"step_{self.env_steps:012d}.npz" if out else "")
                self.save_state(out / "checkpoints" / TRAIN_STATE_FILE if out else "", carry[1])
                last_ckpt = now
                if out is not None:
                    write_logs(out, rows)
                    plot_curves(out / "progress.json", out / "curves.png")
            if stop:
                break
            self._lr_scale = float(lr_scale)
            carry, m, sums = self._iteration(carry, jnp.float32(self._lr_scale))
            m, sums = jax.device_get((m, sums))  # one small transfer per iteration
            self.state, wds, self.key = carry
            self.env_steps += per_iter
            self.iteration += 1
            now = time.perf_counter()
            if t_first is None:
                t_first = now
                self.compile_s = now - t0
                steps_first = self.env_steps
            row = self._log_row(now - t0, m, sums)
            if t_first is not None and now > t_first:
                row["steps_per_s_compiled"] = round((self.env_steps - steps_first) / (now - t_first), 1)
            rows.append(row)
            if bar is not None:
                bar.update(row)
            if callback is not None and self.iteration % log_every == 0:
                callback(row)
            if out is not None and self.iteration % (10 * log_every) == 0:
                write_logs(out, rows)
        if bar is not None:
            bar.close(rows[-1] if rows else None)
        if want_ckpt:
            self.save(out / "final.npz" if out else "", {"wall_seconds": round(time.perf_counter() - t0, 1)})
            self.save_state(out / "checkpoints" / TRAIN_STATE_FILE if out else "", carry[1])
        if out is not None:
            write_logs(out, rows)
            plot_curves(out / "progress.json", out / "curves.png")
        return rows

    def _log_row(self, wall: float, m: dict[str, Any], sums: tuple[dict[str, Any], ...]) -> dict[str, Any]:
        row: dict[str, Any] = {"iteration": self.iteration, "env_steps": int(self.env_steps),
                               "learning_rate": float(m["learning_rate"]), "wall_s": round(self._wall0 + wall, 2),
                               "steps_per_s": round((self.env_steps - self._steps0) / max(wall, 1e-9), 1),
                               "reward_per_step": float(m["reward_per_step"])}
        for key in ("total_loss", "policy_loss", "v_loss", "kl_mean", "policy_dist_mean_std"):
            if key in m:
                row[key] = float(m[key])
        for c, sm in zip(self.cfgs, sums):
            scn = c.scenario
            ne = float(sm["episodes"])
            row[f"{scn}/episodes"] = int(ne)
            for key in METRIC_KEYS:
                cnt = float(sm[key + "#n"])
                row[f"{scn}/{key}"] = float(sm[key]) / cnt if cnt > 0 else float("nan")
            row[f"{scn}/return"] = float(sm["return"]) / ne if ne > 0 else float("nan")
            if "replays" in sm:
                ended = float(sm["ended"])
                row[f"{scn}/replay_rate"] = float(sm["replays"]) / ended if ended > 0 else float("nan")
                row[f"{scn}/replay_buffer_size"] = int(sm["buffer_size"])
                row[f"{scn}/replay_added"] = int(sm["buffer_added"])
        return row


def split_worlds(num_worlds: int, weights: list[float]) -> list[int]:
    """Worlds per scenario in proportion to ``weights`` (largest remainder), each >= 1."""
    w = np.asarray(weights, float)
    if w.ndim != 1 or len(w) == 0 or np.any(~np.isfinite(w)) or np.any(w <= 0):
        raise ValueError(f"scenario weights must be positive numbers, got {weights!r}")
    if num_worlds < len(w):
        raise ValueError(f"ppo.num_worlds={num_worlds} is fewer than the {len(w)} scenarios")
    exact = num_worlds * w / w.sum()
    out = np.maximum(np.floor(exact).astype(int), 1)
    while out.sum() < num_worlds:
        out[np.argmax(exact - out)] += 1
    while out.sum() > num_worlds:
        out[np.argmax(np.where(out > 1, out - exact, -np.inf))] -= 1
    return [int(x) for x in out]
