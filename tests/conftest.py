import os
import platform
import sys

# OpenBLAS picks its kernels by CPU (FMA or not, another summation order), which changes the last bits of
# the model's small matrix products between machines; the bit-exact tests (the seeded records, the fast
# forms' same-bits tests) pin the generic x86-64 kernel so that they hold on every x86-64 CPU. Set before
# NumPy loads OpenBLAS; subprocesses inherit it.
if platform.machine().lower() in ("x86_64", "amd64") and "OPENBLAS_CORETYPE" not in os.environ:
    os.environ["OPENBLAS_CORETYPE"] = "Prescott"
    # a pytest plugin (e.g. jaxtyping's) may have loaded NumPy, and with it OpenBLAS, already: start pytest again
    if "numpy" in sys.modules and os.path.basename(sys.argv[0]) in ("pytest", "py.test", "__main__.py"):
        import gc

        for manager in [o for o in gc.get_objects() if type(o).__name__ == "CaptureManager"]:
            manager.stop_global_capturing()  # give the new process the terminal, not pytest's capture file
        sys.stdout.flush()
        sys.stderr.flush()
        os.execv(sys.executable, [sys.executable, "-m", "pytest", *sys.argv[1:]])

import pytest  # noqa: E402

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
