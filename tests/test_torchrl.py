"""TorchRL builds its specs from the env and rolls out with ``info_mode="flat"``: ``GymEnv`` (one env and
``num_envs=2``, gymnasium's vector env underneath) and ``PettingZooWrapper`` of the parallel env.
Skipped without torchrl (the optional extra ``examples``)."""

from __future__ import annotations

import pytest

pytest.importorskip("torchrl")

import quadswarm_mj  # noqa: E402,F401 - registers QuadSwarm-v0
from quadswarm_mj import quadswarm_v0  # noqa: E402

SHORT = {"episode_seconds": 0.05, "info_mode": "flat"}


@pytest.mark.parametrize("num_envs", [0, 2])
def test_gym_env_rolls_out(num_envs):
    from torchrl.envs import GymEnv

    kw = {"num_envs": num_envs} if num_envs else {}
    env = GymEnv("quadswarm_mj:QuadSwarm-v0", num_quads=1, **kw, **SHORT)  # the id also in spawned workers
    try:
        td = env.rollout(8, break_when_any_done=False)
        lead = (num_envs, 8) if num_envs else (8,)
        assert tuple(td.batch_size) == lead
        assert td["next", "observation"].shape[-1] == quadswarm_mj.EnvConfig(num_quads=1).obs_dim
        assert td["next", "truncated"].any()
    finally:
        env.close()


def test_pettingzoo_wrapper_rolls_out():
    from torchrl.envs import PettingZooWrapper

    env = PettingZooWrapper(env=quadswarm_v0.parallel_env(num_quads=2, **SHORT), return_state=True)
    try:
        td = env.rollout(4)
        assert td.batch_size[0] == 4
    finally:
        env.close()


def test_gym_wrapper_of_the_vector_env_rolls_out():
    """``GymWrapper(QuadSwarmVectorEnv(info_mode="flat"))``: TorchRL checks the flat info's entries,
    ``final_obs`` included, against the specs it builds; where no episode ended that row is zeros
    (inside the observation box), with ``_final_obs`` False."""
    import numpy as np
    from torchrl.envs import GymWrapper

    from quadswarm_mj import QuadSwarmVectorEnv

    venv = QuadSwarmVectorEnv(num_envs=2, num_quads=1, **SHORT)
    env = GymWrapper(venv)
    try:
        td = env.rollout(8, break_when_any_done=False)
        assert tuple(td.batch_size) == (2, 8)
        assert td["next", "truncated"].any()
        venv.reset(seed=0)
        for _ in range(8):
            *_, info = venv.step(np.zeros((2, 1, 4), np.float32))
            final, ended = info["final_obs"], info["_final_obs"]
            assert np.isfinite(final).all() and (final[~ended] == 0).all()
    finally:
        env.close()
