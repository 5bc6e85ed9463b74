"""PettingZoo ParallelEnv conformance."""

from __future__ import annotations

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

from quadswarm_mj import EnvConfig, QuadSwarmParallelEnv


@pytest.mark.parametrize("n", [1, 4])
def test_parallel_api(n):
    parallel_api_test(QuadSwarmParallelEnv(EnvConfig(num_quads=n)), num_cycles=200)


def test_parallel_seed():
    cfg = EnvConfig(num_quads=3, scenario="static_diff_goal")
    parallel_seed_test(lambda: QuadSwarmParallelEnv(cfg), num_cycles=100)


def test_agents_rewards_state():
    env = QuadSwarmParallelEnv(EnvConfig(num_quads=3))
    obs, infos = env.reset(seed=0)
    assert env.agents == ["quad_0", "quad_1", "quad_2"]
    assert obs["quad_1"].shape == (18 + 12,)
    s = env.state()
    assert s.shape == (63,) and env.state_space.contains(s)
    obs, rew, term, trunc, infos = env.step({a: np.zeros(4, np.float32) for a in env.agents})
    assert set(rew) == set(env.possible_agents) and all(isinstance(r, float) for r in rew.values())
    terms = infos["quad_0"]["reward_terms"]
    assert sum(terms.values()) == pytest.approx(rew["quad_0"])
    with pytest.raises(ValueError, match="missing"):
        env.step({"quad_0": np.zeros(4)})


def test_registered_with_pettingzoo():
    import pettingzoo

    if not hasattr(pettingzoo, "make"):
        pytest.skip("this PettingZoo has no registry")
    env = pettingzoo.make("parallel", "quadswarm_v0", num_quads=2)
    assert isinstance(env, QuadSwarmParallelEnv) and env.possible_agents == ["quad_0", "quad_1"]
