"""Speed code, kept apart from the model: each module computes the same values as a plain form in the
model or the engines (a same-values test checks it), only faster on some platform; the engines reach
it through their ops (:mod:`quadswarm_mj.core.ops`), never the model.

* ``numpy_small``: fewest-NumPy-calls forms of the sub-step functions for small arrays (same bits);
  ``numpy_floor``: the paper's floor model on the grounded quads' rows only (same bits); ``numpy_deck``:
  the multi-ranger and flow decks' observation part on few, cheap calls (same bits).
* ``one_quad``: one quad in one world on Python floats (wrench, floor, rotation, rewards, metrics,
  observation), bit-identical to the array forms; ``one_quad_step``: on those bodies, the whole sub-step
  loop and the whole task stage of one quad (``NumpyOps.fused_loop``, ``fused_task``).
* ``numpy_loop``: the sub-step loop for small arrays with the control step's constants computed once.
* ``xla_cpu``: layouts and kernel boundaries for XLA:CPU (``worlds_last``, ``kernel_boundary``, integer
  sort keys); ``depth_xla``: the depth camera's hitbox test; ``jax_deck``: its deck part computed once.
* ``fused_draws``: a JAX step's random numbers from one unrolled threefry hash (``FusedJaxSampler``,
  the distributions of ``jax.random``; the deck rays' ToF noise from the same numbers).
* ``jax_substeps``: the JAX engine's default sub-step loop on components (``ComponentLoop``).
* ``packing``: the JAX engine's state and outputs packed into few buffers at the host boundary.
* ``xla_options``: per-program XLA:CPU compile options.

Nothing here changes a model's equations; docs/engines.md gives the measurements that keep each.
"""
