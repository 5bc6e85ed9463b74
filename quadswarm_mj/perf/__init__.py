"""Speed code, kept apart from the model: each module here computes the same values as a plain form
in the model or the engines (a same-values test checks it), only faster on some platform.

* :mod:`quadswarm_mj.perf.numpy_small`: the fewest-NumPy-calls forms of the sub-step model functions
  for small arrays (the CPU engine's single env), bit-identical to the model's own bodies.
* :mod:`quadswarm_mj.perf.numpy_floor`: the paper's floor model (friction wrench, impact) written in
  place into the CPU engine's small arrays by masked whole-array expressions, bit-identical.
* :mod:`quadswarm_mj.perf.one_quad`: the same for exactly one quad in one world, on Python floats
  (sub-step wrench, floor model, rotation, reward terms, metrics, observation), bit-identical.
* :mod:`quadswarm_mj.perf.xla_cpu`: layouts and kernel boundaries aimed at XLA:CPU (``worlds_last``,
  ``kernel_boundary``, integer sort keys), same values as the plain JAX forms.
* :mod:`quadswarm_mj.perf.fused_draws`: all random numbers of a JAX reset or step from one unrolled
  threefry hash (``FusedJaxSampler``), the same distributions as ``jax.random``.
* :mod:`quadswarm_mj.perf.jax_substeps`: the JAX engine's whole sub-step loop of the default
  configuration on components (``ComponentLoop``, a ``physics`` of the control step), the same
  formulas as the general loop.
* :mod:`quadswarm_mj.perf.packing`: the JAX engine's state and outputs packed into a few buffers at
  the host boundary (fewer transfers per step), unpacked to the same pytree bit for bit.

Nothing here changes a model's equations; docs/engines.md gives the measurements that keep each.
"""
