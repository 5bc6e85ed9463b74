"""Distil a teacher into an observation-based encoder policy on the JAX engine (DAgger).

Teachers: a policy file, or ``controller`` (the privileged baseline controller with neighbour avoidance and
column steering). Each jitted iteration flies the worlds by the teacher (probability beta, annealed 1 -> 0)
or the student, stores (normalized observation, teacher action) in a ring buffer on the device and takes
Adam steps fitting the student's tanh(mean) to the teacher's. The output is a ``quadswarm_mj.policy/2``
file with the teacher's ``env_kwargs``. Guide: docs/training.md ("DAgger"). Examples::

    python -m quadswarm_mj.training.distill --teacher runs/swarm8/best.npz --arch deepsets_deployable \
        --scenario mix --out runs/swarm8_dep --minutes 20
    python -m quadswarm_mj.training.distill ... --out runs/swarm8_dep --minutes 20 --resume   # continue it
    python -m quadswarm_mj.training.distill --teacher controller --arch deepsets_large --width 64 \
        --scenario mix --env 'obstacles={"density": 0.2, "size": 0.6}' --env downwash=true --out runs/o --minutes 20
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.policies import (
    ARCH_PRESETS,
    EncoderPolicy,
    MLPPolicy,
    count_params,
    load_policy,
    param_shapes,
    sha256_file,
)


@dataclass(frozen=True)
class DistillConfig:
    """DAgger hyper-parameters (counts are per iteration unless stated)."""

    num_worlds: int = 128
    unroll_length: int = 32
    buffer_size: int = 1_000_000  # samples (quad observations)
    sgd_steps: int = 32
    batch_size: int = 4096
    learning_rate: float = 3e-3
    beta_iterations: int = 20  # teacher share 1 -> 0 over these iterations

    def __post_init__(self) -> None:
        for name in ("num_worlds", "unroll_length", "buffer_size", "sgd_steps", "batch_size"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"DistillConfig.{name} must be an int >= 1, got {v!r}")
        if not (isinstance(self.beta_iterations, int) and self.beta_iterations >= 0):
            raise ValueError(f"DistillConfig.beta_iterations must be an int >= 0, got {self.beta_iterations!r}")
        if not (np.isfinite(self.learning_rate) and self.learning_rate > 0):
            raise ValueError(f"DistillConfig.learning_rate must be > 0, got {self.learning_rate!r}")


#: the privileged controller teacher's gains: neighbours within 0.6 m repel, columns within 0.6 m of
#: their surface repel (the baseline controller's obstacle setting)
CONTROLLER_AVOID_RADIUS = 0.6


def controller_teacher(cfg: EnvConfig) -> Any:
    """The privileged teacher: ``f(x, state) -> actions (W, N, 4)`` of the position controller on the
    true state, goals, goal velocities, dynamics parameters and (with obstacles) column map of the
    batched env ``state``; ``x`` (the student's observations) is ignored."""
    from quadswarm_mj.controllers import PositionController
    from quadswarm_mj.obstacles import ObstacleMap
    from quadswarm_mj.policies import baseline_gains

    o = cfg.obstacles
    ctrl = PositionController(cfg, baseline_gains(cfg, CONTROLLER_AVOID_RADIUS))

    def f(x: jax.Array, st: Any) -> jax.Array:
        info = st.info
        omap = None if o is None else ObstacleMap(info["obstacles"], info["obstacles_valid"], info["obstacle_radius"])
        a = ctrl(info["state"], info["goals"], info["goal_vel"], info["params"], obstacles=omap)
        return jnp.clip(a, -1.0, 1.0).astype(jnp.float32)

    return f


def teacher_fn(policy: MLPPolicy | EncoderPolicy) -> Any:
    """A jnp function ``f(x, state)``: normalized observations (..., D) -> deterministic actions (..., 4)
    in [-1, 1] (``state`` unused)."""
    if isinstance(policy, MLPPolicy):
        ks = [jnp.asarray(k, jnp.float32) for k in policy.kernels]
        bs = [jnp.asarray(b, jnp.float32) for b in policy.biases]
        act = {"tanh": jnp.tanh, "relu": jax.nn.relu, "swish": jax.nn.swish, "elu": jax.nn.elu}[policy.activation]

        def f(x: jax.Array) -> jax.Array:
            for i, (k, b) in enumerate(zip(ks, bs)):
                x = x @ k + b
                if i < len(ks) - 1:
                    x = act(x)
            return jnp.tanh(x[..., : policy.action_dim])

        return lambda x, st: f(x)
    from quadswarm_mj.training.networks import EncoderNetwork, unflatten_params

    module = EncoderNetwork(arch=dict(policy.arch), layout=dict(policy.obs_layout))
    params = unflatten_params(policy.params)
    return lambda x, st: jnp.tanh(module.apply(params, x)[..., : policy.action_dim])


class Distiller:
    """DAgger from ``teacher`` (a policy object or file) into a student encoder ``arch`` on ``scenario``."""

    def __init__(self, teacher: Any, arch: str | dict[str, Any], scenario: str = "mix",
                 cfg: DistillConfig | None = None, seed: int = 0, env: dict[str, Any] | None = None,
                 width: int | None = None, init_from: str | None = None):
        import optax

        from quadswarm_mj.envs.mjx_env import AutoResetWrapper, MjxQuadSwarmEnv
        from quadswarm_mj.training.networks import EncoderNetwork
        from quadswarm_mj.training.ppo import encoder_arch, env_meta, obs_layout

        self.cfg = cfg or DistillConfig()
        self.teacher_spec = str(teacher) if isinstance(teacher, (str, Path)) else getattr(teacher, "name", "policy")
        if isinstance(teacher, str) and teacher == "controller":
            self.teacher = None
            self.env_cfg = EnvConfig(**{"num_quads": 8, **(env or {}), "scenario": scenario})
        else:
            self.teacher = load_policy(teacher) if isinstance(teacher, (str, Path)) else teacher
            if not isinstance(self.teacher, (MLPPolicy, EncoderPolicy)):
                raise ValueError(f"teacher must be 'controller' or a trained policy file (MLP or encoder), "
                                 f"got {type(self.teacher)}")
            self.env_cfg = EnvConfig(**{**self.teacher.env_kwargs, **(env or {}), "scenario": scenario})
            if self.env_cfg.obs_dim != self.teacher.obs_dim:
                raise ValueError(f"teacher obs_dim {self.teacher.obs_dim} != env obs_dim {self.env_cfg.obs_dim}")
        self.layout = obs_layout(self.env_cfg)
        if isinstance(arch, str):
            if arch not in ARCH_PRESETS:
                raise ValueError(f"arch must be one of {sorted(ARCH_PRESETS)}, got {arch!r}")
            arch = encoder_arch(arch, width)
        self.arch = dict(arch)
        self.num_params = count_params(param_shapes(self.arch, self.layout))
        self.env_meta = env_meta(self.env_cfg)
        self.module = EncoderNetwork(arch=self.arch, layout=self.layout)
        self.env = AutoResetWrapper(MjxQuadSwarmEnv(self.env_cfg))
        self.optimizer = optax.adam(self.cfg.learning_rate)
        key = jax.random.PRNGKey(seed)
        key, k_init, k_env = jax.random.split(key, 3)
        params = self.module.init(k_init, jnp.zeros((1, self.env_cfg.obs_dim)))
        D, c = self.env_cfg.obs_dim, self.cfg
        env0 = jax.jit(jax.vmap(self.env.reset))(jax.random.split(k_env, c.num_worlds))
        teach = controller_teacher(self.env_cfg) if self.teacher is None else teacher_fn(self.teacher)
        if self.teacher is None:  # the student's normalizer: statistics of a teacher-flown warm-up
            self.obs_mean, self.obs_std = self._warmup_stats(env0, teach)
        else:
            self.obs_mean = np.asarray(self.teacher.obs_mean, np.float32)
            self.obs_std = np.asarray(self.teacher.obs_std, np.float32)
        if init_from is not None:  # continue from a student file of the same architecture (its normalizer too)
            from quadswarm_mj.training.networks import unflatten_params

            start = load_policy(init_from)
            want = param_shapes(self.arch, self.layout)
            if not isinstance(start, EncoderPolicy) or {k: tuple(v.shape) for k, v in start.params.items()} != {
                    k: tuple(v) for k, v in want.items()} or dict(start.obs_layout) != dict(self.layout):
                raise ValueError(f"init_from {init_from!r}: not an encoder file with architecture {self.arch} "
                                 f"and layout {self.layout}")
            params = unflatten_params(start.params)
            self.obs_mean = np.asarray(start.obs_mean, np.float32)
            self.obs_std = np.asarray(start.obs_std, np.float32)
        self.mean, self.std = jnp.asarray(self.obs_mean), jnp.asarray(self.obs_std)
        self.carry = {
            "params": params, "opt": self.optimizer.init(params), "key": key, "env": env0,
            "buf_obs": jnp.zeros((c.buffer_size, D), jnp.float32),
            "buf_act": jnp.zeros((c.buffer_size, 4), jnp.float32),
            "filled": jnp.asarray(0, jnp.int32), "head": jnp.asarray(0, jnp.int32),
        }
        self.iterations = 0
        self.samples = 0
        self._init_from = None if init_from is None else str(init_from)
        self._iterate = jax.jit(self._make_iteration(teach), donate_argnums=0)

    def _warmup_stats(self, env0: Any, teach: Any, steps: int = 200) -> tuple[np.ndarray, np.ndarray]:
        """Mean and std (floored at 1e-3) of the raw observations of ``steps`` teacher-flown control steps."""
        def body(st: Any, _: Any) -> tuple[Any, jax.Array]:
            st2 = self.env.vstep(st, teach(None, st))
            return st2, st2.obs.astype(jnp.float32)

        _, obs = jax.jit(lambda s: jax.lax.scan(body, s, None, length=steps))(env0)
        o = np.asarray(obs, np.float64).reshape(-1, self.env_cfg.obs_dim)
        return o.mean(0).astype(np.float32), np.maximum(o.std(0), 1e-3).astype(np.float32)

    def _student_act(self, params: Any, x: jax.Array) -> jax.Array:
        return jnp.tanh(self.module.apply(params, x)[..., :4])

    def _make_iteration(self, teacher: Any) -> Any:
        import optax

        c, N, D = self.cfg, self.env_cfg.num_quads, self.env_cfg.obs_dim
        W, T = c.num_worlds, c.unroll_length

        def loss_fn(params: Any, x: jax.Array, y: jax.Array) -> jax.Array:
            return jnp.mean(jnp.square(self._student_act(params, x) - y))

        def iteration(carry: dict[str, Any], beta: jax.Array) -> tuple[dict[str, Any], dict[str, jax.Array]]:
            key, k_mix, k_sgd = jax.random.split(carry["key"], 3)
            teacher_worlds = jax.random.uniform(k_mix, (W, 1, 1)) < beta
            params = carry["params"]

            def body(st: Any, _: Any) -> tuple[Any, tuple]:
                x = (st.obs.astype(jnp.float32) - self.mean) / self.std  # (W, N, D)
                a_t = teacher(x, st)
                a = jnp.where(teacher_worlds, a_t, self._student_act(params, x))
                st2 = self.env.vstep(st, a)
                em = st2.info["episode_metrics"]
                done = st2.done.astype(jnp.float32) * (~teacher_worlds[:, 0, 0])
                return st2, (x, a_t, done, em["collisions"] * done, em["success"] * done)

            env_state, (xs, ys, dn, col, suc) = jax.lax.scan(body, carry["env"], None, length=T)
            n_new = T * W * N
            idx = (carry["head"] + jnp.arange(n_new)) % c.buffer_size
            buf_obs = carry["buf_obs"].at[idx].set(xs.reshape(-1, D))
            buf_act = carry["buf_act"].at[idx].set(ys.reshape(-1, 4))
            filled = jnp.minimum(carry["filled"] + n_new, c.buffer_size)

            def sgd(state: tuple, k: jax.Array) -> tuple[tuple, jax.Array]:
                p, o = state
                j = jax.random.randint(k, (c.batch_size,), 0, filled)
                loss, g = jax.value_and_grad(loss_fn)(p, buf_obs[j], buf_act[j])
                upd, o = self.optimizer.update(g, o, p)
                return (optax.apply_updates(p, upd), o), loss

            (params, opt), losses = jax.lax.scan(sgd, (params, carry["opt"]), jax.random.split(k_sgd, c.sgd_steps))
            new = {"params": params, "opt": opt, "key": key, "env": env_state, "buf_obs": buf_obs,
                   "buf_act": buf_act, "filled": filled, "head": (carry["head"] + n_new) % c.buffer_size}
            return new, {"loss": losses[-1], "student_episodes": dn.sum(), "student_collisions": col.sum(),
                         "student_success": suc.sum()}

        return iteration

    def beta(self) -> float:
        b = self.cfg.beta_iterations
        return max(0.0, 1.0 - self.iterations / b) if b else 0.0

    def step(self) -> dict[str, float]:
        """One jitted iteration; returns the host-side log row."""
        self.carry, out = self._iterate(self.carry, jnp.asarray(self.beta(), jnp.float32))
        self.iterations += 1
        self.samples += self.cfg.num_worlds * self.cfg.unroll_length * self.env_cfg.num_quads
        out = {k: float(v) for k, v in out.items()}
        eps = out.pop("student_episodes")
        return {"iteration": self.iterations, "samples": self.samples, "loss": out["loss"],
                "student_episodes": eps,
                "student_collisions": out["student_collisions"] / eps if eps else float("nan"),
                "student_success": out["student_success"] / eps if eps else float("nan")}

    def policy(self) -> EncoderPolicy:
        from quadswarm_mj.training.networks import to_numpy_policy

        return to_numpy_policy(self.arch, self.layout, self.carry["params"], self.obs_mean, self.obs_std,
                               self.meta())

    def meta(self) -> dict[str, Any]:
        return {"activation": self.arch.get("activation", "tanh"), "obs_dim": self.env_cfg.obs_dim, "action_dim": 4,
                "env": self.env_meta,
                "train": {"method": "dagger_distillation", "teacher": self.teacher_spec,
                          **({"teacher_avoid_radius": CONTROLLER_AVOID_RADIUS} if self.teacher is None else {}),
                          "scenario": self.env_cfg.scenario, "iterations": self.iterations, "samples": self.samples,
                          "init_from": self._init_from,
                          "config": vars(self.cfg) if not hasattr(self.cfg, "__dataclass_fields__")
                          else {k: getattr(self.cfg, k) for k in self.cfg.__dataclass_fields__}}}

    def save(self, path: str | Path) -> str:
        """Write the student as a policy file; returns its SHA-256."""
        from quadswarm_mj.training.networks import export_policy

        return export_policy(path, self.arch, self.layout, self.carry["params"], self.obs_mean, self.obs_std,
                             self.meta())


    # ------------------------------------------------------------------ resumable learner state
    def save_state(self, path: str | Path, rows: list[dict[str, Any]] | None = None) -> None:
        """The learner state (student parameters, Adam state, normalizer, RNG key, counters and the log
        rows) as a pickle-free ``.npz``, written atomically. The DAgger buffer is not saved: a resumed run
        refills it from its own rollouts."""
        leaves = jax.tree_util.tree_leaves({"params": self.carry["params"], "opt": self.carry["opt"]})
        arrays = {f"leaf_{i:04d}": np.asarray(v) for i, v in enumerate(leaves)}
        arrays["key"] = np.asarray(self.carry["key"])
        arrays["obs_mean"], arrays["obs_std"] = np.asarray(self.obs_mean), np.asarray(self.obs_std)
        arrays["scalars"] = np.array(json.dumps({"iterations": self.iterations, "samples": self.samples,
                                                 "rows": rows or []}))
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez(tmp, **arrays)
        tmp.replace(path)

    def resume(self, path: str | Path) -> list[dict[str, Any]]:
        """Restore :meth:`save_state`'s file (same teacher, arch and env); returns the saved log rows."""
        with np.load(path, allow_pickle=False) as z:
            tree = {"params": self.carry["params"], "opt": self.carry["opt"]}
            leaves, treedef = jax.tree_util.tree_flatten(tree)
            new = [z[f"leaf_{i:04d}"] for i in range(len(leaves))]
            if [np.shape(a) for a in new] != [np.shape(a) for a in leaves]:
                raise ValueError(f"{path}: the saved student/optimizer do not match this architecture")
            tree = jax.tree_util.tree_unflatten(treedef, [jnp.asarray(a) for a in new])
            sc = json.loads(str(z["scalars"]))
            self.obs_mean, self.obs_std = z["obs_mean"].astype(np.float32), z["obs_std"].astype(np.float32)
            key = jnp.asarray(z["key"])
        self.carry.update(params=tree["params"], opt=tree["opt"], key=key)
        self.mean, self.std = jnp.asarray(self.obs_mean), jnp.asarray(self.obs_std)
        self.iterations, self.samples = int(sc["iterations"]), int(sc["samples"])
        # the normalizer is baked into the jitted iteration: rebuild it
        teach = controller_teacher(self.env_cfg) if self.teacher is None else teacher_fn(self.teacher)
        self._iterate = jax.jit(self._make_iteration(teach), donate_argnums=0)
        return list(sc["rows"])


STATE_FILE = "train_state.npz"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--teacher", required=True,
                   help="'controller' (privileged baseline controller) or a policy: pretrained:<name>, a policy .npz")
    p.add_argument("--arch", default="deepsets_deployable", choices=sorted(ARCH_PRESETS))
    p.add_argument("--width", type=int, help="set every hidden width of the encoder preset (heads 2x)")
    p.add_argument("--env", action="append", metavar="FIELD=VALUE", help="EnvConfig field (JSON value)")
    p.add_argument("--scenario", default="mix")
    p.add_argument("--out", required=True, help="output directory (student.npz, progress.json, checkpoints)")
    p.add_argument("--minutes", type=float, default=20.0, help="wall-clock budget (default 20)")
    p.add_argument("--iterations", type=int, help="stop after this many iterations (default: the time budget)")
    p.add_argument("--checkpoint-minutes", type=float, default=5.0)
    p.add_argument("--num-worlds", type=int, default=DistillConfig.num_worlds)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--init-from", help="continue from this student .npz (same --arch/--width and env)")
    p.add_argument("--beta-iterations", type=int, default=DistillConfig.beta_iterations,
                   help="teacher share 1 -> 0 over these iterations (0: the student flies from the start)")
    p.add_argument("--resume", action="store_true", help=f"continue the run in --out from checkpoints/{STATE_FILE} "
                   "(student, Adam state, normalizer, counters; the same options as the first run)")
    args = p.parse_args(argv)
    env: dict[str, Any] = {}
    for item in args.env or []:
        k, _, v = item.partition("=")
        try:
            env[k.strip()] = json.loads(v)
        except json.JSONDecodeError:
            env[k.strip()] = v
    try:
        d = Distiller(args.teacher, args.arch, args.scenario,
                      DistillConfig(num_worlds=args.num_worlds, beta_iterations=args.beta_iterations),
                      seed=args.seed, env=env, width=args.width, init_from=args.init_from)
    except ValueError as e:
        raise SystemExit(f"error: {e}") from None
    out = Path(args.out)
    (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    if args.resume:
        state = out / "checkpoints" / STATE_FILE
        if not state.is_file():
            raise SystemExit(f"error: --resume: no {state}")
        rows = d.resume(state)
    print(f"distilling {args.teacher} into {args.arch} ({d.num_params} actor parameters) on {args.scenario}, "
          f"N={d.env_cfg.num_quads}; output in {out}" + (f" (resumed at iteration {d.iterations})"
                                                          if args.resume else ""), flush=True)
    t0 = last_ckpt = time.perf_counter()
    wall0 = rows[-1]["wall_s"] if rows else 0.0
    while True:
        row = d.step()
        row["wall_s"] = wall0 + time.perf_counter() - t0
        rows.append(row)
        print(f"it {row['iteration']} | {row['samples'] / 1e6:.1f} M samples | {row['wall_s'] / 60:.1f} min | "
              f"loss {row['loss']:.5f} | beta {d.beta():.2f} | student coll/quad {row['student_collisions']:.3f} "
              f"success {row['student_success']:.3f}", flush=True)
        now = time.perf_counter()
        done = (args.iterations is not None and d.iterations >= args.iterations) or now - t0 >= 60 * args.minutes
        if done or now - last_ckpt >= 60 * args.checkpoint_minutes:
            d.save(out / "checkpoints" / f"it_{d.iterations:06d}.npz")
            d.save_state(out / "checkpoints" / STATE_FILE, rows)
            (out / "progress.json").write_text(json.dumps(rows))
            last_ckpt = now
        if done:
            break
    sha = d.save(out / "student.npz")
    print(f"wrote {out / 'student.npz'} (sha256 {sha[:12]}...; teacher "
          f"{sha256_file(args.teacher)[:12] if Path(args.teacher).exists() else args.teacher})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
