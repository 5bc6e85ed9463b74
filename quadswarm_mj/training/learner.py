"""The PPO learner shared by both trainers: networks (Brax's tanh-normal MLPs or the encoders of
:mod:`quadswarm_mj.training.networks`), parameter initialization, the optimizer (Adam after global-norm
clipping, its learning rate an ``optax.inject_hyperparams`` hyper-parameter that the update sets from the
schedule), the policy's action sampling and the update: Brax's running observation normalizer, then
``num_epochs`` x ``num_minibatches`` Adam steps on ``brax.training.agents.ppo.losses.compute_ppo_loss``,
optionally data parallel over a mapped device axis (one ``pmean`` per minibatch).

Also the observation-layout and policy-file metadata helpers (:func:`obs_layout`, :func:`env_meta`,
:func:`encoder_arch`) and the conversions between Brax's parameter trees and (kernel, bias) lists.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
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

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.policies import ARCH_PRESETS, OBS_ENV_FIELDS
from quadswarm_mj.training import networks as enc_networks
from quadswarm_mj.training.ppo_config import ACTIVATIONS, PPOConfig


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
    """The observation layout of ``cfg`` (``quadswarm_mj.policies.validate_layout`` keys); ``obstacle_dim``
    is the tail after the neighbours: the 9 column features (if observed) and the deck readings."""
    return {"self_dim": cfg.self_obs_dim, "num_neighbors": cfg.neighbors, "neighbor_dim": 6,
            "obstacle_dim": cfg.obs_dim - cfg.self_obs_dim - 6 * cfg.neighbors}


def env_meta(cfg: EnvConfig) -> dict[str, Any]:
    """The EnvConfig fields a policy file records (``policy.env_kwargs``): observation layout, the control
    and simulation rates and the neighbour form when not the defaults, downwash when it was on, and the obstacle
    configuration when obstacles are on."""
    env = {k: getattr(cfg, k) for k in OBS_ENV_FIELDS}
    env["room_size"] = list(env["room_size"])
    for k in ("control_hz", "sim_hz", "neighbor_form", "neighbor_near_range"):  # the rates (Hz) a policy acts
        if getattr(cfg, k) != getattr(EnvConfig, k):  # at and the neighbour inputs' form, when not the defaults
            env[k] = getattr(cfg, k)
    if cfg.downwash:  # physics the policy was trained with beyond the defaults (the obstacle runs)
        env["downwash"] = True
    if cfg.obstacles is not None:
        env["obstacles"] = {k: (list(v) if isinstance(v, tuple) else v)
                            for k, v in dataclasses.asdict(cfg.obstacles).items()}
    if cfg.sensors.any:  # the deck sensors the policy reads (their readings end its observation)
        env["sensors"] = {k: (list(v) if isinstance(v, tuple) else v)
                          for k, v in dataclasses.asdict(cfg.sensors).items()}
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
                                     ACTIVATIONS[ppo.activation], min_std=ppo.min_action_std)
        return nets, None
    arch = encoder_arch(ppo.arch, ppo.arch_width, ppo.activation)
    nets = enc_networks.make_ppo_networks(arch, layout, normalize, value_hidden_layer_sizes=ppo.value_hidden,
                                          activation=ppo.activation, min_std=ppo.min_action_std)
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
        b_last[4:] = enc_networks.std_bias(ppo.init_std, ppo.min_action_std)  # Brax's std parameters
        policy = _to_tree(layers[:-1] + [(k_last, b_last)])
    else:
        policy = enc_networks.set_action_std(policy, ppo.init_std, min_std=ppo.min_action_std)
    return ppo_losses.PPONetworkParams(policy=policy, value=value)


def constant_action_std(policy: Any, std: float, arch: dict[str, Any] | None, min_std: float = 0.001) -> Any:
    """Policy parameters whose tanh-normal std is ``std`` (pre-tanh) in every state: the action layer's
    std outputs get zero input weights and the bias softplus^-1(std - min_std); the means are untouched."""
    if arch is not None:
        flat = enc_networks.flatten_params(policy)
        k = np.array(flat["action/kernel"], np.float32)
        k[..., 4:] = 0.0
        flat["action/kernel"] = k
        return enc_networks.set_action_std(enc_networks.unflatten_params(flat), std, min_std=min_std)
    layers = _dense_layers(policy)
    k_last, b_last = (np.array(a, np.float32) for a in layers[-1])
    k_last[:, 4:] = 0.0
    b_last[4:] = enc_networks.std_bias(std, min_std)
    return _to_tree(layers[:-1] + [(k_last, b_last)])


#: Adam's arguments kept as constants (only the learning rate is an injected, per-update hyper-parameter)
_ADAM_STATIC = ("b1", "b2", "eps", "eps_root", "nesterov")


def make_optimizer(ppo: PPOConfig) -> optax.GradientTransformation:
    """Global-norm clipping, then Adam whose learning rate is an ``optax.inject_hyperparams``
    hyper-parameter (``opt_state[1].hyperparams["learning_rate"]``, starting at ``ppo.learning_rate``):
    the update sets it from the schedule (:func:`set_learning_rate`) and the checkpoint keeps it."""
    adam = optax.inject_hyperparams(optax.adam, static_args=_ADAM_STATIC)(learning_rate=ppo.learning_rate)
    return optax.chain(optax.clip_by_global_norm(ppo.max_grad_norm), adam)


def set_learning_rate(opt_state: Any, learning_rate: jax.Array) -> Any:
    """``opt_state`` of :func:`make_optimizer` with its injected learning rate set to ``learning_rate``."""
    clip, adam = opt_state
    hp = {**adam.hyperparams, "learning_rate": jnp.asarray(learning_rate, adam.hyperparams["learning_rate"].dtype)}
    return (clip, adam._replace(hyperparams=hp))


def learning_rate_of(opt_state: Any) -> jax.Array:
    """The injected learning rate of an ``opt_state`` of :func:`make_optimizer`."""
    return opt_state[1].hyperparams["learning_rate"]


def make_policy_step(networks: Any) -> Callable:
    """(normalizer, policy params, obs (A, D), key) -> (actions (A, 4) in [-1, 1], extras) sampled."""
    make_policy = ppo_networks.make_inference_fn(networks)

    def step(normalizer: Any, policy_params: Any, obs: jax.Array, key: jax.Array) -> tuple[jax.Array, dict]:
        return make_policy((normalizer, policy_params))(obs, key)

    return step


def correlated_noise(prev: jax.Array, key: jax.Array, rho: float) -> jax.Array:
    """The next step's standard normal exploration noise of each agent, an AR(1) process:
    ``rho * prev + sqrt(1 - rho^2) * n`` with fresh n ~ N(0, 1) (stationary N(0, 1); lag-k correlation rho^k)."""
    return rho * prev + math.sqrt(1.0 - rho * rho) * jax.random.normal(key, prev.shape, prev.dtype)


def make_noise_policy_step(networks: Any) -> Callable:
    """(normalizer, policy params, obs (A, D), eps (A, 4)) -> (actions (A, 4) in [-1, 1], extras): the
    tanh-normal policy's pre-tanh action ``mean + std * eps`` for the given standard normal draws ``eps``
    (``PPOConfig.noise_correlation``), with the extras of Brax's sampled step (``log_prob``, ``raw_action``,
    ``distribution_params``)."""
    dist = networks.parametric_action_distribution

    def step(normalizer: Any, policy_params: Any, obs: jax.Array, eps: jax.Array) -> tuple[jax.Array, dict]:
        logits = networks.policy_network.apply(normalizer, policy_params, obs)
        normal = dist.create_dist(logits)
        raw = normal.loc + normal.scale * eps
        return dist.postprocess(raw), {"log_prob": dist.log_prob(logits, raw), "raw_action": raw,
                                       "distribution_params": logits}

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


def trainable_mask(params: Any, train_inputs_from: int) -> Any:
    """1.0 where a parameter of ``params`` (PPONetworkParams of an MLP policy) trains under
    ``PPOConfig.train_inputs_from`` > 0, else 0.0: every critic parameter, and the rows >= ``train_inputs_from``
    of the policy's first kernel (the weights of the new observation components)."""
    def policy_leaf(path: tuple, x: jax.Array) -> jax.Array:
        names = [getattr(k, "key", None) for k in path]
        if names[-2:] == ["hidden_0", "kernel"]:
            return (jnp.arange(x.shape[0]) >= train_inputs_from)[:, None].astype(x.dtype) * jnp.ones_like(x)
        return jnp.zeros_like(x)

    return params.replace(policy=jax.tree_util.tree_map_with_path(policy_leaf, params.policy),
                          value=jax.tree_util.tree_map(jnp.ones_like, params.value))


def check_train_inputs_from(ppo: PPOConfig, obs_dim: int, init_from: str | None) -> None:
    """Raise ValueError unless ``ppo.train_inputs_from`` fits a run with ``obs_dim`` and ``init_from``."""
    t = ppo.train_inputs_from
    if t and init_from is None:
        raise ValueError("ppo.train_inputs_from > 0 keeps a warm start's policy: it needs init_from")
    if t and t >= obs_dim:
        raise ValueError(f"ppo.train_inputs_from must be below the observation size {obs_dim} (some inputs train), "
                         f"got {t}")


def make_update_fn(networks: Any, optimizer: optax.GradientTransformation, p: PPOConfig,
                   axis_name: str | None = None) -> Callable:
    """(TrainState, Transition [T, A], key, lr_scale) -> (TrainState, metrics): normalizer update, then
    ``num_epochs`` x ``num_minibatches`` Adam steps on Brax's ``compute_ppo_loss`` (pure; jit it), at the
    learning rate ``lr_scale * p.learning_rate`` (the schedule's factor, set as the optimizer's injected
    hyper-parameter for this update).

    The entropy estimate's normal draws are made per epoch for all its minibatches
    (:class:`DrawnEntropyNormals`). ``axis_name``: data parallel over that mapped axis
    (``shard_map``/``pmap``), as Brax's PPO does under ``pmap``: each device holds A / D agents and
    shuffles them into its own minibatch slices, gradients, metrics and the observation statistics are
    averaged over the devices (``pmean``), so every device applies the same update to the same
    parameters. (The advantage normalization of the loss is per device minibatch.) With
    ``p.train_inputs_from`` > 0 the gradients are masked by :func:`trainable_mask` and the observation
    statistics stay as they are."""
    drawn = networks.replace(parametric_action_distribution=DrawnEntropyNormals(
        networks.parametric_action_distribution))
    loss_fn = functools.partial(ppo_losses.compute_ppo_loss, ppo_network=drawn,
                                entropy_cost=p.entropy_cost, discounting=p.discounting,
                                reward_scaling=p.reward_scaling, gae_lambda=p.gae_lambda,
                                clipping_epsilon=p.clipping_epsilon, normalize_advantage=True)
    grad_fn = jax.value_and_grad(loss_fn, has_aux=True)

    def minibatch_step(carry: Any, batch: Any, normalizer: Any) -> tuple[Any, None]:
        opt_state, params, msum = carry
        data, eps = batch
        (_, metrics), grads = grad_fn(params, normalizer, data, eps)
        if axis_name is not None:  # one all-reduce of one flat vector (each collective is a rendezvous)
            flat, unravel = jax.flatten_util.ravel_pytree((grads, metrics))
            grads, metrics = unravel(jax.lax.pmean(flat, axis_name))
        if p.train_inputs_from:
            grads = jax.tree_util.tree_map(jnp.multiply, grads, trainable_mask(params, p.train_inputs_from))
        upd, opt_state = optimizer.update(grads, opt_state)
        # the metrics are summed in the carry, not stacked per minibatch: XLA:CPU fused the loss
        # metrics' reductions (the KL's logs and divisions over the minibatch) into the stacking's
        # dynamic-update-slice, where they ran as scalar code (~5 % of the update; BENCHMARKS.md)
        msum = jax.tree_util.tree_map(jnp.add, msum, metrics)
        return (opt_state, optax.apply_updates(params, upd), msum), None

    def epoch(carry: Any, _: Any, data: Any, normalizer: Any) -> tuple[Any, None]:
        opt_state, params, msum, key = carry
        key, kperm, keps = jax.random.split(key, 3)

        def shuffle(x: jax.Array) -> jax.Array:
            x = jax.random.permutation(kperm, x)
            return x.reshape((p.num_minibatches, -1) + x.shape[1:])

        batches = jax.tree_util.tree_map(shuffle, data)
        raw = batches.extras["policy_extras"]["raw_action"]  # (minibatches, agents, T, action)
        m_, a_, t_, d_ = raw.shape
        eps = jax.random.normal(keps, (m_, t_, a_, d_), raw.dtype)  # time-major, as the loss sees the actions
        (opt_state, params, msum), _ = jax.lax.scan(functools.partial(minibatch_step, normalizer=normalizer),
                                                    (opt_state, params, msum), (batches, eps))
        return (opt_state, params, msum, key), None

    def update(state: TrainState, data: brax_types.Transition, key: jax.Array,
               lr_scale: jax.Array) -> tuple[TrainState, Any]:
        data = jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), data)  # [T, A] -> [A, T]
        normalizer = state.normalizer
        if p.normalize_observations and not p.train_inputs_from:
            normalizer = running_statistics.update(normalizer, data.observation, pmap_axis_name=axis_name)
        # the metrics' structure and types (one minibatch's loss, traced abstractly: no computation)
        first = jax.tree_util.tree_map(lambda x: x[: x.shape[0] // p.num_minibatches], data)  # [A / M, T]
        eps0 = jnp.zeros_like(first.extras["policy_extras"]["raw_action"].swapaxes(0, 1))  # time-major
        shapes = jax.eval_shape(lambda: grad_fn(state.params, normalizer, first, eps0)[0][1])
        msum = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
        opt_state = set_learning_rate(state.opt_state, lr_scale * p.learning_rate)  # the schedule's value
        (opt_state, params, msum, _), _ = jax.lax.scan(
            functools.partial(epoch, data=data, normalizer=normalizer),
            (opt_state, state.params, msum, key), None, length=p.num_epochs)
        m = jax.tree_util.tree_map(lambda x: x / (p.num_epochs * p.num_minibatches), msum)
        m["learning_rate"] = learning_rate_of(opt_state)
        return TrainState(params=params, opt_state=opt_state, normalizer=normalizer), m

    return update


def normalizer_stats(normalizer: Any, ppo: PPOConfig, obs_dim: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(obs mean, obs std, count) of Brax's running normalizer (0, 1 when normalization is off)."""
    if ppo.normalize_observations:
        return np.asarray(normalizer.mean, np.float32), np.asarray(normalizer.std, np.float32), _count(normalizer)
    return np.zeros(obs_dim, np.float32), np.ones(obs_dim, np.float32), _count(normalizer)
