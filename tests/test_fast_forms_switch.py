"""The public switch of the MuJoCo engine's fused NumPy forms: off and on give the same bits, the flag is restored."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import quadswarm_mj  # noqa: F401  (registers QuadSwarm-v0)
from quadswarm_mj import perf


def _episode(num_quads: int, steps: int = 120) -> list[np.ndarray]:
    env = gym.make("QuadSwarm-v0", num_quads=num_quads)
    obs, _ = env.reset(seed=3)
    env.action_space.seed(3)
    out = [obs]
    for _ in range(steps):
        obs, reward, terminated, truncated, _ = env.step(env.action_space.sample())
        out += [obs, np.asarray(reward)]
        if terminated or truncated:
            obs, _ = env.reset()
            out.append(obs)
    env.close()
    return out


@pytest.mark.parametrize("num_quads", [1, 8])
def test_switch_off_gives_the_same_bits(num_quads: int) -> None:
    assert perf.numpy_fast_forms_enabled()
    fast = _episode(num_quads)
    with perf.numpy_fast_forms(False):
        assert not perf.numpy_fast_forms_enabled()
        plain = _episode(num_quads)
    assert perf.numpy_fast_forms_enabled()
    assert len(fast) == len(plain)
    for a, b in zip(fast, plain):
        assert a.tobytes() == b.tobytes()


def test_switch_is_restored_after_an_error_and_checks_its_argument() -> None:
    env = gym.make("QuadSwarm-v0", num_quads=8)
    env.reset(seed=0)
    ops = env.unwrapped.core._ops  # the CPU engine's ops hand out the fused forms or None
    assert ops.fused_loop is not None and ops.fused_task is not None
    with perf.numpy_fast_forms(False):
        assert ops.fused_loop is None and ops.fused_task is None and ops.fused_stages is None
    env.close()
    with pytest.raises(RuntimeError), perf.numpy_fast_forms(False):
        raise RuntimeError("inside")
    assert perf.numpy_fast_forms_enabled()
    with pytest.raises(TypeError, match="enabled must be a bool"):
        perf.set_numpy_fast_forms("no")  # type: ignore[arg-type]
    perf.set_numpy_fast_forms(False)
    try:
        assert not perf.numpy_fast_forms_enabled()
    finally:
        perf.set_numpy_fast_forms(True)
