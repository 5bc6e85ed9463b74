"""quadswarm_mj.perf.xla_options: the one-world programs compiled with the per-program options give
the same values, bit for bit, as with JAX's default compile options, and applying them changes no
process-wide setting (XLA_FLAGS, JAX config)."""

from __future__ import annotations

import os

import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytest.importorskip("mujoco.mjx")

from quadswarm_mj import EnvConfig  # noqa: E402
from quadswarm_mj.envs.jax_program import KeyStream, Program  # noqa: E402
from quadswarm_mj.perf.xla_options import ONE_WORLD_CPU_OPTIONS, one_world_options  # noqa: E402


def _rollout(prog: Program, steps: int) -> list[np.ndarray]:
    keys = KeyStream(7)
    bufs, out = prog.reset_fn(((), None), masked=False)(keys.draw(), {})
    rng = np.random.default_rng(0)
    outs = [np.asarray(out)]
    for _ in range(steps):
        action = rng.uniform(-1, 1, (prog.cfg.num_quads, 4)).astype(prog.float)
        bufs, out = prog.step(bufs, action)
        outs.append(np.asarray(out))
    outs.extend(np.asarray(b) for b in bufs)  # the final state, packed
    return outs


def test_options_give_the_same_values_bit_for_bit():
    flags, async_dispatch = os.environ.get("XLA_FLAGS"), jax.config.values.get("jax_cpu_enable_async_dispatch")
    cfg = EnvConfig(num_quads=2, episode_seconds=0.3)  # all noise on; 30-step episodes: one ends
    opts = one_world_options()
    if jax.default_backend() == "cpu":
        assert opts == ONE_WORLD_CPU_OPTIONS or opts == {}  # {}: an XLA without the option
    tuned = Program(cfg, None, compiler_options=opts)
    plain = Program(cfg, None, compiler_options={})
    assert tuned.compiler_options == opts and plain.compiler_options == {}
    a, b = _rollout(tuned, 40), _rollout(plain, 40)
    assert len(a) == len(b)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.view(np.uint8), y.view(np.uint8))
    assert os.environ.get("XLA_FLAGS") == flags
    assert jax.config.values.get("jax_cpu_enable_async_dispatch") == async_dispatch
