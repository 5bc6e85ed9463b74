"""PPO for quadswarm_mj: Brax's PPO (loss, networks, observation normalizer) on the batched CPU engine.

Why this split (measurements in TRAINING.md): on this 2-core CPU the MuJoCo C engine stepping B
worlds together (``quadswarm_mj.envs.cpu_core.CpuSwarm``) is several times faster than
MJX on CPU, so rollouts run there (NumPy + MuJoCo, no Python loop over worlds or quads), while
everything learned runs in JAX: the policy's action sampling (one jitted call per control step
for all agents) and the PPO update (one jitted call per iteration: normalizer update, then
``num_epochs`` passes of ``num_minibatches`` Adam steps on
``brax.training.agents.ppo.losses.compute_ppo_loss``). The networks are Brax's
``make_ppo_networks`` (tanh-normal policy, MLPs) with Brax's running observation normalizer, or
(``PPOConfig.arch``) a deep-sets / attention encoder of :mod:`quadswarm_mj.training.networks` saved in
the encoder policy format. The learner pieces (:func:`make_networks`, :func:`init_params`,
:func:`make_update_fn`, :func:`save_policy_file`, the resumable :func:`save_train_state` /
:func:`load_train_state`) are shared with the JAX-engine trainer (:mod:`quadswarm_mj.training.jax_ppo`).

Every quad is an agent and all agents share one policy (parameter sharing, as in QuadSwarm):
the PPO batch has ``num_worlds * num_quads`` agents, each with its own reward (the per-quad
reward of SPEC §8). Several scenarios can be trained at once: the worlds are split evenly among
one engine per scenario (e.g. static_same_goal + dynamic_same_goal for the single-quad policy).

Episodes end by truncation only (15 s). So that episode ends are spread over iterations, the
first episode of every world is truncated early, after a random number of steps in
[1, episode_steps] (:attr:`AgentBatch.first_len`); its scenario starts at t = 0 as every episode
does (no scenario clock is moved, so time-driven goal changes happen at their times). The metrics
of these first, shortened episodes are not logged.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optax
from brax.training import types as brax_types
from brax.training.acme import running_statistics
from brax.training.agents.ppo import losses as ppo_losses
from brax.training.agents.ppo import networks as ppo_networks
from flax import linen

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.envs.cpu_core import CpuSwarm
from quadswarm_mj.metrics import METRIC_KEYS
from quadswarm_mj.policies import ARCH_PRESETS, OBS_ENV_FIELDS, load_policy_file, save_policy
from quadswarm_mj.training import networks as enc_networks

ACTIVATIONS: dict[str, Callable[[Any], Any]] = {"tanh": linen.tanh, "relu": linen.relu, "swish": linen.swish,
                                                "elu": linen.elu}
#: policy architectures of ``--arch``: the MLP and the encoder presets of ``quadswarm_mj.policies``.
ARCH_NAMES = ("mlp", *ARCH_PRESETS)


@dataclass(frozen=True)
class PPOConfig:
    """PPO hyper-parameters. Sizes count agents (quads), not worlds, where noted."""

    num_worlds: int = 1024  # worlds stepped together (split evenly over the scenarios)
    unroll_length: int = 32  # control steps per agent per iteration
    num_minibatches: int = 32
    num_epochs: int = 4
    learning_rate: float = 3e-4
    entropy_cost: float = 1e-3
    discounting: float = 0.99
    gae_lambda: float = 0.95
    clipping_epsilon: float = 0.2
    reward_scaling: float = 1.0
    max_grad_norm: float = 1.0
    policy_hidden: tuple[int, ...] = (64, 64)
    value_hidden: tuple[int, ...] = (64, 64)
    activation: str = "tanh"
    normalize_observations: bool = True
    lr_schedule: str = "linear"  # "constant", or "linear": decays to lr_final_fraction at the end of the budget
    lr_final_fraction: float = 0.1
    init_std: float = 0.6  # initial std of the pre-tanh Gaussian (Brax's default is softplus(0) = 0.69)
    desync_episodes: bool = True  # truncate each world's first episode after a random number of steps
    arch: str = "mlp"  # policy network: "mlp" (policy_hidden) or a quadswarm_mj.policies.ARCH_PRESETS name
    arch_width: int | None = None  # encoders: every hidden width of the preset set to this (heads: 2x); None: as is

    def __post_init__(self) -> None:
        for n in ("num_worlds", "unroll_length", "num_minibatches", "num_epochs"):
            v = getattr(self, n)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"ppo.{n} must be an int >= 1, got {v!r}")
        for n in ("learning_rate", "discounting", "gae_lambda", "clipping_epsilon", "reward_scaling", "max_grad_norm",
                  "init_std"):
            v = getattr(self, n)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"ppo.{n} must be a finite number > 0, got {v!r}")
        if not (0 <= self.entropy_cost < 1):
            raise ValueError(f"ppo.entropy_cost must be in [0, 1), got {self.entropy_cost!r}")
        if self.discounting > 1 or self.gae_lambda > 1:
            raise ValueError("ppo.discounting and ppo.gae_lambda must be <= 1")
        if self.lr_schedule not in ("constant", "linear"):
            raise ValueError(f"ppo.lr_schedule must be 'constant' or 'linear', got {self.lr_schedule!r}")
        if not (0 <= self.lr_final_fraction <= 1):
            raise ValueError(f"ppo.lr_final_fraction must be in [0, 1], got {self.lr_final_fraction!r}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"ppo.activation must be one of {tuple(ACTIVATIONS)}, got {self.activation!r}")
        if self.arch not in ARCH_NAMES:
            raise ValueError(f"ppo.arch must be one of {ARCH_NAMES}, got {self.arch!r}")
        if self.arch_width is not None and (not isinstance(self.arch_width, int) or isinstance(self.arch_width, bool)
                                            or self.arch_width < 1):
            raise ValueError(f"ppo.arch_width must be None or an int >= 1, got {self.arch_width!r}")
        for n in ("policy_hidden", "value_hidden"):
            v = tuple(getattr(self, n))
            if not v or any(not isinstance(h, int) or h < 1 for h in v):
                raise ValueError(f"ppo.{n} must be a non-empty tuple of positive ints, got {v!r}")
            object.__setattr__(self, n, v)



# ---------------------------------------------------------------------------- rollout engines
class AgentBatch:
    """One ``CpuSwarm`` per scenario, seen as one flat batch of A = sum(B_k * N) agents.

    ``cfgs`` must agree on ``num_quads`` and ``obs_dim``; ``worlds`` gives B_k per engine.
    Observations are float32 (A, obs_dim); rewards (A,) are the per-quad rewards.
    """

    def __init__(self, cfgs: list[EnvConfig], worlds: list[int], seed: int, desync: bool = True):
        if not cfgs or len(cfgs) != len(worlds):
            raise ValueError("need one world count per scenario config")
        n, d = cfgs[0].num_quads, cfgs[0].obs_dim
        for c in cfgs:
            if c.num_quads != n or c.obs_dim != d:
                raise ValueError("all training scenarios must share num_quads and the observation layout")
        self.cfgs, self.N, self.obs_dim = cfgs, n, d
        self.engines = [CpuSwarm(c, b) for c, b in zip(cfgs, worlds)]
        for k, e in enumerate(self.engines):
            e.seed(seed * 1000 + k)
            e.reset()
            got = e.observe().shape[-1]
            if got != d:
                raise ValueError(f"the MuJoCo engine's observation has {got} features, the config needs {d}")
            e.seed(seed * 1000 + k)  # the check's reset leaves the seeded streams as before
        self.sizes = [e.B * n for e in self.engines]
        self.num_agents = sum(self.sizes)
        self.desync = desync
        self.rng = np.random.default_rng(seed)
        self.ep_return = [np.zeros((e.B, n)) for e in self.engines]
        self.first = [np.ones(e.B, bool) for e in self.engines]
        #: (B_k,) control steps after which the first episode of each world is truncated.
        self.first_len = [np.full(e.B, e.cfg.episode_steps, np.int64) for e in self.engines]

    def reset(self) -> np.ndarray:
        for k, e in enumerate(self.engines):
            e.reset()
            self.first[k][:] = True
            steps = e.cfg.episode_steps
            self.first_len[k] = (self.rng.integers(1, steps + 1, size=e.B).astype(np.int64) if self.desync
                                 else np.full(e.B, steps, np.int64))
            self.ep_return[k][:] = 0.0
        return self.observe()

    def observe(self) -> np.ndarray:
        return np.concatenate([e.observe().reshape(-1, self.obs_dim) for e in self.engines]).astype(np.float32)

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list]:
        """Step every engine; worlds whose episode ended are reset.

        Returns (next_obs before resets, rewards, truncation flags, obs to act on next, finished)
        where ``finished`` lists (scenario, metrics dict of (n_done,) arrays, returns (n_done,)).
        """
        a = np.asarray(actions, dtype=np.float64)
        next_obs, rew, trunc, cont, finished = [], [], [], [], []
        i = 0
        for k, e in enumerate(self.engines):
            ak = a[i:i + self.sizes[k]].reshape(e.B, self.N, 4)
            i += self.sizes[k]
            out = e.step(ak)
            o = out["obs"].reshape(-1, self.obs_dim)
            r = out["rewards"]
            self.ep_return[k] += r
            # a world's first episode may be cut short (desynchronization); the engine's own time
            # limit ends every other episode
            done = np.asarray(out["truncated"], bool) | (self.first[k] & (e.steps >= self.first_len[k]))
            next_obs.append(o)
            rew.append(r.reshape(-1))
            trunc.append(np.repeat(done, self.N))
            if done.any():
                log = done & ~self.first[k]
                if log.any():
                    m = e.episode_metrics()
                    finished.append((e.cfg.scenario, {key: np.asarray(v)[log] for key, v in m.items()},
                                     self.ep_return[k][log].mean(-1)))
                self.first[k] &= ~done
                self.ep_return[k][done] = 0.0
                e.reset(mask=done)
                cont.append(e.observe().reshape(-1, self.obs_dim))
            else:
                cont.append(o)
        return (np.concatenate(next_obs).astype(np.float32), np.concatenate(rew).astype(np.float32),
                np.concatenate(trunc).astype(np.float32), np.concatenate(cont).astype(np.float32), finished)


# ---------------------------------------------------------------------------- learner
@jax.tree_util.register_dataclass
@dataclass
class TrainState:
    params: ppo_losses.PPONetworkParams
    opt_state: Any
    normalizer: running_statistics.RunningStatisticsState


def _uint64(count: float) -> brax_types.UInt64:
    c = int(count)
    return brax_types.UInt64(hi=np.uint32(c >> 32), lo=np.uint32(c & 0xFFFFFFFF))


def _count(state: running_statistics.RunningStatisticsState) -> float:
    c = state.count
    if isinstance(c, brax_types.UInt64):
        return float(np.asarray(c.hi, np.float64) * 2.0**32 + np.asarray(c.lo, np.float64))
    return float(np.asarray(c))


def _dense_layers(tree: Any) -> list[tuple[np.ndarray, np.ndarray]]:
    """Brax MLP params {'params': {'hidden_i': {'kernel', 'bias'}}} -> [(kernel, bias)] in order."""
    p = tree["params"] if "params" in tree else tree
    names = sorted(p, key=lambda s: int(s.rsplit("_", 1)[-1]))
    return [(np.asarray(p[n]["kernel"], np.float32), np.asarray(p[n]["bias"], np.float32)) for n in names]


def _to_tree(layers: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, Any]:
    return {"params": {f"hidden_{i}": {"kernel": jnp.asarray(k), "bias": jnp.asarray(b)}
                       for i, (k, b) in enumerate(layers)}}


def obs_layout(cfg: EnvConfig) -> dict[str, int]:
    """The observation layout of ``cfg`` (``quadswarm_mj.policies.validate_layout`` keys)."""
    return {"self_dim": cfg.self_obs_dim, "num_neighbors": cfg.neighbors, "neighbor_dim": 6,
            "obstacle_dim": 9 if cfg.obstacles is not None else 0}


def env_meta(cfg: EnvConfig) -> dict[str, Any]:
    """The EnvConfig fields a policy file records (``policy.env_kwargs``): observation layout, downwash
    when it was on, and the obstacle configuration when obstacles are on."""
    env = {k: getattr(cfg, k) for k in OBS_ENV_FIELDS}
    env["room_size"] = list(env["room_size"])
    if cfg.downwash:  # physics the policy was trained with beyond the defaults (the obstacle runs)
        env["downwash"] = True
    if cfg.obstacles is not None:
        env["obstacles"] = {k: (list(v) if isinstance(v, tuple) else v)
                            for k, v in dataclasses.asdict(cfg.obstacles).items()}
    return env


def encoder_arch(name: str, width: int | None = None, activation: str = "tanh") -> dict[str, Any]:
    """The encoder architecture of preset ``name`` (``quadswarm_mj.policies.ARCH_PRESETS``), with every hidden
    width set to ``width`` (the head layers to ``2 * width``, as the original's 2H head) when given."""
    a = {**ARCH_PRESETS[name], "activation": activation}
    if width is None:
        return a
    if a["type"] == "deepsets":
        for k in ("self_layers", "neighbor_layers", "obstacle_layers"):
            a[k] = [width] * len(a[k])
    else:
        a.update(hidden=width, attn_dim=width)
    a["head_layers"] = [2 * width] * len(a["head_layers"])
    return a


def make_networks(ppo: PPOConfig, layout: dict[str, int]) -> tuple[Any, dict[str, Any] | None]:
    """Brax ``PPONetworks`` for ``ppo.arch`` and the encoder architecture dict (None for the MLP)."""
    from quadswarm_mj.policies import layout_obs_dim

    normalize = (running_statistics.normalize if ppo.normalize_observations
                 else brax_types.identity_observation_preprocessor)
    if ppo.arch == "mlp":
        from quadswarm_mj.training.dense import make_mlp_ppo_networks

        # Brax's make_ppo_networks (same parameters) on Dense layers with a faster weight gradient
        nets = make_mlp_ppo_networks(layout_obs_dim(layout), 4, normalize, ppo.policy_hidden, ppo.value_hidden,
                                     ACTIVATIONS[ppo.activation])
        return nets, None
    arch = encoder_arch(ppo.arch, ppo.arch_width, ppo.activation)
    nets = enc_networks.make_ppo_networks(arch, layout, normalize, value_hidden_layer_sizes=ppo.value_hidden,
                                          activation=ppo.activation)
    return nets, arch


def init_params(networks: Any, ppo: PPOConfig, arch: dict[str, Any] | None, key: jax.Array
                ) -> ppo_losses.PPONetworkParams:
    """Fresh policy and value parameters; the policy's std starts at ``ppo.init_std`` (pre-tanh)."""
    kp, kv = jax.random.split(key)
    policy, value = networks.policy_network.init(kp), networks.value_network.init(kv)
    if arch is None:
        layers = _dense_layers(policy)
        k_last, b_last = layers[-1]
        b_last = b_last.copy()
        b_last[4:] = np.log(np.expm1(max(ppo.init_std - 0.001, 1e-4)))  # softplus^-1: Brax's std parameters
        policy = _to_tree(layers[:-1] + [(k_last, b_last)])
    else:
        policy = enc_networks.set_action_std(policy, ppo.init_std)
    return ppo_losses.PPONetworkParams(policy=policy, value=value)


def make_optimizer(ppo: PPOConfig) -> optax.GradientTransformation:
    return optax.chain(optax.clip_by_global_norm(ppo.max_grad_norm), optax.adam(ppo.learning_rate))


def make_policy_step(networks: Any) -> Callable:
    """(normalizer, policy params, obs (A, D), key) -> (actions (A, 4) in [-1, 1], extras) sampled."""
    make_policy = ppo_networks.make_inference_fn(networks)

    def step(normalizer: Any, policy_params: Any, obs: jax.Array, key: jax.Array) -> tuple[jax.Array, dict]:
        return make_policy((normalizer, policy_params))(obs, key)

    return step


class DrawnEntropyNormals:
    """A Brax tanh-normal action distribution whose ``entropy(parameters, eps)`` takes the standard
    normal draws of its one-sample entropy estimate as an array ``eps`` (the shape of the actions)
    instead of a key; everything else is the wrapped distribution's. Same estimator, same
    distribution of draws: the update draws them for a whole epoch before its minibatch loop, because
    inside the loop XLA:CPU fused the normals' erf_inv polynomial into every consumer of the backward
    pass and recomputed it there (measured; BENCHMARKS.md)."""

    def __init__(self, dist: Any):
        self._dist = dist

    def __getattr__(self, name: str) -> Any:
        return getattr(self._dist, name)

    def create_dist(self, parameters: jax.Array) -> Any:
        return _MeanKL(self._dist.create_dist(parameters))

    def entropy(self, parameters: jax.Array, eps: jax.Array) -> jax.Array:
        d = self._dist
        normal = d.create_dist(parameters)
        ent = normal.entropy() + d._postprocessor.forward_log_det_jacobian(eps * normal.scale + normal.loc)
        return jnp.sum(ent, axis=-1) if d._event_ndims == 1 else ent


class _MeanKL:
    """A Brax normal distribution whose ``kl_divergence(old)`` returns the MEAN of the per-sample KL
    as a (1,) array (Brax's loss only takes ``jnp.mean`` of it for its ``kl_mean`` metric, which
    then has the same value up to float rounding). The per-sample terms are reduced by a dot with
    ones: XLA:CPU had fused the KL's logs and divisions into the scalar reduction as scalar code
    (~130 us of each minibatch step, ~5 % of the update; BENCHMARKS.md)."""

    def __init__(self, dist: Any):
        self._dist = dist

    def __getattr__(self, name: str) -> Any:
        return getattr(self._dist, name)

    def kl_divergence(self, old: Any) -> jax.Array:
        old = old._dist if isinstance(old, _MeanKL) else old
        per = self._dist.kl_divergence(old).reshape(-1)
        return (jnp.dot(per, jnp.ones_like(per)) / per.shape[0]).reshape(1)


def make_update_fn(networks: Any, optimizer: optax.GradientTransformation, p: PPOConfig,
                   axis_name: str | None = None) -> Callable:
    """(TrainState, Transition [T, A], key, lr_scale) -> (TrainState, metrics): normalizer update, then
    ``num_epochs`` x ``num_minibatches`` Adam steps on Brax's ``compute_ppo_loss`` (pure; jit it).

    The entropy estimate's normal draws are made per epoch for all its minibatches
    (:class:`DrawnEntropyNormals`). ``axis_name``: data parallel over that mapped axis
    (``shard_map``/``pmap``), as Brax's PPO does under ``pmap``: each device holds A / D agents and
    shuffles them into its own minibatch slices, gradients, metrics and the observation statistics are
    averaged over the devices (``pmean``), so every device applies the same update to the same
    parameters. (The advantage normalization of the loss is per device minibatch.)"""
    drawn = networks.replace(parametric_action_distribution=DrawnEntropyNormals(
        networks.parametric_action_distribution))
    loss_fn = functools.partial(ppo_losses.compute_ppo_loss, ppo_network=drawn,
                                entropy_cost=p.entropy_cost, discounting=p.discounting,
                                reward_scaling=p.reward_scaling, gae_lambda=p.gae_lambda,
                                clipping_epsilon=p.clipping_epsilon, normalize_advantage=True)
    grad_fn = jax.value_and_grad(loss_fn, has_aux=True)

    def minibatch_step(carry: Any, batch: Any, normalizer: Any, lr_scale: Any) -> tuple[Any, None]:
        opt_state, params, msum = carry
        data, eps = batch
        (_, metrics), grads = grad_fn(params, normalizer, data, eps)
        if axis_name is not None:  # one all-reduce of one flat vector (each collective is a rendezvous)
            flat, unravel = jax.flatten_util.ravel_pytree((grads, metrics))
            grads, metrics = unravel(jax.lax.pmean(flat, axis_name))
        upd, opt_state = optimizer.update(grads, opt_state)
        upd = jax.tree_util.tree_map(lambda u: u * lr_scale, upd)  # learning-rate schedule
        # the metrics are summed in the carry, not stacked per minibatch: XLA:CPU fused the loss
        # metrics' reductions (the KL's logs and divisions over the minibatch) into the stacking's
        # dynamic-update-slice, where they ran as scalar code (~5 % of the update; BENCHMARKS.md)
        msum = jax.tree_util.tree_map(jnp.add, msum, metrics)
        return (opt_state, optax.apply_updates(params, upd), msum), None

    def epoch(carry: Any, _: Any, data: Any, normalizer: Any, lr_scale: Any) -> tuple[Any, None]:
        opt_state, params, msum, key = carry
        key, kperm, keps = jax.random.split(key, 3)

        def shuffle(x: jax.Array) -> jax.Array:
            x = jax.random.permutation(kperm, x)
            return x.reshape((p.num_minibatches, -1) + x.shape[1:])

        batches = jax.tree_util.tree_map(shuffle, data)
        raw = batches.extras["policy_extras"]["raw_action"]  # (minibatches, agents, T, action)
        m_, a_, t_, d_ = raw.shape
        eps = jax.random.normal(keps, (m_, t_, a_, d_), raw.dtype)  # time-major, as the loss sees the actions
        (opt_state, params, msum), _ = jax.lax.scan(functools.partial(minibatch_step, normalizer=normalizer,
                                                                      lr_scale=lr_scale),
                                                    (opt_state, params, msum), (batches, eps))
        return (opt_state, params, msum, key), None

    def update(state: TrainState, data: brax_types.Transition, key: jax.Array,
               lr_scale: jax.Array) -> tuple[TrainState, Any]:
        data = jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), data)  # [T, A] -> [A, T]
        normalizer = state.normalizer
        if p.normalize_observations:
            normalizer = running_statistics.update(normalizer, data.observation, pmap_axis_name=axis_name)
        # the metrics' structure and types (one minibatch's loss, traced abstractly: no computation)
        first = jax.tree_util.tree_map(lambda x: x[: x.shape[0] // p.num_minibatches], data)  # [A / M, T]
        eps0 = jnp.zeros_like(first.extras["policy_extras"]["raw_action"].swapaxes(0, 1))  # time-major
        shapes = jax.eval_shape(lambda: grad_fn(state.params, normalizer, first, eps0)[0][1])
        msum = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
        (opt_state, params, msum, _), _ = jax.lax.scan(
            functools.partial(epoch, data=data, normalizer=normalizer, lr_scale=lr_scale),
            (state.opt_state, state.params, msum, key), None, length=p.num_epochs)
        m = jax.tree_util.tree_map(lambda x: x / (p.num_epochs * p.num_minibatches), msum)
        m["learning_rate"] = lr_scale * p.learning_rate
        return TrainState(params=params, opt_state=opt_state, normalizer=normalizer), m

    return update


def normalizer_stats(normalizer: Any, ppo: PPOConfig, obs_dim: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(obs mean, obs std, count) of Brax's running normalizer (0, 1 when normalization is off)."""
    if ppo.normalize_observations:
        return np.asarray(normalizer.mean, np.float32), np.asarray(normalizer.std, np.float32), _count(normalizer)
    return np.zeros(obs_dim, np.float32), np.ones(obs_dim, np.float32), _count(normalizer)


def save_policy_file(path: str | Path, ppo: PPOConfig, arch: dict[str, Any] | None, cfg: EnvConfig,
                     state: TrainState, train_meta: dict[str, Any]) -> str:
    """Write the trained policy as a ``quadswarm_mj.policies`` file: format 1 (MLP) or 2 (encoder, via
    ``networks.export_policy``: architecture and observation layout recorded); both also hold the critic
    (``value/layer_i/...``) and the normalizer count. Returns the SHA-256."""
    layout = obs_layout(cfg)
    d = cfg.obs_dim
    mean, std, count = normalizer_stats(state.normalizer, ppo, d)
    meta = {"activation": ppo.activation, "obs_dim": d, "action_dim": 4, "env": env_meta(cfg), "train": train_meta}
    extra = {"norm_count": np.array(count, np.float64)}
    for i, (k, b) in enumerate(_dense_layers(state.params.value)):
        extra[f"value/layer_{i}/kernel"] = k
        extra[f"value/layer_{i}/bias"] = b
    if arch is None:
        layers = _dense_layers(state.params.policy)
        return save_policy(path, [k for k, _ in layers], [b for _, b in layers], mean, std, meta, extra)
    return enc_networks.export_policy(path, arch, layout, state.params.policy, mean, std, meta, extra)


def _value_layers(arrays: dict[str, np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
    """The critic's (kernel, bias) layers stored in a policy file (``value/layer_i/...``; [] if none)."""
    out, i = [], 0
    while f"value/layer_{i}/kernel" in arrays:
        out.append((arrays[f"value/layer_{i}/kernel"], arrays[f"value/layer_{i}/bias"]))
        i += 1
    return out


def start_run(out_dir: str | Path | None, history: list[dict[str, Any]] | None, total_steps: int | None,
              seconds: float | None, progress: bool) -> tuple[Path | None, list[dict[str, Any]], float, Any]:
    """Common start of both trainers' ``train``: the output directory (``checkpoints/`` created), the
    earlier log rows of a resumed run, their wall time (s) and the ProgressBar (None without progress)."""
    if total_steps is None and seconds is None:
        raise ValueError("give a budget: total_steps and/or seconds")
    out = Path(out_dir) if out_dir is not None else None
    if out is not None:
        (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = list(history or [])
    wall0 = float(rows[-1]["wall_s"]) if rows else 0.0
    bar = None
    if progress:  # one \r-updated line on a terminal, a line every 10 s otherwise (training/progress.py)
        from quadswarm_mj.training.progress import ProgressBar

        bar = ProgressBar(total_steps, seconds)
    return out, rows, wall0, bar


def ppo_meta(ppo: PPOConfig) -> dict[str, Any]:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(ppo).items()}


# ---------------------------------------------------------------------------- resumable checkpoints
TRAIN_STATE_FILE = "train_state.npz"


def _key_data(key: jax.Array) -> np.ndarray:
    if jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key):
        return np.asarray(jax.random.key_data(key))
    return np.asarray(key)


def save_train_state(path: str | Path, state: TrainState, key: jax.Array, scalars: dict[str, Any],
                     extra: dict[str, Any] | None = None) -> None:
    """The full learner state (parameters, Adam state, normalizer), the trainer's RNG key and JSON
    ``scalars`` (step counters, lr scale, configuration) as a pickle-free ``.npz``, written atomically
    (temporary file, then rename). ``extra``: more named arrays (e.g. the worlds' step counters)."""
    leaves = jax.tree_util.tree_flatten_with_path(state)[0]
    arrays: dict[str, np.ndarray] = {f"state{jax.tree_util.keystr(kp)}": np.asarray(v) for kp, v in leaves}
    arrays["rng"] = _key_data(key)
    arrays["scalars"] = np.array(json.dumps(scalars, default=str))
    for k, v in (extra or {}).items():
        arrays[f"extra/{k}"] = np.asarray(v)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **arrays)
    tmp.replace(path)


def load_train_state(path: str | Path, template: TrainState) -> tuple[TrainState, jax.Array, dict[str, Any],
                                                                       dict[str, np.ndarray]]:
    """Inverse of :func:`save_train_state` for a learner of the same networks and optimizer (``template``
    gives the tree structure): (state, key, scalars, extra arrays). Raises ValueError on a mismatch."""
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
    out = []
    for kp, like in leaves:
        name = f"state{jax.tree_util.keystr(kp)}"
        if name not in arrays:
            raise ValueError(f"checkpoint {str(path)!r} lacks {name} (was it written by another --arch or network "
                             f"size?)")
        v = arrays[name]
        if tuple(v.shape) != tuple(np.shape(like)):
            raise ValueError(f"checkpoint {str(path)!r}: {name} has shape {v.shape}, this run needs "
                             f"{tuple(np.shape(like))}")
        out.append(jnp.asarray(v, dtype=jnp.asarray(like).dtype))
    state = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(template), out)
    scalars = json.loads(str(arrays["scalars"]))
    extra = {k[len("extra/"):]: v for k, v in arrays.items() if k.startswith("extra/")}
    return state, jnp.asarray(arrays["rng"]), scalars, extra


def linear_lr_scale(ppo: PPOConfig, frac: float, start: float = 1.0) -> float:
    """Learning-rate factor at budget fraction ``frac``: constant ``start``, or linear from ``start`` to
    ``lr_final_fraction`` (resumed runs start from the checkpoint's factor)."""
    if ppo.lr_schedule != "linear":
        return start
    end = min(ppo.lr_final_fraction, start)
    return start - (start - end) * min(max(frac, 0.0), 1.0)


class PPOTrainer:
    """PPO on ``AgentBatch`` (the CPU engine). Use :meth:`train` (budget in agent-steps and/or seconds)."""

    def __init__(self, cfgs: list[EnvConfig], ppo: PPOConfig, seed: int = 0, init_from: str | None = None):
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
        """Start from a policy checkpoint (transfer, e.g. single -> swarm): layers are copied; a
        larger observation (more neighbours) gets zero input weights for the new components, so
        the starting policy ignores them; the new components' normalizer is mean 0, std 1."""
        pol = load_policy_file(path)
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        if self.arch is not None or not hasattr(pol, "kernels"):
            return self._load_init_encoder(path, pol, arrays, params, normalizer)
        d_old, d = pol.obs_dim, self.obs_dim
        if d_old > d:
            raise ValueError(f"init_from policy has obs_dim {d_old} > this run's {d}")

        def pad(layers: list[tuple[np.ndarray, np.ndarray]], like: Any) -> list[tuple[np.ndarray, np.ndarray]]:
            want = _dense_layers(like)
            if [k.shape[1] for k, _ in layers] != [k.shape[1] for k, _ in want] or len(layers) != len(want):
                raise ValueError(f"init_from network sizes {[k.shape for k, _ in layers]} do not match this run's "
                                 f"{[k.shape for k, _ in want]}")
            k0 = np.zeros((d, layers[0][0].shape[1]), np.float32)
            k0[:d_old] = layers[0][0]
            rest = [(np.asarray(k, np.float32), np.asarray(b, np.float32)) for k, b in layers[1:]]
            return [(k0, np.asarray(layers[0][1], np.float32))] + rest

        pol_layers = pad([(k, b) for k, b in zip(pol.kernels, pol.biases)], params.policy)
        value = params.value
        vl = _value_layers(arrays)
        if vl:
            value = _to_tree(pad(vl, params.value))
        params = ppo_losses.PPONetworkParams(policy=_to_tree(pol_layers), value=value)
        mean = np.zeros(d, np.float32)
        std = np.ones(d, np.float32)
        mean[:d_old], std[:d_old] = pol.obs_mean, pol.obs_std
        count = float(arrays["norm_count"]) if "norm_count" in arrays else 1e6
        normalizer = normalizer.replace(count=_uint64(count), mean=jnp.asarray(mean), std=jnp.asarray(std),
                                        summed_variance=jnp.asarray(std.astype(np.float64) ** 2 * count, jnp.float32))
        return params, normalizer

    def _load_init_encoder(self, path: str, pol: Any, arrays: dict[str, np.ndarray], params: Any,
                           normalizer: Any) -> tuple[Any, Any]:
        """Start from an encoder policy file of the same architecture and observation layout."""
        from quadswarm_mj.policies import validate_arch

        if self.arch is None or not hasattr(pol, "arch"):
            raise ValueError(f"init_from {path!r}: an MLP run starts from an MLP file and an encoder run from an "
                             f"encoder file of the same --arch")
        if pol.obs_layout != obs_layout(self.cfgs[0]) or pol.arch != validate_arch(self.arch, self.layout):
            raise ValueError(f"init_from {path!r}: architecture {pol.arch} / layout {pol.obs_layout} differ from this "
                             f"run's {self.arch} / {self.layout}")
        policy = enc_networks.unflatten_params(pol.params)
        value = params.value
        vl = _value_layers(arrays)
        if vl:
            if [k.shape for k, _ in vl] == [k.shape for k, _ in _dense_layers(params.value)]:
                value = _to_tree(vl)
        count = float(arrays["norm_count"]) if "norm_count" in arrays else 1e6
        mean, std = np.asarray(pol.obs_mean, np.float32), np.asarray(pol.obs_std, np.float32)
        normalizer = normalizer.replace(count=_uint64(count), mean=jnp.asarray(mean), std=jnp.asarray(std),
                                        summed_variance=jnp.asarray(std.astype(np.float64) ** 2 * count, jnp.float32))
        return ppo_losses.PPONetworkParams(policy=policy, value=value), normalizer

    # ------------------------------------------------------------------ export
    def export_arrays(self) -> dict[str, Any]:
        """Policy layers (MLP only), value layers and normalizer statistics as NumPy arrays."""
        mean, std, count = normalizer_stats(self.state.normalizer, self.ppo, self.obs_dim)
        pol = _dense_layers(self.state.params.policy) if self.arch is None else None
        return {"policy": pol, "value": _dense_layers(self.state.params.value), "obs_mean": mean, "obs_std": std,
                "norm_count": count}

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
            self._lr_scale = linear_lr_scale(self.ppo, frac, self.lr_start)
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


# ---------------------------------------------------------------------------- logs and curves
def write_logs(out: Path, rows: list[dict[str, Any]]) -> None:
    """``progress.json`` (list of rows) and ``progress.csv`` (one column per key)."""
    out = Path(out)
    (out / "progress.json").write_text(json.dumps(rows, allow_nan=True))
    if not rows:
        return
    keys = list(rows[0])
    for r in rows[1:]:
        keys += [k for k in r if k not in keys]
    lines = [",".join(keys)]
    for r in rows:
        lines.append(",".join("" if r.get(k) is None else str(r.get(k)) for k in keys))
    (out / "progress.csv").write_text("\n".join(lines) + "\n")


def _smooth_metric(rows: list[dict[str, Any]], key: str, window: int) -> np.ndarray:
    """Episode-weighted mean of ``key`` over the last ``window`` rows (NaN where no episode ended)."""
    scn = key.split("/")[0]
    vals = np.array([r.get(key, np.nan) for r in rows], float)
    cnt = np.array([r.get(f"{scn}/episodes", 0) for r in rows], float)
    ok = np.isfinite(vals) & (cnt > 0)
    num = np.convolve(np.where(ok, vals * cnt, 0.0), np.ones(window))[: len(rows)]
    den = np.convolve(np.where(ok, cnt, 0.0), np.ones(window))[: len(rows)]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / den, np.nan)


def plot_curves(progress_json: str | Path, png: str | Path, title: str | None = None,
                window: int | None = None, marks: list[tuple[float, str]] | None = None) -> None:
    """Reward and episode-metric curves vs agent-steps (matplotlib, Agg). Episode metrics are
    averaged over the episodes that ended in the last ``window`` iterations (default: about
    1/60 of the run, at least 10), weighted by episode count. ``marks``: (agent-steps, label)
    vertical lines, e.g. the checkpoint that was shipped."""
    try:  # optional: without matplotlib the run goes on without curves
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    rows = json.loads(Path(progress_json).read_text())
    if not rows:
        return
    window = min(window or max(10, len(rows) // 60), len(rows))
    x = np.array([r["env_steps"] for r in rows], float) / 1e6
    wall = np.array([r["wall_s"] for r in rows], float) / 60
    scns = list(dict.fromkeys(k.split("/")[0] for r in rows[:1] for k in r if "/" in k))
    panels = [("reward_per_step", "reward per agent-step"), ("success", "success rate"),
              ("goal_reach_rate", "goal-reach rate"), ("collisions", "collisions / quad / episode"),
              ("mean_distance", "mean distance to goal (m)"), ("floor_hits", "floor hits / quad / episode"),
              ("wall_hits", "wall hits / quad / episode"), ("_time", "wall time (min)")]
    fig, axes = plt.subplots(2, 4, figsize=(17, 7.5))
    for ax, (key, label) in zip(axes.ravel(), panels):
        if key == "reward_per_step":
            y = np.array([r[key] for r in rows], float)
            ax.plot(x, y, lw=0.5, alpha=0.4, color="C0")
            k = np.ones(window) / window
            ax.plot(x[window - 1:], np.convolve(y, k, mode="valid"), lw=1.5, color="C0")
        elif key == "_time":
            ax.plot(x, wall, lw=1.5, color="k")
            ax.set_ylabel("min")
        else:
            for i, s in enumerate(scns):
                y = _smooth_metric(rows, f"{s}/{key}", window)
                ok = np.isfinite(y)
                if ok.any():
                    ax.plot(x[ok], y[ok], lw=1.5, color=f"C{i + 1}", label=s)
            if key in ("success", "goal_reach_rate"):
                ax.set_ylim(-0.02, 1.02)
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7)
        for steps, lab in marks or []:
            ax.axvline(steps / 1e6, color="k", ls="--", lw=1)
            if key == "reward_per_step":
                ax.annotate(lab, (steps / 1e6, 0.02), xycoords=("data", "axes fraction"), fontsize=7,
                            rotation=90, ha="right", va="bottom")
        ax.set_title(label, fontsize=10)
        ax.set_xlabel("agent-steps (M)")
        ax.grid(alpha=0.3)
    fig.suptitle(title or f"{Path(progress_json).parent.name}: {rows[-1]['env_steps'] / 1e6:.1f} M agent-steps in "
                 f"{rows[-1]['wall_s'] / 60:.1f} min (stochastic training policy; episode metrics averaged over "
                 f"{window} iterations)", fontsize=11)
    fig.tight_layout()
    fig.savefig(png, dpi=80)
    plt.close(fig)
