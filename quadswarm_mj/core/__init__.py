"""The engine core, written once for both engines: the control step (:mod:`quadswarm_mj.core.control`:
:func:`~quadswarm_mj.core.control.control_step` = the sub-steps of :mod:`quadswarm_mj.core.substeps`,
the stages after them in :mod:`quadswarm_mj.core.step`, then the task step), the engine differences
passed into it (:mod:`quadswarm_mj.core.ops`), the engines' shared dynamic state
(:mod:`quadswarm_mj.core.swarm`: ``SwarmState`` and ``step_state``, the control step on it), the JAX
engine's ``State`` (:mod:`quadswarm_mj.core.state`). The reset math is :mod:`quadswarm_mj.core.reset`.
The rigid-body back ends are in :mod:`quadswarm_mj.physics`."""
