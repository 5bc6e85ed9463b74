"""Input validation gaps (issue 11 item 4): NaN/inf in configs, rooms too small for the spawn
rules, reset states and goals outside the room. Each is a ValueError naming the field and the
allowed range, raised before any state changes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, QuadParams, QuadSwarmEnv
from quadswarm_mj.config import MIN_ROOM_HEIGHT, MIN_ROOM_SIDE, SPAWN_MARGIN, SPAWN_MIN_Z
from quadswarm_mj.scenarios.base import room_bounds, spawn_state

BAD = [math.nan, math.inf, -math.inf]


@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_formation_center_must_be_finite(bad, axis):
    fc = [0.0, 0.0, 2.0]
    fc[axis] = bad
    with pytest.raises(ValueError, match=r"formation_center must be 3 finite numbers \(m\)"):
        EnvConfig(formation_center=tuple(fc))


SCALAR_FIELDS = ["mass", "arm", "rotor_z", "thrust_to_weight", "torque_to_thrust", "motor_settling_time", "max_omega",
                 "gravity"]


@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("name", SCALAR_FIELDS)
def test_quad_params_scalars_must_be_finite(name, bad):
    with pytest.raises(ValueError, match=rf"quad\.{name} must be a finite number (>|>=) ") as e:
        EnvConfig(quad={name: bad})
    assert repr(bad) in str(e.value)
    with pytest.raises(ValueError, match=rf"quad\.{name} must be a finite number"):
        QuadParams(**{name: bad})


@pytest.mark.parametrize("bad", BAD + [0.0, -1e-5])
@pytest.mark.parametrize("i", [0, 1, 2])
def test_quad_inertia_must_be_finite_and_positive(i, bad):
    inertia = list(QuadParams().inertia)
    inertia[i] = bad
    with pytest.raises(ValueError, match=r"quad\.inertia must be 3 finite numbers >= 1e-09 and <= 1 \(kg m\^2"):
        EnvConfig(quad={"inertia": tuple(inertia)})


def test_quad_geometry_ranges():
    with pytest.raises(ValueError, match=r"quad\.rotor_z must be a finite number >= -0\.1 and <= 0\.1, got 0\.2"):
        QuadParams(arm=0.1, rotor_z=0.2)
    with pytest.raises(ValueError, match=rf"quad\.arm must be < {SPAWN_MARGIN} m"):
        QuadParams(arm=0.6)


def test_spawn_constants_are_the_spawn_rules():
    """The config's SPAWN_* constants are what spawn_state does: extreme draws in a 3 m high room
    land on z = SPAWN_MIN_Z and z = H - SPAWN_MARGIN, and SPAWN_MARGIN from the walls."""
    cfg = EnvConfig(num_quads=2, room_size=(10.0, 10.0, 3.0))
    goals = np.array([[0.0, 0.0, 0.3], [4.9, -4.9, 2.9]])
    lo = spawn_state(cfg, goals, np.array([0.0, 0.0, 0.0, 0.5, 1.0, 0.0, 1.0, 0.5]))["pos"]
    assert lo[0, 2] == SPAWN_MIN_Z and lo[1, 2] == 3.0 - SPAWN_MARGIN
    assert lo[1, 0] == 5.0 - SPAWN_MARGIN and lo[1, 1] == -5.0 + SPAWN_MARGIN
    assert MIN_ROOM_HEIGHT == SPAWN_MIN_Z + SPAWN_MARGIN and MIN_ROOM_SIDE == 2 * SPAWN_MARGIN


@pytest.mark.parametrize("room,field", [((10.0, 10.0, 1.2), r"room_size\[2\] \(height\) must be >= 1\.25 m"),
                                        ((10.0, 10.0, 0.5), r"room_size\[2\] \(height\) must be >= 1\.25 m"),
                                        ((0.9, 10.0, 3.0), r"room_size\[0\] and room_size\[1\].* must be >= 1\.0 m"),
                                        ((10.0, 0.5, 3.0), r"room_size\[0\] and room_size\[1\].* must be >= 1\.0 m")])
def test_room_too_small_for_the_spawn_rules(room, field):
    with pytest.raises(ValueError, match=field):
        EnvConfig(room_size=room)


@pytest.mark.parametrize("scenario", ["static_diff_goal", "dynamic_same_goal", "swap_goals"])
def test_smallest_room_spawns_quads_and_goals_inside(scenario):
    cfg = EnvConfig(num_quads=4, scenario=scenario, room_size=(MIN_ROOM_SIDE, MIN_ROOM_SIDE, MIN_ROOM_HEIGHT))
    low, high = room_bounds(cfg)
    assert all(a <= b for a, b in zip(low, high))  # the goal band is not empty
    env = QuadSwarmEnv(cfg)
    arm = cfg.quad.arm
    for seed in range(5):
        _, info = env.reset(seed=seed)
        p, g = info["state"]["pos"], info["goals"]
        assert np.all(p[:, 2] >= SPAWN_MIN_Z) and np.all(p[:, 2] + arm <= cfg.room_size[2])
        assert np.all(np.abs(p[:, :2]) + arm <= np.array(cfg.room_size[:2]) / 2)
        assert np.all(g >= np.array(cfg.room_low)) and np.all(g <= np.array(cfg.room_high))


def _snapshot(env: QuadSwarmEnv) -> dict[str, np.ndarray]:
    c = env.core
    snap = {k: v.copy() for k, v in c.state_dict().items()}
    snap["goals"] = c.sstate.goals.copy()
    snap["steps"] = np.array(c.steps, copy=True)
    return snap


@pytest.mark.parametrize("key,value,words", [
    ("pos", [[0.0, 0.0, 2.0], [2.5, 0.0, 2.0]], ["'pos'", "inside the room [-2, 2] x [-2, 2] x [0, 3] m", "(1,)"]),
    ("pos", [[0.0, 0.0, -0.1], [0.0, 1.0, 2.0]], ["'pos'", "[0, 3]", "(0,)"]),
    ("pos", [[0.0, 0.0, 3.5], [0.0, 1.0, 2.0]], ["'pos'", "(0,)"]),
    ("goals", [[0.0, 0.0, 2.0], [0.0, -9.0, 1.0]], ["'goals'", "inside the room", "(1,)"]),
    ("goals", [[0.0, 0.0, 2.0], [0.0, 0.0, math.inf]], ["'goals'", "NaN or inf"]),
    ("pos", [[math.nan, 0.0, 2.0], [0.0, 0.0, 1.0]], ["'pos'", "NaN or inf"]),
])
def test_reset_state_outside_room_rejected_and_state_unchanged(key, value, words):
    env = QuadSwarmEnv(EnvConfig(num_quads=2, room_size=(4.0, 4.0, 3.0)))
    env.reset(seed=0)
    for _ in range(3):
        env.step(np.zeros((2, 4)))
    before = _snapshot(env)
    with pytest.raises(ValueError) as e:
        env.reset(seed=1, options={"state": {key: value}})
    for w in words:
        assert w in str(e.value), (w, str(e.value))
    after = _snapshot(env)
    for k in before:
        np.testing.assert_array_equal(after[k], before[k], err_msg=k)
    env.step(np.zeros((2, 4)))  # still usable: the episode goes on


def test_reset_state_on_the_room_boundary_is_accepted():
    env = QuadSwarmEnv(EnvConfig(num_quads=2, room_size=(4.0, 4.0, 3.0)))
    _, info = env.reset(seed=0, options={"state": {"pos": [[2.0, -2.0, 3.0], [0.0, 0.0, 0.0]],
                                                   "goals": [[-2.0, 2.0, 0.0], [0.0, 0.0, 3.0]]}})
    np.testing.assert_allclose(info["goals"], [[-2.0, 2.0, 0.0], [0.0, 0.0, 3.0]])
