"""The engines' shared state structure (quadswarm_mj.core.swarm.SwarmState): importable without JAX, held by
the MuJoCo engine (CpuSwarm.state, its attribute views) and inside the JAX engine's State.info (State.swarm,
to_info/from_info), with the same fields and per-world shapes in both engines, and docs/api.md's example."""

from __future__ import annotations

import dataclasses
import functools
import re
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.core.swarm import READOUTS, SwarmState, from_info, to_info
from quadswarm_mj.envs.cpu_core import CpuSwarm
from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv
from quadswarm_mj.obstacle_config import ObstacleConfig

FIELDS = [f.name for f in dataclasses.fields(SwarmState)]
CASES = {"default": EnvConfig(num_quads=3), "velocity_mode": EnvConfig(num_quads=3, control_mode="velocity"),
         "obstacles": EnvConfig(num_quads=3, obstacles=ObstacleConfig())}


@functools.cache
def _jax_stepped(case: str):
    """The JAX engine's State of ``case`` after reset and one step (jitted; computed once per case)."""
    cfg = CASES[case]
    env = MjxQuadSwarmEnv(cfg)
    return jax.jit(env.step)(jax.jit(env.reset)(jax.random.key(1)), jnp.zeros((cfg.num_quads, 4)))


def test_importing_the_structure_imports_no_jax():
    code = "import sys, quadswarm_mj.core.swarm, quadswarm_mj.envs.cpu_core; assert 'jax' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_replace_makes_a_new_instance_and_rejects_unknown_fields():
    s = CpuSwarm(EnvConfig(num_quads=2), visual=False).state
    t = s.replace(step=s.step + 1)
    assert t is not s and t.motor_u is s.motor_u and int(t.step[0]) == 1 and int(s.step[0]) == 0
    with pytest.raises(TypeError, match="no field"):
        s.replace(steps=1)
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.step = 1  # type: ignore[misc]


@pytest.mark.parametrize("case", sorted(CASES))
def test_cpu_engine_holds_one_state_replaced_per_step(case: str):
    cfg, B = CASES[case], 2
    core = CpuSwarm(cfg, B, visual=False)
    core.seed(0)
    core.reset()
    s0 = core.state
    assert isinstance(s0, SwarmState) and s0.step.shape == (B,) and s0.motor_u.shape == (B, cfg.num_quads, 4)
    core.step(np.zeros((B, cfg.num_quads, 4)))
    s1 = core.state
    assert s1 is not s0 and s1.step.tolist() == [1, 1] and s0.step.tolist() == [0, 0]
    # the attribute views read the fields in force
    for attr, field in (("u", "motor_u"), ("f_norm", "thrust"), ("on_floor", "on_floor"), ("steps", "step"),
                        ("sstate", "scenario"), ("metrics", "metrics_acc"), ("omap", "obstacles"),
                        ("obst_contact", "obstacle_contact"), ("ctrl_state", "ctrl_state")):
        assert getattr(core, attr) is getattr(s1, field), attr
    assert core.params["gravity"] == cfg.quad.gravity and set(core.params) - {"gravity"} == set(s1.params)
    # a partial reset replaces the rows of the reset worlds only
    core.reset(np.array([False, True]))
    s2 = core.state
    assert s2.step.tolist() == [1, 0] and s2.total_steps == s1.total_steps == 1
    np.testing.assert_array_equal(s2.motor_eps[0], s1.motor_eps[0])
    np.testing.assert_array_equal(s2.scenario.goals[0], s1.scenario.goals[0])


@pytest.mark.parametrize("case", sorted(CASES))
def test_both_engines_hold_the_same_fields_and_shapes(case: str):
    """The MuJoCo engine's (B, N, ...) state and the JAX engine's per-world (N, ...) state have the same
    fields with the same per-world shapes and dtype kinds (the engine-only fields aside)."""
    cfg = CASES[case]
    core = CpuSwarm(cfg, 2, visual=False)
    core.seed(0)
    core.reset()
    core.step(np.zeros((2, cfg.num_quads, 4)))
    swarm = _jax_stepped(case).swarm
    only_cpu, only_jax = {"rotor_cmd", "total_steps"}, {"rng", "step_numbers", "total_steps"}
    for name in FIELDS:
        c, j = getattr(core.state, name), getattr(swarm, name)
        if name in only_cpu | only_jax:
            continue
        assert (c is None) == (j is None), name
        cl, jl = jax.tree_util.tree_leaves_with_path(c), jax.tree_util.tree_leaves_with_path(j)
        assert [p for p, _ in cl] == [p for p, _ in jl], name
        for (path, a), (_, b) in zip(cl, jl):
            assert np.shape(a)[1:] == np.shape(b), (name, path)
            assert np.asarray(a).dtype.kind == np.asarray(b).dtype.kind, (name, path)


@pytest.mark.parametrize("case", sorted(CASES))
def test_jax_info_is_the_state_plus_readouts(case: str):
    info = _jax_stepped(case).info
    readouts = {k: info[k] for k in READOUTS} | {k: v for k, v in info.items() if k in ("multiranger", "flow")}
    readouts["state"] = {k: info["state"][k] for k in ("pos", "vel", "omega")}
    again = to_info(from_info(info), readouts)
    assert jax.tree.structure(again) == jax.tree.structure(info)
    for a, b in zip(jax.tree.leaves(again), jax.tree.leaves(info)):
        assert a is b
    # a pytree: a batch of worlds has a leading worlds axis on every leaf, which vmap maps over
    one = from_info(info)
    batch = jax.tree.map(lambda *a: jnp.stack(a), one, one, one)
    assert isinstance(batch, SwarmState) and all(np.shape(x)[0] == 3 for x in jax.tree.leaves(batch))
    sums = jax.vmap(lambda s: s.motor_u.sum() + s.step)(batch)
    np.testing.assert_array_equal(sums, np.full(3, float(one.motor_u.sum() + one.step), np.float32))


@pytest.mark.slow
def test_docs_example_runs():
    text = (Path(__file__).parent.parent / "docs" / "api.md").read_text(encoding="utf-8")
    code = re.findall(r"```python\n(.*?)```", text.split("## The state structure", 1)[1], flags=re.S)[0]
    out = subprocess.run([sys.executable, "-c", code], check=True, timeout=300, capture_output=True, text=True)
    assert out.stdout.splitlines() == ["(2, 4, 4) [1 1]", "(2, 4, 4) [0 0]", "(2, 4, 4)"]
