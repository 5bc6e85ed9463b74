"""The JAX engine behind the NumPy front ends (``engine="jax"`` of ``QuadSwarmEnv``,
``QuadSwarmParallelEnv`` and ``QuadSwarmVectorEnv``): the modules it is made of, re-exported here.

* :mod:`~quadswarm_mj.envs.jax_program`: the compiled reset/step/renewal of one world or B worlds of
  :class:`~quadswarm_mj.envs.mjx_env.MjxQuadSwarmEnv` (cached per (config, number of worlds), so
  envs of the same config share compiles), the host-side key stream;
* :mod:`~quadswarm_mj.envs.jax_single`: :class:`JaxSingleBackend`, one world;
* :mod:`~quadswarm_mj.envs.jax_vector`: :class:`JaxVectorBackend`, B worlds, run in this process
  (:mod:`~quadswarm_mj.envs.jax_worlds`, sharded over every device whose count divides B) or in
  worker processes, one single-device program per CPU core (:mod:`~quadswarm_mj.envs.jax_workers`);
* :mod:`quadswarm_mj.perf.packing`: the state and outputs packed at the host boundary.

Sharding (bit-identical to one device when each device's worlds x quads are a multiple of 16) and
seeding (``reset(seed=s)`` through ``np.random.SeedSequence(s)``; later unseeded resets continue the
stream): docs/engines.md.
"""

from __future__ import annotations

from quadswarm_mj.envs.jax_program import STATE_KEYS, KeyStream, Program, host_rows, init_arrays, init_variant, program
from quadswarm_mj.envs.jax_single import JaxSingleBackend
from quadswarm_mj.envs.jax_vector import VECTOR_INFO_KEYS, JaxVectorBackend
from quadswarm_mj.envs.jax_workers import (
    MAX_OUTPUT_BLOCKS,
    MIN_WORLDS_PER_WORKER,
    WorkerShard,
    WorkerWorlds,
    jax_shard,
    worker_environ,
)
from quadswarm_mj.envs.jax_worlds import RENEWED, LocalWorlds
from quadswarm_mj.perf.packing import LeafPacker, OutputLayout, StatePacker

# the names these had when they lived here
_Program, _program, _init_variant, _init_arrays, _host_rows = Program, program, init_variant, init_arrays, host_rows

__all__ = ["MAX_OUTPUT_BLOCKS", "MIN_WORLDS_PER_WORKER", "RENEWED", "STATE_KEYS", "VECTOR_INFO_KEYS",
           "JaxSingleBackend", "JaxVectorBackend", "KeyStream", "LeafPacker", "LocalWorlds", "OutputLayout",
           "Program", "StatePacker", "WorkerShard", "WorkerWorlds", "jax_shard", "program", "worker_environ"]
