"""quadswarm_mj: Crazyflie 2.x swarms for deep RL on MuJoCo (CPU) and MJX (JAX).

Public API: ``EnvConfig``, ``QuadSwarmEnv``, ``list_scenarios``; ``import quadswarm_mj``
registers the Gymnasium id ``QuadSwarm-v0``. JAX is not imported here.
"""

import os

# MuJoCo fixes its GL backend when first imported; unset means GLFW, which needs a display.
os.environ.setdefault("MUJOCO_GL", "egl")
if os.environ.get("MUJOCO_GL") in ("egl", "osmesa"):
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

from quadswarm_mj.config import (  # noqa: E402
    CollisionParams,
    EnvConfig,
    NoiseConfig,
    QuadParams,
    RandomizationConfig,
    RewardScales,
)
from quadswarm_mj.envs.gym_env import QuadSwarmEnv  # noqa: E402
from quadswarm_mj.scenarios import get_scenario, list_scenarios  # noqa: E402

__all__ = [
    "CollisionParams",
    "EnvConfig",
    "NoiseConfig",
    "QuadParams",
    "QuadSwarmEnv",
    "RandomizationConfig",
    "RewardScales",
    "get_scenario",
    "list_scenarios",
]
__version__ = "0.1.0"


def _register() -> None:
    import gymnasium

    if "QuadSwarm-v0" not in gymnasium.registry:
        gymnasium.register(id="QuadSwarm-v0", entry_point="quadswarm_mj.envs.gym_env:QuadSwarmEnv",
                           disable_env_checker=False)


_register()
