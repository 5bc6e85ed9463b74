"""Speed code, kept apart from the model: each module computes the same values as a plain form in the
model or the engines (a same-values test checks it), only faster on some platform; the engines reach
it through their ops (:mod:`quadswarm_mj.core.ops`), never the model.

* ``numpy_small``: fewest-NumPy-calls forms of the sub-step functions for small arrays (same bits);
  ``numpy_floor``: the paper's floor model on the grounded quads' rows only; ``numpy_deck``, ``numpy_depth``:
  the decks' and the depth camera's parts on few calls (same bits; work arrays: ``scratch_cache``).
* ``one_quad``: one quad in one world on Python floats (wrench, floor, rotation, rewards, metrics,
  observation), bit-identical to the array forms; ``one_quad_step``: on those bodies, the whole sub-step
  loop and the whole task stage of one quad (``NumpyOps.fused_loop``, ``fused_task``).
* ``numpy_loop``, ``numpy_swarm``, ``numpy_swarm_task``: the sub-step loop and the task half of several quads.
* ``xla_cpu``: layouts and kernel boundaries for XLA:CPU (``worlds_last``, ``kernel_boundary``, integer
  sort keys); ``depth_xla``: the depth camera's hitbox test; ``jax_deck``: its deck part computed once.
* ``fused_draws``: opt-in (``draws="fused"``) a JAX step's numbers from one threefry hash; the ToF
  noise (``tof_numbers``) and the float32 erfinv that both draw forms use.
* ``jax_substeps``: the JAX engine's default sub-step loop on components (``ComponentLoop``).
* ``packing``: the JAX engine's state and outputs packed into few buffers at the host boundary.
* ``xla_options``: per-program XLA:CPU compile options.

Nothing here changes a model's equations; docs/engines.md gives the measurements that keep each.
"""

from collections.abc import Iterator
from contextlib import contextmanager

_NUMPY_FORMS = ("one_quad", "numpy_loop", "numpy_swarm", "numpy_swarm_task")


def numpy_fast_forms_enabled() -> bool:
    """Whether the MuJoCo engine's fused NumPy forms (the modules above) are in use (the default)."""
    from importlib import import_module

    return all(import_module(f"{__name__}.{name}").ENABLED for name in _NUMPY_FORMS)


def set_numpy_fast_forms(enabled: bool) -> None:
    """Turn the MuJoCo engine's fused NumPy forms on (default) or off for this process.

    Off, every step runs the model's plain array functions: the same values bit for bit (each form's
    same-values test), only slower (docs/engines.md gives the figures). Takes effect at the next step.
    """
    if not isinstance(enabled, bool):
        raise TypeError(f"set_numpy_fast_forms: enabled must be a bool, got {type(enabled).__name__}")
    from importlib import import_module

    for name in _NUMPY_FORMS:
        import_module(f"{__name__}.{name}").ENABLED = enabled


@contextmanager
def numpy_fast_forms(enabled: bool) -> Iterator[None]:
    """Context manager: the fused NumPy forms on or off inside the block, restored after it."""
    from importlib import import_module

    modules = [import_module(f"{__name__}.{name}") for name in _NUMPY_FORMS]
    before = [module.ENABLED for module in modules]
    set_numpy_fast_forms(enabled)
    try:
        yield
    finally:
        for module, value in zip(modules, before):
            module.ENABLED = value
