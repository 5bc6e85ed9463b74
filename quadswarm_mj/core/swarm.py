"""The engines' dynamic state as one structure: :class:`SwarmState`, shared by both engines.

A frozen dataclass of named fields (docs/api.md, "The state structure"). Every array leaf has leading
batch dims: (B, N, ...) on the MuJoCo engine (all its worlds), (N, ...) per world on the JAX engine
(``vmap`` adds a worlds axis). The rigid bodies' positions and velocities stay in the physics back end
(``MjData``, ``mjx.Data``); everything else one control step reads and writes is here. The CPU engine
holds one instance (``CpuSwarm.state``, replaced every step); the JAX engine's ``State.info`` is its
flat dict (:func:`to_info`, :func:`from_info`: the documented keys; ``State.swarm`` reads it back).
:func:`step_state` is :func:`quadswarm_mj.core.control.control_step` on a ``SwarmState``. Importing this
module does not import JAX; :func:`register_pytree` registers the class when JAX is in use.
"""

from __future__ import annotations

import dataclasses
import sys
from typing import Any

from quadswarm_mj.core.control import control_step


@dataclasses.dataclass(frozen=True, eq=False)
class SwarmState:
    """The per-step dynamic quantities of N quads (leading dims ``...``: the worlds).

    Positions m and velocities m/s are world-local/world, ``omega`` rad/s body, rotations body->world."""

    rot: Any  # (..., N, 3, 3) rotation of the physics' quaternion (MuJoCo engine: None = recompute from it)
    motor_u: Any  # (..., N, 4) normalized rotor speeds
    motor_eps: Any  # (..., N, 4) Ornstein-Uhlenbeck motor noise
    thrust: Any  # (..., N, 4) normalized rotor thrusts of the last sub-step (f_norm)
    on_floor: Any  # (..., N) bool grounded (the paper's floor) or near the floor (MuJoCo contacts)
    at_wall: Any  # (..., N) bool
    at_ceiling: Any  # (..., N) bool
    contact: Any  # (..., N, N) bool pairs inside the hitbox at the last control step
    step: Any  # (...,) int control steps in this episode
    total_steps: Any  # int control steps across episodes (reward annealing; MuJoCo engine: one Python int)
    scenario: Any  # quadswarm_mj.scenarios.ScenarioState (goals, goal_vel, timers, ...)
    metrics_acc: Any  # {name: (..., N) or (...,)} accumulators of quadswarm_mj.metrics
    params: Any  # {name: (..., N, ...)} per-quad dynamics parameters (gravity excluded)
    ctrl_state: Any = None  # (..., N, 6) control-mode integrators, None in "rotor" mode
    rotor_cmd: Any = None  # (..., N, 4) last sub-step's rotor command of the extended actuation (MuJoCo engine)
    obstacles: Any = None  # quadswarm_mj.obstacles.ObstacleMap (centres (..., M, 2) m, valid, radius m) or None
    obstacle_contact: Any = None  # (..., N) bool quads touching a column at the last step
    obstacle_metrics: Any = None  # accumulators of quadswarm_mj.obstacles.metrics_update
    rng: Any = None  # JAX engine: the key of the next step's draws (MuJoCo engine: its Generator, held apart)
    step_numbers: Any = None  # JAX engine: the next step's random numbers when carried (perf.fused_draws)

    def replace(self, **changes: Any) -> SwarmState:
        """A copy with ``changes`` (field -> value); the fields not named are shared, not copied."""
        bad = changes.keys() - _FIELDS
        if bad:
            raise TypeError(f"SwarmState has no field(s) {sorted(bad)}")
        d = self.__dict__.copy()
        d.update(changes)
        new = object.__new__(SwarmState)
        object.__setattr__(new, "__dict__", d)
        return new


_FIELDS = frozenset(f.name for f in dataclasses.fields(SwarmState))
_FLAGS = ("on_floor", "at_wall", "at_ceiling", "contact")


def register_pytree() -> None:
    """Register :class:`SwarmState` as a JAX pytree (every field a child; None fields have no leaves).
    Idempotent; called by the JAX engine's modules and at import when JAX is already imported."""
    global _registered
    if _registered:
        return
    import jax

    jax.tree_util.register_dataclass(SwarmState, data_fields=[f.name for f in dataclasses.fields(SwarmState)],
                                     meta_fields=[])
    _registered = True


_registered = False
if "jax" in sys.modules:
    register_pytree()


# ------------------------------------------------------------------ the control step on a SwarmState
def step_state(cfg: Any, scenario: Any, state: SwarmState, q: Any, v: Any, aux: Any, params: dict[str, Any],
               action: Any, consts: dict[str, Any], physics: Any, ops: Any,
               obst_threshold: Any = None) -> tuple[SwarmState, dict[str, Any], dict[str, Any], dict[str, Any]]:
    """:func:`~quadswarm_mj.core.control.control_step` from ``state`` (``rot`` set) and the physics'
    ``q``/``v`` (back end storage) and ``aux`` (its own carry or None). ``params``: ``state.params`` with
    ``gravity`` (m/s^2) as the model functions read them; ``obst_threshold``: the obstacle success
    distance per world (None: the scenario's). Returns ``(next state, k, c, task)``: the state after the
    step (``rng``/``step_numbers`` unchanged: the engine's) and control_step's results."""
    f = state.__dict__  # the fields (read as a dict: the per-step path)
    ctrl = None if consts["act"] is None else (f["rotor_cmd"], f["ctrl_state"])
    s = {"q": q, "v": v, "R": f["rot"], "u": f["motor_u"], "eps": f["motor_eps"], "f_norm": f["thrust"],
         "on_floor": f["on_floor"], "at_wall": f["at_wall"], "at_ceiling": f["at_ceiling"], "contact": f["contact"],
         "params": params, "aux": aux, "ctrl": ctrl, "steps": f["step"], "total_steps": f["total_steps"],
         "sstate": f["scenario"], "metrics_acc": f["metrics_acc"]}
    obstacles = f["obstacles"] is not None
    if obstacles:
        s.update(omap=f["obstacles"], obst_metrics=f["obstacle_metrics"], obst_threshold=obst_threshold)
    k, c, r = control_step(cfg, scenario, s, action, consts, physics, ops)
    d = f.copy()  # the next state's fields (= state.replace(...) without its checks)
    d["rot"], d["motor_u"], d["motor_eps"], d["thrust"] = k["R"], k["u"], k["eps"], k["f_norm"]
    d["on_floor"], d["at_wall"], d["at_ceiling"] = k["on_floor"], k["at_wall"], k["at_ceiling"]
    d["contact"], d["step"], d["total_steps"] = k["contact"], r["steps"], r["total_steps"]
    d["scenario"], d["metrics_acc"] = r["sstate"], r["metrics_acc"]
    if k["ctrl"] is not None:
        d["rotor_cmd"], d["ctrl_state"] = k["ctrl"]
    if obstacles:
        d["obstacle_contact"], d["obstacle_metrics"] = k["obst_contact"], r["obst_metrics"]
    new = object.__new__(SwarmState)
    object.__setattr__(new, "__dict__", d)
    return new, k, c, r


# ------------------------------------------------------------------ the JAX engine's info dict
#: the keys of ``State.info`` that are read-outs, not state: derived from the state and the physics
#: (``state`` pos/vel/omega, ``goals``, ``goal_vel``, ``time``, ``truncation``, the deck readings) or
#: kept by the auto-reset across an episode end (``episode_metrics``)
READOUTS = ("state", "goals", "goal_vel", "episode_metrics", "time", "truncation")


def to_info(state: SwarmState, readouts: dict[str, Any]) -> dict[str, Any]:
    """The JAX engine's ``State.info`` of ``state`` (one world) and its ``readouts`` (:data:`READOUTS`
    with ``state`` = {pos, vel, omega}, plus the deck readings, if any). Keys: docs/api.md."""
    info = {**readouts,
            "state": {**readouts["state"], "rot": state.rot, "thrust": state.thrust},
            "params": state.params, "motor_u": state.motor_u, "motor_eps": state.motor_eps,
            **{k: getattr(state, k) for k in _FLAGS},
            "scenario": state.scenario, "metrics_acc": state.metrics_acc, "step": state.step,
            "total_steps": state.total_steps, "rng": state.rng}
    if state.step_numbers is not None:
        info["step_numbers"] = state.step_numbers
    if state.ctrl_state is not None:
        info["ctrl_state"] = state.ctrl_state
    if state.obstacles is not None:
        om = state.obstacles
        info.update({"obstacles": om.centres, "obstacles_valid": om.valid, "obstacle_radius": om.radius,
                     "obstacle_contact": state.obstacle_contact, "obstacle_metrics": state.obstacle_metrics})
    return info


def from_info(info: dict[str, Any]) -> SwarmState:
    """The :class:`SwarmState` held in a JAX engine ``State.info`` (the inverse of :func:`to_info`)."""
    omap = None
    if "obstacles" in info:
        from quadswarm_mj.obstacles import ObstacleMap

        omap = ObstacleMap(info["obstacles"], info["obstacles_valid"], info["obstacle_radius"])
    return SwarmState(rot=info["state"]["rot"], motor_u=info["motor_u"], motor_eps=info["motor_eps"],
                      thrust=info["state"]["thrust"], **{k: info[k] for k in _FLAGS}, step=info["step"],
                      total_steps=info["total_steps"], scenario=info["scenario"], metrics_acc=info["metrics_acc"],
                      params=info["params"], ctrl_state=info.get("ctrl_state"), obstacles=omap,
                      obstacle_contact=info.get("obstacle_contact"), obstacle_metrics=info.get("obstacle_metrics"),
                      rng=info["rng"], step_numbers=info.get("step_numbers"))
