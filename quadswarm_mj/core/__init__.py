"""The engine core: the control step's stages written once (:mod:`quadswarm_mj.core.step`), the engine
differences passed into them (:mod:`quadswarm_mj.core.ops`), the JAX engine's state (:mod:`quadswarm_mj.
core.state`). The reset math is :func:`quadswarm_mj.pipeline.initial_state`, the task stage
:func:`quadswarm_mj.pipeline.task_stage` (both engines call each)."""
