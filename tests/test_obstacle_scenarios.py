"""Obstacle scenarios (SPEC_obstacles A.5): spawn and goal rules, mix with obstacles, jit/vmap."""

from __future__ import annotations

import numpy as np
import pytest

import quadswarm_mj
from quadswarm_mj import EnvConfig, ObstacleConfig, get_scenario
from quadswarm_mj import obstacles as ob
from quadswarm_mj.random_draws import NumpySampler
from quadswarm_mj.scenarios import obstacle_scenarios as osc
from quadswarm_mj.scenarios.mix import MIX_CHOICES, OBSTACLE_MIX_CHOICES

O_NAMES = ["o_random", "o_static_same_goal", "o_dynamic_same_goal", "o_swap_goals", "o_ep_rand_bezier"]
ARM = 0.04596194
DT = 0.01


def _maps(cfg: EnvConfig, b: int, seed: int = 0) -> ob.ObstacleMap:
    m, _ = ob.generate_map(cfg.obstacles, NumpySampler(np.random.default_rng(seed)).draw(
        ob.map_draw_spec(cfg.obstacles), (b,)))
    return m


def _min_clearance(points: np.ndarray, m: ob.ObstacleMap) -> np.ndarray:
    """(B, K) 2D distance from each point to the nearest valid column surface (m)."""
    d = np.linalg.norm(points[..., :, None, :2] - m.centres[..., None, :, :], axis=-1)
    d = np.where(m.valid[..., None, :], d, np.inf)
    return d.min(-1) - m.radius[..., None]


def _run(name: str, n: int = 4, b: int = 40, steps: int = 0, seed: int = 0, **ocfg):
    cfg = EnvConfig(num_quads=n, scenario=name, obstacles=ObstacleConfig(**ocfg))
    scn = get_scenario(name)
    m = _maps(cfg, b, seed)
    rng = np.random.default_rng(seed + 1)
    nu = osc.scenario_num_uniforms(scn, cfg)
    s = osc.scenario_init(scn, cfg, rng.uniform(size=(b, nu)), m)
    hist = [s]
    for k in range(1, steps + 1):
        s = osc.scenario_step(scn, cfg, s, np.full(b, k * DT), None, rng.uniform(size=(b, nu)), m)
        hist.append(s)
    return cfg, scn, m, hist


# ----------------------------------------------------------------------------- registry, config


def test_registered_and_require_obstacles():
    names = quadswarm_mj.list_scenarios()
    assert names[-6:] == O_NAMES + ["mix"]
    for name in O_NAMES:
        with pytest.raises(ValueError) as e:
            EnvConfig(scenario=name)
        assert name in str(e.value) and "obstacles=ObstacleConfig()" in str(e.value)
        assert EnvConfig(scenario=name, obstacles=ObstacleConfig()).scenario == name


# ----------------------------------------------------------------------------------- spawns


@pytest.mark.parametrize("n", [1, 8])
def test_spawn_free_cells_jitter_height(n):
    cfg = EnvConfig(num_quads=n, scenario="o_random", obstacles=ObstacleConfig(density_random=True, size_random=True))
    b = 200
    m = _maps(cfg, b, 3)
    u = np.random.default_rng(4).uniform(size=(b, osc.scenario_spawn_uniforms(cfg)))
    sp = osc.scenario_spawn(cfg, None, u, m)
    pos = sp["pos"]
    assert pos.shape == (b, n, 3) and sp["yaw"].shape == (b, n)
    assert np.all(_min_clearance(pos, m) > ARM)  # never inside (or touching) a column
    cc = ob.cell_centers(cfg.obstacles)
    off = np.abs(pos[..., None, :2] - cc).max(-1).min(-1)
    assert np.all(off <= 0.1 + 1e-12)  # a cell centre + U(-0.1, 0.1)
    assert np.all(pos[..., 2] >= 0.75) and np.all(pos[..., 2] <= 3.1)
    if n > 1:
        d = np.linalg.norm(pos[:, :, None, :2] - pos[:, None, :, :2], axis=-1) + 10 * np.eye(n)
        assert d.min() >= 1.0 - 0.2 * np.sqrt(2) - 1e-9  # distinct cells


def test_spawn_without_obstacles_is_the_base_rule():
    cfg = EnvConfig(num_quads=3)
    assert osc.scenario_spawn_uniforms(cfg) == 12
    goals = np.zeros((3, 3)) + np.array([0.0, 0.0, 2.0])
    sp = osc.scenario_spawn(cfg, goals, np.full(12, 0.5))
    np.testing.assert_allclose(sp["pos"], goals)


# ------------------------------------------------------------------------------------ goals


@pytest.mark.parametrize("name", O_NAMES)
def test_goals_never_inside_a_column_and_inside_room(name):
    cfg, _, m, hist = _run(name, n=4, b=30, steps=700)
    lo, hi = np.array(cfg.room_low), np.array(cfg.room_high)
    for s in hist[::7]:
        assert np.all(s.goals >= lo) and np.all(s.goals <= hi)
        if name != "o_ep_rand_bezier":  # the Bezier goal ignores obstacles (A.5)
            assert np.all(_min_clearance(s.goals, m) > ARM)


def test_o_random_distinct_free_cells():
    cfg, scn, m, hist = _run("o_random", n=8, b=50, steps=300)
    g = hist[0].goals
    assert np.all(_min_clearance(g, m) > 0.5)
    assert np.all((g[..., 2] >= 1.0) & (g[..., 2] <= 3.0))
    np.testing.assert_allclose(np.mod(g[..., :2], 1.0), 0.5)
    d = np.linalg.norm(g[:, :, None, :2] - g[:, None, :, :2], axis=-1) + 10 * np.eye(8)
    assert d.min() >= 1.0 - 1e-9
    np.testing.assert_array_equal(hist[-1].goals, g)  # never changes
    assert scn.approach_goal_metric == 0.5


def _brute_max_square(free: np.ndarray, gx: int, gy: int) -> int:
    f = free.reshape(gy, gx)
    best, best_s = 0, 0
    for i in range(gy):
        for j in range(gx):
            s = 0
            while i - s >= 0 and j - s >= 0 and f[i - s:i + 1, j - s:j + 1].all():
                s += 1
            if s > best_s:
                best_s, best = s, (i - (s - 1) // 2) * gx + (j - (s - 1) // 2)
    return best


def test_max_square_cell_matches_brute_force():
    cfg = EnvConfig(obstacles=ObstacleConfig(area=(8.0, 6.0)))
    rng = np.random.default_rng(0)
    free = rng.uniform(size=(300, 48)) > rng.uniform(0.1, 0.7, (300, 1))
    got = osc.max_square_cell(cfg, free)
    want = [_brute_max_square(f, 8, 6) for f in free]
    np.testing.assert_array_equal(got, want)
    assert osc.max_square_cell(cfg, np.zeros(48, bool)) == 0


def test_o_static_same_goal_at_largest_free_square():
    cfg, scn, m, hist = _run("o_static_same_goal", n=4, b=30, steps=200)
    g = hist[0].goals
    assert np.all(g == g[:, :1])
    free = ob.free_cells(cfg.obstacles, m, 0.2)
    cells = osc.max_square_cell(cfg, free)
    np.testing.assert_allclose(g[:, 0, :2], ob.cell_centers(cfg.obstacles)[cells])
    assert np.all((g[..., 2] >= 1.5) & (g[..., 2] <= 3.0))
    np.testing.assert_array_equal(hist[-1].goals, g)
    assert scn.approach_goal_metric == 1.0


def test_o_dynamic_same_goal_jumps():
    cfg, _, m, hist = _run("o_dynamic_same_goal", n=3, b=20, steps=1300)
    goals = np.stack([s.goals for s in hist])  # (T, B, N, 3)
    assert np.all(goals == goals[:, :, :1])
    moved = np.any(goals[1:] != goals[:-1], axis=(-1, -2))  # (T - 1, B) jump at step k + 1
    assert moved[0].mean() > 0.5  # tick 1 is an event (a goal may repeat its cell by chance)
    for w in range(20):
        ticks = np.flatnonzero(moved[:, w]) + 1
        gaps = np.diff(ticks)
        assert np.all((gaps >= 400) & (gaps < 600)) and len(ticks) >= 2
    jumps = np.linalg.norm(goals[1:, :, 0] - goals[:-1, :, 0], axis=-1)[moved]
    assert np.mean(jumps <= 4.0) > 0.95  # within 4 m (the nearest candidate when none is)
    assert np.all((goals[2:, ..., 2] >= 0.75) & (goals[2:, ..., 2] <= 3.0))


def test_o_swap_goals_formation_and_shuffles():
    cfg, _, m, hist = _run("o_swap_goals", n=8, b=10, steps=1300)
    g0 = hist[0].goals
    free = ob.free_cells(cfg.obstacles, m, 0.2)
    centre = ob.cell_centers(cfg.obstacles)[osc.max_square_cell(cfg, free)]
    spread = np.linalg.norm(g0[..., :2] - centre[:, None], axis=-1)
    assert np.all(spread < 3.0)
    swaps = np.zeros(10, int)
    for a, b in zip(hist[:-1], hist[1:]):
        changed = np.any(a.goals != b.goals, axis=(-1, -2))
        swaps += changed
        for w in range(10):  # a permutation of the same goals
            np.testing.assert_allclose(np.sort(a.goals[w], axis=0), np.sort(b.goals[w], axis=0))
    assert np.all(swaps >= 2)  # every U(4, 6) s over 13 s (a shuffle may be the identity: rare for N = 8)


def test_o_ep_rand_bezier_curve():
    cfg, _, m, hist = _run("o_ep_rand_bezier", n=2, b=20, steps=1250, seed=2)
    g = np.stack([s.goals[:, 0] for s in hist])  # (T, B, 3)
    assert np.all(_min_clearance(hist[0].goals, m) > ARM)  # starts at a free cell
    a = hist[1].aux
    # a segment starts at tick 1 from the start goal; goal = curve[tick % 600] afterwards
    np.testing.assert_allclose(a[:, 0:3], g[0])
    k = 300
    tau = k / 599
    want = (1 - tau) ** 2 * a[:, 0:3] + 2 * (1 - tau) * tau * a[:, 3:6] + tau**2 * a[:, 6:9]
    np.testing.assert_allclose(g[k], want, atol=1e-12)
    ok = np.all((a[:, 3:9].reshape(-1, 2, 3)[..., 2] > 2.0) & (a[:, 3:9].reshape(-1, 2, 3)[..., 2] < 2.5), -1)
    assert ok.mean() > 0.8
    np.testing.assert_allclose(hist[600].aux[:, 0:3], g[599])  # tick 600: next segment from the goal
    step = np.linalg.norm(np.diff(g[2:599], axis=0), axis=-1)
    assert step.max() < 0.1  # continuous between events
    np.testing.assert_allclose(hist[300].goal_vel[:, 0], (g[301] - g[299]) / (2 * DT), rtol=0.02, atol=1e-3)


# -------------------------------------------------------------------------------------- mix


@pytest.mark.parametrize("n", [1, 6])
def test_mix_with_obstacles_draws_o_random_and_static(n):
    cfg, scn, m, hist = _run("mix", n=n, b=200, steps=5)
    kinds = set(np.unique(hist[0].kind))
    assert kinds == ({0} if n == 1 else {0, 1})
    assert OBSTACLE_MIX_CHOICES == ("o_random", "o_static_same_goal")
    assert np.all(_min_clearance(hist[-1].goals, m) > ARM)
    thr = osc.approach_threshold(scn, cfg, hist[0])
    np.testing.assert_allclose(thr, np.where(hist[0].kind == 0, 0.5, 1.0))


def test_mix_without_obstacles_unchanged():
    cfg = EnvConfig(num_quads=4, scenario="mix")
    scn = get_scenario("mix")
    assert osc.scenario_num_uniforms(scn, cfg) == scn.num_uniforms(4)
    assert all(c.name in MIX_CHOICES for c in scn.choices(4))
    s = osc.scenario_init(scn, cfg, np.random.default_rng(0).uniform(size=(5, scn.num_uniforms(4))))
    assert s.goals.shape == (5, 4, 3)


# ---------------------------------------------------------------------------------- jit, vmap


@pytest.mark.parametrize("name", O_NAMES + ["mix"])
def test_jit_vmap_matches_numpy(name):
    jax = pytest.importorskip("jax")
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    try:
        n, b, steps = 3, 4, 3
        cfg = EnvConfig(num_quads=n, scenario=name, obstacles=ObstacleConfig())
        scn = get_scenario(name)
        m = _maps(cfg, b, 5)
        nu = osc.scenario_num_uniforms(scn, cfg)
        rng = np.random.default_rng(6)
        u0 = rng.uniform(size=(b, nu))
        us = rng.uniform(size=(steps, b, nu))
        usp = rng.uniform(size=(b, osc.scenario_spawn_uniforms(cfg)))
        ts = np.arange(1, steps + 1) * 0.01 + np.array([0, 0, 5.99])[:steps]  # include a late event time

        def run(m, u0, us, usp):
            s = osc.scenario_init(scn, cfg, u0, m)
            out = [s.goals]
            for k in range(steps):
                xp = np if isinstance(u0, np.ndarray) else jnp
                s = osc.scenario_step(scn, cfg, s, xp.zeros(u0.shape[:-1]) + ts[k], None, us[k], m)
                out.append(s.goals)
            sp = osc.scenario_spawn(cfg, None, usp, m)
            return out, sp["pos"]

        want_g, want_p = run(m, u0, us, usp)

        def one(c, v, r, u0, us, usp):  # one world, vmapped over worlds
            return run(ob.ObstacleMap(c, v, r), u0, us, usp)

        f = jax.jit(jax.vmap(one, in_axes=(0, 0, 0, 0, 1, 0)))
        got_g, got_p = f(jnp.asarray(m.centres), jnp.asarray(m.valid), jnp.asarray(m.radius), jnp.asarray(u0),
                         jnp.asarray(us), jnp.asarray(usp))
        for a, g in zip(want_g, got_g):
            np.testing.assert_allclose(np.asarray(g), a, atol=1e-9)
        np.testing.assert_allclose(np.asarray(got_p), want_p, atol=1e-9)
    finally:
        jax.config.update("jax_enable_x64", False)
