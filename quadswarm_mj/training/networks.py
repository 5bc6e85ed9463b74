"""Flax policy networks for the trainer: deep-sets and attention encoders (SPEC_obstacles C.1).

The modules mirror :func:`quadswarm_mj.policies.encoder_forward` parameter for parameter: flax
parameter paths joined by ``/`` (``self_0/kernel``, ``attn/w_q/kernel``, ``attn/ln/scale``, ...) are
the names of :func:`quadswarm_mj.policies.param_shapes`, so :func:`export_policy` writes trained
parameters straight into the NumPy policy format (``quadswarm_mj.policy/2``).

Observations are ``[self | K x 6 neighbours | 9 SDF]`` (already normalized by Brax's
preprocessor); the output is the ``2 * action_dim`` parameters of Brax's tanh-normal distribution.
:func:`make_ppo_networks` returns Brax ``PPONetworks`` whose policy is such an encoder (the value
network stays Brax's MLP), a drop-in for ``brax...ppo.networks.make_ppo_networks`` in the trainer.
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import linen

from quadswarm_mj.policies import (
    LN_EPS,
    NEIGHBOR_DIM,
    EncoderPolicy,
    layout_obs_dim,
    num_tokens,
    param_shapes,
    save_encoder_policy,
    validate_arch,
    validate_layout,
)
from quadswarm_mj.training.dense import dense_dot_general

ACTIVATION_FNS: dict[str, Callable[[jax.Array], jax.Array]] = {
    "tanh": linen.tanh, "relu": linen.relu, "swish": linen.swish, "elu": linen.elu}
#: Xavier-uniform kernels and zero biases, as the original (SPEC_obstacles C.1).
KERNEL_INIT = jax.nn.initializers.xavier_uniform()
#: ``linen.Dense`` with the faster weight gradient of :mod:`quadswarm_mj.training.dense` (same values).
Dense = functools.partial(linen.Dense, dot_general=dense_dot_general)


def _mlp(x: jax.Array, prefix: str, sizes: Sequence[int], act: str) -> jax.Array:
    fn = ACTIVATION_FNS[act]
    for i, n in enumerate(sizes):
        x = fn(Dense(n, kernel_init=KERNEL_INIT, name=f"{prefix}_{i}")(x))
    return x


class Attention(linen.Module):
    """Attention over tokens (..., T, H): per head softmax(Q K^T / sqrt(d)) V, concat, bias-free fc,
    residual, LayerNorm (eps 1e-6). One head with d = H is the original OneHeadAttention."""

    hidden: int
    num_heads: int = 1
    attn_dim: int = 16

    @linen.compact
    def __call__(self, tokens: jax.Array) -> jax.Array:
        qk = self.num_heads * self.attn_dim
        shape = tokens.shape[:-1] + (self.num_heads, self.attn_dim)
        q, k, v = (Dense(qk, use_bias=False, kernel_init=KERNEL_INIT, name=f"w_{c}")(tokens).reshape(shape)
                   for c in "qkv")
        s = jnp.einsum("...ihd,...jhd->...hij", q, k) / math.sqrt(self.attn_dim)
        w = jax.nn.softmax(s, axis=-1)
        o = jnp.einsum("...hij,...jhd->...ihd", w, v).reshape(tokens.shape[:-1] + (qk,))
        o = Dense(self.hidden, use_bias=False, kernel_init=KERNEL_INIT, name="fc")(o) + tokens
        return linen.LayerNorm(epsilon=LN_EPS, use_fast_variance=False, name="ln")(o)


class EncoderNetwork(linen.Module):
    """Deep-sets or attention policy network: observations (..., obs_dim) -> (..., 2 * action_dim)."""

    arch: dict[str, Any]
    layout: dict[str, Any]

    @linen.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        lay = validate_layout(dict(self.layout))
        a = validate_arch(dict(self.arch), lay)
        act = a["activation"]
        sd, k, od = lay["self_dim"], lay["num_neighbors"], lay["obstacle_dim"]
        xs, xn, xo = x[..., :sd], x[..., sd: sd + NEIGHBOR_DIM * k], x[..., sd + NEIGHBOR_DIM * k:]
        if a["type"] == "deepsets":
            parts = [_mlp(xs, "self", a["self_layers"], act)]
            if k:
                e = _mlp(xn.reshape(xn.shape[:-1] + (k, NEIGHBOR_DIM)), "nbr", a["neighbor_layers"], act)
                parts.append(e.mean(axis=-2))
            if od:
                parts.append(_mlp(xo, "obst", a["obstacle_layers"], act))
        else:
            h, el = a["hidden"], a["embed_layers"]
            toks = []
            if k:
                toks.append(_mlp(xn, "nbr", [h] * el, act))
            if od:
                toks.append(_mlp(xo, "obst", [h] * el, act))
            att = Attention(h, a["num_heads"], a["attn_dim"], name="attn")(jnp.stack(toks, axis=-2))
            parts = [_mlp(xs, "self", [h] * el, act), att.reshape(att.shape[:-2] + (h * num_tokens(lay),))]
        y = _mlp(jnp.concatenate(parts, axis=-1), "head", a["head_layers"], act)
        return Dense(2 * a["action_dim"], kernel_init=KERNEL_INIT, name="action")(y)


def flatten_params(params: Any) -> dict[str, np.ndarray]:
    """Flax params (``{'params': {...}}`` or the inner dict) -> ``{"self_0/kernel": array, ...}``."""
    tree = params.get("params", params) if hasattr(params, "get") else params
    out: dict[str, np.ndarray] = {}

    def walk(node: Any, path: tuple[str, ...]) -> None:
        if hasattr(node, "items"):
            for key, val in node.items():
                walk(val, path + (str(key),))
        else:
            out["/".join(path)] = np.asarray(node)

    walk(tree, ())
    return out


def unflatten_params(flat: dict[str, Any]) -> dict[str, Any]:
    """Inverse of :func:`flatten_params`: ``{'params': nested dict of jnp arrays}`` (for resuming from a file)."""
    tree: dict[str, Any] = {}
    for name, v in flat.items():
        node = tree
        *parents, leaf = name.split("/")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = jnp.asarray(v, jnp.float32)
    return {"params": tree}


def to_numpy_policy(arch: dict[str, Any], layout: dict[str, Any], params: Any, obs_mean: Any = None,
                    obs_std: Any = None, meta: dict[str, Any] | None = None) -> EncoderPolicy:
    """The NumPy :class:`EncoderPolicy` of trained flax params (obs mean/std: Brax's normalizer, or 0/1)."""
    flat = flatten_params(params)
    shapes = param_shapes(arch, layout)
    if set(flat) != set(shapes):
        raise ValueError(f"flax params {sorted(flat)} do not match the architecture's {sorted(shapes)}")
    d = layout_obs_dim(layout)
    mean = np.zeros(d) if obs_mean is None else np.asarray(obs_mean, np.float64)
    std = np.ones(d) if obs_std is None else np.asarray(obs_std, np.float64)
    # the NumPy policy holds float32-rounded weights, as the file does
    p32 = {n: np.asarray(v, np.float32).astype(np.float64) for n, v in flat.items()}
    return EncoderPolicy(dict(arch), dict(layout), p32, np.asarray(mean, np.float32).astype(np.float64),
                         np.asarray(std, np.float32).astype(np.float64), meta=dict(meta or {}))


def export_policy(path: str | os.PathLike, arch: dict[str, Any], layout: dict[str, Any], params: Any,
                  obs_mean: Any = None, obs_std: Any = None, meta: dict[str, Any] | None = None,
                  extra: dict[str, np.ndarray] | None = None) -> str:
    """Write trained flax params as a NumPy policy file (``quadswarm_mj.policy/2``); returns its SHA-256."""
    return save_encoder_policy(path, to_numpy_policy(arch, layout, params, obs_mean, obs_std, meta), extra=extra)


def make_policy_network(arch: dict[str, Any], layout: dict[str, Any],
                        preprocess_observations_fn: Callable[..., jax.Array] | None = None) -> Any:
    """A Brax ``FeedForwardNetwork`` (init(key), apply(normalizer_params, params, obs)) of the encoder."""
    from brax.training import networks as brax_networks
    from brax.training import types as brax_types

    pre = preprocess_observations_fn or brax_types.identity_observation_preprocessor
    module = EncoderNetwork(arch=dict(arch), layout=dict(layout))
    dummy = jnp.zeros((1, layout_obs_dim(layout)))

    def apply(processor_params: Any, policy_params: Any, obs: jax.Array) -> jax.Array:
        return module.apply(policy_params, pre(obs, processor_params))

    return brax_networks.FeedForwardNetwork(init=lambda key: module.init(key, dummy), apply=apply)


def make_ppo_networks(arch: dict[str, Any], layout: dict[str, Any],
                      preprocess_observations_fn: Callable[..., jax.Array] | None = None,
                      value_hidden_layer_sizes: Sequence[int] = (256, 256), activation: str = "tanh",
                      min_std: float = 0.001) -> Any:
    """Brax ``PPONetworks`` with an encoder policy (tanh-normal, 4 actions, std floor ``min_std``) and an MLP
    value network (Brax's, on :mod:`quadswarm_mj.training.dense` layers: the same parameters)."""
    from brax.training import types as brax_types
    from brax.training.agents.ppo import networks as ppo_networks
    from brax.training.distribution import NormalTanhDistribution

    from quadswarm_mj.training.dense import make_mlp_network

    pre = preprocess_observations_fn or brax_types.identity_observation_preprocessor
    value = make_mlp_network(layout_obs_dim(layout), list(value_hidden_layer_sizes) + [1],
                             ACTIVATION_FNS[activation], pre, squeeze=True)
    dist = NormalTanhDistribution(event_size=4, min_std=min_std)
    return ppo_networks.PPONetworks(policy_network=make_policy_network(arch, layout, pre), value_network=value,
                                    parametric_action_distribution=dist)


def std_bias(std: float, min_std: float = 0.001) -> float:
    """The pre-softplus output that gives Brax's tanh-normal std ``std`` (softplus(b) + ``min_std``)."""
    return float(np.log(np.expm1(max(std - min_std, 1e-4))))


def set_action_std(params: Any, init_std: float, action_dim: int = 4, min_std: float = 0.001) -> Any:
    """Params with the action layer's std biases set so Brax's tanh-normal std starts at ``init_std``
    (softplus^-1(init_std - min_std), as ``ppo.py`` does for its MLP); the means are untouched."""
    flat = flatten_params(params)
    b = np.array(flat["action/bias"], np.float32)
    b[action_dim:] = std_bias(init_std, min_std)
    flat["action/bias"] = b
    return unflatten_params(flat)
