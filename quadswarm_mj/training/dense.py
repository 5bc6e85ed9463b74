"""Dense layers whose weight gradient XLA:CPU computes with a fast matrix product, and the trainer's
MLP policy and value networks built from them.

``jax.grad`` of ``x @ W`` gives the weight gradient as ``x^T dy`` through the transpose rule of
``dot_general``; in the PPO update XLA:CPU then materialized ``dy^T`` and ran the product with both
operands transposed, ~3x slower than a plain product (measured: 1024 x 64 by 1024 x 64, one core,
321 us against 131 us; the four such products were ~40 % of the update). :func:`dense_dot_general`
is ``lax.dot_general`` for a Dense layer with a custom VJP that states the gradients directly
(``dx = dy W^T``, ``dW = x^T dy`` over the flattened leading axes), which XLA compiles to the
plain forms. Same values (the same sums; in the trainer's update the parameters came out bit for
bit equal).

:func:`make_mlp_ppo_networks` is Brax's ``make_ppo_networks`` (tanh-normal policy, MLP value) with
these layers: the same parameter tree (``params/hidden_i/kernel|bias``), the same initializers, so
the same parameters for the same key, and the same ``apply`` signatures.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
from flax import linen
from jax import lax


@jax.custom_vjp
def _dense_dot(x: jax.Array, kernel: jax.Array) -> jax.Array:
    return lax.dot_general(x, kernel, (((x.ndim - 1,), (0,)), ((), ())))


def _dense_dot_fwd(x: jax.Array, kernel: jax.Array) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
    return _dense_dot(x, kernel), (x, kernel)


def _dense_dot_bwd(res: tuple[jax.Array, jax.Array], dy: jax.Array) -> tuple[jax.Array, jax.Array]:
    x, kernel = res
    x2, dy2 = x.reshape(-1, x.shape[-1]), dy.reshape(-1, dy.shape[-1])
    dx = lax.dot_general(dy2, kernel, (((1,), (1,)), ((), ()))).reshape(x.shape)  # dy W^T
    dk = lax.dot_general(x2.T, dy2, (((1,), (0,)), ((), ())))  # x^T dy, summed over all leading axes
    return dx, dk.astype(kernel.dtype)


_dense_dot.defvjp(_dense_dot_fwd, _dense_dot_bwd)


def dense_dot_general(x: jax.Array, kernel: jax.Array, dimension_numbers: Any, precision: Any = None,
                      preferred_element_type: Any = None) -> jax.Array:
    """``lax.dot_general`` for ``flax.linen.Dense`` (x (..., I) contracted with kernel (I, O)), with
    the custom VJP above. Other dimension numbers are refused."""
    want = (((x.ndim - 1,), (0,)), ((), ()))
    got = tuple(tuple(tuple(int(a) for a in d) for d in pair) for pair in dimension_numbers)
    if got != want or kernel.ndim != 2:
        raise ValueError(f"dense_dot_general handles Dense's contraction {want} only, got {dimension_numbers}")
    return _dense_dot(x, kernel)


class MLP(linen.Module):
    """Brax's ``networks.MLP`` (layers ``hidden_0`` ... ``hidden_{n-1}``, activation between them, not
    after the last) with :func:`dense_dot_general` in its Dense layers."""

    layer_sizes: Sequence[int]
    activation: Callable[[jax.Array], jax.Array] = linen.relu
    kernel_init: Any = jax.nn.initializers.lecun_uniform()

    @linen.compact
    def __call__(self, data: jax.Array) -> jax.Array:
        hidden = data
        for i, size in enumerate(self.layer_sizes):
            hidden = linen.Dense(size, name=f"hidden_{i}", kernel_init=self.kernel_init,
                                 dot_general=dense_dot_general)(hidden)
            if i != len(self.layer_sizes) - 1:
                hidden = self.activation(hidden)
        return hidden


def make_mlp_network(obs_size: int, layer_sizes: Sequence[int], activation: Callable[[jax.Array], jax.Array],
                     preprocess_observations_fn: Callable[..., jax.Array], squeeze: bool = False) -> Any:
    """A Brax ``FeedForwardNetwork``: ``init(key)`` and ``apply(normalizer_params, params, obs)`` of an
    :class:`MLP` on preprocessed observations (``squeeze``: drop the last axis, as Brax's value net)."""
    from brax.training import networks as brax_networks

    module = MLP(layer_sizes=list(layer_sizes), activation=activation)
    dummy = jnp.zeros((1, obs_size))

    def apply(processor_params: Any, params: Any, obs: jax.Array) -> jax.Array:
        out = module.apply(params, preprocess_observations_fn(obs, processor_params))
        return jnp.squeeze(out, axis=-1) if squeeze else out

    return brax_networks.FeedForwardNetwork(init=lambda key: module.init(key, dummy), apply=apply)


def make_mlp_ppo_networks(obs_size: int, action_size: int, preprocess_observations_fn: Callable[..., jax.Array],
                          policy_hidden_layer_sizes: Sequence[int], value_hidden_layer_sizes: Sequence[int],
                          activation: Callable[[jax.Array], jax.Array], min_std: float = 0.001) -> Any:
    """Brax ``PPONetworks`` as ``brax...ppo.networks.make_ppo_networks`` makes them for a tanh-normal
    policy (same parameters for the same key), on :class:`MLP` layers; ``min_std``: the std's floor."""
    from brax.training.agents.ppo import networks as ppo_networks
    from brax.training.distribution import NormalTanhDistribution

    dist = NormalTanhDistribution(event_size=action_size, min_std=min_std)
    policy = make_mlp_network(obs_size, list(policy_hidden_layer_sizes) + [dist.param_size], activation,
                              preprocess_observations_fn)
    value = make_mlp_network(obs_size, list(value_hidden_layer_sizes) + [1], activation, preprocess_observations_fn,
                             squeeze=True)
    return ppo_networks.PPONetworks(policy_network=policy, value_network=value, parametric_action_distribution=dist)
