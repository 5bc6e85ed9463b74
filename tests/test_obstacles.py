"""Obstacles (SPEC_obstacles A.1-A.4, D.1-D.4): config, map, features, contacts, response, penalty, metrics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, ObstacleConfig
from quadswarm_mj import obstacles as ob
from quadswarm_mj.random_draws import MeanSampler, NumpySampler

ARM = 0.04596194


def _draws(n: int, seed: int | None = 0, mean: bool = False, batch: tuple[int, ...] = ()) -> dict:
    spec = ob.response_draw_spec(n)
    return MeanSampler().draw(spec, batch) if mean else NumpySampler(np.random.default_rng(seed)).draw(spec, batch)


# ---------------------------------------------------------------------------------- config


def test_config_defaults_and_obs_dim():
    o = ObstacleConfig()
    assert (o.density, o.size, o.area, o.cell) == (0.2, 0.6, (8.0, 8.0), 1.0)
    assert o.grid == (8, 8) and o.num_columns() == 12 and o.slots == 12
    base = EnvConfig()
    cfg = EnvConfig(obstacles=o)
    assert base.obstacles is None
    assert cfg.obs_dim == base.obs_dim + 9
    assert EnvConfig(obstacles={"density": 0.1}).obstacles == ObstacleConfig(density=0.1)
    nf = cfg.without_noise()
    assert nf.obstacles == o and nf.noise.stochastic_collisions is False


def test_config_randomization_sets_and_slots():
    o = ObstacleConfig(density_random=True, size_random=True)
    assert [o.num_columns(d) for d in o.density_values] == [3, 6, 9, 12]
    assert o.size_values == (0.3, 0.4, 0.5) and o.max_size == 0.5 and o.slots == 12
    assert ObstacleConfig(density=0.05, max_columns=20).slots == 20


@pytest.mark.parametrize("kwargs,word", [
    ({"density": 1.5}, "obstacles.density"), ({"density": -0.1}, "obstacles.density"),
    ({"size": 0.0}, "obstacles.size"), ({"size": 1.0}, "obstacles.size"), ({"size": 1.2, "cell": 1.0}, "cell"),
    ({"area": (8.0,)}, "obstacles.area"), ({"area": (0.5, 8.0)}, "obstacles.area[0]"),
    ({"size_values": (0.3, 1.5)}, "obstacles.size_values[1]"), ({"max_columns": 3}, "obstacles.max_columns"),
    ({"density_random": 1}, "obstacles.density_random"), ({"collision_reward": -1.0}, "obstacles.collision_reward"),
])
def test_bad_obstacle_config_rejected(kwargs, word):
    with pytest.raises(ValueError) as e:
        ObstacleConfig(**kwargs)
    assert word in str(e.value)
    with pytest.raises(ValueError) as e2:
        EnvConfig(obstacles=kwargs)
    assert word in str(e2.value)


def test_area_must_fit_room_and_leave_free_cells():
    with pytest.raises(ValueError, match=r"obstacles.area\[1\].*room_size\[1\]"):
        EnvConfig(room_size=(10.0, 6.0, 10.0), obstacles={"area": (8.0, 8.0)})
    with pytest.raises(ValueError, match="free cells"):
        EnvConfig(num_quads=8, obstacles={"area": (3.0, 3.0), "density": 0.5})
    with pytest.raises(ValueError, match="obstacles must be"):
        EnvConfig(obstacles=0.2)


# ------------------------------------------------------------------------------------- map (D.3)


def test_map_layout_d3():
    o = ObstacleConfig()
    cc = ob.cell_centers(o)
    for r in range(8):
        for c in range(8):
            np.testing.assert_allclose(cc[r * o.grid[0] + c], (c - 3.5, 3.5 - r))
    rng = np.random.default_rng(3)
    for _ in range(20):
        m, ids = ob.generate_map(o, NumpySampler(rng).draw(ob.map_draw_spec(o)))
        centres = ob.active_centres(m)
        assert centres.shape == (12, 2) and m.valid.all()
        assert len({tuple(x) for x in centres}) == 12  # distinct cells
        np.testing.assert_allclose(np.mod(centres, 1.0), 0.5)  # half-integer centres
        assert np.all(np.abs(centres) <= 3.5)
        np.testing.assert_allclose(centres, cc[ids])


def test_map_density_size_randomization_uses_value_sets():
    o = ObstacleConfig(density_random=True, size_random=True)
    d = NumpySampler(np.random.default_rng(0)).draw(ob.map_draw_spec(o), (400,))
    m, _ = ob.generate_map(o, d)
    counts = m.valid.sum(-1)
    assert set(np.unique(counts)) == {3, 6, 9, 12}
    assert set(np.round(np.unique(2 * m.radius), 6)) == {0.3, 0.4, 0.5}


def test_map_cells_uniform_without_replacement():
    o = ObstacleConfig()
    d = NumpySampler(np.random.default_rng(1)).draw(ob.map_draw_spec(o), (4000,))
    _, ids = ob.generate_map(o, d)
    freq = np.bincount(ids.ravel(), minlength=64) / 4000
    np.testing.assert_allclose(freq, 12 / 64, atol=0.03)


def test_map_from_centres_pads_and_rejects():
    o = ObstacleConfig()
    m = ob.map_from_centres(o, np.array([[0.0, 0.0], [3.0, 3.0]]))
    assert m.centres.shape == (12, 2) and m.valid.sum() == 2 and float(m.radius) == 0.3
    np.testing.assert_allclose(ob.active_centres(m), [[0, 0], [3, 3]])
    with pytest.raises(ValueError, match="column slots"):
        ob.map_from_centres(o, np.zeros((13, 2)))
    with pytest.raises(ValueError, match=r"\(M, 2\)"):
        ob.map_from_centres(o, np.zeros(4))


def test_free_cells_match_generated_map():
    o = ObstacleConfig()
    m, ids = ob.generate_map(o, NumpySampler(np.random.default_rng(5)).draw(ob.map_draw_spec(o)))
    free = ob.free_cells(o, m, clearance=0.2)
    expect = np.ones(64, bool)
    expect[ids] = False
    np.testing.assert_array_equal(free, expect)


# -------------------------------------------------------------------------------- features (D.1)


def test_features_d1():
    f = ob.obstacle_features(np.zeros((1, 3)), np.array([[0.2, 0.0]]), np.array([True]), np.float64(0.3))
    want = [math.hypot(x - 0.2, y) - 0.3 for x in (-0.1, 0.0, 0.1) for y in (-0.1, 0.0, 0.1)]
    np.testing.assert_allclose(f[0], want, atol=1e-12)
    assert f[0, 4] == pytest.approx(-0.1)  # centre index 4, negative inside


def test_features_nearest_valid_column_and_placeholder():
    pos = np.array([[1.0, 0.0, 2.0]])
    centres = np.array([[1.5, 0.0], [1.2, 0.0], [9.0, 9.0]])
    f = ob.obstacle_features(pos, centres, np.array([True, False, True]), np.float64(0.3))
    assert f[0, 4] == pytest.approx(0.5 - 0.3)  # the invalid closer column is ignored
    f0 = ob.obstacle_features(pos, centres, np.zeros(3, bool), np.float64(0.3))
    np.testing.assert_allclose(f0, 100.0 - 0.3)
    lo, hi = ob.feature_bounds(EnvConfig(obstacles={}))
    assert lo.shape == hi.shape == (9,) and np.all(np.isfinite(hi)) and np.all(hi >= 100) and np.all(lo < -0.5)


# ------------------------------------------------------------------- detection, response (D.2)


def test_collision_normal_d2():
    n = ob.collision_normal(np.zeros(3), np.array([0.5, 0.5]))
    np.testing.assert_allclose(n, [-math.sqrt(0.5), -math.sqrt(0.5), 0.0])
    np.testing.assert_allclose(ob.collision_normal(np.array([0.5, 0.5, 1.0]), np.array([0.5, 0.5])), 0.0)


def test_detection_threshold_first_hit_any_height():
    r = 0.3
    thr = ARM + r
    centres = np.array([[5.0, 5.0], [0.0, 0.0], [0.1, 0.0]])
    valid = np.ones(3, bool)
    pos = np.array([[-thr + 1e-9, 0.0, 0.05], [-thr - 1e-6, 0.0, 2.0], [0.0, 0.0, 9.0]])
    contact, index, centre = ob.detect(pos, centres, valid, np.float64(r), ARM)
    np.testing.assert_array_equal(contact, [True, False, True])
    assert index[0] == 1 and index[2] == 1  # first hit in index order (columns 1 and 2 both hit)
    np.testing.assert_allclose(centre[2], [0.0, 0.0])


def test_response_mean_draws_half_speed_along_normal():
    pos = np.array([[0.0, 0.0, 2.0]])
    vel = np.array([[1.0, 0.0, 0.3]])
    centre = np.array([[0.3, 0.3]])
    v, w = ob.obstacle_response(pos, vel, np.ones((1, 3)), centre, np.float64(0.3), np.array([True]),
                                _draws(1, mean=True))
    n = np.array([-math.sqrt(0.5), -math.sqrt(0.5), 0.0])
    np.testing.assert_allclose(v[0], 0.5 * np.linalg.norm(vel[0]) * n, atol=1e-12)
    np.testing.assert_allclose(w, 1.0)  # no kick with mean draws


def test_response_inside_column_keeps_speed_and_stochastic_bounds():
    pos = np.array([[0.1, 0.0, 2.0]])
    vel = np.array([[-1.0, 0.0, 0.0]])
    v, _ = ob.obstacle_response(pos, vel, np.zeros((1, 3)), np.zeros((1, 2)), np.float64(0.3), np.array([True]),
                                _draws(1, mean=True))
    np.testing.assert_allclose(v[0], [1.0, 0.0, 0.0], atol=1e-12)  # 2D distance 0.1 < 0.3: decay 1
    # random draws: speed <= |v|, pointing away from the column, kick in [pi/2, pi]
    rng = np.random.default_rng(0)
    n = 2000
    p = np.stack([rng.uniform(0.32, 0.34, n), np.zeros(n), np.full(n, 2.0)], -1)
    vel = rng.normal(size=(n, 3))
    d = NumpySampler(rng).draw(ob.response_draw_spec(n))
    v, w = ob.obstacle_response(p, vel, np.zeros((n, 3)), np.zeros((n, 2)), np.float64(0.3), np.ones(n, bool), d)
    sp = np.linalg.norm(v, axis=-1)
    assert np.all(sp <= np.linalg.norm(vel, axis=-1) + 1e-12)
    assert np.all(v[:, 0] > 0)  # accepted noise keeps (v_ref + eta) . n > 0
    km = np.linalg.norm(w, axis=-1)
    assert np.all(km >= math.pi / 2 * (1 - 1e-4)) and np.all(km <= math.pi + 1e-9)  # unit(dir): eps 1e-5
    ratio = sp / np.linalg.norm(vel, axis=-1)
    assert ratio.min() < 0.3 and ratio.max() > 0.7  # the U(0.2, 0.8) decay is used


def test_response_only_new_contacts():
    pos = np.array([[-0.33, 0.0, 2.0], [2.0, 2.0, 2.0]])
    vel = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    centres, valid = np.array([[0.0, 0.0]]), np.array([True])
    out = ob.obstacle_step(pos, vel, np.zeros((2, 3)), np.array([True, False]), centres, valid, np.float64(0.3),
                           ARM, _draws(2, mean=True))
    np.testing.assert_array_equal(out["contact"], [True, False])
    np.testing.assert_array_equal(out["new_contact"], [False, False])
    np.testing.assert_allclose(out["vel"], vel)
    out = ob.obstacle_step(pos, vel, np.zeros((2, 3)), np.zeros(2, bool), centres, valid, np.float64(0.3), ARM,
                           _draws(2, mean=True))
    np.testing.assert_allclose(out["vel"][0], [-0.5, 0.0, 0.0])
    np.testing.assert_allclose(out["vel"][1], vel[1])
    det = ob.obstacle_step(pos, vel, np.zeros((2, 3)), np.zeros(2, bool), centres, valid, np.float64(0.3), ARM,
                           None, respond=False)
    np.testing.assert_array_equal(det["new_contact"], [True, False])
    np.testing.assert_allclose(det["vel"], vel)


# --------------------------------------------------------------------- penalty, metrics (D.4)


def test_contact_dwell_one_penalty_one_kick_one_count_d4():
    o = ObstacleConfig(collision_reward=5.0)
    centres, valid, r = np.array([[0.0, 0.0]]), np.array([True]), np.float64(0.3)
    pos = np.array([[-0.33, 0.0, 2.0]])  # held in contact
    vel, omega = np.zeros((1, 3)), np.zeros((1, 3))
    prev = np.zeros(1, bool)
    om = ob.metrics_init(np.zeros((1,)), (), 1)
    rng = np.random.default_rng(0)
    total, kicks = 0.0, 0
    last = np.full((5, 1), 3.0)
    for k in range(10):
        t = 2.0 + 0.01 * k  # after the grace period
        out = ob.obstacle_step(pos, vel + np.array([[0.5, 0.0, 0.0]]), omega, prev, centres, valid, r, ARM,
                               NumpySampler(rng).draw(ob.response_draw_spec(1)))
        kicks += int(np.any(out["omega"] != omega))
        omega, prev = out["omega"], out["contact"]
        total += float(ob.obstacle_penalty(out["new_contact"], o.collision_reward).sum())
        om = ob.metrics_update(om, t, out["new_contact"], last, 100, 0.5)
    assert total == -5.0 and kicks == 1
    assert om["obstacle_collisions"][0] == 1 and om["obstacle_contacts"][0] == 1


def test_penalty_not_time_scaled_no_grace_and_annealed():
    new = np.array([True, False, True])
    np.testing.assert_allclose(ob.obstacle_penalty(new, 5.0), [-5.0, 0.0, -5.0])
    np.testing.assert_allclose(ob.obstacle_penalty(new, 5.0, anneal=0.5), [-2.5, 0.0, -2.5])


def test_metrics_grace_rate_success():
    om = ob.metrics_init(np.zeros(3), (), 3)
    near = np.full((5, 3), 0.2)
    om = ob.metrics_update(om, 0.5, np.array([True, False, False]), near, 10, 0.5)  # before the grace period
    assert om["obstacle_contacts"][0] == 1 and om["obstacle_collisions"][0] == 0
    om = ob.metrics_update(om, 1.5, np.array([False, True, False]), near, 11, 0.5)
    quad_coll = np.array([0.0, 0.0, 0.0])
    res = ob.metrics_finalize(om, quad_coll)
    assert res["obstacle_collisions"] == pytest.approx(1 / 3)
    assert res["collision_rate"] == pytest.approx(1 / 3)
    assert res["success"] == pytest.approx(2 / 3)  # quad 0's contact was in the grace period
    res = ob.metrics_finalize(om, np.array([1.0, 0.0, 0.0]))
    assert res["collision_rate"] == pytest.approx(2 / 3) and res["success"] == pytest.approx(1 / 3)
    # goal not reached: no success; the latch needs 5 steps
    om2 = ob.metrics_update(ob.metrics_init(np.zeros(3), (), 3), 2.0, np.zeros(3, bool), near, 3, 0.5)
    assert ob.metrics_finalize(om2, quad_coll)["success"] == 0.0
    om3 = ob.metrics_update(ob.metrics_init(np.zeros(3), (), 3), 2.0, np.zeros(3, bool), near * 5, 10, 0.5)
    assert ob.metrics_finalize(om3, quad_coll)["success"] == 0.0


def test_geom_positions_parks_invalid():
    p = ob.geom_positions(np.array([[1.0, 2.0], [3.0, 4.0]]), np.array([True, False]), 10.0, (0.0, 0.0, -20.0))
    np.testing.assert_allclose(p, [[1, 2, 5], [0, 0, -20]])


# ------------------------------------------------------------------------ NumPy vs jax.jit


def test_numpy_vs_jax_jit():
    jax = pytest.importorskip("jax")
    jax.config.update("jax_enable_x64", True)
    try:
        import jax.numpy as jnp

        o = ObstacleConfig()
        rng = np.random.default_rng(7)
        B, N = 3, 4
        md = NumpySampler(rng).draw(ob.map_draw_spec(o), (B,))
        m_np, ids_np = ob.generate_map(o, md)
        pos = np.concatenate([rng.uniform(-4, 4, (B, N, 2)), rng.uniform(1, 3, (B, N, 1))], -1)
        pos[:, 0, :2] = m_np.centres[:, 0] + np.array([0.32, 0.0])  # guaranteed contacts
        vel, omega = rng.normal(size=(B, N, 3)), rng.normal(size=(B, N, 3))
        prev = np.zeros((B, N), bool)
        dr = NumpySampler(rng).draw(ob.response_draw_spec(N), (B,))

        def run(md, pos, vel, omega, prev, dr):
            m, ids = ob.generate_map(o, md)
            out = ob.obstacle_step(pos, vel, omega, prev, m.centres, m.valid, m.radius, ARM, dr)
            f = ob.obstacle_features(pos, m.centres, m.valid, m.radius)
            free = ob.free_cells(o, m, 0.2)
            pen = ob.obstacle_penalty(out["new_contact"], 5.0)
            return ids, out["vel"], out["omega"], out["contact"], out["new_contact"], f, free, pen

        want = run(md, pos, vel, omega, prev, dr)
        j = lambda d: {k: jnp.asarray(v) for k, v in d.items()}  # noqa: E731
        got = jax.jit(run)(j(md), jnp.asarray(pos), jnp.asarray(vel), jnp.asarray(omega), jnp.asarray(prev), j(dr))
        assert want[4][:, 0].all()
        for a, b in zip(want, got):
            np.testing.assert_allclose(np.asarray(b), a, rtol=1e-12, atol=1e-12)
    finally:
        jax.config.update("jax_enable_x64", False)


# ------------------------------------------------------------------------------ arena, render


def _arena(model_name: str, worlds: int = 1, **ocfg):
    from quadswarm_mj.arena import build_arena

    cfg = EnvConfig(num_quads=1, collision_model=model_name, obstacles=ObstacleConfig(**ocfg))
    return cfg, build_arena(cfg, worlds)


def test_arena_pool_parked_and_collision_bits():
    for cm, bit in (("paper", 0), ("mujoco", 2), ("blend", 2)):
        cfg, a = _arena(cm, worlds=2)
        ids = a.obstacle_geom_ids
        m = a.model
        assert ids.shape == (2, 12) and a.obstacle_name(1, 3) == "w1obst3" and m.geom(int(ids[1, 3])).name == "w1obst3"
        assert np.all(m.geom_type[ids] == 5)  # mjGEOM_CYLINDER
        assert np.all(m.geom_contype[ids] == 0) and np.all(m.geom_conaffinity[ids] == bit)
        hb = m.geom("q0/hitbox" if a.num_worlds == 1 else "w0q0/hitbox").id
        assert (m.geom_contype[hb] & bit) == bit  # hitboxes pair with columns, room geoms never do
        room = [m.geom(g).id for g in ("floor", "wall_px", "ceiling")]
        assert np.all((m.geom_contype[room] & m.geom_conaffinity[ids[0, 0]]) == 0)
        # radius, half height: floor to ceiling
        np.testing.assert_allclose(m.geom_size[ids, :2], np.broadcast_to([0.3, 5.0], ids.shape + (2,)))
        assert np.all(m.body_pos[m.geom_bodyid[ids], 2] + m.geom_size[ids, 1] < 0)  # parked below the floor
        assert np.all(m.body_mocapid[m.geom_bodyid[ids]] == a.obstacle_mocap_ids)
    cfg, a = _arena("paper")
    assert a.obstacle_geom_ids.shape == (1, 12) and a.model.geom(int(a.obstacle_geom_ids[0, 0])).name == "obst0"
    from quadswarm_mj.arena import build_arena

    assert build_arena(EnvConfig(num_quads=1)).obstacle_geom_ids is None


def test_place_obstacles_and_mjx_mocap_pos():
    import mujoco

    from quadswarm_mj.arena import obstacle_mocap_pos, place_obstacles, set_obstacle_radius

    cfg, a = _arena("mujoco", worlds=2, size_random=True)
    m = a.model
    d = mujoco.MjData(m)
    base = d.mocap_pos.copy()
    c = np.zeros((2, 12, 2))
    c[:, 0], c[:, 1] = [1.5, -0.5], [3.5, 3.5]
    v = np.zeros((2, 12), bool)
    v[0, :2], v[1, :1] = True, True
    place_obstacles(a, d.mocap_pos, c, v, 10.0)
    set_obstacle_radius(m, a, np.array([0.25, 0.15]))
    mid, gid = a.obstacle_mocap_ids, a.obstacle_geom_ids
    np.testing.assert_allclose(d.mocap_pos[mid[0, :2]], [[1.5, -0.5, 5.0], [3.5, 3.5, 5.0]])
    np.testing.assert_allclose(d.mocap_pos[mid[1, 0]], [1.5 + a.world_offsets[1, 0], -0.5, 5.0])
    assert d.mocap_pos[mid[1, 1], 2] < 0 and np.all(m.geom_size[gid[1], 0] == 0.15)
    mujoco.mj_forward(m, d)
    np.testing.assert_allclose(d.geom_xpos[gid[0, 0]], [1.5, -0.5, 5.0])
    with pytest.raises(ValueError, match="compiled radius"):
        set_obstacle_radius(m, a, np.array([0.3, 0.3]))  # compiled for the largest size, 0.25
    gp = obstacle_mocap_pos(base, mid[0], c[0], v[0], 10.0, a.obstacle_park)
    np.testing.assert_allclose(gp[mid[0]], d.mocap_pos[mid[0]])
    np.testing.assert_allclose(gp[mid[1]], base[mid[1]])
    jnp = pytest.importorskip("jax.numpy")
    gj = obstacle_mocap_pos(jnp.asarray(base), mid[0], jnp.asarray(c[0]), jnp.asarray(v[0]), 10.0, a.obstacle_park)
    np.testing.assert_allclose(np.asarray(gj), gp, atol=1e-6)


def _fly_into_column(cm: str) -> float:
    """Max x (m) of a quad pushed at 1 m/s toward a column at the origin (gravity cancelled)."""
    import mujoco

    from quadswarm_mj.arena import place_obstacles

    cfg, a = _arena(cm)
    m = a.model
    d = mujoco.MjData(m)
    place_obstacles(a, d.mocap_pos, np.zeros((1, 12, 2)), np.arange(12)[None] < 1, 10.0)
    qs, vs, b = a.qpos_start, a.qvel_start, a.first_body
    d.qpos[qs:qs + 7] = [-0.6, 0.0, 2.0, 1, 0, 0, 0]
    d.qvel[vs:vs + 6] = [1.0, 0, 0, 0, 0, 0]
    xmax = -1.0
    for _ in range(200):
        d.xfrc_applied[b, 2] = m.body_subtreemass[b] * 9.81
        mujoco.mj_step(m, d)
        xmax = max(xmax, float(d.qpos[qs]))
    return xmax


def test_columns_collide_through_mujoco_not_in_paper():
    limit = -(0.3 + ARM)
    assert _fly_into_column("mujoco") < limit + 0.01  # stopped at the surface (soft contact)
    assert _fly_into_column("paper") > 0.35  # passes through (-0.6 + 1 m/s * 1 s): the paper model handles it


def test_renderer_draws_columns():
    import mujoco

    from quadswarm_mj.arena import place_obstacles
    from quadswarm_mj.render import SwarmRenderer

    cfg, a = _arena("paper")

    class Core:  # the parts of an engine the renderer reads
        arena, model = a, a.model
        data = mujoco.MjData(a.model)

        class sstate:  # noqa: N801
            goals = np.array([[[0.0, 0.0, 2.0]]])

    Core.data.qpos[a.qpos_start:a.qpos_start + 7] = [0.0, -2.0, 2.0, 1, 0, 0, 0]
    try:
        r = SwarmRenderer(Core(), width=96, height=72, camera="fixed:overview", show_goals=False, shadows=False)
    except Exception as e:  # noqa: BLE001 - no GL on this machine
        pytest.skip(f"no offscreen GL: {e}")
    with r:
        empty = r.render().astype(float)
        place_obstacles(a, Core.data.mocap_pos, np.zeros((1, 12, 2)), np.arange(12)[None] < 1, 10.0)
        col = r.render().astype(float)
        given = r.render(obstacles=np.array([[0.0, 0.0]])).astype(float)
        none = r.render(obstacles=np.zeros((0, 2))).astype(float)
    changed = (np.abs(col - empty).max(-1) > 30).mean()
    assert changed > 0.01, changed  # the column is visible (a 0.6 m column in a 10 m room)
    np.testing.assert_allclose(given, col)
    np.testing.assert_allclose(none, empty)


# ------------------------------------------------------------------------------- controller


def test_controller_obstacle_term_repels_at_a_column_side():
    from quadswarm_mj.controllers import ControllerGains, PositionController

    ctrl = PositionController(EnvConfig(), ControllerGains(obstacle_radius=0.5, obstacle_gain=8.0))
    pos = np.array([[0.5, 0.0, 2.0], [0.0, 0.7, 2.0], [3.0, 0.0, 2.0]])  # right, above (+y) and far from a column
    acc = ctrl.obstacle_acceleration(pos, np.zeros((3, 3)), np.array([[0.0, 0.0]]), np.array([True]), 0.3)
    assert acc[0, 0] > 0 and abs(acc[0, 2]) == 0  # pushed away along +x, horizontal only
    assert acc[1, 1] > 0 and acc[1, 1] < acc[0, 0]  # farther from the surface: weaker
    np.testing.assert_allclose(acc[2], 0.0)
    np.testing.assert_allclose(acc[0, 0], 8.0 * (1 - 0.2 / 0.5))
    none = ctrl.obstacle_acceleration(pos, np.zeros((3, 3)), np.array([[0.0, 0.0]]), np.array([False]), 0.3)
    np.testing.assert_allclose(none, 0.0)
    # approaching: the brake adds along the normal; moving sideways: the swirl follows the motion
    a2 = ctrl.obstacle_acceleration(pos[:1], np.array([[-1.0, 0.5, 0.0]]), np.array([[0.0, 0.0]]), None, 0.3)
    assert a2[0, 0] > acc[0, 0] and a2[0, 1] > 0


def test_controller_obstacles_argument_changes_actions_only_when_on():
    from quadswarm_mj.controllers import ControllerGains, PositionController

    cfg = EnvConfig(num_quads=1)
    state = {"pos": np.array([[0.45, 0.0, 2.0]]), "vel": np.zeros((1, 3)), "rot": np.eye(3)[None],
             "omega": np.zeros((1, 3))}
    goals = np.array([[0.45, 0.0, 2.0]])
    cols = np.array([[0.0, 0.0]])
    off = PositionController(cfg)
    on = PositionController(cfg, ControllerGains(obstacle_radius=0.5))
    np.testing.assert_allclose(off(state, goals, obstacles=cols), off(state, goals))
    assert np.abs(on(state, goals, obstacles=cols) - on(state, goals)).max() > 1e-3
    m = ob.map_from_centres(ObstacleConfig(), cols)
    np.testing.assert_allclose(on(state, goals, obstacles=m), on(state, goals, obstacles=cols))
    with pytest.raises(ValueError, match="obstacle_radius"):
        ControllerGains(obstacle_radius=-1.0)


@pytest.mark.parametrize("y0", [0.0, 0.1])
def test_controller_flies_around_a_column(y0):
    from quadswarm_mj import QuadSwarmEnv
    from quadswarm_mj.controllers import ControllerGains, PositionController

    cfg = EnvConfig(num_quads=1, motor_start="hover").without_noise()
    env = QuadSwarmEnv(cfg)  # columns are not in the engine yet: only the controller sees this one
    ctrl = PositionController(cfg, ControllerGains(obstacle_radius=0.6))
    goal = np.array([[2.5, 0.0, 2.0]])
    _, info = env.reset(seed=0, options={"state": {"pos": np.array([[-2.5, y0, 2.0]]), "goals": goal}})
    dmin = np.inf
    for _ in range(600):
        a = ctrl(info["state"], goal, obstacles=np.array([[0.0, 0.0]]))
        _, _, _, _, info = env.step(a[0])
        p = info["state"]["pos"][0]
        dmin = min(dmin, float(np.hypot(p[0], p[1])))
    env.close()
    assert dmin > 0.3 + ARM  # never touched the column
    assert np.linalg.norm(p - goal[0]) < 0.1  # and got past it


def test_reset_map_given_or_random():
    o = ObstacleConfig()
    d = NumpySampler(np.random.default_rng(0)).draw(ob.map_draw_spec(o))
    np.testing.assert_allclose(ob.reset_map(o, d).centres, ob.generate_map(o, d)[0].centres)
    given = ob.reset_map(o, d, np.array([[0.0, 0.0], [3.0, 3.0]]))
    np.testing.assert_allclose(ob.active_centres(given), [[0.0, 0.0], [3.0, 3.0]])


def test_one_grid_gives_the_contact_test_and_the_features_exactly():
    from quadswarm_mj.obstacles import (
        contact_hits,
        features_from_grid,
        hits_from_grid,
        obstacle_features,
        obstacle_grid,
    )

    rng = np.random.default_rng(5)
    pos = rng.uniform(-2, 2, (4, 8, 3))
    centres = rng.uniform(-2, 2, (4, 13, 2))
    valid = rng.random((4, 13)) < 0.6
    valid[1] = False  # a world without columns
    radius = rng.uniform(0.1, 0.4, 4)
    pos[0, 0, :2] = centres[0, 0] + 0.05  # a quad inside a column
    grid = obstacle_grid(pos, centres, valid)
    np.testing.assert_array_equal(hits_from_grid(grid, radius, 0.046), contact_hits(pos, centres, valid, radius, 0.046))
    np.testing.assert_array_equal(features_from_grid(grid, radius), obstacle_features(pos, centres, valid, radius))
    assert hits_from_grid(grid, radius, 0.046)[0, 0].any() and not hits_from_grid(grid, radius, 0.046)[1].any()


def test_jax_first_hit_selects_equal_numpy():
    """first_hit's XLA path (selects from the last column to the first, no argmax or gathers) gives
    NumPy's index and centre exactly, under jit and vmap, with and without hits."""
    jax = pytest.importorskip("jax")
    import jax.numpy as jnp

    from quadswarm_mj.obstacles import contact_hits, first_hit

    rng = np.random.default_rng(11)
    W, N, M = 6, 8, 12
    pos = rng.uniform(-2, 2, (W, N, 3)).astype(np.float32)
    centres = rng.uniform(-2, 2, (W, M, 2)).astype(np.float32)
    valid = rng.random((W, M)) < 0.6
    valid[1] = False  # a world without columns
    radius = rng.uniform(0.1, 0.4, W).astype(np.float32)
    pos[0, :3, :2] = centres[0, :3] + 0.05  # quads inside columns
    pos[2, 0, :2] = centres[2, 5] + 0.1
    hit = contact_hits(pos, centres, valid, radius, 0.046)
    hit[3, 0] = True  # several columns at once: the first counts
    assert hit.any() and (~hit.any(-1)).any()
    want_i, want_c = first_hit(hit, centres)
    got_i, got_c = jax.jit(jax.vmap(first_hit))(jnp.asarray(hit), jnp.asarray(centres))
    np.testing.assert_array_equal(np.asarray(got_i), want_i)
    np.testing.assert_array_equal(np.asarray(got_c), want_c)
