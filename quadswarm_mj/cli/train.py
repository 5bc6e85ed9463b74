"""Train a quadswarm_mj policy with PPO (Brax's loss, networks and normalizer in JAX).

Two rollout engines (``--engine``): ``mujoco`` (the batched CPU MuJoCo engine, one jitted call per
control step for the actions and one per iteration for the update) and ``jax`` (``MjxQuadSwarmEnv``:
rollouts and updates in one jitted function per iteration, runs unchanged on a GPU; see
``quadswarm_mj.training.jax_ppo``). Presets (``--preset``, the options given override them)::

    python scripts/train.py --preset single --minutes 1 --out runs/single   # the default: one quad, < 1 min
    python scripts/train.py --preset swarm8 --out runs/swarm8 --minutes 90  # 8 quads, deep sets, JAX engine
    python scripts/train.py --resume runs/swarm8 --minutes 90               # continue from the last checkpoint

``single_v1`` and ``swarm8_v1`` are the recipes of ``pretrained:single`` and ``pretrained:swarm8_v1``;
the other presets are listed in docs/training.md. Everything is configurable: ``--scenario``,
``--num-quads``, ``--reward TERM=SCALE``, ``--env FIELD=VALUE``, ``--arch``, the PPO hyper-parameters,
``--replay-prob``, ``--anneal-agent-steps``, the budget (``--minutes`` and/or ``--timesteps`` in
agent-steps) and ``--seed``.

Output in ``--out``: ``run.json``, ``progress.csv``/``progress.json`` (per iteration), ``curves.png``,
``checkpoints/step_*.npz`` with ``checkpoints/train_state.npz`` (what ``--resume`` reads) and
``final.npz``; every ``step_*.npz``/``final.npz`` is a policy file for ``scripts/evaluate.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from quadswarm_mj.policies import ARCH_PRESETS  # NumPy only

ARCH_CHOICES = ("mlp", *ARCH_PRESETS)
#: the original's obstacle-run settings (SPEC_obstacles A.6 / C): K = 2, 20 % density, 0.6 m columns, downwash,
#: the floor-distance self observation; obstacles themselves are wired into the engines separately
OBSTACLE_ENV: dict[str, Any] = {"num_neighbors": 2, "downwash": True, "obs_self": "floor",
                                "obstacles": {"density": 0.2, "size": 0.6}}
#: collision-penalty annealing (SPEC_obstacles A.6: 3e8 of 1e9 frames in the original), in agent-steps here
SWARM_ANNEAL = 5e7

PRESETS: dict[str, dict[str, Any]] = {
    # every preset is described in docs/training.md (the presets table); one quad from scratch in under a minute: the
    # 4e6-agent-step budget, not the wall clock, sets the learning-rate schedule (reproducible from its seed)
    "single": {"scenarios": ["static_same_goal"], "num_quads": 1, "env": {}, "rewards": {"pos": 3.0}, "engine": "jax",
               "timesteps": 4e6, "ppo": {"num_worlds": 1024, "unroll_length": 32, "learning_rate": 2e-3}},
    # the recipe of the shipped pretrained:single (static and jumping goals, MuJoCo engine, 30 min)
    "single_v1": {"scenarios": ["static_same_goal", "dynamic_same_goal"], "num_quads": 1, "env": {}, "rewards": {},
                  "ppo": {"num_worlds": 1024, "unroll_length": 32}},
    # the recipe of the shipped pretrained:swarm8_v1 (CPU engine, two scenarios, MLP over the sorted neighbours)
    "swarm8_v1": {"scenarios": ["static_diff_goal", "swap_goals"], "num_quads": 8, "env": {}, "rewards": {},
                  "ppo": {"num_worlds": 128, "unroll_length": 32}},
    # the paper scenarios: mix (nine scenarios) + run_away on a tenth of the worlds (as much as each of the nine)
    "swarm8": {"scenarios": ["mix", "run_away"], "weights": [9, 1], "num_quads": 8, "env": {}, "rewards": {},
               "engine": "jax", "replay_prob": 0.75, "anneal_agent_steps": SWARM_ANNEAL,
               "ppo": {"num_worlds": 128, "unroll_length": 32, "arch": "deepsets_large", "arch_width": 64}},
    # the swarm by PPO alone from pretrained:swarm8_v1 (TRAINING.md "Swarm policies by PPO alone")
    "swarm8_rl": {"scenarios": ["mix", "run_away"], "weights": [9, 1], "num_quads": 8, "env": {},
                  "rewards": {"pos": 2.0}, "engine": "jax", "replay_prob": 0.75, "anneal_agent_steps": 0,
                  "init_from": "pretrained:swarm8_v1",
                  "ppo": {"num_worlds": 128, "unroll_length": 32, "learning_rate": 1e-4}},
    # among columns by PPO alone (TRAINING.md): from pretrained:swarm8_rl, the 9 column features added at zero input
    # weight and observed as slopes; o_random only; density and size randomized, column-proximity shaping, a 3.3 s
    # horizon
    "swarm8_obstacles_rl": {"scenarios": ["o_random"], "num_quads": 8,
                            "env": {**OBSTACLE_ENV, "num_neighbors": 6, "obs_self": "base",
                                    "obstacles": {**OBSTACLE_ENV["obstacles"], "density_random": True,
                                                  "size_random": True, "size_values": [0.3, 0.4, 0.5, 0.6],
                                                  "collision_reward": 8.5, "proximity_reward": 6.0,
                                                  "feature_form": "slopes"}},
                            "rewards": {"pos": 2.0}, "engine": "jax", "replay_prob": 0.5, "anneal_agent_steps": 0,
                            "init_from": "pretrained:swarm8_rl",
                            "ppo": {"num_worlds": 128, "unroll_length": 32, "learning_rate": 1e-4,
                                    "discounting": 0.997, "warm_start_std": 0.12, "entropy_cost": 0.0}},
    # deployable variant: deep sets 16-wide, 1,012 actor parameters
    "swarm8_deployable": {"scenarios": ["mix", "run_away"], "weights": [9, 1], "num_quads": 8, "env": {},
                          "rewards": {}, "engine": "jax", "replay_prob": 0.75, "anneal_agent_steps": SWARM_ANNEAL,
                          "ppo": {"num_worlds": 128, "unroll_length": 32, "arch": "deepsets_deployable"}},
    # the original's final obstacle run: attention over a neighbour and an obstacle token (27,460 parameters)
    "swarm8_obstacles": {"scenarios": ["mix"], "num_quads": 8, "env": OBSTACLE_ENV, "rewards": {}, "engine": "jax",
                         "replay_prob": 0.75, "anneal_agent_steps": SWARM_ANNEAL,
                         "ppo": {"num_worlds": 128, "unroll_length": 32, "arch": "attention_large",
                                 "arch_width": 32}},
    # deployable variant: single-head attention, 16 wide (1,828 actor parameters; the original's onboard ~1,800)
    "swarm8_obstacles_deployable": {"scenarios": ["mix"], "num_quads": 8, "env": OBSTACLE_ENV, "rewards": {},
                                    "engine": "jax", "replay_prob": 0.75, "anneal_agent_steps": SWARM_ANNEAL,
                                    "ppo": {"num_worlds": 128, "unroll_length": 32,
                                            "arch": "attention_deployable"}},
    # --- the recipes of the shipped policies: PPO fine-tuning from pretrained:swarm8_v1, no annealing
    "swarm8_finetune": {"scenarios": ["mix", "run_away"], "weights": [9, 1], "num_quads": 8, "env": {},
                        "rewards": {"pos": 2.0}, "engine": "jax", "replay_prob": 0.75, "anneal_agent_steps": 0,
                        "init_from": "pretrained:swarm8_v1",
                        "ppo": {"num_worlds": 128, "unroll_length": 32, "learning_rate": 1.5e-4}},
    # the obstacle mix in the warm start's layout + the 9 obstacle features (input weights start at zero)
    "swarm8_obstacles_finetune": {"scenarios": ["mix"], "num_quads": 8,
                                  "env": {**OBSTACLE_ENV, "num_neighbors": 6, "obs_self": "base"}, "rewards": {},
                                  "engine": "jax", "replay_prob": 0.75, "anneal_agent_steps": 0,
                                  "init_from": "pretrained:swarm8_v1", "ppo": {"num_worlds": 128, "unroll_length": 32}},
}


def resolve_policy_path(spec: str | None) -> str | None:
    """``pretrained:<name>`` -> the shipped file (SHA-256 checked); other paths unchanged."""
    if spec is None or not spec.startswith("pretrained:"):
        return spec
    from quadswarm_mj.policies import load_pretrained, pretrained_dir, read_manifest

    name = spec.split(":", 1)[1]
    load_pretrained(name)  # checks the name and the file's SHA-256
    return str(pretrained_dir() / read_manifest()["policies"][name]["file"])


def _parse_value(text: str) -> Any:
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _kv(items: list[str] | None, what: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for it in items or []:
        if "=" not in it:
            raise SystemExit(f"error: {what} must be KEY=VALUE, got {it!r}")
        k, v = it.split("=", 1)
        v = _parse_value(v)
        out[k.strip()] = tuple(v) if isinstance(v, list) else v
    return out


#: options of one launch, not of the run's configuration: a resumed run takes them from its new command line
BUDGET_ARGS = ("--minutes", "--timesteps", "--checkpoint-minutes", "--out", "--resume", "--num-processes",
               "--process-id", "--coordinator")


def _env_int(name: str) -> int | None:
    v = os.environ.get(name)
    return int(v) if v not in (None, "") else None


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", choices=sorted(PRESETS), default="single", help="defaults to start from (single)")
    p.add_argument("--engine", choices=("mujoco", "jax"),
                   help="rollout engine: mujoco (batched CPU MuJoCo, default) or jax (MjxQuadSwarmEnv: rollouts and "
                        "updates in one jitted loop; the swarm8* presets' default)")
    p.add_argument("--cpu-devices", default="cores", metavar="N",
                   help="--engine jax: JAX CPU devices the iteration runs data parallel on: 'cores' (default: one per "
                        "core, quadswarm_mj.use_cpu_cores()) or an int (1: JAX's single default device). Results "
                        "depend on the device count (each device draws its own streams)")
    p.add_argument("--num-processes", type=int, default=_env_int("QUADSWARM_NUM_PROCESSES"),
                   help="--engine jax: data parallel over this many processes (hosts) with jax.distributed; every "
                        "process runs the same command with its --process-id (env QUADSWARM_NUM_PROCESSES)")
    p.add_argument("--process-id", type=int, default=_env_int("QUADSWARM_PROCESS_ID"),
                   help="this process's index in [0, --num-processes); 0 writes the output (env QUADSWARM_PROCESS_ID; "
                        "left out: detected on SLURM/Open MPI clusters)")
    p.add_argument("--coordinator", default=os.environ.get("QUADSWARM_COORDINATOR"), metavar="HOST:PORT",
                   help="address of process 0's coordinator, e.g. 10.0.0.1:1234 (env QUADSWARM_COORDINATOR; left "
                        "out: detected on clusters)")
    p.add_argument("--scenario", action="append", help="training scenario(s); repeat or comma-separate")
    p.add_argument("--num-quads", type=int, help="quads per world (N)")
    p.add_argument("--reward", action="append", metavar="TERM=SCALE", help="reward scale (RewardScales field)")
    p.add_argument("--env", action="append", metavar="FIELD=VALUE", help="EnvConfig field (JSON value)")
    p.add_argument("--out", help="output directory (default runs/train, or the --resume directory)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--minutes", type=float, help="wall-clock budget of this run in minutes")
    p.add_argument("--timesteps", type=float, help="budget of this run in agent-steps (quad control steps), e.g. 5e7")
    p.add_argument("--init-from", help="start from this policy .npz (e.g. the single-quad policy for swarm8)")
    p.add_argument("--resume", metavar="DIR", help="continue the run in DIR from its last checkpoint (optimizer, "
                   "normalizer, step counter, RNG); its run.json gives the configuration; the budget is new or, "
                   "without --timesteps and --minutes, the rest of the run's own --timesteps")
    p.add_argument("--checkpoint-minutes", type=float, default=5.0, help="checkpoint period (default 5)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (log lines only)")
    p.add_argument("--replay-prob", type=float, help="JAX engine: probability that an episode end restarts from a "
                   "saved pre-collision state (SPEC_obstacles C.2; 0 disables; swarm8 presets 0.75)")
    p.add_argument("--anneal-agent-steps", type=float, help="ramp the collision and proximity penalties from 0 over "
                   "this many agent-steps (sets rewards.anneal_steps; 0: off)")
    g = p.add_argument_group("PPO (defaults from the preset, then PPOConfig)")
    g.add_argument("--arch", choices=ARCH_CHOICES, help="policy network: mlp (--policy-hidden) or an encoder preset "
                   "of quadswarm_mj.policies.ARCH_PRESETS")
    g.add_argument("--arch-width", type=int, help="encoders: set every hidden width of the preset to this")
    g.add_argument("--num-worlds", type=int)
    g.add_argument("--unroll-length", type=int)
    g.add_argument("--num-minibatches", type=int)
    g.add_argument("--num-epochs", type=int)
    g.add_argument("--lr", "--learning-rate", dest="learning_rate", type=float)
    g.add_argument("--entropy-cost", type=float)
    g.add_argument("--warm-start-std", type=float,
                   help="with --init-from: the policy's action std (pre-tanh) set to this in every state")
    g.add_argument("--train-inputs-from", type=int, metavar="N",
                   help="with --init-from (MLP): train only the policy's first-layer weights of the observation "
                        "components >= N (e.g. 18, the inputs pretrained:single lacks) and the critic; the rest of "
                        "the policy and the observation statistics stay as loaded (default 0: train everything)")
    g.add_argument("--min-action-std", type=float,
                   help="floor of the policy's action std (pre-tanh; default 0.001): exploration cannot fall below it")
    g.add_argument("--noise-correlation", type=float,
                   help="JAX engine: AR(1) correlation of each agent's action noise per step, in [0, 1) (default 0)")
    g.add_argument("--lr-schedule", choices=("constant", "linear"), help="linear (default): decay to 10 %% at the end")
    g.add_argument("--lr-decay-timesteps", dest="lr_decay_steps", type=float, metavar="N",
                   help="linear schedule: decay over N agent-steps from the run's first step (default: the budget); a "
                        "run stopped before N keeps a higher final rate")
    g.add_argument("--discounting", type=float)
    g.add_argument("--gae-lambda", type=float)
    g.add_argument("--clipping-epsilon", type=float)
    g.add_argument("--reward-scaling", type=float)
    g.add_argument("--policy-hidden", help="comma list, e.g. 64,64")
    g.add_argument("--value-hidden", help="comma list, e.g. 64,64")
    g.add_argument("--activation", choices=("tanh", "relu", "swish", "elu"))
    return p


def _strip_budget(argv: list[str]) -> list[str]:
    """``argv`` without the budget/output options (for re-parsing a resumed run's configuration)."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
            continue
        name = a.split("=", 1)[0]
        if name in BUDGET_ARGS:
            skip = "=" not in a
            continue
        out.append(a)
    return out


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # run as a command: the opt-in XLA:CPU tuning (quadswarm_mj.tune_jax_cpu), before JAX starts
        from quadswarm_mj.devices import tune_jax_cpu

        tune_jax_cpu()
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    resume_file = None
    resume_total = None  # a resumed run's total step budget, when it had one and no new budget is given
    if args.resume:
        rdir = Path(args.resume)
        resume_file = rdir / "checkpoints" / "train_state.npz"
        if not (rdir / "run.json").is_file() or not resume_file.is_file():
            raise SystemExit(f"error: --resume {rdir}: needs {rdir / 'run.json'} and {resume_file}")
        old = json.loads((rdir / "run.json").read_text())
        # the stored configuration, then this command line's options on top (budget, output, progress)
        argv = _strip_budget(old["argv"]) + argv
        args = build_parser().parse_args(argv)
        if args.out is None:
            args.out = str(rdir)
        if args.timesteps is None and args.minutes is None:  # no new budget: finish the run's own step budget
            resume_total = old.get("total_timesteps") or build_parser().parse_args(old["argv"]).timesteps
    if args.out is None:
        args.out = "runs/train"
    preset = PRESETS[args.preset]
    if args.timesteps is None and preset.get("timesteps") and not args.resume:
        args.timesteps = float(preset["timesteps"])  # the preset's budget (--minutes, if given, caps it)
    if args.minutes is None and args.timesteps is None and not resume_total:
        args.minutes = 30.0
    from quadswarm_mj.config import EnvConfig, RewardScales
    from quadswarm_mj.training.ppo import PPOConfig, PPOTrainer

    engine = args.engine or preset.get("engine", "mujoco")
    nproc = args.num_processes or 1
    if nproc > 1 and engine != "jax":
        raise SystemExit("error: --num-processes needs --engine jax (the data-parallel trainer)")
    if engine == "jax":  # before any JAX operation: the device count is fixed when JAX starts
        from quadswarm_mj.devices import cpu_devices_option, use_cpu_cores

        try:
            ndev = cpu_devices_option(args.cpu_devices)
            if nproc > 1:  # this process joins the job (gloo CPU collectives, then jax.distributed.initialize)
                from quadswarm_mj.training.distributed import initialize

                initialize(nproc, args.process_id, args.coordinator, ndev)
            else:
                use_cpu_cores(ndev, strict=False)
        except (ValueError, RuntimeError) as e:
            raise SystemExit(f"error: {e}") from None
    main_process = nproc == 1 or _process_index() == 0
    scenarios = [s.strip() for item in (args.scenario or preset["scenarios"]) for s in item.split(",") if s.strip()]
    weights = preset.get("weights") if args.scenario is None else None
    n = args.num_quads if args.num_quads is not None else preset["num_quads"]
    rewards = {**preset["rewards"], **_kv(args.reward, "--reward")}
    env = {**preset["env"], **_kv(args.env, "--env")}
    ppo_kw = dict(preset["ppo"])
    for k in ("num_worlds", "unroll_length", "num_minibatches", "num_epochs", "learning_rate", "entropy_cost",
              "discounting", "gae_lambda", "clipping_epsilon", "reward_scaling", "activation", "lr_schedule", "arch",
              "arch_width", "warm_start_std", "min_action_std",
              "noise_correlation", "train_inputs_from", "lr_decay_steps"):
        if getattr(args, k) is not None:
            ppo_kw[k] = int(args.lr_decay_steps) if k == "lr_decay_steps" else getattr(args, k)
    if args.arch == "mlp":
        ppo_kw.pop("arch_width", None)
    for k in ("policy_hidden", "value_hidden"):
        if getattr(args, k):
            ppo_kw[k] = tuple(int(x) for x in getattr(args, k).split(","))
    init_from = resolve_policy_path(args.init_from if args.init_from is not None else preset.get("init_from"))
    anneal = args.anneal_agent_steps if args.anneal_agent_steps is not None else preset.get("anneal_agent_steps", 0)
    replay_prob = args.replay_prob if args.replay_prob is not None else preset.get("replay_prob", 0.0)
    try:
        ppo = PPOConfig(**ppo_kw)
        if anneal and "anneal_steps" not in rewards:
            from quadswarm_mj.training.jax_ppo import anneal_steps_for

            rewards["anneal_steps"] = anneal_steps_for(anneal, ppo.num_worlds, n)
        scales = RewardScales(**rewards)
        cfgs = [EnvConfig(num_quads=n, scenario=s, rewards=scales, **env) for s in scenarios]
        if engine == "jax":
            from quadswarm_mj.training.jax_ppo import JaxPPOTrainer
            from quadswarm_mj.training.replay import ReplayConfig

            trainer: Any = JaxPPOTrainer(cfgs, ppo, seed=args.seed, init_from=init_from,
                                         replay=ReplayConfig(prob=replay_prob), weights=weights)
        else:
            if replay_prob:
                if args.replay_prob:
                    raise ValueError("--replay-prob needs --engine jax (the replay buffer lives in the jitted loop)")
                replay_prob = 0.0
            if weights is not None and len(set(weights)) > 1:
                raise ValueError(f"scenario weights {weights} need --engine jax (the CPU trainer splits worlds evenly)")
            trainer = PPOTrainer(cfgs, ppo, seed=args.seed, init_from=init_from)
        if resume_file is not None:
            trainer.resume(resume_file)
    except (TypeError, ValueError) as e:
        raise SystemExit(f"error: {e}") from None
    if resume_total:  # the rest of the budget: the learning-rate schedule continues where it stopped
        args.timesteps = float(resume_total) - trainer.env_steps
        if args.timesteps <= 0:
            raise SystemExit(f"error: --resume {args.resume}: the run already reached its budget of "
                             f"{int(resume_total)} agent-steps; give --timesteps or --minutes to train further")
    out = Path(args.out)
    if main_process:
        out.mkdir(parents=True, exist_ok=True)
    agents = trainer.num_agents if engine == "jax" else trainer.batch.num_agents
    run = {"argv": argv, "engine": engine, "scenarios": scenarios, "weights": weights, "num_quads": n,
           "env": {k: (list(v) if isinstance(v, tuple) else v) for k, v in env.items()}, "rewards": rewards,
           "ppo": {k: (list(v) if isinstance(v, tuple) else v) for k, v in ppo.__dict__.items()},
           "replay_prob": replay_prob, "seed": args.seed, "init_from": init_from, "agents": agents, "processes": nproc,
           "obs_dim": trainer.obs_dim, "resumed_from": args.resume,
           "resumed_at_env_steps": int(trainer.env_steps) if args.resume else None,
           "total_timesteps": None if args.timesteps is None else int(trainer.env_steps + args.timesteps)}
    if not main_process:
        pass
    elif not (args.resume and Path(args.resume).resolve() == out.resolve()):
        (out / "run.json").write_text(json.dumps(run, indent=1, default=str))
    else:
        (out / f"run_resume_{int(trainer.env_steps)}.json").write_text(json.dumps(run, indent=1, default=str))
    if main_process:
        print(f"training {', '.join(scenarios)} with N={n} on the {engine} engine: {agents} agents, obs_dim "
              f"{trainer.obs_dim}, arch {ppo.arch}; output in {out}"
              + (f" (resumed at {trainer.env_steps} agent-steps)" if args.resume else ""), flush=True)

    def log(row: dict[str, Any]) -> None:
        if args.no_progress and main_process:
            parts = [f"it {row['iteration']}", f"{row['env_steps'] / 1e6:.2f} M steps", f"{row['wall_s'] / 60:.1f} min",
                     f"{row['steps_per_s']:.0f} steps/s", f"r/step {row['reward_per_step']:.4f}"]
            for s in scenarios:
                for key in ("success", "goal_reach_rate", "collisions", "replay_rate"):
                    v = row.get(f"{s}/{key}")
                    if v is not None and v == v:
                        parts.append(f"{s}/{key} {v:.3f}")
            print(" | ".join(parts), flush=True)

    history = None
    if args.resume and (out / "progress.json").is_file():
        history = [r for r in json.loads((out / "progress.json").read_text()) if r["env_steps"] <= trainer.env_steps]
    trainer.train(total_steps=None if args.timesteps is None else int(args.timesteps),
                  seconds=None if args.minutes is None else 60.0 * args.minutes, out_dir=out,
                  checkpoint_every_s=60.0 * args.checkpoint_minutes, progress=not args.no_progress, callback=log,
                  history=history)
    if main_process:
        print(f"done: {trainer.env_steps} agent-steps; policy {out / 'final.npz'}, curves {out / 'curves.png'}")
    return 0


def _process_index() -> int:
    import jax

    return jax.process_index()


if __name__ == "__main__":
    raise SystemExit(main())
