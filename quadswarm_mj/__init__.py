"""quadswarm_mj: Crazyflie 2.x swarms for deep RL on MuJoCo (CPU) and MJX (JAX).

Public API: ``EnvConfig``, ``QuadSwarmEnv``, ``list_scenarios``; ``import quadswarm_mj``
registers the Gymnasium id ``QuadSwarm-v0``. JAX is not imported here.

Importing or using the package changes no environment variable, JAX config value or allocator
setting of your process. The XLA:CPU tuning that speeds up the JAX engine's small programs is an
explicit opt-in: :func:`tune_jax_cpu` (call it before JAX starts; the console commands do).
Headless rendering picks MuJoCo's EGL context when the package first renders (``quadswarm_mj.render``).
"""

from quadswarm_mj import _quiet_imports

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
from quadswarm_mj.devices import tune_jax_cpu, use_cpu_cores  # noqa: E402
from quadswarm_mj.envs.gym_env import QuadSwarmEnv  # noqa: E402
from quadswarm_mj.envs.parallel_env import QuadSwarmParallelEnv  # noqa: E402
from quadswarm_mj.envs.vector_env import QuadSwarmVectorEnv  # noqa: E402
from quadswarm_mj.scenarios import get_scenario, list_scenarios  # noqa: E402
from quadswarm_mj.sensor_config import SensorConfig  # noqa: E402

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
    "SensorConfig",
    "get_scenario",
    "list_scenarios",
    "tune_jax_cpu",
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
