"""The rigid-body back ends passed into the control step as ``physics``
(:func:`quadswarm_mj.core.substeps.substep_loop`: ``substep``, ``local_pos``, ``velocities``): MuJoCo's
C engine on ``MjData`` or ``mujoco.batch`` (:mod:`quadswarm_mj.physics.mujoco_c`, which owns the world
offsets of the generated room), the exact free-body step on NumPy or JAX
(:mod:`quadswarm_mj.physics.freebody`, around :func:`quadswarm_mj.freebody.freebody_step`), and
``mjx.step`` (:mod:`quadswarm_mj.physics.mjx`, the JAX engine's ``physics="mjx"``)."""
