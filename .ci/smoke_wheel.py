"""Smoke test of an installed (non-editable) quadswarm_mj wheel, run from outside the checkout.

    cd "$(mktemp -d)" && python /path/to/checkout/.ci/smoke_wheel.py --wheel dist/quadswarm_mj-*.whl \
        --checkout /path/to/checkout

Checks: the wheel holds the MJCF assets, the shipped policies and their manifest; the package is
imported from site-packages (not the checkout); an env builds and steps; one frame renders
(headless: with MUJOCO_GL unset the package picks EGL itself and leaves the variable unset);
``load_policy("pretrained:swarm8")`` flies the swarm; importing MJX prints
nothing; every console command answers ``--help``; ``quadswarm-render`` writes a short video.
Exits non-zero on the first failure.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

WHEEL_FILES = ("quadswarm_mj/assets/crazyflie2.xml", "quadswarm_mj/assets/arenas/room.xml",
               "quadswarm_mj/pretrained/manifest.json", "quadswarm_mj/pretrained/single.npz",
               "quadswarm_mj/pretrained/swarm8.npz", "quadswarm_mj/cli/render.py")
COMMANDS = ("quadswarm-render", "quadswarm-train", "quadswarm-evaluate", "quadswarm-benchmark", "quadswarm-profile-jax")


def check(cond: bool, what: str) -> None:
    if not cond:
        raise SystemExit(f"smoke test FAILED: {what}")
    print(f"ok  {what}", flush=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--wheel", required=True, type=Path)
    p.add_argument("--checkout", required=True, type=Path, help="the source checkout (must not be imported)")
    a = p.parse_args()
    checkout = a.checkout.resolve()
    check(not Path.cwd().resolve().is_relative_to(checkout), f"running outside the checkout (cwd {Path.cwd()})")

    names = set(zipfile.ZipFile(a.wheel).namelist())
    for f in WHEEL_FILES:
        check(f in names, f"wheel contains {f}")
    check(not any(n.startswith(("tests/", "scripts/", "assets/")) for n in names), "wheel holds only the package")

    gl_before = os.environ.get("MUJOCO_GL")  # the package's renderer is headless either way
    import numpy as np

    import quadswarm_mj
    from quadswarm_mj import EnvConfig, QuadSwarmEnv
    from quadswarm_mj.policies import load_policy

    where = Path(quadswarm_mj.__file__).resolve()
    # the wheel venv may live inside the checkout (.ci/venv-wheel): what matters is that the package
    # is the installed copy in site-packages, not the checkout's source tree
    check(not where.is_relative_to(checkout / "quadswarm_mj") and "site-packages" in where.parts,
          f"imported from {where.parent}")

    env = QuadSwarmEnv(EnvConfig(num_quads=4, scenario="swap_goals"), render_mode="rgb_array")
    obs, info = env.reset(seed=0)
    for _ in range(20):
        obs, reward, _, _, info = env.step(np.zeros((4, 4)))
    check(obs.shape == (4, env.cfg.obs_dim) and np.isfinite(obs).all() and np.isfinite(reward), "env steps")
    frame = env.render()
    check(frame.shape == (480, 640, 3) and frame.dtype == np.uint8 and frame.std() > 1.0,
          f"one frame rendered (MUJOCO_GL={gl_before!r})")
    check(os.environ.get("MUJOCO_GL") == gl_before, "MUJOCO_GL left as it was")
    env.close()

    policy = load_policy("pretrained:swarm8")
    env = QuadSwarmEnv(scenario="static_diff_goal", **policy.env_kwargs)
    obs, info = env.reset(seed=0)
    d0 = np.linalg.norm(info["state"]["pos"] - info["goals"], axis=-1).mean()
    for _ in range(300):
        obs, _, _, _, info = env.step(policy(obs))
    d1 = np.linalg.norm(info["state"]["pos"] - info["goals"], axis=-1).mean()
    check(obs.shape == (8, policy.obs_dim) and d1 < d0,
          f"pretrained:swarm8 flies to its goals ({d0:.2f} -> {d1:.2f} m)")

    out = subprocess.run([sys.executable, "-c", "import quadswarm_mj.envs.mjx_env, mujoco.mjx; print('x')"],
                         capture_output=True, text=True, timeout=600)
    check(out.returncode == 0 and out.stdout == "x\n" and "Failed to import" not in out.stderr,
          f"importing MJX prints nothing (stdout {out.stdout!r}, stderr tail {out.stderr[-300:]!r})")

    bindir = Path(sys.executable).parent
    for cmd in COMMANDS:
        exe = shutil.which(cmd, path=str(bindir))
        check(exe is not None, f"console command {cmd} installed")
        out = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=300)
        check(out.returncode == 0 and "usage:" in out.stdout, f"{cmd} --help")
    out = subprocess.run([shutil.which("quadswarm-render", path=str(bindir)), "--num-quads", "2", "--seconds", "0.3",
                          "--out", "smoke.mp4", "--width", "160", "--height", "120"], capture_output=True, text=True,
                         timeout=600)
    check(out.returncode == 0 and Path("smoke.mp4").stat().st_size > 0, "quadswarm-render writes a video"
          + ("" if out.returncode == 0 else f" (stderr tail {out.stderr[-300:]!r})"))
    print("wheel smoke test passed")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
