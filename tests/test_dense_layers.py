"""quadswarm_mj.training.dense: the trainer's Dense layers with a stated VJP are Brax's networks
(same parameters for the same key, same outputs) and give the same gradients as plain autodiff."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.training import types as brax_types
from brax.training.agents.ppo import networks as ppo_networks
from flax import linen

from quadswarm_mj.training.dense import dense_dot_general, make_mlp_ppo_networks


def _nets(make_ours: bool):
    pre = brax_types.identity_observation_preprocessor
    if make_ours:
        return make_mlp_ppo_networks(54, 4, pre, (64, 64), (64, 64), linen.tanh)
    return ppo_networks.make_ppo_networks(54, 4, preprocess_observations_fn=pre, policy_hidden_layer_sizes=(64, 64),
                                          value_hidden_layer_sizes=(64, 64), activation=linen.tanh)


def test_same_parameters_and_outputs_as_brax_networks():
    ours, brax = _nets(True), _nets(False)
    key = jax.random.key(3)
    for name in ("policy_network", "value_network"):
        p_ours, p_brax = getattr(ours, name).init(key), getattr(brax, name).init(key)
        assert jax.tree.structure(p_ours) == jax.tree.structure(p_brax)
        for a, b in zip(jax.tree.leaves(p_ours), jax.tree.leaves(p_brax)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        obs = jax.random.normal(jax.random.key(1), (5, 7, 54))
        np.testing.assert_allclose(np.asarray(getattr(ours, name).apply(None, p_ours, obs)),
                                   np.asarray(getattr(brax, name).apply(None, p_brax, obs)), rtol=1e-6, atol=1e-6)
    assert ours.parametric_action_distribution.param_size == brax.parametric_action_distribution.param_size == 8


@pytest.mark.parametrize("lead", [(), (6,), (4, 5)])
def test_gradients_equal_plain_autodiff(lead):
    kx, kw, kd = jax.random.split(jax.random.key(0), 3)
    x = jax.random.normal(kx, lead + (9,))
    w = jax.random.normal(kw, (9, 7))
    dy = jax.random.normal(kd, lead + (7,))
    dims = (((x.ndim - 1,), (0,)), ((), ()))

    def loss(f):
        return lambda a, b: jnp.sum(f(a, b, dims) * dy)

    want = jax.grad(loss(jax.lax.dot_general), argnums=(0, 1))(x, w)
    got = jax.jit(jax.grad(loss(dense_dot_general), argnums=(0, 1)))(x, w)
    for g, h in zip(got, want):
        assert g.shape == h.shape
        np.testing.assert_allclose(np.asarray(g), np.asarray(h), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.asarray(dense_dot_general(x, w, dims)),
                               np.asarray(jax.lax.dot_general(x, w, dims)), rtol=1e-6, atol=1e-6)


def test_other_contractions_are_refused():
    x, w = jnp.ones((3, 4)), jnp.ones((5, 4))
    with pytest.raises(ValueError, match="contraction"):
        dense_dot_general(x, w, (((1,), (1,)), ((), ())))
