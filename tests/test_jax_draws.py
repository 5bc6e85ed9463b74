"""The JAX engine's random words (quadswarm_mj.perf.fused_draws): the unrolled threefry hash and the
materialized numbers are rewrites of JAX's own (same words, same uniforms; normals within a few float32
ulp)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.extend.random import threefry_2x32

from quadswarm_mj.perf.fused_draws import (
    FusedJaxSampler,
    _materialized_numbers,
    _unit_numbers,
    erf_inv_f32,
    step_key_and_numbers,
    step_words,
    threefry_2x32_unrolled,
)
from quadswarm_mj.random_draws import Normal, Uniform


@pytest.mark.parametrize("seed", [0, 1, 12345])
def test_unrolled_threefry_equals_jax(seed):
    key = jax.random.key_data(jax.random.key(seed))
    count = jnp.asarray(np.random.default_rng(seed).integers(0, 2**32, size=206, dtype=np.uint32))
    np.testing.assert_array_equal(np.asarray(jax.jit(threefry_2x32_unrolled)(key, count)),
                                  np.asarray(threefry_2x32(key, count)))


@pytest.mark.parametrize("total", [1, 7, 204])
def test_materialized_numbers_are_the_unit_numbers(total):
    words = jax.random.bits(jax.random.key(3), (total,), jnp.uint32)
    u, n = jax.jit(_materialized_numbers, static_argnums=1)(words, True)
    u_ref, n_ref = jax.jit(_unit_numbers)(words)
    np.testing.assert_array_equal(np.asarray(u), np.asarray(u_ref))
    np.testing.assert_array_equal(np.asarray(n), np.asarray(n_ref))
    # the transform is jax.random's: same floats as jax.random.uniform / normal make from these bits
    assert np.all((np.asarray(u) >= 0) & (np.asarray(u) < 1))


def test_erf_inv_f32_is_accurate_and_at_least_as_accurate_as_xla():
    from scipy.special import erfinv

    # every uniform the normals are made from lies in [nextafter(-1, 0), 1); a dense sweep and the tails
    lo = np.nextafter(np.float32(-1.0), np.float32(0.0))
    u = np.linspace(0.0, 1.0, 200_001, dtype=np.float32)[:-1]
    tails = np.concatenate([np.nextafter(np.float32(1.0), np.float32(0.0)) - np.arange(200, dtype=np.float32) * 2**-24,
                            lo + np.arange(200, dtype=np.float32) * 2**-24])
    x = np.concatenate([np.maximum(lo, lo + (1.0 - lo) * u), tails]).astype(np.float32)
    ours = np.asarray(jax.jit(erf_inv_f32)(jnp.asarray(x)), np.float64)
    xla = np.asarray(jax.jit(jax.lax.erf_inv)(jnp.asarray(x)), np.float64)
    exact = erfinv(x.astype(np.float64))
    ulp = np.spacing(np.abs(exact).astype(np.float32)).astype(np.float64)
    err_ours, err_xla = np.abs(ours - exact) / ulp, np.abs(xla - exact) / ulp
    assert np.all(np.isfinite(ours)) and np.array_equal(np.sign(ours), np.sign(exact))
    assert err_ours.max() <= 8  # XLA's own erf_inv is up to ~64 ulp off in the tails (log1p of a rounded x^2)
    assert err_ours.max() <= err_xla.max()


def test_unit_normals_are_standard_normal():
    from scipy import stats

    words = jax.random.bits(jax.random.key(11), (200_000,), jnp.uint32)
    n = np.asarray(jax.jit(_unit_numbers)(words)[1], np.float64)
    assert stats.kstest(n, "norm").pvalue > 1e-3
    assert abs(n.mean()) < 0.01 and abs(n.std() - 1.0) < 0.01


def test_from_words_shapes_and_moments():
    spec = {"a": Uniform(-2.0, 3.0, (4,)), "b": Normal(1.0, 0.5, (2, 3))}
    words = jax.random.bits(jax.random.key(0), (FusedJaxSampler.num_words(spec, (5000,)),), jnp.uint32)
    d = jax.jit(lambda w: FusedJaxSampler.from_words(spec, w, (5000,)))(words)
    a, b = np.asarray(d["a"]), np.asarray(d["b"])
    assert a.shape == (5000, 4) and b.shape == (5000, 2, 3)
    assert a.min() >= -2.0 and a.max() < 3.0 and abs(a.mean() - 0.5) < 0.05
    assert abs(b.mean() - 1.0) < 0.01 and abs(b.std() - 0.5) < 0.01


def test_step_words_stream_is_disjoint_from_split_and_fold_in():
    key = jax.random.key(7)
    nxt, words = step_words(key, 10)
    assert words.shape == (10,) and words.dtype == jnp.uint32
    nd = np.asarray(jax.random.key_data(nxt))
    others = [jax.random.fold_in(key, 1), *jax.random.split(key), *jax.random.split(key, 3)]
    for k in others:
        assert not np.array_equal(nd, np.asarray(jax.random.key_data(k)))
    # deterministic
    nxt2, words2 = step_words(key, 10)
    np.testing.assert_array_equal(np.asarray(words), np.asarray(words2))


def test_step_words_keeps_the_key_type():
    typed, raw = jax.random.key(1), jax.random.PRNGKey(1)  # typed key, legacy uint32[2] key
    assert jax.dtypes.issubdtype(step_words(typed, 4)[0].dtype, jax.dtypes.prng_key)
    nxt = step_words(raw, 4)[0]
    assert nxt.dtype == jnp.uint32 and nxt.shape == (2,)


@pytest.mark.parametrize("total", [1, 2, 3, 6, 204])
@pytest.mark.parametrize("typed", [True, False])
def test_step_key_and_numbers_is_step_words_then_unit_numbers_bit_for_bit(total, typed):
    """One pass over the threefry rounds (the two words of a block leave one kernel as a complex64)
    gives exactly the next key and numbers of step_words + unit_numbers, batched over worlds too
    (random words include NaN and denormal bit patterns, which must pass unchanged)."""
    mask = np.random.default_rng(total).random(total) < 0.7
    spec = {f"d{i}": (Normal() if m else Uniform(0.0, 1.0)) for i, m in enumerate(mask)}

    def old(key):
        k, w = step_words(key, total)
        return (jax.random.key_data(k) if typed else k), FusedJaxSampler.unit_numbers(spec, w)

    def new(key):
        k, x = step_key_and_numbers(key, mask)
        return (jax.random.key_data(k) if typed else k), x

    keys = jax.random.split(jax.random.key(5), 300)
    if not typed:
        keys = jax.random.key_data(keys)
    (k_old, x_old), (k_new, x_new) = jax.jit(jax.vmap(old))(keys), jax.jit(jax.vmap(new))(keys)
    assert np.asarray(x_new).tobytes() == np.asarray(x_old).tobytes()
    assert np.asarray(k_new).tobytes() == np.asarray(k_old).tobytes()
    k1, _ = step_key_and_numbers(jax.random.key(1) if typed else jax.random.PRNGKey(1), mask)
    assert jax.dtypes.issubdtype(k1.dtype, jax.dtypes.prng_key) == typed


def test_step_numbers_with_tof_positions_are_the_deck_noise_of_the_same_uniforms():
    """At ``tof_mask`` positions step_key_and_numbers carries tof_numbers (the deck rays' ToF noise,
    NaN where the reading is lost) of the uniform it would carry there, to float32 round-off; every
    other number and the next key are unchanged bit for bit."""
    from quadswarm_mj.perf.fused_draws import tof_numbers
    from quadswarm_mj.sensors import tof_normal

    rng = np.random.default_rng(3)
    total, dropout = 301, 0.05
    mask = rng.random(total) < 0.4
    tof = ~mask & (rng.random(total) < 0.6)
    spec = {f"d{i}": (Normal() if m else Uniform(0.0, 1.0)) for i, m in enumerate(mask)}

    def plain(key):
        k, w = step_words(key, total)
        return jax.random.key_data(k), FusedJaxSampler.unit_numbers(spec, w)

    def with_tof(key):
        k, x = step_key_and_numbers(key, mask, tof, dropout)
        return jax.random.key_data(k), x

    keys = jax.random.split(jax.random.key(8), 200)
    (k0, x0), (k1, x1) = jax.jit(jax.vmap(plain))(keys), jax.jit(jax.vmap(with_tof))(keys)
    x0, x1 = np.asarray(x0), np.asarray(x1)
    assert np.asarray(k0).tobytes() == np.asarray(k1).tobytes()
    assert x0[:, ~tof].tobytes() == x1[:, ~tof].tobytes()
    u = x0[:, tof]
    lost = u < dropout
    assert lost.any() and np.array_equal(np.isnan(x1[:, tof]), lost)
    want = np.asarray(jax.jit(lambda v: tof_normal(v, dropout))(jnp.asarray(u)))
    # float32 round-off of the argument 2 w - 1 (another fusion may contract it into an FMA), amplified
    # by erfinv's slope near -1 in the tail: most numbers agree to a few ulp, the tail to 1e-3
    np.testing.assert_allclose(x1[:, tof][~lost], want[~lost], rtol=1e-3, atol=1e-3)
    assert np.median(np.abs(x1[:, tof][~lost] - want[~lost])) < 1e-6
    mine = np.asarray(jax.jit(lambda v: tof_numbers(v, dropout))(jnp.asarray(u)))
    assert np.array_equal(np.isnan(mine), lost)
    np.testing.assert_allclose(mine[~lost], want[~lost], rtol=1e-3, atol=1e-3)


def test_jax_unit_numbers_are_uniform_and_normal_at_their_positions():
    """random_draws.jax_unit_numbers (the JAX engine's default step numbers): N(0, 1) at the mask's
    positions and U[0, 1) elsewhere (KS), deterministic per key, a new key of the same type."""
    from scipy import stats

    from quadswarm_mj.random_draws import jax_unit_numbers

    mask = np.random.default_rng(0).random(301) < 0.4
    keys = jax.random.split(jax.random.key(2), 400)
    k, x = jax.jit(jax.vmap(lambda key: jax_unit_numbers(key, mask)))(keys)
    assert x.shape == (400, 301) and x.dtype == jnp.float32
    x = np.asarray(x, np.float64)
    u = x[:, ~mask].ravel()
    assert u.min() >= 0.0 and u.max() < 1.0 and stats.kstest(u, "uniform").pvalue > 1e-3
    assert stats.kstest(x[:, mask].ravel(), "norm").pvalue > 1e-3
    _, again = jax.jit(lambda key: jax_unit_numbers(key, mask))(keys[0])
    np.testing.assert_array_equal(np.asarray(again), x[0].astype(np.float32))
    assert jax.dtypes.issubdtype(k.dtype, jax.dtypes.prng_key)
    raw = jax_unit_numbers(jax.random.PRNGKey(1), mask)[0]
    assert raw.dtype == jnp.uint32 and raw.shape == (2,)


def test_jax_unit_numbers_own_positions_and_the_tof_table():
    """With ``own_mask`` the positions' numbers come from ``own`` (the JAX engine: the deck rays' ToF noise,
    sensors.tof_from_words); the rest stay uniform / normal at their positions (KS). The table is the
    model's tof_normal at the 2^16 levels (NaN: lost), and its numbers have the dropout rate and a
    standard normal noise."""
    from scipy import stats

    from quadswarm_mj.random_draws import jax_unit_numbers
    from quadswarm_mj.sensors import tof_from_words, tof_noise_table, tof_normal

    dropout = 0.05
    table = tof_noise_table(dropout)
    levels = (np.arange(65536) + 0.5) / 65536
    kept = levels >= dropout
    assert table.dtype == np.float32 and not table.flags.writeable
    np.testing.assert_array_equal(np.isnan(table), ~kept)
    np.testing.assert_array_equal(table[kept], tof_normal(levels[kept], dropout).astype(np.float32))
    assert np.all(np.diff(table[kept]) >= 0.0)

    rng = np.random.default_rng(1)
    normal, own = rng.random(300) < 0.3, np.zeros(300, bool)
    own[100:227] = True  # a run in the middle, as the deck's entry in the step spec
    normal &= ~own
    keys = jax.random.split(jax.random.key(4), 500)
    _, x = jax.jit(jax.vmap(lambda k: jax_unit_numbers(k, normal, None, own,
                                                       lambda w: tof_from_words(w, 127, dropout), 64)))(keys)
    x = np.asarray(x, np.float64)
    uni = ~normal & ~own
    assert np.all(np.isfinite(x[:, ~own])) and stats.kstest(x[:, uni].ravel(), "uniform").pvalue > 1e-3
    assert stats.kstest(x[:, normal].ravel(), "norm").pvalue > 1e-3
    z = x[:, own].ravel()
    lost = np.isnan(z)
    assert abs(lost.mean() - dropout) < 4.0 * np.sqrt(dropout * (1 - dropout) / z.size)
    assert np.all(np.isin(z[~lost].astype(np.float32), table[kept]))
    assert stats.kstest(z[~lost], "norm").pvalue > 1e-3
    odd = np.asarray(jax.jit(lambda w: tof_from_words(w, 7, dropout))(jnp.arange(4, dtype=jnp.uint32)))
    np.testing.assert_array_equal(odd, table[[0, 0, 0, 1, 0, 2, 0]])  # high then low half of each word
    assert odd.shape == (7,) and odd.dtype == np.float32


def test_jax_sampler_shapes_moments_and_spec_order():
    """random_draws.JaxSampler (one uniform and one normal call): each entry in its shape and law, the
    spec's order kept."""
    from quadswarm_mj.random_draws import JaxSampler

    spec = {"b": Normal(1.0, 0.5, (2, 3)), "a": Uniform(-2.0, 3.0, (4,)), "c": Normal(0.0, 2.0)}
    d = JaxSampler(jax.random.key(0)).draw(spec, (5000,))  # eager: jit's output dict has sorted keys
    assert list(d) == ["b", "a", "c"]
    a, b, c = (np.asarray(d[k]) for k in "abc")
    assert a.shape == (5000, 4) and b.shape == (5000, 2, 3) and c.shape == (5000,)
    assert a.min() >= -2.0 and a.max() < 3.0 and abs(a.mean() - 0.5) < 0.05
    assert abs(b.mean() - 1.0) < 0.01 and abs(b.std() - 0.5) < 0.01 and abs(c.std() - 2.0) < 0.1


def test_host_programs_pick_their_draws_by_batch():
    """The one-world program behind QuadSwarmEnv(engine="jax") and the PettingZoo env uses the fused draws
    (2.2-2.5x its steps/s against jax.random's small kernels, docs/engines.md); batched programs (the JAX
    vector env's workers) use jax.random."""
    from quadswarm_mj import EnvConfig
    from quadswarm_mj.envs.jax_program import Program

    cfg = EnvConfig(num_quads=2)
    assert Program(cfg, None).env.draws == "fused"
    assert Program(cfg, 4).env.draws == "jax"
