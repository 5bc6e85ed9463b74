"""The once-per-control-step stages written once (quadswarm_mj.core.step.velocity_stages): the CPU
engine's ops (event gating, NumPy draws) and the JAX engine's ops (always-on, budgeted slots) on
identical float64 inputs give the same state, with walls, the ceiling, quad-quad contacts and
downwash all happening; noise off (every draw its mean), within the budgets."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.core.ops import NumpyOps
from quadswarm_mj.core.step import velocity_stages
from quadswarm_mj.envs.cpu_core import CpuSwarm
from quadswarm_mj.spatial import quat_to_rotmat


def _inputs(cfg: EnvConfig) -> tuple[dict, dict]:
    rng = np.random.default_rng(0)
    hi = np.asarray(cfg.room_high)
    pos = np.array([[hi[0] + 0.02, 0.0, 2.0],  # beyond a wall
                    [0.0, 0.0, hi[2] + 0.01],  # above the ceiling
                    [1.0, 1.0, 2.0], [1.05, 1.0, 2.0],  # a pair in contact
                    [-2.0, -2.0, 2.0], [-2.0, -2.0, 2.4]])  # one above the other: downwash
    n = pos.shape[0]
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q[4:] = [1.0, 0.0, 0.0, 0.0]  # level: the lower quad is in the upper one's downwash
    kin = {"pos": pos[None], "vel": rng.normal(size=(1, n, 3)), "omega": rng.normal(size=(1, n, 3)),
           "R": quat_to_rotmat(q)[None], "quat": q[None], "u": rng.uniform(size=(1, n, 4)),
           "hit_floor": np.zeros((1, n), bool), "on_floor": np.zeros((1, n), bool)}
    prev = {"on_floor": np.zeros((1, n), bool), "at_wall": np.zeros((1, n), bool),
            "at_ceiling": np.zeros((1, n), bool), "contact": np.zeros((1, n, n), bool)}
    return kin, prev


def _compare(model: str) -> None:
    """Run in a fresh process with ``jax_enable_x64`` (float64 on both sides)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from quadswarm_mj.core.ops import JaxOps
    from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv
    from quadswarm_mj.random_draws import MeanSampler

    cfg = EnvConfig(num_quads=6, downwash=True, collision_model=model).without_noise()
    swarm = CpuSwarm(cfg, 1)
    swarm.reset()
    kin, prev = _inputs(cfg)
    ref = velocity_stages(cfg, kin, prev, NumpyOps(swarm))
    assert ref["hit_wall"].any() and ref["new_contact"].any() and ref["changed"]
    assert ref["hit_ceiling"].any() or model != "paper"
    env = MjxQuadSwarmEnv(cfg, physics="freebody" if model == "paper" else "mjx")
    rnd = MeanSampler(dtype=jnp.float64, xp=jnp).draw(env._step_mean_spec)

    def stages(k: dict, p: dict) -> dict:
        out = velocity_stages(cfg, k, p, JaxOps(cfg, rnd, jnp.float64))
        return {key: v for key, v in out.items() if key != "changed"}

    got = jax.jit(stages)({k: jnp.asarray(v[0]) for k, v in kin.items()},
                          {k: jnp.asarray(v[0]) for k, v in prev.items()})
    for key in ("pos", "vel", "omega", "R", "quat", "u", "dist"):
        assert got[key].dtype == jnp.float64, key
        np.testing.assert_allclose(np.asarray(got[key]), ref[key][0], rtol=0, atol=1e-12, err_msg=key)
    for key in ("at_wall", "at_ceiling", "hit_wall", "hit_ceiling", "contact", "new_contact"):
        np.testing.assert_array_equal(np.asarray(got[key]), ref[key][0], err_msg=key)
    assert not np.allclose(ref["vel"], kin["vel"])  # the stages acted


@pytest.mark.parametrize("model", ["paper", "blend"])
def test_velocity_stages_numpy_ops_equal_jax_ops_in_float64(model):
    pytest.importorskip("jax")
    here = str(Path(__file__).parent)
    code = f"import sys; sys.path.insert(0, {here!r}); import test_core_step as t; t._compare({model!r})"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600,
                       cwd=Path(__file__).parent.parent)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]


def test_jax_random_draws_are_the_default_and_fused_the_opt_in():
    """``draws="jax"`` (the default: the next step's numbers from ``jax.random``, carried in the state) and
    ``draws="fused"`` (opt-in, perf.fused_draws, carried the same way) both run the step, with the same draws'
    layout; a bad value is a clear error."""
    jax = pytest.importorskip("jax")
    from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv

    with pytest.raises(ValueError, match="draws must be one of"):
        MjxQuadSwarmEnv(EnvConfig(num_quads=2), draws="numpy")
    cfg = EnvConfig(num_quads=2, downwash=True)
    assert MjxQuadSwarmEnv(cfg).draws == "jax"
    data = jax.random.key_data
    out = {}
    for draws in ("jax", "fused"):
        env = MjxQuadSwarmEnv(cfg, draws=draws)
        assert env._carry_numbers
        s = jax.jit(env.reset)(jax.random.key(3))
        s2 = jax.jit(env.step)(s, jax.numpy.full((2, 4), cfg.quad.hover_action))
        assert np.all(np.isfinite(np.asarray(s2.obs))) and int(s2.info["step"]) == 1
        assert not np.array_equal(np.asarray(data(s2.info["rng"])), np.asarray(data(s.info["rng"])))
        out[draws] = np.asarray(s2.info["step_numbers"])
    assert out["jax"].shape == out["fused"].shape and not np.array_equal(out["jax"], out["fused"])
