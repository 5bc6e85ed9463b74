"""The JAX engine's draw budget: bounded per-step draws for the event models, expanded to the dense
draws the model functions take, with SPEC §5's per-event distributions (a KS test against the CPU
engine's per-event draws)."""

from __future__ import annotations

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, QuadSwarmEnv
from quadswarm_mj.collisions import expand_per_quad, pairwise_contacts
from quadswarm_mj.downwash import expand_downwash_draws
from quadswarm_mj.random_draws import event_slots, spread


def new_pairs_upper(pos: np.ndarray, prev_contact: np.ndarray, hitbox: float) -> np.ndarray:
    """(N, N) mask of the new contact pairs with i < j (the events ranked by the budget)."""
    contact, _ = pairwise_contacts(pos, hitbox)
    n = pos.shape[-2]
    return contact & ~prev_contact & np.triu(np.ones((n, n), bool), k=1)


def expand_quad_draws(new_upper: np.ndarray, slots: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The reference: dense draws of ``collisions.quad_collisions`` (one world) from the per-slot draws of
    ``collisions.quad_collision_slot_spec``, slot r to the r-th new upper pair in row-major order."""
    n = new_upper.shape[-1]
    hot = event_slots(np, new_upper.reshape(n * n), slots["kick_mag"].shape[-1])  # (N N, S)

    def pairs(x: np.ndarray) -> np.ndarray:  # (S, *shape) -> (N, N, *shape), zero off the new upper pairs
        return spread(np, hot, x).reshape((n, n) + tuple(x.shape[1:]))

    def tries(x: np.ndarray) -> np.ndarray:  # (T, S, 3) -> (T, N, N, 3)
        return np.stack([pairs(x[t]) for t in range(x.shape[0])])

    own = tries(slots["own_i"]) + np.swapaxes(tries(slots["own_j"]), -2, -3)
    return {"shared": tries(slots["shared"]), "own": own, "decay": slots["decay"],
            "kick_dir": pairs(slots["kick_dir"]), "kick_mag": pairs(slots["kick_mag"])}


def test_event_slots_rank_in_index_order_and_wrap_beyond_budget():
    mask = np.array([False, True, True, False, True, True, True])
    hot = event_slots(np, mask, 2)
    assert hot.shape == (7, 2)
    assert np.all(hot[~mask] == 0) and np.all(hot[mask].sum(-1) == 1)
    np.testing.assert_array_equal(hot[mask].argmax(-1), [0, 1, 0, 1, 0])  # rank r -> slot r mod 2


def test_quad_pair_draws_go_to_the_new_upper_pairs_in_row_major_order():
    n, T, S = 4, 3, 2
    rng = np.random.default_rng(0)
    slots = {"shared": rng.normal(size=(T, S, 3)), "own_i": rng.normal(size=(T, S, 3)),
             "own_j": rng.normal(size=(T, S, 3)), "kick_dir": rng.normal(size=(S, 3)),
             "kick_mag": rng.uniform(size=(S,)), "decay": rng.uniform(size=(n,))}
    new = np.zeros((n, n), bool)
    new[0, 3] = new[1, 2] = new[2, 3] = True  # row-major ranks 0, 1, 2 -> slots 0, 1, 0
    d = expand_quad_draws(new, slots)
    assert d["shared"].shape == (T, n, n, 3) and d["own"].shape == (T, n, n, 3)
    for (i, j), s in (((0, 3), 0), ((1, 2), 1), ((2, 3), 0)):
        np.testing.assert_allclose(d["shared"][:, i, j], slots["shared"][:, s])
        np.testing.assert_allclose(d["own"][:, i, j], slots["own_i"][:, s])  # e_i of the pair
        np.testing.assert_allclose(d["own"][:, j, i], slots["own_j"][:, s])  # e_j of the pair
        np.testing.assert_allclose(d["kick_dir"][i, j], slots["kick_dir"][s])
        np.testing.assert_allclose(d["kick_mag"][i, j], slots["kick_mag"][s])
    assert np.all(d["shared"][:, ~new] == 0)
    np.testing.assert_array_equal(d["decay"], slots["decay"])


def test_per_quad_and_downwash_draws():
    rng = np.random.default_rng(1)
    yaw = rng.uniform(size=(2,))
    out = expand_per_quad(np.array([False, True, False, True, True]), {"yaw": yaw})["yaw"]
    np.testing.assert_allclose(out, [0.0, yaw[0], 0.0, yaw[1], yaw[0]])
    mask = np.zeros((3, 3), bool)
    mask[2, 0] = mask[0, 1] = True  # row-major: (0, 1) rank 0, (2, 0) rank 1
    slots = {"acc": rng.uniform(size=(4,)), "z_dir": rng.uniform(size=(4, 3)),
             "omega_mag": rng.uniform(size=(4,)), "omega_dir": rng.normal(size=(4, 3))}
    d = expand_downwash_draws(mask, slots)
    np.testing.assert_allclose(d["acc"][0, 1], slots["acc"][0])
    np.testing.assert_allclose(d["z_dir"][2, 0], slots["z_dir"][1])
    assert d["omega_dir"].shape == (3, 3, 3) and np.all(d["acc"][~mask] == 0)


@pytest.mark.parametrize("slots", [1, 2, 3])
def test_per_quad_draws_under_jax_equal_the_numpy_rule(slots):
    """The JAX engine's per-world path (selects, no cumsum or gather) gives event r the draws of slot
    r mod S, exactly as the NumPy one-hot path, including more events than slots."""
    import jax

    rng = np.random.default_rng(slots)
    masks = rng.random((64, 8)) < rng.uniform(0.0, 1.0, (64, 1))
    draws = {"c": rng.normal(size=(64, slots)).astype(np.float32),
             "v": rng.normal(size=(64, slots, 3)).astype(np.float32)}
    got = jax.jit(jax.vmap(expand_per_quad))(masks, draws)
    for w in range(64):
        ref = expand_per_quad(masks[w], {k: v[w].astype(np.float64) for k, v in draws.items()})
        for k in draws:
            np.testing.assert_array_equal(np.asarray(got[k][w]), ref[k].astype(np.float32), err_msg=k)
    assert masks.sum(axis=1).max() > slots  # the wrap-around (r mod S) was exercised


def _headon_state(cfg: EnvConfig) -> dict[str, np.ndarray]:
    """Two quads just outside each other's hitbox closing at 2 m/s: a new contact within one step."""
    gap = cfg.hitbox + 0.005
    return {"pos": np.array([[-gap / 2, 0.0, 2.0], [gap / 2, 0.0, 2.0]]),
            "vel": np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])}


@pytest.mark.slow
def test_post_collision_speed_and_spin_distributions_match_cpu_engine():
    """2000 forced head-on collisions per engine: the post-collision speeds and spin magnitudes of
    both quads have the same distribution (two-sample KS test) on the CPU engine (per-event NumPy
    draws) and the JAX engine (budgeted draws from jax.random)."""
    stats = pytest.importorskip("scipy.stats")
    jax = pytest.importorskip("jax")
    pytest.importorskip("mujoco.mjx")
    import jax.numpy as jnp

    from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv

    M = 2000
    cfg = EnvConfig(num_quads=2, motor_start="hover")
    init = _headon_state(cfg)
    hover = np.full((2, 4), cfg.quad.hover_action)
    env = QuadSwarmEnv(cfg)
    cpu_speed, cpu_spin = [], []
    for k in range(M):
        env.reset(seed=k, options={"state": init})
        _, _, _, _, info = env.step(hover)
        assert info["new_collisions"].all()
        cpu_speed.append(np.linalg.norm(info["state"]["vel"], axis=-1))
        cpu_spin.append(np.linalg.norm(info["state"]["omega"], axis=-1))
    jenv = MjxQuadSwarmEnv(cfg)

    def one(key):
        s = jenv.reset(key, init)
        return jenv.step(s, jnp.asarray(hover, jnp.float32))

    s = jax.jit(jax.vmap(one))(jax.random.split(jax.random.key(123), M))
    assert np.asarray(s.info["contact"])[:, 0, 1].all()
    jax_speed = np.linalg.norm(np.asarray(s.info["state"]["vel"]), axis=-1)
    jax_spin = np.linalg.norm(np.asarray(s.info["state"]["omega"]), axis=-1)
    cpu_speed, cpu_spin = np.array(cpu_speed), np.array(cpu_spin)
    for q in range(2):
        for a, b in ((cpu_speed[:, q], jax_speed[:, q]), (cpu_spin[:, q], jax_spin[:, q])):
            assert np.std(a) > 0.05 * np.mean(a)  # the noise is really there
            assert stats.ks_2samp(a, b).pvalue > 1e-3
    # and the test can fail: a JAX engine without collision noise is rejected
    quiet = MjxQuadSwarmEnv(cfg.replace(noise={**cfg.noise.__dict__, "stochastic_collisions": False}))

    def one_quiet(key):
        return quiet.step(quiet.reset(key, init), jnp.asarray(hover, jnp.float32))

    s0 = jax.jit(jax.vmap(one_quiet))(jax.random.split(jax.random.key(5), 200))
    spin0 = np.linalg.norm(np.asarray(s0.info["state"]["omega"]), axis=-1)[:, 0]
    assert stats.ks_2samp(cpu_spin[:, 0], spin0).pvalue < 1e-6


def test_budgeted_quad_collisions_equal_the_dense_model_within_the_budget_and_defer_beyond():
    from quadswarm_mj.collisions import quad_collisions, quad_collisions_budgeted
    from quadswarm_mj.spatial import yaw_cos_sin, yaw_half_cos_sin, yaw_of, yaw_quat

    rng = np.random.default_rng(3)
    n, T, S, hb = 6, 3, 2, 0.3
    seen = {"within": 0, "beyond": 0}
    for _ in range(300):
        pos, vel, om = rng.uniform(-0.4, 0.4, (n, 3)), rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
        prev = rng.random((n, n)) < 0.5
        prev = prev | prev.T
        slots = {"shared": rng.normal(size=(T, S, 3)), "own_i": rng.normal(size=(T, S, 3)),
                 "own_j": rng.normal(size=(T, S, 3)), "kick_dir": rng.normal(size=(S, 3)),
                 "kick_mag": rng.uniform(size=(S,)), "decay": rng.uniform(0.2, 1.0, size=(n,))}
        new = new_pairs_upper(pos, prev, hb)
        b = quad_collisions_budgeted(pos, vel, om, prev, hb, slots)
        if new.sum() <= S:
            seen["within"] += 1
            a = quad_collisions(pos, vel, om, prev, hb, expand_quad_draws(new, slots))
            for key in ("vel", "omega", "contact", "new_contact"):
                np.testing.assert_allclose(b[key], a[key], rtol=1e-12, atol=1e-12, err_msg=key)
        else:  # the pairs beyond the budget are left out of contact: new again at the next step
            seen["beyond"] += 1
            ranked = np.argwhere(new)[S:]
            assert not b["contact"][ranked[:, 0], ranked[:, 1]].any() and b["new_contact"].sum() == 2 * S
    assert seen["within"] > 50 and seen["beyond"] > 0
    R = rng.normal(size=(200, 3, 3))
    c, s = yaw_cos_sin(R)
    ch, sh = yaw_half_cos_sin(c, s)
    np.testing.assert_allclose(np.stack([ch, 0 * c, 0 * c, sh], -1), yaw_quat(yaw_of(R)), atol=1e-12)
