"""The pure model functions give the same results on NumPy and under jax.jit (float32)."""

from __future__ import annotations

import numpy as np
import pytest

from quadswarm_mj import EnvConfig
from quadswarm_mj.actuation import action_to_command, motor_noise_step, rotor_positions, substep_wrench
from quadswarm_mj.collisions import (
    floor_draw_spec,
    floor_impact,
    floor_wrench,
    quad_collision_draw_spec,
    quad_collisions,
    wall_collisions,
    wall_draw_spec,
)
from quadswarm_mj.downwash import apply_downwash, downwash_draw_spec
from quadswarm_mj.observations import build_obs, obs_bounds, sensor_noise_spec
from quadswarm_mj.random_draws import NumpySampler
from quadswarm_mj.randomization import params_from_draws, randomization_draw_spec
from quadswarm_mj.rewards import reward_terms
from quadswarm_mj.spatial import quat_to_rotmat, rotmat_to_quat

jax = pytest.importorskip("jax")
jnp = jax.numpy

N = 6
CFG = EnvConfig(num_quads=N, randomize=True)
RTOL, ATOL = 2e-5, 2e-5


def tree_close(a, b):
    if isinstance(a, dict):
        for k in a:
            tree_close(a[k], b[k])
    elif isinstance(a, (tuple, list)):
        for x, y in zip(a, b):
            tree_close(x, y)
    else:
        np.testing.assert_allclose(np.asarray(b, dtype=np.float64), np.asarray(a, dtype=np.float64),
                                   rtol=RTOL, atol=ATOL)


def to_jax(tree):
    return jax.tree_util.tree_map(lambda x: jnp.asarray(np.asarray(x, np.float32) if np.asarray(x).dtype.kind == "f"
                                                        else x), tree)


def as32(tree):
    """NumPy inputs rounded to float32 so both backends see identical values."""
    return jax.tree_util.tree_map(lambda x: (np.asarray(x, np.float32).astype(np.float64)
                                             if np.asarray(x).dtype.kind == "f" else np.asarray(x)), tree)


def check(fn, *args):
    args = as32(args)
    ref = fn(*args)
    got = jax.jit(fn)(*to_jax(args))
    tree_close(ref, got)
    return ref


@pytest.fixture(scope="module")
def world():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(N, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    pos = rng.uniform(-1, 1, (N, 3)) * 0.08 + np.array([0, 0, 2.0])
    pos[0] = [5.2, 0.0, 3.0]  # beyond a wall
    pos[1] = [0.0, 0.0, 0.03]  # below the floor height
    return {"pos": pos, "vel": rng.normal(size=(N, 3)), "omega": rng.normal(size=(N, 3)), "quat": q,
            "R": quat_to_rotmat(q), "rng": rng}


def test_rotations(world):
    check(lambda q: quat_to_rotmat(q), world["quat"])
    check(lambda R: rotmat_to_quat(R) * jnp.sign(rotmat_to_quat(R)[..., :1]) if not isinstance(R, np.ndarray)
          else rotmat_to_quat(R) * np.sign(rotmat_to_quat(R)[..., :1]), world["R"])
    np.testing.assert_allclose(quat_to_rotmat(rotmat_to_quat(world["R"])), world["R"], atol=1e-12)


def test_randomization_and_actuation(world):
    draws = NumpySampler(world["rng"]).draw(randomization_draw_spec(CFG))
    params = check(lambda d: params_from_draws(CFG, d), draws)
    assert np.ptp(params["mass"]) > 0
    rp = rotor_positions(CFG.quad)
    u0 = world["rng"].uniform(0, 1, (N, 4))
    a = world["rng"].uniform(-1.5, 1.5, (N, 4))
    eps = world["rng"].normal(0, 0.01, (N, 4))
    normal = world["rng"].normal(size=(N, 4))

    def chain(u, a, eps, normal, R, p):
        cmd = action_to_command(a)
        e = motor_noise_step(eps, p["motor_sigma"], 0.15, normal)
        return substep_wrench(u, cmd, e, p, R, rp)

    check(chain, u0, a, eps, normal, world["R"], params)


def test_collisions(world):
    s = NumpySampler(world["rng"])
    draws = s.draw(quad_collision_draw_spec(N, 3, 0.8, 0.15, (0.2, 0.8), (10 * np.pi, 20 * np.pi)))
    prev = np.zeros((N, N), bool)
    out = check(lambda p, v, w, d: quad_collisions(p, v, w, prev, 0.0919, d), world["pos"], world["vel"],
                world["omega"], draws)
    assert out["new_contact"].any()
    wd = s.draw(wall_draw_spec(N, (0.2, 0.8), (10 * np.pi, 20 * np.pi)))
    out = check(lambda p, v, w, d: wall_collisions(p, v, w, np.zeros(N, bool), np.zeros(N, bool), (-5, -5, 0),
                                                   (5, 5, 10), d, (0.1, 6.0)), world["pos"], world["vel"],
                world["omega"], wd)
    assert out["hit_wall"][0]
    fd = s.draw(floor_draw_spec(N))
    on = np.zeros(N, bool)
    on[2] = True
    out = check(lambda p, v, w, q, R, u, d: floor_impact(p, v, w, q, R, u, on, 0.046, d["yaw"]), world["pos"],
                world["vel"], world["omega"], world["quat"], world["R"], np.ones((N, 4)) * 0.5, fd)
    assert out["hit_floor"][1]
    check(lambda f, t, v: floor_wrench(on, f, t, v, np.full(N, 0.028), 9.81, 0.6, 0.005),
          world["vel"] * 0.1, world["omega"] * 1e-3, world["vel"])


def test_downwash(world):
    pos = world["pos"].copy()
    pos[3] = pos[2] - 0.3 * world["R"][2][:, 2] + 0.01  # quad 3 in the downwash of quad 2
    draws = NumpySampler(world["rng"]).draw(downwash_draw_spec(N))
    v, _ = check(lambda p, v, w, R, d: apply_downwash(p, v, w, R, 0.01, d), pos, world["vel"], world["omega"],
                 world["R"], draws)
    assert not np.allclose(v[3], as32(world["vel"])[3])


def test_observations_and_rewards(world):
    cfg = EnvConfig(num_quads=N, obs_self="wall", neighbor_sort="original")
    lo, hi = obs_bounds(cfg)
    noise = NumpySampler(world["rng"]).draw(sensor_noise_spec(cfg))
    goals = world["pos"] + 0.5
    check(lambda p, v, R, w, g, n: build_obs(cfg, p, v, R, w, g, n, lo, hi), world["pos"], world["vel"],
          world["R"], world["omega"], goals, noise)
    onf = np.zeros(N, bool)
    onf[1] = True
    new = np.zeros((N, N), bool)
    new[2, 3] = new[3, 2] = True
    dist = np.linalg.norm(world["pos"][:, None] - world["pos"][None], axis=-1)

    def rew(p, v, R, w, g, a, f, pf, d):
        return reward_terms(cfg, p, v, R, w, g, a, f, pf, onf, onf, onf, onf, new, d, 0.5)

    check(rew, world["pos"], world["vel"], world["R"], world["omega"], goals, world["vel"][:, :2].repeat(2, 1),
          np.full((N, 4), 0.4), np.full((N, 4), 0.5), dist)
