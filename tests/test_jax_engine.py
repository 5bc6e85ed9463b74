"""engine="jax" behind QuadSwarmEnv, QuadSwarmParallelEnv and QuadSwarmVectorEnv: the MuJoCo
engine's spaces and info, seeding, input validation, auto-reset and reset options, and noise-free
agreement with the MuJoCo engine within the MJX parity tolerance (float32).

Compiles are the cost: every config below is compiled once per module (the compiled programs are
cached per config and number of worlds, so envs of one config share them)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

pytest.importorskip("jax")
pytest.importorskip("mujoco.mjx")

from gymnasium.utils.env_checker import check_env  # noqa: E402
from pettingzoo.test import parallel_api_test  # noqa: E402

from quadswarm_mj import EnvConfig, QuadSwarmEnv, QuadSwarmParallelEnv, QuadSwarmVectorEnv  # noqa: E402
from quadswarm_mj.metrics import METRIC_KEYS  # noqa: E402
from quadswarm_mj.spatial import yaw_rotmat  # noqa: E402

pytestmark = pytest.mark.slow

N = 8
T = 150
PARITY_TOL = 1e-3  # m, float32 MJX vs float64 MuJoCo over 150 steps (measured: 3e-5 m)
# noise-free, episodes of 160 steps: 150 parity steps, then the time limit (auto-reset)
CFG = EnvConfig(num_quads=N, episode_seconds=1.6).without_noise()
NOISY = EnvConfig(num_quads=3, episode_seconds=0.3)  # paper defaults (all noise on), short episodes


def parity_setup(cfg: EnvConfig) -> tuple[dict, np.ndarray]:
    """4 x 2 grid, 1 m apart, yawed, slowly moving and spinning; hover actions with collective,
    yaw and small per-rotor oscillations (the case of tests/test_mjx_env.py)."""
    xy = np.stack(np.meshgrid(np.arange(4) - 1.5, np.arange(2) - 0.5, indexing="ij"), -1).reshape(N, 2)
    pos = np.concatenate([xy, 2.0 + 0.1 * np.arange(N)[:, None]], -1)
    init = {"pos": pos, "vel": np.tile([0.1, -0.05, 0.02], (N, 1)), "rot": yaw_rotmat(np.linspace(-2.5, 2.5, N)),
            "omega": np.tile([0.01, -0.01, 0.3], (N, 1)), "goals": pos + np.array([0.3, -0.2, 0.5]),
            "motors": "hover"}
    t = np.arange(T)[:, None, None] * cfg.control_dt
    i = np.arange(N)[None, :, None]
    r = np.arange(4)[None, None, :]
    spin = np.array([-1.0, 1.0, -1.0, 1.0])
    acts = (cfg.quad.hover_action + 0.03 * np.sin(2 * np.pi * (0.5 + 0.1 * i) * t + 0.3 * i)
            + 0.03 * spin * np.cos(2 * np.pi * 0.7 * t + i) + 0.002 * np.sin(2 * np.pi * (1 + 0.2 * r) * t + r + i))
    return init, acts


def run(env: QuadSwarmEnv, init: dict, acts: np.ndarray) -> dict:
    obs0, info0 = env.reset(seed=0, options={"state": init})
    pos, rew, infos = [], [], []
    for a in acts:
        _, _, _, _, info = env.step(a)
        pos.append(info["state"]["pos"])
        rew.append(info["rewards"])
        infos.append(info)
    return {"obs0": obs0, "info0": info0, "pos": np.array(pos), "rew": np.array(rew), "infos": infos}


@pytest.fixture(scope="module")
def parity():
    init, acts = parity_setup(CFG)
    ref = run(QuadSwarmEnv(CFG), init, acts)
    env = QuadSwarmEnv(CFG, engine="jax")
    jx = run(env, init, acts)
    return {"init": init, "acts": acts, "ref": ref, "jax": jx, "env": env}


@pytest.fixture(scope="module")
def noisy_env():
    return QuadSwarmEnv(NOISY, engine="jax")


@pytest.fixture(scope="module")
def vec():
    """2 worlds: world 0 starts in the parity state, world 1 elsewhere (shifted, still)."""
    init, acts = parity_setup(CFG)
    env = QuadSwarmVectorEnv(CFG, num_envs=2, engine="jax")
    state = {k: np.stack([v, v + np.array([0.0, 0.0, -0.5])]) if k == "pos" else
             (v if isinstance(v, str) else np.stack([v, v])) for k, v in init.items()}
    obs0, info0 = env.reset(seed=0, options={"state": state})
    steps = []
    for a in acts:
        steps.append(env.step(np.stack([a, np.full_like(a, CFG.quad.hover_action)])))
    return {"env": env, "state": state, "obs0": obs0, "info0": info0, "steps": steps}


def keys_of(d: dict, prefix: str = "") -> dict[str, tuple]:
    """{path: (shape, dtype kind)} of a nested info dict."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(keys_of(v, prefix + k + "/"))
        else:
            a = np.asarray(v)
            out[prefix + k] = (a.shape, a.dtype.kind)
    return out


# ------------------------------------------------------------------------------- single env
def test_engine_argument_is_validated():
    for cls in (QuadSwarmEnv, QuadSwarmParallelEnv):
        with pytest.raises(ValueError, match=r"engine must be one of \['mujoco', 'jax'\]"):
            cls(EnvConfig(num_quads=2), engine="mjx")
    with pytest.raises(ValueError, match="engine must be one of"):
        QuadSwarmVectorEnv(EnvConfig(num_quads=2), num_envs=2, engine=None)


def test_single_env_parity_with_mujoco_engine_150_steps(parity):
    ref, jx = parity["ref"], parity["jax"]
    # a real test: the quads move, stay in the air and apart
    assert np.abs(ref["pos"] - parity["init"]["pos"]).max() > 0.2
    assert ref["pos"][..., 2].min() > 1.0
    err = np.abs(ref["pos"] - jx["pos"]).max()
    assert err < PARITY_TOL, err
    scale = np.abs(ref["rew"]).max()
    assert scale > 0 and np.abs(ref["rew"] - jx["rew"]).max() < PARITY_TOL * scale
    a, b = ref["infos"][-1], jx["infos"][-1]
    for k in ("rot", "omega"):
        np.testing.assert_allclose(b["state"][k], a["state"][k], atol=1e-3)
    np.testing.assert_allclose(b["state"]["thrust"], a["state"]["thrust"], atol=1e-5)
    for k in a["reward_terms"]:
        np.testing.assert_allclose(b["reward_terms"][k], a["reward_terms"][k], atol=PARITY_TOL * scale)
    # own-state part of the first observation (the neighbour slots of the 1 m grid tie in distance,
    # so their order may differ between float32 and float64)
    own = 18
    np.testing.assert_allclose(jx["obs0"][:, :own], ref["obs0"][:, :own], atol=1e-5)


def test_single_env_spaces_and_info_keys_match_mujoco_engine(parity):
    env = parity["env"]
    ref_env = QuadSwarmEnv(CFG)
    assert env.observation_space == ref_env.observation_space
    assert env.action_space == ref_env.action_space
    ref, jx = parity["ref"], parity["jax"]
    assert keys_of(jx["info0"]) == keys_of(ref["info0"])
    assert keys_of(jx["infos"][0]) == keys_of(ref["infos"][0])
    assert jx["obs0"].dtype == np.float32 and env.observation_space.contains(jx["obs0"])
    np.testing.assert_allclose(jx["info0"]["state"]["pos"], parity["init"]["pos"], atol=1e-6)
    np.testing.assert_allclose(jx["info0"]["goals"], parity["init"]["goals"], atol=1e-6)


def test_single_env_episode_end_metrics_and_reset_required(parity):
    env = parity["env"]
    env.reset(seed=1)
    a = np.full((N, 4), CFG.quad.hover_action)
    for k in range(CFG.episode_steps):
        _, r, term, trunc, info = env.step(a)
        assert isinstance(r, float) and term is False
        assert trunc == (k == CFG.episode_steps - 1)
    assert set(info["episode_metrics"]) == set(METRIC_KEYS)
    assert all(isinstance(v, float) for v in info["episode_metrics"].values())
    assert info["time"] == pytest.approx(CFG.episode_steps * CFG.control_dt, rel=1e-6)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(a)


def test_single_env_seeded_runs_are_bit_identical(noisy_env):
    env = noisy_env
    rng = np.random.default_rng(0)
    acts = rng.uniform(-1, 1, (12, 3, 4))

    def rollout(seed):
        obs, info = env.reset(seed=seed)
        out = [obs, info["params"]["mass"]]
        for a in acts:
            o, r, _, _, info = env.step(a)
            out += [o, np.array(r), info["state"]["pos"]]
        return out

    a, b, c = rollout(3), rollout(3), rollout(4)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a[0], c[0])
    # unseeded resets continue the stream: a new episode, not a copy
    env.reset(seed=3)
    o1, _ = env.reset()
    assert not np.array_equal(o1, a[0])


def test_single_env_episode_constants_kept_from_reset(noisy_env):
    """Steps do not return the dynamics parameters: info["params"] holds copies of the reset's (no
    object shared between two calls' infos, so a caller's edits of one info cannot reach the next);
    with domain randomization a new episode brings new parameters."""
    env = noisy_env
    prog = env._jax.prog
    assert not any(k.startswith("params/") for k in prog.step_layout.names)
    assert any(k.startswith("params/") for k in prog.layout.names)
    _, info0 = env.reset(seed=11)
    p0 = {k: np.array(v) for k, v in info0["params"].items()}
    _, _, _, _, info1 = env.step(np.zeros((3, 4)))
    _, _, _, _, info2 = env.step(np.zeros((3, 4)))
    for k, v in p0.items():
        np.testing.assert_array_equal(info1["params"][k], v)
        assert not np.shares_memory(info1["params"][k], info2["params"][k])
        info1["params"][k][...] = -1.0  # a caller's copy, not the env's
    np.testing.assert_array_equal(info2["params"]["mass"], p0["mass"])
    _, _, _, _, info3 = env.step(np.zeros((3, 4)))
    np.testing.assert_array_equal(info3["params"]["mass"], p0["mass"])
    rnd = QuadSwarmEnv(NOISY.replace(randomize=True), engine="jax")
    _, r0 = rnd.reset(seed=11)
    _, _, _, _, r1 = rnd.step(np.zeros((3, 4)))
    np.testing.assert_array_equal(r1["params"]["mass"], r0["params"]["mass"])
    _, r2 = rnd.reset(seed=12)
    _, _, _, _, r3 = rnd.step(np.zeros((3, 4)))
    assert not np.array_equal(r3["params"]["mass"], r0["params"]["mass"])
    np.testing.assert_array_equal(r3["params"]["mass"], r2["params"]["mass"])


def test_single_env_bad_actions_rejected_state_unchanged(noisy_env):
    env = noisy_env
    good = np.full((3, 4), 0.1)
    env.reset(seed=5)
    o_ref, *_ = env.step(good)
    env.reset(seed=5)
    for bad, msg in ((np.full((3, 4), np.nan), "NaN"), (np.full((3, 4), np.inf), "inf"),
                     (np.zeros((3, 3)), "wrong shape"), ("x", "numeric")):
        with pytest.raises(ValueError, match=msg):
            env.step(bad)
    o, *_ = env.step(good)
    np.testing.assert_array_equal(o, o_ref)
    with pytest.raises(ValueError, match="unknown keys"):
        env.reset(options={"state": {"position": np.zeros((3, 3))}})


def test_check_env_on_jax_engine(noisy_env):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(noisy_env, skip_render_check=True)
    assert not caught, [str(w.message) for w in caught]


def test_parallel_api_on_jax_engine(noisy_env):
    env = QuadSwarmParallelEnv(NOISY, engine="jax")
    assert env.env.engine == "jax"
    parallel_api_test(env, num_cycles=80)


def test_render_jax_engine_matches_mujoco_engine(parity):
    init = parity["init"]
    frames = []
    for engine in ("mujoco", "jax"):
        env = QuadSwarmEnv(CFG, render_mode="rgb_array", engine=engine)
        env.reset(seed=0, options={"state": init})
        frames.append(env.render().astype(np.float64))
        env.close()
    assert frames[1].shape == (480, 640, 3)
    assert frames[0].std() > 1.0  # not a blank frame
    assert np.abs(frames[0] - frames[1]).mean() < 0.5  # same pose (float32 rounding only)


# ------------------------------------------------------------------------------- vector env
def test_vector_spaces_info_keys_and_world0_parity(vec, parity):
    env = vec["env"]
    ref_vec = QuadSwarmVectorEnv(CFG, num_envs=2, num_shards=1)
    try:
        assert env.single_observation_space == ref_vec.single_observation_space
        assert env.action_space == ref_vec.action_space and env.observation_space == ref_vec.observation_space
        assert env.metadata["autoreset_mode"] == ref_vec.metadata["autoreset_mode"]
        _, ref_info0 = ref_vec.reset(seed=0, options={"state": vec["state"]})
        *_, ref_info = ref_vec.step(np.full((2, N, 4), CFG.quad.hover_action))
        assert keys_of(vec["info0"]) == keys_of(ref_info0)
        assert keys_of(vec["steps"][0][4]) == keys_of(ref_info)
    finally:
        ref_vec.close()
    obs, reward, term, trunc, info = vec["steps"][0]
    assert obs.dtype == np.float32 and reward.shape == (2,) and not term.any() and not trunc.any()
    pos0 = np.array([s[4]["state"]["pos"][0] for s in vec["steps"]])
    err = np.abs(pos0 - parity["ref"]["pos"]).max()
    assert err < PARITY_TOL, err
    # world 1 hovers from its own start: it is a separate world
    assert np.abs(vec["steps"][-1][4]["state"]["pos"][1] - vec["state"]["pos"][1]).max() < 0.5
    rew0 = np.array([s[4]["rewards"][0] for s in vec["steps"]])
    np.testing.assert_allclose(np.array([s[1][0] for s in vec["steps"]]), rew0.mean(-1), rtol=1e-12)


def test_vector_same_step_autoreset(vec):
    env = vec["env"]
    a = np.full((2, N, 4), CFG.quad.hover_action)
    done_step = CFG.episode_steps - T  # the fixture ran T steps of this episode
    for k in range(done_step):
        obs, reward, term, trunc, info = env.step(a)
        last = k == done_step - 1
        assert trunc.all() == last and trunc.any() == last
        assert ("final_obs" in info) == last
    assert info["_final_obs"].all() and info["_episode_metrics"].all()
    assert set(info["episode_metrics"]) == set(METRIC_KEYS)
    assert np.isfinite(info["episode_metrics"]["mean_distance"]).all()
    # the returned observation and info are the new episode's (random goals and spawn, time 0)
    np.testing.assert_array_equal(info["time"], 0.0)
    assert not np.allclose(info["goals"], vec["state"]["goals"])
    assert not np.allclose(obs, info["final_obs"])
    assert env.single_observation_space.contains(info["final_obs"][0])
    obs2, _, _, trunc2, info2 = env.step(a)
    assert not trunc2.any() and "final_obs" not in info2
    np.testing.assert_allclose(info2["time"], CFG.control_dt, rtol=1e-6)


def test_vector_reset_mask_seeding_and_bad_actions(vec):
    env = vec["env"]
    obs, info = env.reset(seed=7)
    obs_b, info_b = env.reset(seed=7)
    np.testing.assert_array_equal(obs, obs_b)
    assert not np.array_equal(obs[0], obs[1])  # worlds draw different goals and spawns
    a = np.full((2, N, 4), CFG.quad.hover_action)
    for _ in range(3):
        obs, _, _, _, info = env.step(a)
    obs_m, info_m = env.reset(options={"reset_mask": np.array([False, True])})
    np.testing.assert_array_equal(obs_m[0], obs[0])  # world 0 untouched
    np.testing.assert_allclose(info_m["time"], [3 * CFG.control_dt, 0.0], rtol=1e-6)
    # masked reset with a start state: only world 1 takes it
    st = {"pos": np.tile(np.array([[0.5, 0.5, 1.5]]), (2, N, 1)) + 0.3 * np.arange(N)[None, :, None]}
    _, info_s = env.reset(options={"reset_mask": np.array([False, True]), "state": st})
    np.testing.assert_allclose(info_s["state"]["pos"][1], st["pos"][1], atol=1e-6)
    np.testing.assert_array_equal(info_s["state"]["pos"][0], info_m["state"]["pos"][0])
    # bad actions: rejected before any state change
    ref_obs, *_ = env.step(a)
    env.reset(seed=7)
    for _ in range(3):
        env.step(a)
    env.reset(options={"reset_mask": np.array([False, True])})
    env.reset(options={"reset_mask": np.array([False, True]), "state": st})
    bad = a.copy()
    bad[1, 2, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        env.step(bad)
    with pytest.raises(ValueError, match="wrong shape"):
        env.step(a[:1])
    obs_after, *_ = env.step(a)
    np.testing.assert_array_equal(obs_after, ref_obs)
    with pytest.raises(ValueError, match="reset_mask"):
        env.reset(options={"reset_mask": np.array([1, 0])})
