"""The CPU engine's seeded runs, recorded before the step pipeline was restructured.

``tests/reference_data/cpu_seeded_before_pipeline.npz`` holds obs, rewards and state of a few
seeded runs made with the code before ``quadswarm_mj.pipeline`` existed; the CPU engine must
reproduce them bit for bit. Regenerate (only after an intended change of the CPU model, e.g. the
reward's time scaling) with ``OPENBLAS_CORETYPE=Prescott PYTHONPATH=$PWD python tests/test_cpu_seeded.py --regenerate``
(the kernel tests/conftest.py pins).
"""

from __future__ import annotations

import pathlib
import sys

import numpy as np

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.envs.cpu_core import CpuSwarm
from quadswarm_mj.envs.gym_env import QuadSwarmEnv

REF = pathlib.Path(__file__).parent / "reference_data" / "cpu_seeded_before_pipeline.npz"
STEPS = 200


def _gym_run(cfg: EnvConfig, seed: int, options: dict | None = None, act_scale: float = 0.3) -> dict[str, np.ndarray]:
    env = QuadSwarmEnv(cfg)
    obs, info = env.reset(seed=seed, options=options)
    rng = np.random.default_rng(seed + 1)
    hover = cfg.quad.hover_action
    out: dict[str, list] = {"obs": [obs], "reward": [], "rewards": [], "pos": [], "vel": [], "rot": [], "omega": [],
                            "thrust": [], "goals": []}
    for _ in range(STEPS):
        a = np.clip(hover + act_scale * rng.standard_normal(env.action_space.shape), -1, 1)
        obs, r, term, trunc, info = env.step(a)
        out["obs"].append(obs)
        out["reward"].append(r)
        out["rewards"].append(info["rewards"])
        for k in ("pos", "vel", "rot", "omega", "thrust"):
            out[k].append(info["state"][k])
        out["goals"].append(info["goals"])
    return {k: np.asarray(v) for k, v in out.items()}


def _core_run(cfg: EnvConfig, B: int, seed: int, backend: str) -> dict[str, np.ndarray]:
    core = CpuSwarm(cfg, num_worlds=B, backend=backend, visual=False)
    core.seed(seed)
    core.reset()
    rng = np.random.default_rng(seed + 1)
    out: dict[str, list] = {"obs": [core.observe()], "rewards": [], "pos": [], "vel": [], "omega": []}
    for t in range(STEPS):
        a = np.clip(cfg.quad.hover_action + 0.5 * rng.standard_normal((B, cfg.num_quads, 4)), -1, 1)
        o = core.step(a)
        out["obs"].append(o["obs"])
        out["rewards"].append(o["rewards"])
        s = core.state_dict()
        for k in ("pos", "vel", "omega"):
            out[k].append(s[k])
        if t == 120:  # a partial reset (world 1 only)
            core.reset(mask=np.arange(B) == 1)
    return {k: np.asarray(v) for k, v in out.items()}


def _cluster() -> dict:
    """Four quads 0.1 m apart flying at each other (quad-quad events), one near a wall, one falling."""
    pos = np.array([[0.0, 0.0, 2.0], [0.12, 0.0, 2.0], [0.0, 0.12, 2.0], [4.8, 0.0, 1.0]])
    vel = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, -1.5, 0.0], [2.0, 0.0, -1.0]])
    return {"state": {"pos": pos, "vel": vel}}


def runs() -> dict[str, np.ndarray]:
    mix = EnvConfig(num_quads=8, scenario="mix", randomize=True, downwash=True)
    one = EnvConfig(num_quads=1, scenario="static_same_goal")
    four = EnvConfig(num_quads=4, downwash=True, randomize=True)
    vec = EnvConfig(num_quads=4, scenario="swap_goals", randomize=True)
    cases = {
        "mix8": _gym_run(mix, 3),
        "one": _gym_run(one, 5, act_scale=0.6),
        "cluster4": _gym_run(four, 7, _cluster()),
        "vec3_mjdata": _core_run(vec, 3, 11, "mjdata"),
        "vec3_batch": _core_run(vec, 3, 11, "batch"),
    }
    return {f"{c}/{k}": v for c, d in cases.items() for k, v in d.items()}


def test_cpu_seeded_run_unchanged() -> None:
    ref = np.load(REF)
    got = runs()
    assert sorted(got) == sorted(ref.files)
    for k in ref.files:
        np.testing.assert_array_equal(got[k], ref[k], err_msg=k)


if __name__ == "__main__" and "--regenerate" in sys.argv:
    np.savez_compressed(REF, **runs())
    print("wrote", REF)
