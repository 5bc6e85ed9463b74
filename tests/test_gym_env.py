"""Gymnasium API contract of QuadSwarmEnv: spaces, checker, info, truncation, seeding, bad input."""

from __future__ import annotations

import warnings

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import quadswarm_mj
from quadswarm_mj import EnvConfig, QuadParams, QuadSwarmEnv
from quadswarm_mj.rewards import TERMS

HOVER = QuadParams().hover_action


@pytest.mark.parametrize("n", [1, 8])
def test_check_env_passes_without_warnings(n):
    env = QuadSwarmEnv(EnvConfig(num_quads=n))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=True)
    assert not caught, [str(w.message) for w in caught]


def test_spaces_shapes_single_and_multi():
    e1 = QuadSwarmEnv(EnvConfig(num_quads=1))
    assert e1.action_space.shape == (4,) and e1.observation_space.shape == (18,)
    e8 = QuadSwarmEnv(EnvConfig(num_quads=8))
    assert e8.action_space.shape == (8, 4) and e8.observation_space.shape == (8, 18 + 6 * 6)
    obs, info = e1.reset(seed=0)
    assert obs.shape == (18,) and obs.dtype == np.float32
    for k, shape in {"pos": (1, 3), "vel": (1, 3), "rot": (1, 3, 3), "omega": (1, 3), "thrust": (1, 4)}.items():
        assert info["state"][k].shape == shape
    assert info["goals"].shape == (1, 3) and info["goal_vel"].shape == (1, 3)
    assert info["params"]["mass"].shape == (1,)


def test_gymnasium_make_takes_config_fields():
    env = gymnasium.make("QuadSwarm-v0", num_quads=4, scenario="static_diff_goal", room_size=(6, 6, 4))
    assert env.unwrapped.cfg.num_quads == 4 and env.unwrapped.cfg.room_size == (6.0, 6.0, 4.0)
    obs, _ = env.reset(seed=1)
    assert obs.shape == (4, 18 + 6 * 3)
    env.close()


def test_info_state_is_a_fresh_copy():
    env = QuadSwarmEnv(EnvConfig(num_quads=2))
    _, info = env.reset(seed=0)
    pos = info["state"]["pos"].copy()
    info["state"]["pos"][:] = 99.0
    _, _, _, _, info2 = env.step(np.full((2, 4), HOVER))
    assert np.abs(info2["state"]["pos"] - pos).max() < 0.1  # the env was not corrupted


def _leaves(d, prefix=""):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _leaves(v, f"{prefix}{k}/")
        elif isinstance(v, np.ndarray):
            yield f"{prefix}{k}", v


def test_info_arrays_are_not_shared_between_calls_or_with_the_engine():
    """Every array of an info is the caller's: none shares memory with another call's info or with
    the engine (state, parameters, goals, reward terms, rewards), so editing one changes nothing else."""
    env = QuadSwarmEnv(EnvConfig(num_quads=3, randomize=True))
    _, info0 = env.reset(seed=0)
    _, _, _, _, info1 = env.step(np.full((3, 4), HOVER))
    _, _, _, _, info2 = env.step(np.full((3, 4), HOVER))
    c = env.core
    engine = [c.qpos, c.qvel, c.f_norm, c.on_floor, c.sstate.goals, c.sstate.goal_vel, *c.params.values()]
    a, b = dict(_leaves(info1)), dict(_leaves(info2))
    assert {"rewards", "reward_terms/pos", "params/mass", "state/pos"} <= set(a)
    for name, x in a.items():
        for other in [*b.values(), *dict(_leaves(info0)).values(), *engine]:
            assert not np.shares_memory(x, other), name
    for name, x in a.items():  # entries of one info may be rows of one buffer (one copy), never overlapping
        for name2, y in a.items():
            assert name2 == name or not np.shares_memory(x, y), (name, name2)
    np.testing.assert_array_equal(info1["params"]["mass"], info0["params"]["mass"])  # the episode's
    info1["reward_terms"]["pos"][:] = 1e9
    assert np.all(info1["rewards"] < 1e9) and np.all(info2["reward_terms"]["pos"] < 1e9)


def test_reset_state_is_exact_and_goals_kept():
    env = QuadSwarmEnv(EnvConfig(num_quads=2, scenario="static_same_goal"))
    c, s = np.cos(0.3), np.sin(0.3)
    rot = np.array([[[c, -s, 0], [s, c, 0], [0, 0, 1]], np.eye(3)])
    state = {"pos": np.array([[1.0, 2.0, 3.0], [-1.0, 0.5, 1.5]]), "vel": np.array([[0.1, 0, 0], [0, 0.2, 0]]),
             "rot": rot, "omega": np.array([[0, 0, 0.5], [0.1, 0, 0]]), "motors": "hover",
             "goals": np.array([[0.0, 0.0, 2.0], [1.0, 1.0, 1.0]])}
    _, info = env.reset(seed=3, options={"state": state})
    for k in ("pos", "vel", "rot", "omega"):
        np.testing.assert_allclose(info["state"][k], state[k], atol=1e-12)
    np.testing.assert_allclose(info["goals"], state["goals"])
    np.testing.assert_allclose(info["state"]["thrust"], 1 / 1.9, atol=1e-9)  # motors at hover
    for _ in range(5):
        _, _, _, _, info = env.step(np.full((2, 4), HOVER))
    np.testing.assert_allclose(info["goals"], state["goals"])


def test_reward_terms_sum_to_rewards_and_team_reward_is_mean():
    env = QuadSwarmEnv(EnvConfig(num_quads=8, scenario="static_diff_goal"))
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(50):
        _, r, term, trunc, info = env.step(rng.uniform(-1, 1, (8, 4)))
        assert set(info["reward_terms"]) == set(TERMS)
        total = sum(info["reward_terms"][k] for k in TERMS)
        np.testing.assert_allclose(total, info["rewards"], rtol=1e-12, atol=1e-15)
        assert isinstance(r, float) and r == float(np.mean(info["rewards"]))  # exactly the mean
        assert not term


def test_truncation_at_1500_steps_with_episode_metrics():
    env = QuadSwarmEnv(EnvConfig(num_quads=2))
    env.reset(seed=0)
    a = np.full((2, 4), HOVER)
    for t in range(1500):
        _, _, term, trunc, info = env.step(a)
        assert not term
        if t < 1499:
            assert not trunc
    assert trunc
    m = info["episode_metrics"]
    assert set(m) == {"success", "collisions", "collision_rate", "floor_hits", "wall_hits", "ceiling_hits",
                      "mean_distance", "goal_reach_rate"}
    assert all(np.isfinite(v) for v in m.values())
    with pytest.raises(RuntimeError, match="reset"):
        env.step(a)


def _rollout(seed: int, scenario: str, steps: int = 200):
    env = QuadSwarmEnv(EnvConfig(num_quads=8, scenario=scenario))
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    obs_l, rew_l = [obs], []
    for _ in range(steps):
        obs, _, _, trunc, info = env.step(rng.uniform(-1, 1, (8, 4)))
        obs_l.append(obs)
        rew_l.append(info["rewards"])
    return np.array(obs_l), np.array(rew_l)


@pytest.mark.parametrize("scenario", ["mix", "static_diff_goal"])
def test_same_seed_bit_identical(scenario):
    if scenario not in quadswarm_mj.list_scenarios():
        pytest.skip(f"{scenario} not registered")
    o1, r1 = _rollout(7, scenario)
    o2, r2 = _rollout(7, scenario)
    assert np.array_equal(o1, o2) and np.array_equal(r1, r2)
    o3, _ = _rollout(8, scenario)
    assert not np.array_equal(o1, o3)


def test_reset_sequence_reproducible_across_episodes():
    def run():
        env = QuadSwarmEnv(EnvConfig(num_quads=3, noise={"motor_noise_ratio": 0.05}))
        out = [env.reset(seed=11)[0]]
        for _ in range(3):
            out.append(env.reset()[0])
        return np.array(out)

    a, b = run(), run()
    assert np.array_equal(a, b)
    assert not np.array_equal(a[1], a[2])


# ---------------------------------------------------------------------------------- bad input


def _snapshot(env: QuadSwarmEnv):
    c = env.core
    return (c.data.qpos.copy(), c.data.qvel.copy(), c.u.copy(), c.motor_eps.copy(), c.steps.copy(),
            c.rng.bit_generator.state)


@pytest.mark.parametrize("bad,word", [(np.nan, "NaN"), (np.inf, "inf"), (-np.inf, "inf")])
def test_nonfinite_action_rejected_and_state_untouched(bad, word):
    env = QuadSwarmEnv(EnvConfig(num_quads=3))
    env.reset(seed=0)
    env.step(np.zeros((3, 4)))
    before = _snapshot(env)
    a = np.zeros((3, 4))
    a[1, 2] = bad
    with pytest.raises(ValueError, match=word):
        env.step(a)
    after = _snapshot(env)
    for x, y in zip(before[:-1], after[:-1]):
        assert np.array_equal(x, y)
    assert before[-1] == after[-1]


@pytest.mark.parametrize("n,shape", [(3, (3, 3)), (3, (4,)), (1, (1, 4)), (1, (3,))])
def test_wrong_action_shape_names_both_shapes(n, shape):
    env = QuadSwarmEnv(EnvConfig(num_quads=n))
    env.reset(seed=0)
    expected = (4,) if n == 1 else (n, 4)
    with pytest.raises(ValueError, match="shape") as e:
        env.step(np.zeros(shape))
    assert str(expected) in str(e.value) and str(tuple(shape)) in str(e.value)


def test_out_of_range_actions_are_clipped():
    def run(scale):
        env = QuadSwarmEnv(EnvConfig(num_quads=1).without_noise())
        env.reset(seed=0, options={"state": {"pos": [[0, 0, 2.0]], "motors": "hover"}})
        _, _, _, _, info = env.step(np.array([1.0, -1.0, 1.0, -1.0]) * scale)
        return info["state"]

    a, b = run(1.0), run(5.0)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


def test_bad_reset_state_shape():
    env = QuadSwarmEnv(EnvConfig(num_quads=2))
    with pytest.raises(ValueError, match="shape"):
        env.reset(options={"state": {"pos": np.zeros((3, 3))}})
    with pytest.raises(ValueError, match="unknown"):
        env.reset(options={"state": {"position": np.zeros((2, 3))}})


def test_render_mode_validated():
    with pytest.raises(ValueError, match="render_mode"):
        QuadSwarmEnv(EnvConfig(num_quads=1), render_mode="human_window")
