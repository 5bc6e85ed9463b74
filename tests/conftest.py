import os
import platform
import sys

# OpenBLAS picks its kernels by CPU (FMA or not, another summation order), which changes the last bits of
# the model's small matrix products between machines; the bit-exact tests (the seeded records, the fast
# forms' same-bits tests) pin the generic x86-64 kernel so that they hold on every x86-64 CPU. NumPy likewise
# dispatches AVX-512 kernels of some ufuncs (sin, exp, ...) on CPUs that have it (Intel Xeon), with other last
# bits than its AVX2 ones: the records are of the AVX2 kernels, so the AVX-512 targets are switched off
# (NPY_DISABLE_CPU_FEATURES). Set before NumPy loads; subprocesses inherit them.


def _numpy_avx512_targets() -> str:
    """NumPy's dispatch targets beyond AVX2 that this CPU has (space-separated; '' if none), asked of a
    subprocess so that NumPy is not loaded here."""
    import subprocess

    code = ("from numpy._core._multiarray_umath import __cpu_dispatch__ as d, __cpu_features__ as f\n"
            "print(' '.join(t for t in d if ('512' in t or t == 'X86_V4') and f.get(t)))")
    try:
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                             env={**os.environ, "NPY_DISABLE_CPU_FEATURES": ""})
    except (OSError, subprocess.SubprocessError):
        return ""
    return out.stdout.strip() if out.returncode == 0 else ""


if platform.machine().lower() in ("x86_64", "amd64") and "OPENBLAS_CORETYPE" not in os.environ:
    os.environ["OPENBLAS_CORETYPE"] = "Prescott"
    if "NPY_DISABLE_CPU_FEATURES" not in os.environ:
        os.environ["NPY_DISABLE_CPU_FEATURES"] = _numpy_avx512_targets()
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
