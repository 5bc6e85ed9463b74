"""The JAX engine's state: :class:`State`, one world's pytree (``jax.vmap`` adds a leading worlds
axis to every leaf). Its ``info`` is the flat dict of the engines' shared
:class:`~quadswarm_mj.core.swarm.SwarmState` plus read-outs (``State.swarm`` reads it back). Also
importable as ``quadswarm_mj.envs.mjx_env.State``."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
from mujoco import mjx

from quadswarm_mj.core.swarm import SwarmState, from_info, register_pytree

register_pytree()


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class State:
    """Environment state of one world of :class:`~quadswarm_mj.envs.mjx_env.MjxQuadSwarmEnv` (a pytree).

    ``State`` fields (one world; a vmapped state has a leading worlds axis on every leaf):

    * ``data``: ``mjx.Data``. Quad ``i``'s free joint is ``qpos[7 i: 7 i + 7]`` (position m, world;
      quaternion w, x, y, z body->world) and ``qvel[6 i: 6 i + 6]`` (linear m/s world, angular rad/s
      body). Derived fields (``xpos``...) are those of the last physics sub-step; after ``reset`` and
      the once-per-control-step velocity models they lag ``qpos``/``qvel`` until the next ``mjx.step``
      (with ``physics="freebody"`` they keep the values of the initial data: call ``mjx.forward`` or
      ``mj_forward`` after ``mjx.get_data`` to render). ``info["state"]["rot"]`` must match the
      quaternion in ``qpos``: ``step`` uses it as the first sub-step's rotation (code that edits
      ``qpos`` writes ``rot`` too).
    * ``obs`` (N, obs_dim), ``reward`` (N,) per quad, ``done`` () bool (time limit; there is no
      termination), ``metrics`` {"reward/<term>": (N,)} for every term of
      :func:`quadswarm_mj.rewards.env_terms` (``TERMS``, plus ``obstacle_collision`` with obstacles on;
      they sum to ``reward``).
    * ``info``: ``state`` {pos (N, 3) m world, vel (N, 3) m/s world, rot (N, 3, 3) body->world,
      omega (N, 3) rad/s body, thrust (N, 4) normalized rotor thrusts} as the CPU env's
      ``info["state"]``; ``params`` (per-quad dynamics parameters, see
      :mod:`quadswarm_mj.randomization`; gravity excluded); ``goals``, ``goal_vel`` (N, 3); ``motor_u``
      (N, 4) normalized rotor speed; ``motor_eps`` (N, 4) OU motor noise; ``on_floor``, ``at_wall``,
      ``at_ceiling`` (N,) bool; ``contact`` (N, N) bool (pairs inside the hitbox at the last control
      step; none after reset: a pair overlapping at the start is a new contact at the first step);
      ``scenario`` (:class:`~quadswarm_mj.scenarios.ScenarioState`); ``metrics_acc`` (accumulators of
      :mod:`quadswarm_mj.metrics`); ``episode_metrics`` (episode metrics so far, per world);
      ``step`` () int control steps in this episode; ``time`` () s;
      ``total_steps`` () int across episodes (reward annealing; kept by :class:`AutoResetWrapper`);
      ``truncation`` () float (1.0 at the time limit); ``rng`` (the key for the next step's draws).
      With obstacles (``cfg.obstacles``): ``obstacles`` (M_max, 2) column centres (x, y m; fixed
      slots), ``obstacles_valid`` (M_max,) bool (the columns in force), ``obstacle_radius`` () m,
      ``obstacle_contact`` (N,) bool (quads touching a column), ``obstacle_metrics`` (accumulators of
      :func:`quadswarm_mj.obstacles.metrics_update`); ``episode_metrics`` then adds
      ``obstacle_collisions`` and ``collision_rate``. The map is drawn at every reset (or given as
      ``init_state["obstacles"]``) and the column geoms are moved there through ``data.mocap_pos``
      (MuJoCo contacts with ``physics="mjx"`` and "mujoco"/"blend"; under size randomization the
      contact geoms get each world's drawn radius through the model, ``geom_size``). The obstacle
      response draws for at most ``obstacles.OBSTACLE_BUDGET`` new column contacts per step.
    """

    data: mjx.Data
    obs: jax.Array
    reward: jax.Array
    done: jax.Array
    metrics: dict[str, jax.Array]
    info: dict[str, Any]

    def replace(self, **changes: Any) -> State:
        return dataclasses.replace(self, **changes)

    @property
    def swarm(self) -> SwarmState:
        """The :class:`~quadswarm_mj.core.swarm.SwarmState` held in ``info`` (its arrays, not copies;
        leading worlds axis if the state is batched)."""
        return from_info(self.info)
