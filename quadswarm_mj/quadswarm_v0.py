"""PettingZoo-style module: ``from quadswarm_mj import quadswarm_v0; env = quadswarm_v0.parallel_env()``."""

from quadswarm_mj.envs.parallel_env import QuadSwarmParallelEnv, parallel_env

__all__ = ["QuadSwarmParallelEnv", "parallel_env"]
