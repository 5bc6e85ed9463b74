"""The rigid-body integrators passed into the control step: MuJoCo's C engine on ``MjData`` or
``mujoco.batch`` (:mod:`quadswarm_mj.physics.mujoco_c`), the exact free-body step on NumPy or JAX
(:mod:`quadswarm_mj.freebody`), and ``mjx.step`` (the JAX engine, ``physics="mjx"``)."""
