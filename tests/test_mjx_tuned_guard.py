"""physics="mjx" under both XLA:CPU options of tune_jax_cpu() hangs on jax >= 0.10 beyond
MJX_TUNED_MAX_WORLDS worlds per program (scripts/mjx_tuned_hang.py): the package's batched programs raise
a clear RuntimeError instead, and nothing changes with JAX's defaults or the free-body physics."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

PROBE = """
    import json, sys
    import quadswarm_mj
    if sys.argv[1] == "tuned":
        quadswarm_mj.tune_jax_cpu()
    import jax
    from quadswarm_mj.devices import MJX_TUNED_MAX_WORLDS, check_mjx_batch
    out = {}
    for name, physics, worlds in (("small", "mjx", MJX_TUNED_MAX_WORLDS), ("big", "mjx", 4 * MJX_TUNED_MAX_WORLDS),
                                  ("freebody", "freebody", 4 * MJX_TUNED_MAX_WORLDS)):
        try:
            check_mjx_batch(physics, worlds)
            out[name] = "ok"
        except RuntimeError as e:
            out[name] = str(e)
    print(json.dumps({"jax": jax.__version__, "out": out}))
"""


def _run(mode: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("QUADSWARM_MJ_TUNE_JAX", "XLA_FLAGS")}
    env["JAX_PLATFORMS"] = "cpu"
    res = subprocess.run([sys.executable, "-c", textwrap.dedent(PROBE), mode], capture_output=True, text=True,
                         timeout=300, env=env, cwd=ROOT)
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_guard_only_where_it_would_hang():
    tuned, default = _run("tuned"), _run("default")
    assert set(default["out"].values()) == {"ok"}
    new_jax = tuple(int(p) for p in tuned["jax"].split(".")[:2]) >= (0, 10)
    big = tuned["out"]["big"]
    assert tuned["out"]["small"] == "ok" and tuned["out"]["freebody"] == "ok"
    if new_jax:
        assert "hangs" in big and "tune_jax_cpu" in big and "QUADSWARM_MJ_TUNE_JAX=0" in big
    else:
        assert big == "ok"
