"""PPO for quadswarm_mj: Brax's PPO (loss, networks, observation normalizer) on the batched CPU engine.

Rollouts run on :class:`~quadswarm_mj.envs.cpu_core.CpuSwarm` (NumPy + MuJoCo); the action sampling (one
jitted call per control step for all agents) and the update (one jitted call per iteration) run in JAX.
Every quad is an agent sharing one policy; several scenarios train at once, the worlds split evenly among
one engine per scenario. The pieces, shared with :mod:`quadswarm_mj.training.jax_ppo` and importable from
here too: :mod:`~quadswarm_mj.training.ppo_config`, :mod:`~quadswarm_mj.training.learner`,
:mod:`~quadswarm_mj.training.checkpoints`, :mod:`~quadswarm_mj.training.run_logs`,
:mod:`~quadswarm_mj.training.cpu_rollout`. Guide: docs/training.md.
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

# the pieces, re-exported (quadswarm_mj.training.ppo.<name>)
from quadswarm_mj.training.checkpoints import (  # noqa: F401
    TRAIN_STATE_FILE,
    load_init,
    load_train_state,
    save_policy_file,
    save_train_state,
)
from quadswarm_mj.training.cpu_rollout import AgentBatch
from quadswarm_mj.training.learner import (  # noqa: F401
    DrawnEntropyNormals,
    TrainState,
    _dense_layers,
    check_train_inputs_from,
    encoder_arch,
    env_meta,
    init_params,
    learning_rate_of,
    make_networks,
    make_optimizer,
    make_policy_step,
    make_update_fn,
    normalizer_stats,
    obs_layout,
    set_learning_rate,
)
from quadswarm_mj.training.ppo_config import (  # noqa: F401
    ACTIVATIONS,
    ARCH_NAMES,
    PPOConfig,
    linear_lr_scale,
    ppo_meta,
    run_lr_scale,
)
from quadswarm_mj.training.run_logs import plot_curves, start_run, write_logs  # noqa: F401


class PPOTrainer:
    """PPO on ``AgentBatch`` (the CPU engine). Use :meth:`train` (budget in agent-steps and/or seconds)."""

    def __init__(self, cfgs: list[EnvConfig], ppo: PPOConfig, seed: int = 0, init_from: str | None = None):
        if ppo.noise_correlation:
            raise ValueError("ppo.noise_correlation (correlated exploration) needs the JAX engine (engine='jax')")
        self.cfgs, self.ppo, self.seed = cfgs, ppo, seed
        nscn = len(cfgs)
        base, extra = divmod(ppo.num_worlds, nscn)
        worlds = [base + (1 if k < extra else 0) for k in range(nscn)]
        if min(worlds) < 1:
            raise ValueError(f"ppo.num_worlds={ppo.num_worlds} is fewer than the {nscn} scenarios")
        self.batch = AgentBatch(cfgs, worlds, seed, ppo.desync_episodes)
        A = self.batch.num_agents
        if A % ppo.num_minibatches:
            raise ValueError(f"the number of agents ({A} = worlds x quads) must be divisible by "
                             f"ppo.num_minibatches={ppo.num_minibatches}")
        self.obs_dim = self.batch.obs_dim
        check_train_inputs_from(ppo, self.obs_dim, init_from)
        self.layout = obs_layout(cfgs[0])
        self.networks, self.arch = make_networks(ppo, self.layout)
        self.optimizer = make_optimizer(ppo)
        key = jax.random.PRNGKey(seed)
        self.key, kinit = jax.random.split(key)
        params = init_params(self.networks, ppo, self.arch, kinit)
        normalizer = running_statistics.init_state(jax.ShapeDtypeStruct((self.obs_dim,), jnp.float32))
        if init_from is not None:
            params, normalizer = self._load_init(init_from, params, normalizer)
        self.state = TrainState(params=params, opt_state=self.optimizer.init(params), normalizer=normalizer)
        self._policy_step = jax.jit(make_policy_step(self.networks))
        self._update = jax.jit(make_update_fn(self.networks, self.optimizer, ppo))
        self.env_steps = 0  # agent-steps
        self.iteration = 0
        self.lr_start = 1.0  # learning-rate factor at the start of this run (resumed runs: the checkpoint's)
        self._lr_scale = 1.0

    # ------------------------------------------------------------------ init from a checkpoint
    def _load_init(self, path: str, params: Any, normalizer: Any) -> tuple[Any, Any]:
        """Warm start from a policy file (:func:`~quadswarm_mj.training.checkpoints.load_init`)."""
        return load_init(path, params, normalizer, self.arch, self.layout, self.obs_dim,
                         action_std=self.ppo.warm_start_std, min_std=self.ppo.min_action_std)

    def train_meta(self, extra_meta: dict[str, Any] | None = None) -> dict[str, Any]:
        return {"engine": "mujoco", "scenarios": [c.scenario for c in self.cfgs], "env_steps": int(self.env_steps),
                "iterations": int(self.iteration), "seed": self.seed, "ppo": ppo_meta(self.ppo), **(extra_meta or {})}

    def save(self, path: str | Path, extra_meta: dict[str, Any] | None = None) -> str:
        """Write a policy .npz (loadable by ``quadswarm_mj.policies``; also holds the critic and
        the normalizer count). Returns its SHA-256."""
        return save_policy_file(path, self.ppo, self.arch, self.cfgs[0], self.state, self.train_meta(extra_meta))

    def save_state(self, path: str | Path) -> None:
        """The resumable learner state (see :func:`save_train_state`)."""
        save_train_state(path, self.state, self.key, {"engine": "mujoco", "env_steps": int(self.env_steps),
                                                      "iteration": int(self.iteration),
                                                      "lr_scale": float(self._lr_scale)})

    def resume(self, path: str | Path) -> None:
        """Continue from a :meth:`save_state` file: parameters, Adam state, normalizer, RNG key, counters."""
        self.state, self.key, sc, _ = load_train_state(path, self.state)
        self.env_steps, self.iteration = int(sc["env_steps"]), int(sc["iteration"])
        self.lr_start = float(sc.get("lr_scale", 1.0))
        # the CPU engine's own NumPy streams are reseeded from the seed and the iteration
        for k, e in enumerate(self.batch.engines):
            e.seed(self.seed * 1000 + k + 7919 * self.iteration)

    # ------------------------------------------------------------------ training loop
    def collect(self, obs: np.ndarray) -> tuple[brax_types.Transition, np.ndarray, list]:
        """One unroll of ``unroll_length`` steps for all agents; returns (data [T, A], next obs, finished)."""
        T = self.ppo.unroll_length
        st = self.state
        obs_l, act_l, rew_l, nobs_l, trunc_l, ext_l, finished = [], [], [], [], [], [], []
        for _ in range(T):
            self.key, k = jax.random.split(self.key)
            act, extras = self._policy_step(st.normalizer, st.params.policy, obs, k)
            act_np = np.asarray(act)
            nobs, r, tr, cont, fin = self.batch.step(act_np)
            obs_l.append(obs)
            act_l.append(act_np)
            rew_l.append(r)
            nobs_l.append(nobs)
            trunc_l.append(tr)
            ext_l.append(extras)
            finished.extend(fin)
            obs = cont
        extras = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *ext_l)
        trunc = np.stack(trunc_l)
        data = brax_types.Transition(
            observation=np.stack(obs_l), action=np.stack(act_l), reward=np.stack(rew_l),
            discount=np.ones_like(trunc), next_observation=np.stack(nobs_l),
            extras={"policy_extras": extras, "state_extras": {"truncation": trunc}})
        return data, obs, finished

    def train(self, total_steps: int | None = None, seconds: float | None = None, out_dir: str | Path | None = None,
              log_every: int = 1, checkpoint_every_s: float = 300.0, progress: bool = True,
              callback: Callable[[dict[str, Any]], None] | None = None,
              history: list[dict[str, Any]] | None = None) -> list[dict[str, Any]]:
        """Train until ``total_steps`` agent-steps or ``seconds`` of wall time (whichever first).

        Writes ``progress.csv``/``progress.json``, ``curves.png`` and ``checkpoints/`` into
        ``out_dir`` when given. Returns the log rows.
        """
        out, rows, self._wall0, bar = start_run(out_dir, history, total_steps, seconds, progress)
        per_iter = self.batch.num_agents * self.ppo.unroll_length
        t0 = time.perf_counter()
        last_ckpt = t0
        obs = self.batch.reset()
        pending: list = []
        rew_acc, rew_n = 0.0, 0
        steps0 = self._steps0 = self.env_steps  # budgets count this run's steps (a resumed run continues the counter)
        if bar is not None:
            bar.steps0 = steps0
        while True:
            elapsed = time.perf_counter() - t0
            if total_steps is not None and self.env_steps - steps0 >= total_steps:
                break
            if seconds is not None and elapsed >= seconds:
                break
            data, obs, fin = self.collect(obs)
            pending.extend(fin)
            rew_acc += float(np.mean(data.reward))
            rew_n += 1
            self.key, k = jax.random.split(self.key)
            frac = 0.0
            if total_steps is not None:
                frac = max(frac, (self.env_steps - steps0) / max(total_steps, 1))
            if seconds is not None:
                frac = max(frac, (time.perf_counter() - t0) / seconds)
            self._lr_scale = run_lr_scale(self.ppo, self.env_steps, frac, self.lr_start)
            self.state, m = self._update(self.state, data, k, jnp.float32(self._lr_scale))
            self.env_steps += per_iter
            self.iteration += 1
            now = time.perf_counter()
            if self.iteration % log_every == 0:
                row = self._log_row(now - t0, rew_acc / max(rew_n, 1), pending, m)
                rows.append(row)
                pending, rew_acc, rew_n = [], 0.0, 0
                if bar is not None:
                    bar.update(row)
                if callback is not None:
                    callback(row)
                if out is not None and (self.iteration % (10 * log_every) == 0):
                    write_logs(out, rows)
            if out is not None and now - last_ckpt >= checkpoint_every_s:
                self.save(out / "checkpoints" / f"step_{self.env_steps:012d}.npz")
                self.save_state(out / "checkpoints" / TRAIN_STATE_FILE)
                last_ckpt = now
                write_logs(out, rows)
                plot_curves(out / "progress.json", out / "curves.png")
        if bar is not None:
            bar.close(rows[-1] if rows else None)
        if out is not None:
            self.save(out / "final.npz", {"wall_seconds": round(time.perf_counter() - t0, 1)})
            self.save_state(out / "checkpoints" / TRAIN_STATE_FILE)
            write_logs(out, rows)
            plot_curves(out / "progress.json", out / "curves.png")
        return rows

    def _log_row(self, wall: float, reward: float, finished: list, m: Any) -> dict[str, Any]:
        row: dict[str, Any] = {"iteration": self.iteration, "env_steps": int(self.env_steps),
                               "learning_rate": float(m["learning_rate"]) if "learning_rate" in m else None,
                               "wall_s": round(self._wall0 + wall, 2),
                               "steps_per_s": round((self.env_steps - self._steps0) / max(wall, 1e-9), 1),
                               "reward_per_step": reward}
        for key in ("total_loss", "policy_loss", "v_loss", "kl_mean", "policy_dist_mean_std"):
            if key in m:
                row[key] = float(m[key])
        for c in self.cfgs:
            scn = c.scenario
            got = [(mm, ret) for s, mm, ret in finished if s == scn]
            row[f"{scn}/episodes"] = int(sum(len(ret) for _, ret in got))
            for key in (*METRIC_KEYS, "return"):
                if got:
                    vals = np.concatenate([ret if key == "return" else mm[key] for mm, ret in got])
                    vals = vals[np.isfinite(vals)]
                    row[f"{scn}/{key}"] = float(vals.mean()) if vals.size else float("nan")
                else:
                    row[f"{scn}/{key}"] = float("nan")
        return row
