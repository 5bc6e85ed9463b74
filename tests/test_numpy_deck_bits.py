"""The MuJoCo engine's multi-ranger/flow form (:mod:`quadswarm_mj.perf.numpy_deck`) gives the model's bits
(:func:`quadswarm_mj.sensors.deck_part`) over many random scenes (raising no floating-point error: it sets no
error state), on the edge cases of its cast (a quad on a column's surface: a true range of -0.0) and keeps the
caller's floating-point error state."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.perf import numpy_deck
from quadswarm_mj.sensor_config import SensorConfig
from quadswarm_mj.sensor_rays import axis_hits
from quadswarm_mj.sensors import deck_part, deck_ranges

_SETS = [{"multiranger": True, "flow": True}, {"multiranger": True, "flow": True, "noise": False},
         {"multiranger": True, "flow": True, "dropout": 0.3}, {"multiranger": True}, {"flow": True},
         {"multiranger": True, "noise": False}, {"flow": True, "noise": False, "light_lux": 10.0}]


def _scene(rng: np.random.Generator, n: int, lead: tuple[int, ...], kind: int):
    """Random quads of one of 4 kinds: 0 spread, 1 crowded (a quad inside another's hitbox, one ahead of
    another, one straight above another), 2 level on the floor in a row (the benchmark's start: rays
    parallel to the planes, neighbours on the rays' lines), 3 axis-aligned or upside down at random."""
    pos = rng.uniform([-2.5, -2.5, 0.2], [2.5, 2.5, 2.8], lead + (n, 3))
    R = Rotation.random(int(np.prod(lead + (n,))), random_state=rng).as_matrix().reshape(lead + (n, 3, 3))
    if kind == 1 and n >= 5:
        pos[..., 1, :] = pos[..., 0, :] + [0.4, 0.05, -0.03]
        pos[..., 2, :] = pos[..., 0, :] + rng.uniform(-0.05, 0.05, 3)
        pos[..., 3, :] = pos[..., 4, :] + [0.0, 0.0, 0.5]
    elif kind == 2:
        pos[..., 0] = np.arange(n) * 0.5 - 2.0
        pos[..., 1] = np.where(np.arange(n) % 2, 0.5, -0.5)
        pos[..., 2] = 0.046
        R[...] = np.eye(3)
    elif kind == 3:
        flips = np.array([np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]),
                          np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])])
        R[...] = flips[rng.integers(0, 4, lead + (n,))]
    vel, omega = 2.0 * rng.normal(size=lead + (n, 3)), 3.0 * rng.normal(size=lead + (n, 3))
    if kind == 2:
        vel *= 0.01
        omega *= 0.01
    omap = (rng.uniform(-2.5, 2.5, lead + (6, 2)), rng.uniform(size=lead + (6,)) < 0.7,
            np.full(lead, 0.25))
    return pos, vel, R, omega, omap


def _draws(rng: np.random.Generator, s: SensorConfig, shape: tuple[int, ...]):
    if not s.noise:
        return None
    d = {"range_u": rng.uniform(size=shape + (s.num_rays,))}
    if s.flow:
        d["flow_noise"] = rng.normal(size=shape + (2,))
    return d


@pytest.mark.parametrize("sensors", _SETS)
def test_numpy_deck_is_the_model_bitwise_over_many_scenes(sensors):
    s = SensorConfig(**sensors)
    rng = np.random.default_rng(7)
    hits = 0
    for trial in range(40):
        n, lead = ((8, (1,)), (8, (2,)), (5, ()), (1, (1,)))[trial % 4]
        c = EnvConfig(num_quads=n, room_size=(6.0, 5.0, 3.0), sensors=s)
        pos, vel, R, omega, omap = _scene(rng, n, lead, trial % 5 % 4)
        draws = _draws(rng, s, lead + (n,))
        for cols in (None, omap):
            want = deck_part(c, pos, vel, R, omega, cols, draws)
            with np.errstate(all="raise"):  # no floating-point error inside the fast form (it sets no errstate)
                got = numpy_deck.deck_part(c, pos, vel, R, omega, cols, draws)
                into = numpy_deck.deck_part(c, pos, vel, R, omega, cols, draws, np.full(want.shape, np.nan))
            assert got.shape == want.shape and got.tobytes() == want.tobytes(), (trial, cols is None)
            assert into.tobytes() == want.tobytes()
        if n > 1:
            free = axis_hits(pos, R, c.room_low, c.room_high)
            hits += np.count_nonzero(axis_hits(pos, R, c.room_low, c.room_high, None, c.hitbox) < free)
    assert hits > 0  # the hitbox hits are exercised


@pytest.mark.parametrize("noise", [False, True])
def test_a_quad_on_a_column_surface_reads_as_the_model(noise):
    """A level quad exactly on a column's surface (|offset| = radius in binary): the ray into the column has
    the true range -0.0; the fast form's reading has the model's bits (+0.0 after max(t, 0))."""
    s = SensorConfig(multiranger=True, flow=True, noise=noise)
    c = EnvConfig(num_quads=8, room_size=(6.0, 5.0, 3.0), sensors=s)
    pos = np.zeros((1, 8, 3))
    pos[0, :, 0], pos[0, :, 1], pos[0, :, 2] = np.arange(8) * 0.5 - 2.0, -1.5, 1.0
    pos[0, 0, :2] = (1.25, 1.0)  # 0.25 m in +x from the column at (1, 1), radius 0.25
    R = np.broadcast_to(np.eye(3), (1, 8, 3, 3)).copy()
    cols = (np.array([[[1.0, 1.0]]]), np.array([[True]]), np.array([0.25]))
    zeros = np.zeros((1, 8, 3))
    t = deck_ranges(c, pos, R, cols)
    assert t[0, 0, 1] == 0.0 and np.signbit(t[0, 0, 1])  # back (-x): -0.0
    draws = _draws(np.random.default_rng(3), s, (1, 8))
    if draws is not None:
        draws["range_u"][0, 0, 1] = 0.5  # kept
    want = deck_part(c, pos, zeros, R, zeros, cols, draws)
    got = numpy_deck.deck_part(c, pos, zeros, R, zeros, cols, draws)
    assert got.tobytes() == want.tobytes()
    if not noise:
        assert want[0, 0, 1] == 0.0 and not np.signbit(want[0, 0, 1])


def test_numpy_deck_restores_the_callers_error_state():
    """The error state set inside the fast form (divide, invalid, over ignored) is the caller's state with
    those three changed, and the caller's state is back after the call (also after an error)."""
    s = SensorConfig(multiranger=True, flow=True)
    c = EnvConfig(num_quads=8, sensors=s)
    rng = np.random.default_rng(0)
    pos, vel, R, omega, _ = _scene(rng, 8, (1,), 2)
    draws = _draws(rng, s, (1, 8))
    with np.errstate(all="raise", under="warn"):
        before = np.geterr()
        numpy_deck.deck_part(c, pos, vel, R, omega, None, draws)  # R has exact zeros: 1 / 0 inside
        assert np.geterr() == before
        with pytest.raises(KeyError):
            numpy_deck.deck_part(c, pos, vel, R, omega, None, {"range_u": draws["range_u"]})  # no flow_noise
        assert np.geterr() == before
        with pytest.raises(FloatingPointError):
            np.divide(np.ones(1), np.zeros(1))
