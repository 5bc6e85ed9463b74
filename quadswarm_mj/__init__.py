"""quadswarm_mj: Crazyflie 2.x swarms for deep RL on MuJoCo (CPU) and MJX (JAX).

Public API: ``EnvConfig``, ``QuadSwarmEnv``, ``list_scenarios``; ``import quadswarm_mj``
registers the Gymnasium id ``QuadSwarm-v0``. JAX is not imported here.
"""

import os

# MuJoCo fixes its GL backend when first imported; unset means GLFW, which needs a display.
os.environ.setdefault("MUJOCO_GL", "egl")
if os.environ.get("MUJOCO_GL") in ("egl", "osmesa"):
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

from quadswarm_mj import _quiet_imports  # noqa: E402
from quadswarm_mj.devices import tune_jax_cpu  # noqa: E402

tune_jax_cpu()  # XLA:CPU options for the JAX engine's small programs, if JAX has not started (devices.py)

_quiet_imports.install()  # mujoco.mjx prints "Failed to import warp" twice without NVIDIA Warp

from quadswarm_mj.config import (  # noqa: E402
    CollisionParams,
    EnvConfig,
    NoiseConfig,
    ObstacleConfig,
    QuadParams,
    RandomizationConfig,
    RewardScales,
)
from quadswarm_mj.devices import use_cpu_cores  # noqa: E402
from quadswarm_mj.envs.gym_env import QuadSwarmEnv  # noqa: E402
from quadswarm_mj.envs.parallel_env import QuadSwarmParallelEnv  # noqa: E402
from quadswarm_mj.envs.vector_env import QuadSwarmVectorEnv  # noqa: E402
from quadswarm_mj.scenarios import get_scenario, list_scenarios  # noqa: E402

__all__ = [
    "CollisionParams",
    "EnvConfig",
    "NoiseConfig",
    "ObstacleConfig",
    "QuadParams",
    "QuadSwarmEnv",
    "QuadSwarmParallelEnv",
    "QuadSwarmVectorEnv",
    "RandomizationConfig",
    "RewardScales",
    "get_scenario",
    "list_scenarios",
    "use_cpu_cores",
]
__version__ = "0.1.0"


def _register() -> None:
    import gymnasium

    if "QuadSwarm-v0" not in gymnasium.registry:
        gymnasium.register(id="QuadSwarm-v0", entry_point="quadswarm_mj.envs.gym_env:QuadSwarmEnv",
                           disable_env_checker=False)
    try:  # PettingZoo >= 1.26 has a registry
        import pettingzoo

        if hasattr(pettingzoo, "register") and "quadswarm_v0" not in getattr(pettingzoo, "parallel_registry", {}):
            pettingzoo.register("parallel", "quadswarm_v0", "quadswarm_mj.envs.parallel_env:QuadSwarmParallelEnv")
    except Exception:  # noqa: BLE001 - registration is a convenience, never fatal
        pass


_register()
