"""Agent-steps/s of the PPO trainers with the same settings, one after the other in one process (a
measurement, not part of the package): ``python scripts/compare_trainers.py --num-quads 8 --num-worlds 128
--iterations 8 --engines jax,mujoco`` (``brax`` adds Brax's ``ppo.train`` on ``BraxQuadSwarmEnv``).
Results and reading: docs/training.md ("Which trainer is faster here, and why")."""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.training.jax_ppo import JaxPPOTrainer
from quadswarm_mj.training.ppo_config import PPOConfig


def measure_trainers(cfg: EnvConfig, ppo: PPOConfig, iterations: int = 4, engines: tuple[str, ...] = ("jax", "mujoco",
                     "brax")) -> dict[str, dict[str, float]]:
    """Agent-steps/s of the trainers on ``cfg`` with the same PPO settings, measured one after the other in
    this process: ``jax`` (``JaxPPOTrainer``, after its first, compiling iteration), ``mujoco``
    (:class:`~quadswarm_mj.training.ppo.PPOTrainer` on the CPU engine, after its first iteration) and
    ``brax`` (``brax.training.agents.ppo.train`` on ``BraxQuadSwarmEnv``, its own ``training/sps`` of the
    second training epoch, i.e. without compile; the same networks, loss settings and batch). Each entry:
    ``agent_steps_per_s``, ``compile_s`` (first iteration / first epoch, incl. compile), ``iterations``."""
    import functools

    out: dict[str, dict[str, float]] = {}
    per_iter = ppo.num_worlds * cfg.num_quads * ppo.unroll_length
    for eng in engines:
        if eng in ("jax", "mujoco"):
            from quadswarm_mj.training.ppo import PPOTrainer

            tr: Any = (JaxPPOTrainer([cfg], ppo) if eng == "jax" else PPOTrainer([cfg], ppo))
            t0 = time.perf_counter()
            rows = tr.train(total_steps=per_iter * (iterations + 1), progress=False)
            first = rows[0]["wall_s"]
            rest = rows[-1]["wall_s"] - first
            out[eng] = {"agent_steps_per_s": per_iter * iterations / max(rest, 1e-9), "compile_s": first,
                        "iterations": iterations, "total_s": time.perf_counter() - t0}
        elif eng == "brax":
            from brax.training.agents.ppo import networks as bnet
            from brax.training.agents.ppo import train as brax_ppo

            from quadswarm_mj.envs.brax_env import BraxQuadSwarmEnv

            env = BraxQuadSwarmEnv(cfg)
            agents = ppo.num_worlds * cfg.num_quads
            log: list[tuple[float, int, dict]] = []
            t0 = time.perf_counter()

            def progress(step: int, m: dict, log: list = log) -> None:
                log.append((time.perf_counter(), step, dict(m)))

            brax_ppo.train(env, wrap_env=False, num_timesteps=per_iter * 2 * iterations,
                           episode_length=cfg.episode_steps,
                           num_envs=agents, num_eval_envs=cfg.num_quads, batch_size=agents // ppo.num_minibatches,
                           num_minibatches=ppo.num_minibatches, unroll_length=ppo.unroll_length,
                           num_updates_per_batch=ppo.num_epochs, learning_rate=ppo.learning_rate,
                           entropy_cost=ppo.entropy_cost, discounting=ppo.discounting, gae_lambda=ppo.gae_lambda,
                           clipping_epsilon=ppo.clipping_epsilon, reward_scaling=ppo.reward_scaling,
                           normalize_observations=ppo.normalize_observations, max_grad_norm=ppo.max_grad_norm,
                           action_repeat=1, num_evals=3, seed=0,
                           network_factory=functools.partial(bnet.make_ppo_networks,
                                                             policy_hidden_layer_sizes=ppo.policy_hidden,
                                                             value_hidden_layer_sizes=ppo.value_hidden),
                           progress_fn=progress)
            sps = [float(m["training/sps"]) for _, _, m in log if "training/sps" in m]
            out[eng] = {"agent_steps_per_s": sps[-1] if sps else float("nan"),
                        "first_epoch_sps": sps[0] if sps else float("nan"), "iterations": iterations,
                        "total_s": time.perf_counter() - t0}
        else:
            raise ValueError(f"unknown trainer {eng!r}: use jax, mujoco, brax")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description="agent-steps/s of the trainers (same run, same PPO settings)")
    ap.add_argument("--num-quads", type=int, default=8)
    ap.add_argument("--num-worlds", type=int, default=128)
    ap.add_argument("--scenario", default="static_diff_goal")
    ap.add_argument("--iterations", type=int, default=4)
    ap.add_argument("--arch", default="mlp")
    ap.add_argument("--engines", default="jax,mujoco,brax")
    ap.add_argument("--cpu-devices", type=int, default=None, help="JAX CPU devices (default: one per core)")
    a = ap.parse_args()
    from quadswarm_mj.devices import use_cpu_cores

    use_cpu_cores(a.cpu_devices, strict=False)
    res = measure_trainers(EnvConfig(num_quads=a.num_quads, scenario=a.scenario),
                           PPOConfig(num_worlds=a.num_worlds, arch=a.arch), a.iterations,
                           tuple(a.engines.split(",")))
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
