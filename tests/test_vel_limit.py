"""``RewardScales.vel_limit``: the ``vel`` cost is the speed above the limit (m/s), on both engines."""

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, QuadSwarmEnv
from quadswarm_mj.config import RewardScales
from quadswarm_mj.rewards import reward_terms


def _terms(cfg, vel, xp=np):
    n = vel.shape[-2]
    z3 = xp.zeros(vel.shape)
    eye = xp.broadcast_to(xp.eye(3), vel.shape[:-1] + (3, 3))
    zf = xp.zeros(vel.shape[:-1], dtype=bool)
    z4 = xp.zeros(vel.shape[:-1] + (4,))
    return reward_terms(cfg, z3, vel, eye, z3, z3 + 1.0, z4, z4, z4, zf, zf, zf, zf,
                        xp.zeros(vel.shape[:-1] + (n,), dtype=bool),
                        xp.ones(vel.shape[:-1] + (n,)) * 10.0)


def test_vel_cost_is_the_speed_above_the_limit():
    cfg = EnvConfig(num_quads=3, rewards=RewardScales(vel=2.0, vel_limit=1.5))
    vel = np.array([[[1.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 0.0, -2.5]]])
    got = _terms(cfg, vel)["vel"]
    np.testing.assert_allclose(got, -cfg.sim_dt * 2.0 * np.array([[0.0, 1.5, 1.0]]), rtol=0, atol=1e-15)
    plain = _terms(EnvConfig(num_quads=3, rewards=RewardScales(vel=2.0)), vel)["vel"]  # limit 0: ||v||
    np.testing.assert_allclose(plain, -cfg.sim_dt * 2.0 * np.array([[1.0, 3.0, 2.5]]), rtol=0, atol=1e-15)


def test_vel_limit_numpy_equals_jit():
    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    cfg = EnvConfig(num_quads=4, rewards=RewardScales(vel=3.0, vel_limit=1.0))
    vel = np.random.default_rng(0).normal(scale=1.5, size=(2, 4, 3)).astype(np.float32)
    ref = _terms(cfg, vel.astype(np.float64))["vel"]
    got = jax.jit(lambda v: _terms(cfg, v, jnp)["vel"])(jnp.asarray(vel))
    np.testing.assert_allclose(np.asarray(got), ref, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("num_quads", [1, 3])
def test_env_reports_the_hinged_vel_term(num_quads):
    """The CPU env's ``info["reward_terms"]["vel"]`` follows the state's speed (one quad and a swarm:
    the engine's whole-stage fast forms step aside for the limit)."""
    cfg = EnvConfig(num_quads=num_quads, rewards=RewardScales(vel=2.0, vel_limit=0.3))
    env = QuadSwarmEnv(cfg)
    env.reset(seed=3)
    env.action_space.seed(3)
    above = 0
    for _ in range(60):
        _, _, term, trunc, info = env.step(env.action_space.sample())
        speed = np.linalg.norm(np.asarray(info["state"]["vel"]).reshape(num_quads, 3), axis=-1)
        want = -cfg.sim_dt * 2.0 * np.maximum(speed - 0.3, 0.0)
        np.testing.assert_allclose(np.asarray(info["reward_terms"]["vel"]).reshape(num_quads), want, rtol=1e-12,
                                   atol=1e-15)
        above += int((speed > 0.3).sum())
        assert not (term or trunc)
    assert above > 0  # the hinge was exercised on both sides


@pytest.mark.parametrize("bad", [-0.1, 25.0, float("nan")])
def test_vel_limit_out_of_range_names_the_field(bad):
    with pytest.raises(ValueError, match="rewards.vel_limit"):
        RewardScales(vel_limit=bad)
