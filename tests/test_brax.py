"""Brax front end: shapes of the folded (quads-as-agents) env, and a few PPO iterations of
``brax.training.agents.ppo.train`` on CPU with tiny settings."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytest.importorskip("brax")
import jax.numpy as jnp  # noqa: E402
from brax.envs.wrappers.training import EvalWrapper  # noqa: E402

from quadswarm_mj import EnvConfig  # noqa: E402
from quadswarm_mj.envs.brax_env import SWARM_METRICS, BraxQuadSwarmEnv  # noqa: E402
from quadswarm_mj.rewards import TERMS  # noqa: E402

N = 2


def test_folded_shapes_and_agent_count_check():
    env = BraxQuadSwarmEnv(EnvConfig(num_quads=N, episode_seconds=0.05))
    assert env.action_size == 4 and env.observation_size == env.cfg.obs_dim and env.episode_length == 5
    keys = jax.random.split(jax.random.PRNGKey(0), 3 * N)
    s = jax.eval_shape(env.reset, keys)
    assert s.obs.shape == (3 * N, env.cfg.obs_dim) and s.reward.shape == (3 * N,) and s.done.shape == (3 * N,)
    assert s.pipeline_state.obs.shape == (3, N, env.cfg.obs_dim)  # 3 worlds of N quads
    s1 = jax.eval_shape(env.step, s, jnp.zeros((3 * N, 4)))
    assert set(s1.metrics) == {f"reward/{t}" for t in TERMS}
    assert {"steps", "truncation", "episode_done", "episode_metrics"} <= set(s1.info)
    assert {"sum_reward", "length", *SWARM_METRICS} <= set(s1.info["episode_metrics"])
    with pytest.raises(ValueError, match="multiple of num_quads"):
        env.reset(jax.random.split(jax.random.PRNGKey(0), 3))
    # Brax's evaluator wrapper accepts the env (it needs info["steps"] and per-agent metrics)
    ev = EvalWrapper(env)
    e0 = jax.eval_shape(ev.reset, keys)
    e1 = jax.eval_shape(ev.step, e0, jnp.zeros((3 * N, 4)))
    assert e1.info["eval_metrics"].episode_steps.shape == (3 * N,)
    assert set(e1.info["eval_metrics"].episode_metrics) == {"reward", *(f"reward/{t}" for t in TERMS)}


_PPO_SCRIPT = textwrap.dedent("""
    import json
    import jax
    import jax.numpy as jnp
    import numpy as np
    from brax.training.agents.ppo import train as ppo
    from quadswarm_mj import EnvConfig
    from quadswarm_mj.envs.brax_env import BraxQuadSwarmEnv

    N = 2
    cfg = EnvConfig(num_quads=N, episode_seconds=0.05)  # 5-step episodes: several auto-resets per iteration
    env = BraxQuadSwarmEnv(cfg)
    progress = []
    make_policy, params, metrics = ppo.train(
        env, wrap_env=False, num_timesteps=160, episode_length=env.episode_length, action_repeat=1,
        num_envs=4 * N, num_eval_envs=2 * N, batch_size=8, num_minibatches=2, unroll_length=5,
        num_updates_per_batch=1, num_evals=1, run_evals=False, log_training_metrics=True, training_metrics_steps=40,
        progress_fn=lambda step, m: progress.append((int(step), {k: float(v) for k, v in m.items()})), seed=0)
    policy = make_policy(params, deterministic=True)
    action, _ = policy(jnp.zeros((3, cfg.obs_dim)), jax.random.PRNGKey(1))
    print(json.dumps({
        "metrics": {k: float(v) for k, v in metrics.items()},
        "progress": progress,
        "episode_length": env.episode_length,
        "action_shape": list(action.shape),
        "action_max": float(jnp.abs(action).max()),
        "params_finite": bool(all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(params))),
    }))
""")


def _brax_trainer_runs_on_this_jax() -> bool:
    import jax

    return hasattr(jax, "device_put_replicated")  # brax <= 0.14.2's PPO calls it; jax 0.10 removed it


@pytest.mark.slow
@pytest.mark.skipif(not _brax_trainer_runs_on_this_jax(),
                    reason="brax's PPO trainer calls jax.device_put_replicated, which this jax (>= 0.10) removed")
def test_ppo_trains_a_few_iterations_on_cpu():
    """brax.training.agents.ppo.train runs 2 PPO iterations on the env (several episodes end and
    auto-reset inside them). Brax's evaluator is left out here to save its compile (its wrapper is
    checked by tracing in the test above).

    Runs in a subprocess with XLA's backend optimization off: on CPU the run is almost all XLA
    compile time, which that flag roughly halves."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu",
           "XLA_FLAGS": (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0").strip()}
    out = subprocess.run([sys.executable, "-c", _PPO_SCRIPT], capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    r = json.loads(out.stdout.strip().splitlines()[-1])
    metrics, length = r["metrics"], r["episode_length"]
    assert np.isfinite(metrics["training/policy_loss"]) and np.isfinite(metrics["training/v_loss"])
    assert metrics["training/sps"] > 0
    # the training logger saw completed episodes of the folded env, with per-term reward sums and
    # the swarm's episode metrics
    logged = [m for _, m in r["progress"] if "episode/sum_reward" in m]
    assert logged and all(m["episode/length"] == pytest.approx(length) for m in logged)
    assert all(m["episode/sum_reward"] < 0 and np.isfinite(m["episode/reward/pos"]) for m in logged)
    assert all(np.isfinite(m["episode/success"]) and np.isfinite(m["episode/mean_distance"]) for m in logged)
    assert max(step for step, _ in r["progress"]) >= 160
    # the trained policy maps per-quad observations to per-quad rotor commands in [-1, 1]
    assert r["action_shape"] == [3, 4] and r["action_max"] <= 1.0
    assert r["params_finite"]
