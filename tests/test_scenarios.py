"""The eleven scenarios of SPEC §10: registry, 10 s env runs, the promised goal changes, goals
inside the room (also small rooms), the reset-goals contract, and NumPy == jax.jit.

Most behaviour tests call the pure ``init``/``step`` functions directly on a batch of worlds
(no physics), so they are cheap; the env tests run the full CPU simulator.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

import quadswarm_mj
from quadswarm_mj import EnvConfig, QuadParams, QuadSwarmEnv
from quadswarm_mj.scenarios import MIX_CHOICES, MIX_CHOICES_SINGLE, get_scenario
from quadswarm_mj.scenarios.base import room_bounds

NAMES = ["static_same_goal", "static_diff_goal", "dynamic_same_goal", "dynamic_diff_goal", "dynamic_formations",
         "swap_goals", "swarm_vs_swarm", "ep_lissajous3D", "ep_rand_bezier", "run_away", "mix"]
HOVER = QuadParams().hover_action
DT = 0.01


def rollout(name: str, n: int = 8, worlds: int = 32, seconds: float = 15.0, seed: int = 0,
            room: tuple[float, float, float] = (10.0, 10.0, 10.0)) -> dict[str, np.ndarray]:
    """Run a scenario's pure functions: arrays (T + 1, B, ...) for t = 0, dt, ..., seconds."""
    cfg = EnvConfig(num_quads=n, scenario=name, room_size=room)
    sc = get_scenario(name)
    rng = np.random.default_rng(seed)
    m = sc.num_uniforms(n)
    s = sc.init(cfg, rng.uniform(size=(worlds, m)))
    out = {k: [getattr(s, k)] for k in s._fields}
    pos = np.zeros((worlds, n, 3))
    for k in range(1, int(round(seconds / DT)) + 1):
        s = sc.step(cfg, s, np.full(worlds, k * DT), pos, rng.uniform(size=(worlds, m)))
        for f in s._fields:
            out[f].append(getattr(s, f))
    res = {k: np.array(v) for k, v in out.items()}
    res["t"] = np.arange(len(res["goals"])) * DT
    res["cfg"] = cfg
    return res


def changes(goals: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """(T, B, N) bool: goal of quad i in world b changed from step k to k + 1."""
    return np.linalg.norm(np.diff(goals, axis=0), axis=-1) > tol


def min_pair_dist(g: np.ndarray) -> np.ndarray:
    """Closest goal pair distance (...,) of goals (..., N, 3)."""
    d = np.linalg.norm(g[..., :, None, :] - g[..., None, :, :], axis=-1)
    d = d + np.where(np.eye(g.shape[-2], dtype=bool), np.inf, 0.0)
    return d.min(axis=(-2, -1))


def assert_inside(cfg: EnvConfig, goals: np.ndarray) -> None:
    low, high = room_bounds(cfg)
    assert np.all(goals >= np.array(low) - 1e-9) and np.all(goals <= np.array(high) + 1e-9)
    assert np.all(goals >= np.array(cfg.room_low)) and np.all(goals <= np.array(cfg.room_high))


# ---------------------------------------------------------------- registry


def test_list_scenarios_has_all_eleven():
    # the o_* obstacle scenarios (tests/test_obstacle_scenarios.py) are registered before mix
    assert [n for n in quadswarm_mj.list_scenarios() if not n.startswith("o_")] == NAMES
    assert set(MIX_CHOICES) == set(NAMES) - {"run_away", "mix"} and len(MIX_CHOICES) == 9
    assert MIX_CHOICES_SINGLE == ("static_same_goal", "static_diff_goal", "ep_lissajous3D", "ep_rand_bezier",
                                  "dynamic_same_goal")


def test_unknown_scenario_lists_known_ones():
    with pytest.raises(ValueError) as e:
        EnvConfig(scenario="warp_drive")
    assert "warp_drive" in str(e.value) and all(n in str(e.value) for n in NAMES)


# ---------------------------------------------------------------- full env, 10 s, 8 quads


@pytest.mark.parametrize("name", NAMES)
def test_env_runs_10s_goals_inside_room(name):
    env = QuadSwarmEnv(EnvConfig(num_quads=8, scenario=name))
    obs, info = env.reset(seed=3)
    rng = np.random.default_rng(0)
    random_actions = NAMES.index(name) % 2 == 1  # half the scenarios with hover, half with random actions
    goals = [info["goals"]]
    for _ in range(1000):
        a = rng.uniform(-1, 1, (8, 4)) if random_actions else np.full((8, 4), HOVER)
        obs, r, term, trunc, info = env.step(a)
        assert np.isfinite(obs).all() and math.isfinite(r) and np.isfinite(info["rewards"]).all()
        assert not term and not trunc
        assert info["goals"].shape == (8, 3) and info["goal_vel"].shape == (8, 3)
        assert np.isfinite(info["goal_vel"]).all()
        assert_inside(env.cfg, info["goals"])
        goals.append(info["goals"])
    goals = np.array(goals)
    moved = changes(goals).any()
    if name.startswith("static"):
        assert not moved
    elif name != "mix":
        assert moved  # every dynamic scenario changes its goals within 10 s
    env.close()


# ---------------------------------------------------------------- behaviour per scenario


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("room", [(10.0, 10.0, 10.0), (3.0, 3.0, 2.0), (1.0, 1.2, 1.25)])  # the smallest room allowed
def test_goals_inside_room_and_finite(name, room):
    r = rollout(name, n=8, worlds=16, seconds=15.0, room=room)
    assert np.isfinite(r["goals"]).all() and np.isfinite(r["goal_vel"]).all()
    assert r["goals"].shape == r["goal_vel"].shape == (1501, 16, 8, 3)
    assert_inside(r["cfg"], r["goals"])


@pytest.mark.parametrize("name", ["static_same_goal", "static_diff_goal"])
def test_static_goals_fixed(name):
    r = rollout(name)
    assert not changes(r["goals"]).any() and np.all(r["goal_vel"] == 0)
    if name == "static_same_goal":
        np.testing.assert_allclose(r["goals"], np.broadcast_to([0.0, 0.0, 2.0], r["goals"].shape))
    else:
        d = min_pair_dist(r["goals"][0])
        assert d.min() >= 0.25 - 1e-9 and d.max() <= 0.5 + 1e-9


def event_steps(r: dict, world: int) -> np.ndarray:
    """Indices k (time k * dt) at which any goal of ``world`` changed."""
    return np.nonzero(changes(r["goals"])[:, world].any(-1))[0] + 1


def assert_periods(r: dict, lo: float = 4.0, hi: float = 6.0) -> None:
    for b in range(r["goals"].shape[1]):
        k = event_steps(r, b)
        assert len(k) >= 2  # two events in 15 s for periods <= 6 s
        gaps = np.diff(np.r_[0, k]) * DT
        assert gaps.min() >= lo - 1e-6 and gaps.max() <= hi + DT + 1e-6, gaps


def test_dynamic_same_goal_jumps_every_4_to_6_s():
    r = rollout("dynamic_same_goal")
    g = r["goals"]
    np.testing.assert_array_equal(g, np.broadcast_to(g[:, :, :1], g.shape))  # one shared goal
    assert np.all(r["goal_vel"] == 0)
    assert_periods(r)
    jumps = np.linalg.norm(np.diff(g[:, :, 0], axis=0), axis=-1)
    assert jumps[jumps > 0].min() > 1e-3 and g[..., 2].min() >= 0.25


def test_dynamic_diff_goal_redraws_formation():
    r = rollout("dynamic_diff_goal")
    assert_periods(r)
    g = r["goals"]
    d = min_pair_dist(g)
    assert d.min() >= 0.25 - 1e-9 and d.max() <= 0.5 + 1e-9  # spacing in 0.25-0.5 m at every step
    centroid = g.mean(-2)
    kinds = set()
    for b in range(g.shape[1]):
        for k in event_steps(r, b):
            assert np.linalg.norm(centroid[k, b] - centroid[k - 1, b]) > 1e-3  # centre redrawn
            # formation type and orientation, seen through its extent per axis in units of spacing
            kinds.add(tuple(np.round(np.ptp(g[k, b], axis=0) / d[k, b], 3)))
    assert len(kinds) == 8  # all eight formation types occur


def test_dynamic_formations_shrink_and_expand():
    r = rollout("dynamic_formations", seconds=30.0)
    s = min_pair_dist(r["goals"])  # = current spacing (closest pair of a unit formation is 1 apart)
    assert s.min() >= -1e-9 and s.max() <= 1.0 + 1e-9
    ds = np.diff(s, axis=0) / DT
    for b in range(s.shape[1]):
        assert (ds[:, b] > 0.05).any() and (ds[:, b] < -0.05).any()  # grows and shrinks
        moving = np.abs(ds[:, b]) > 1e-6
        assert np.all(np.abs(ds[moving, b]) <= 0.3 + 1e-6)
    # the shape is kept: goals = centre + unit offsets * spacing
    c = r["aux"][..., None, 0:3]
    np.testing.assert_allclose(r["goals"], c + r["offsets"] * s[..., None, None], atol=1e-9)
    # goal_vel is the time derivative (central differences, away from the reversals)
    fd = (r["goals"][2:] - r["goals"][:-2]) / (2 * DT)
    smooth = np.abs(np.diff(ds, axis=0)) < 1e-6
    np.testing.assert_allclose(fd[smooth], r["goal_vel"][1:-1][smooth], atol=1e-6)


def test_swap_goals_permutes_same_set():
    r = rollout("swap_goals")
    assert_periods(r)
    g = r["goals"]
    assert np.all(r["goal_vel"] == 0)
    d = min_pair_dist(g[0])
    assert d.min() >= 0.4 - 1e-9 and d.max() <= 0.8 + 1e-9
    for b in range(g.shape[1]):
        ref = np.sort(g[0, b].round(9).view([("", g.dtype)] * 3).ravel())
        for k in event_steps(r, b):
            assert changes(g)[k - 1, b].sum() >= 2  # goals really move between quads
            got = np.sort(g[k, b].round(9).view([("", g.dtype)] * 3).ravel())
            np.testing.assert_array_equal(got, ref)  # same goal set


def test_swarm_vs_swarm_halves_swap_centres():
    r = rollout("swarm_vs_swarm")
    assert_periods(r)
    g = r["goals"]
    ca, cb = g[..., :4, :].mean(-2), g[..., 4:, :].mean(-2)
    sep = np.linalg.norm(ca - cb, axis=-1)
    assert np.median(sep[0]) >= 2.0
    for b in range(g.shape[1]):
        for k in event_steps(r, b):
            np.testing.assert_allclose(ca[k, b], cb[k - 1, b], atol=1e-9)
            np.testing.assert_allclose(cb[k, b], ca[k - 1, b], atol=1e-9)
    d = min_pair_dist(g[:, :, :4])
    assert d.min() >= 0.25 - 1e-9


def test_ep_lissajous3d_closed_form_and_derivative():
    r = rollout("ep_lissajous3D", worlds=2)
    t = r["t"][:, None]
    ref = np.stack([-2 + 1.0 * np.sin(0.4 * t), 0.6 * np.sin(0.8 * t + np.pi / 2),
                    2 + 0.3 * np.cos(0.8 * t + np.pi / 2)], -1)
    for i in range(8):
        np.testing.assert_allclose(r["goals"][:, :, i], np.broadcast_to(ref, (len(t), 2, 3)), atol=1e-12)
    fd = (r["goals"][2:] - r["goals"][:-2]) / (2 * DT)
    np.testing.assert_allclose(r["goal_vel"][1:-1], fd, atol=1e-4)


def test_ep_rand_bezier_segments_every_5s():
    r = rollout("ep_rand_bezier")
    g = r["goals"][:, :, 0]
    np.testing.assert_array_equal(r["goals"], np.broadcast_to(g[:, :, None], r["goals"].shape))
    ends = g[::500]  # t = 0, 5, 10, 15 s: segment end points
    d = np.linalg.norm(np.diff(ends, axis=0), axis=-1)
    assert d.min() >= 5.0 - 1e-9 and d.max() <= 10.0 + 1e-9, d
    # continuous path, goal_vel = derivative, constant acceleration within each 5 s segment
    v = r["goal_vel"][:, :, 0]
    fd = (g[2:] - g[:-2]) / (2 * DT)
    inner = np.ones(len(fd), bool)
    inner[[499 - 1, 499, 999 - 1, 999]] = False  # central differences across the joins
    np.testing.assert_allclose(v[1:-1][inner], fd[inner], atol=1e-6)
    acc = np.diff(v, axis=0) / DT
    for seg in range(3):
        a = acc[seg * 500:seg * 500 + 499]  # acc[500 k - 1] straddles the join
        np.testing.assert_allclose(a, np.broadcast_to(a[:1], a.shape), atol=1e-6)
    assert np.abs(acc[500] - acc[498]).min() > 1e-6  # a new curve after 5 s
    np.testing.assert_allclose(r["next_event"][0:500], 5.0)  # t < 5 s
    np.testing.assert_allclose(r["next_event"][500:1000], 10.0)


def test_run_away_two_quads_every_second():
    r = rollout("run_away", seconds=10.0)
    ch = changes(r["goals"])  # (T, B, N)
    k_event = np.arange(100, 1001, 100)  # t = 1, 2, ..., 10 s
    is_event = np.zeros(len(ch), bool)
    is_event[k_event - 1] = True
    assert not ch[~is_event].any()
    np.testing.assert_array_equal(ch[is_event].sum(-1), 2)  # exactly two quads per event
    # they take goals of the formation (goals another quad had at the start)
    start = r["goals"][0]
    for k in k_event:
        d = np.linalg.norm(r["goals"][k][:, :, None] - start[:, None], axis=-1).min(-1)
        np.testing.assert_allclose(d, 0.0, atol=1e-12)
    d = min_pair_dist(start)
    assert d.min() >= 0.25 - 1e-9 and d.max() <= 0.5 + 1e-9


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("n", [8, 1])
def test_mix_draws_uniformly_and_runs_the_drawn_scenario(n):
    r = rollout("mix", n=n, worlds=270, seconds=6.0, seed=5)
    kinds = r["kind"][0]
    allowed = MIX_CHOICES if n > 1 else MIX_CHOICES_SINGLE
    counts = np.bincount(kinds, minlength=len(MIX_CHOICES))
    assert set(np.nonzero(counts)[0]) == set(range(len(allowed)))  # all allowed, none other
    assert counts.max() < 3 * counts[counts > 0].min()  # roughly uniform
    assert np.all(r["kind"] == kinds)  # fixed for the whole episode
    # each world follows exactly the drawn scenario with the same uniforms
    cfg = r["cfg"]
    rng = np.random.default_rng(5)
    mix = get_scenario("mix")
    m = mix.num_uniforms(n)
    us = [rng.uniform(size=(270, m)) for _ in range(601)]
    for i, name in enumerate(allowed):
        w = kinds == i
        sc = get_scenario(name)
        k = sc.num_uniforms(n)
        s = sc.init(cfg, us[0][w, 1:1 + k])
        np.testing.assert_array_equal(s.goals, r["goals"][0, w])
        for step in range(1, 601):
            s = sc.step(cfg, s, np.full(w.sum(), step * DT), np.zeros((w.sum(), n, 3)), us[step][w, 1:1 + k])
        np.testing.assert_array_equal(s.goals, r["goals"][-1, w])
        np.testing.assert_array_equal(s.goal_vel, r["goal_vel"][-1, w])


def test_mix_env_picks_different_scenarios_across_resets():
    env = QuadSwarmEnv(EnvConfig(num_quads=8, scenario="mix"))
    seen = set()
    for seed in range(40):
        env.reset(seed=seed)
        seen.add(int(env.core.sstate.kind[0]))
    assert len(seen) >= 6 and seen <= set(range(9))
    env1 = QuadSwarmEnv(EnvConfig(num_quads=1, scenario="mix"))
    seen1 = set()
    for seed in range(40):
        env1.reset(seed=seed)
        seen1.add(int(env1.core.sstate.kind[0]))
    assert seen1 == set(range(5))


# ---------------------------------------------------------------- reset-goals contract


def test_given_goals_kept_by_static_and_held_until_event():
    G = np.random.default_rng(1).uniform([-3, -3, 1], [3, 3, 4], size=(4, 3))
    for name in ("static_same_goal", "static_diff_goal"):
        env = QuadSwarmEnv(EnvConfig(num_quads=4, scenario=name))
        _, info = env.reset(seed=0, options={"state": {"goals": G}})
        np.testing.assert_array_equal(info["goals"], G)
        for _ in range(200):
            info = env.step(np.full((4, 4), HOVER))[-1]
        np.testing.assert_array_equal(info["goals"], G)
    env = QuadSwarmEnv(EnvConfig(num_quads=4, scenario="swap_goals"))
    env.reset(seed=0, options={"state": {"goals": G}})
    first_event = float(env.core.sstate.next_event[0])
    assert 4.0 <= first_event <= 6.0
    for k in range(1, 700):
        info = env.step(np.full((4, 4), HOVER))[-1]
        if k * DT < first_event - 1e-3:
            np.testing.assert_array_equal(info["goals"], G)
    # after the swap: the given goals, permuted
    np.testing.assert_array_equal(np.sort(info["goals"], axis=0), np.sort(G, axis=0))
    assert not np.array_equal(info["goals"], G)


# ---------------------------------------------------------------- JAX == NumPy


def test_jit_matches_numpy():
    """init + three steps under jax.jit(jax.vmap(...)) (float32) equal NumPy (float64) for the same
    uniforms. ``mix`` with one world per sub-scenario covers nine scenarios; ``run_away`` is the
    tenth, and ``static_same_goal`` sits inside mix too. One compile."""
    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    n = 8
    times = np.array([1.0, 6.0, 12.5], np.float32)  # run_away at 1 s; 4-6 s events by 6 s; again by 12.5 s
    names = ("mix", "run_away")
    scs = [get_scenario(name) for name in names]
    cfgs = [EnvConfig(num_quads=n, scenario=name) for name in names]
    worlds = len(MIX_CHOICES)
    rng = np.random.default_rng(11)
    us = [rng.uniform(size=(1 + len(times), worlds, sc.num_uniforms(n))).astype(np.float32) for sc in scs]
    us[0][0, :, 0] = (np.arange(worlds) + 0.5) / worlds  # mix: world w runs MIX_CHOICES[w]

    def run_all(us_one):  # one world; vmapped over worlds below
        out = []
        for sc, cfg, u in zip(scs, cfgs, us_one):
            def body(s, x, sc=sc, cfg=cfg):
                t, ut = x
                return sc.step(cfg, s, t, jnp.zeros((n, 3), ut.dtype), ut), None

            s, _ = jax.lax.scan(body, sc.init(cfg, u[0]), (jnp.asarray(times), u[1:]))
            out.append(s)
        return out

    got = jax.jit(jax.vmap(run_all, in_axes=(1,)))([jnp.asarray(u) for u in us])
    np.testing.assert_array_equal(np.asarray(got[0].kind), np.arange(worlds))
    for name, sc, cfg, u, s_j in zip(names, scs, cfgs, us, got):
        u64 = u.astype(np.float64)
        s = sc.init(cfg, u64[0])
        for i, t in enumerate(times):
            s = sc.step(cfg, s, np.full(worlds, float(t)), np.zeros((worlds, n, 3)), u64[i + 1])
        for field in s._fields:
            a, b = np.asarray(getattr(s_j, field)), getattr(s, field)
            assert a.shape == b.shape, (name, field)
            if field in ("kind", "slots"):
                np.testing.assert_array_equal(a, b, err_msg=f"{name}.{field}")
            else:
                np.testing.assert_allclose(a, b, rtol=1e-4, atol=2e-4, err_msg=f"{name}.{field}")
        assert np.any(s.next_event > 6.0)  # events did fire


@pytest.mark.parametrize("name", NAMES)
def test_unbatched_world_matches_batched(name):
    """Batch shape () (how the MJX env calls a scenario under vmap) gives the batched result."""
    n = 5
    cfg = EnvConfig(num_quads=n, scenario=name)
    sc = get_scenario(name)
    rng = np.random.default_rng(4)
    us = rng.uniform(size=(801, 2, sc.num_uniforms(n)))
    sb, s1 = sc.init(cfg, us[0]), sc.init(cfg, us[0, 0])
    for k in range(1, 801):
        sb = sc.step(cfg, sb, np.full(2, k * DT), np.zeros((2, n, 3)), us[k])
        s1 = sc.step(cfg, s1, np.asarray(k * DT), np.zeros((n, 3)), us[k, 0])
    for f in sb._fields:
        np.testing.assert_array_equal(getattr(s1, f), getattr(sb, f)[0], err_msg=f)


def test_no_numpy_warnings_in_scenarios():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for name in NAMES:
            rollout(name, n=3, worlds=4, seconds=7.0)
