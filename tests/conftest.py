import os
import sys

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")


@pytest.fixture(autouse=True)
def _jax_x64_restored():
    """Tests that switch on ``jax_enable_x64`` must not leak it into later tests (the JAX engine's
    dtypes, float32 observations and compiled programs depend on it)."""
    jax = sys.modules.get("jax")
    before = bool(jax.config.jax_enable_x64) if jax is not None else False
    yield
    jax = sys.modules.get("jax")
    if jax is not None and bool(jax.config.jax_enable_x64) != before:
        jax.config.update("jax_enable_x64", before)
