"""C export for the Crazyflie (SPEC_obstacles B): the generated C99, compiled with the system compiler and
called through ctypes, acts as the NumPy policy on observations from real episodes."""

from __future__ import annotations

import ctypes
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from quadswarm_mj.envs.gym_env import QuadSwarmEnv
from quadswarm_mj.export import ENTRY, export_c, generate_c
from quadswarm_mj.policies import (
    ARCH_PRESETS,
    EncoderPolicy,
    list_pretrained,
    load_policy,
    random_encoder_policy,
    save_encoder_policy,
)

CC = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler (cc, gcc or clang) on PATH: cannot compile the "
                                                 "exported C")
N_OBS = 1000
TOL = 1e-5

# env layouts for the new architectures: 3 quads, K = 2, obs_self "floor" (19) as the obstacle runs
ENV_KW = {"num_quads": 3, "num_neighbors": 2, "obs_self": "floor"}
ARCHS = {
    "deepsets": {"type": "deepsets", "self_layers": [32, 24], "neighbor_layers": [16, 16], "obstacle_layers": [16, 8],
                 "head_layers": [32]},
    "deepsets_deployable": ARCH_PRESETS["deepsets_deployable"],
    "attention_sim2real": ARCH_PRESETS["attention_sim2real"],
    "attention_deployable": ARCH_PRESETS["attention_deployable"],
    "attention_multihead": {"type": "attention", "hidden": 24, "embed_layers": 2, "num_heads": 4, "attn_dim": 24,
                            "head_layers": [48]},
}


def _compile(c_path: Path, extra_flags: tuple[str, ...] = ()) -> ctypes.CDLL:
    so = c_path.with_suffix(".so")
    res = subprocess.run([CC, "-std=c99", "-O2", "-shared", "-fPIC", *extra_flags, str(c_path), "-o", str(so), "-lm"],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-4000:]
    lib = ctypes.CDLL(str(so))
    fn = getattr(lib, ENTRY)
    fn.restype = None
    fn.argtypes = [ctypes.POINTER(ctypes.c_float), ctypes.POINTER(ctypes.c_float)]
    return lib


def _c_actions(lib: ctypes.CDLL, obs: np.ndarray) -> np.ndarray:
    fn = getattr(lib, ENTRY)
    obs = np.ascontiguousarray(obs, dtype=np.float32)
    out = np.zeros((obs.shape[0], 4), np.float32)
    fp = ctypes.POINTER(ctypes.c_float)
    for i in range(obs.shape[0]):
        fn(obs[i].ctypes.data_as(fp), out[i].ctypes.data_as(fp))
    return out


def _sdf(pos: np.ndarray, centres: np.ndarray, radius: float) -> np.ndarray:
    """The 9 obstacle features of SPEC_obstacles A.2 at positions (N, 3): x-major 3 x 3 grid, 0.1 m spacing,
    min 2D distance to a column centre minus the radius."""
    off = np.array([(dx, dy) for dx in (-0.1, 0.0, 0.1) for dy in (-0.1, 0.0, 0.1)])
    pts = pos[:, None, :2] + off[None]  # (N, 9, 2)
    d = np.linalg.norm(pts[:, :, None, :] - centres[None, None, :, :2], axis=-1)
    return d.min(-1) - radius


def _episode_obs(policy, env_kwargs: dict, scenario: str, obstacles: bool = False, seed: int = 0) -> np.ndarray:
    """N_OBS single-quad observations from episodes of ``policy`` in QuadSwarmEnv (short episodes, resets).

    With ``obstacles`` the 9 SDF features of fixed columns are appended at the true positions (the env on
    this branch has no obstacles yet; the layout and the values are those of SPEC_obstacles A.2)."""
    env = QuadSwarmEnv(scenario=scenario, episode_seconds=2.0, **env_kwargs)
    centres = np.random.default_rng(seed).uniform(-3.5, 3.5, (12, 2))
    obs, info = env.reset(seed=seed)
    rows: list[np.ndarray] = []
    while sum(len(r) for r in rows) < N_OBS:
        o = np.atleast_2d(obs)
        if obstacles:
            o = np.concatenate([o, _sdf(np.atleast_2d(info["state"]["pos"]), centres, 0.3)], -1).astype(np.float32)
        rows.append(o)
        obs, _, term, trunc, info = env.step(policy(o).reshape(np.shape(obs)[:-1] + (4,)))
        if term or trunc:
            obs, info = env.reset()
    return np.concatenate(rows)[:N_OBS]


def _random_policy(name: str, obstacles: bool, seed: int = 0) -> EncoderPolicy:
    layout = {"self_dim": 19, "num_neighbors": 2, "neighbor_dim": 6, "obstacle_dim": 9 if obstacles else 0}
    pol = random_encoder_policy(ARCHS[name], layout, seed=seed, meta={"env": ENV_KW})
    pol.name = f"random_{name}"
    return pol


def _with_stats(pol: EncoderPolicy, obs: np.ndarray) -> EncoderPolicy:
    """The same weights with the observation mean/std of ``obs`` (so the C normalization is exercised)."""
    return EncoderPolicy(pol.arch, pol.obs_layout, pol.params, obs.mean(0), obs.std(0) + 0.1, meta=pol.meta,
                         name=pol.name)


@needs_cc
@pytest.mark.parametrize("name", list_pretrained())
def test_shipped_policy_c_matches_numpy_on_episode_observations(tmp_path, name):
    """Every shipped policy (the manifest's list), on observations of real episodes of the env it
    was trained for (its env_kwargs: columns included for the obstacle policies)."""
    pol = load_policy(f"pretrained:{name}")
    if pol.env_kwargs.get("num_quads", 1) == 1:
        scenario = "static_same_goal"
    else:
        scenario = "o_random" if pol.env_kwargs.get("obstacles") is not None else "swap_goals"
    obs = _episode_obs(pol, pol.env_kwargs, scenario)
    assert obs.shape == (N_OBS, pol.obs_dim)
    c_path, h_path = export_c(pol, tmp_path)
    c = _c_actions(_compile(c_path), obs)
    ref = pol(obs)
    assert np.abs(ref).max() > 0.1  # the policy acts: not a trivial comparison of zeros
    np.testing.assert_allclose(c, ref, atol=TOL, rtol=0)
    hdr = h_path.read_text()
    assert f"#define QS_POLICY_OBS_DIM {pol.obs_dim}" in hdr
    assert f"#define QS_POLICY_NUM_PARAMS {pol.num_params}" in hdr
    assert "value" not in c_path.read_text()  # the file holds a critic; only the actor is exported


@needs_cc
@pytest.mark.parametrize("obstacles", [True, False])
@pytest.mark.parametrize("name", sorted(ARCHS))
def test_encoder_c_matches_numpy_on_episode_observations(tmp_path, name, obstacles):
    pol = _random_policy(name, obstacles)
    obs = _episode_obs(pol, ENV_KW, "swap_goals", obstacles=obstacles, seed=1)
    pol = _with_stats(pol, obs)
    c_path, h_path = export_c(pol, tmp_path)
    c = _c_actions(_compile(c_path), obs)
    ref = pol(obs)
    assert np.std(ref, axis=0).min() > 1e-3  # actions vary over the observations
    np.testing.assert_allclose(c, ref, atol=TOL, rtol=0)
    hdr = h_path.read_text()
    assert f"#define QS_POLICY_OBSTACLE_DIM {9 if obstacles else 0}" in hdr
    assert "#define QS_POLICY_NUM_NEIGHBORS 2" in hdr
    assert f"#define QS_POLICY_NUM_PARAMS {pol.num_params}" in hdr


@needs_cc
def test_c_is_plain_c99_with_math_h_only(tmp_path):
    """Strict C99 (no warnings with -Wall -Wextra -pedantic), one exported symbol, includes math.h only."""
    for name in ("attention_multihead", "deepsets"):
        pol = _random_policy(name, obstacles=True)
        c_path, h_path = export_c(pol, tmp_path / name)
        lib = _compile(c_path, ("-Wall", "-Wextra", "-pedantic", "-Werror"))
        assert hasattr(lib, ENTRY)
        src = c_path.read_text()
        assert re.findall(r"#include\s*[<\"]([^>\"]+)[>\"]", src) == ["math.h", "qs_policy.h"]
        assert "#include" not in h_path.read_text()
        assert "static const float qs_self_0_kernel[19]" in src
        non_static = [ln for ln in src.splitlines() if re.match(r"^[A-Za-z].*\(", ln) and not ln.startswith("static")]
        assert non_static == [f"void {ENTRY}(const float *obs, float *action)"]
    nm = shutil.which("nm")
    if nm:
        syms = subprocess.run([nm, "-g", "--defined-only", str(c_path.with_suffix(".so"))], capture_output=True,
                              text=True).stdout
        assert ENTRY in syms and "qs_dense" not in syms


@needs_cc
def test_c_clips_and_handles_extreme_observations(tmp_path):
    pol = _random_policy("attention_sim2real", obstacles=True)
    c_path, _ = export_c(pol, tmp_path)
    lib = _compile(c_path)
    obs = np.random.default_rng(0).normal(0, 50.0, (200, pol.obs_dim)).astype(np.float32)  # saturating inputs
    c = _c_actions(lib, obs)
    assert np.all(np.abs(c) <= 1.0) and np.all(np.isfinite(c))
    np.testing.assert_allclose(c, pol(obs), atol=TOL, rtol=0)


def test_cli_exports_pretrained_and_npz(tmp_path):
    out = tmp_path / "out"
    res = subprocess.run([sys.executable, "-m", "quadswarm_mj.export", "pretrained:single", "--out", str(out)],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert (out / "qs_policy.c").is_file() and (out / "qs_policy.h").is_file()
    assert "actor parameters" in res.stdout
    pol = _random_policy("attention_deployable", obstacles=True)
    save_encoder_policy(tmp_path / "att.npz", pol)
    res = subprocess.run([sys.executable, "-m", "quadswarm_mj.export", str(tmp_path / "att.npz"), "--out",
                          str(out), "--name", "att_policy"], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert "#define QS_POLICY_OBS_DIM 40" in (out / "att_policy.h").read_text()
    res = subprocess.run([sys.executable, "-m", "quadswarm_mj.export", "pretrained:nope", "--out", str(out)],
                         capture_output=True, text=True)
    assert res.returncode != 0 and "unknown pretrained policy" in res.stderr


def test_export_rejects_what_it_cannot_export(tmp_path):
    with pytest.raises(ValueError, match="only trained network policies"):
        generate_c(load_policy("controller"))
    with pytest.raises(ValueError, match="C identifier"):
        export_c(load_policy("pretrained:single"), tmp_path, name="my-policy")
