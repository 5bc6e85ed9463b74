"""The configuration's limits (physical and numerical bounds every config is checked against) and the
small validators the config dataclasses share. Re-exported by :mod:`quadswarm_mj.config`."""

from __future__ import annotations

import math
import numbers
from typing import Any

COLLISION_MODELS = ("paper", "mujoco", "blend")
MOTOR_STARTS = ("zero", "hover")
OBS_SELF_VARIANTS = ("base", "floor", "wall")
NEIGHBOR_SORTS = ("distance", "original")
NEIGHBOR_FORMS = ("raw", "near")  # EnvConfig.neighbor_form (quadswarm_mj.observations.near_neighbors)
#: Spawn rules of ``quadswarm_mj.scenarios.base.spawn_state`` (SPEC §9): quads start at z >= SPAWN_MIN_Z
#: and SPAWN_MARGIN (m) from the walls and the ceiling; the room must leave that band non-empty.
SPAWN_MIN_Z = 0.75
SPAWN_MARGIN = 0.5
MIN_ROOM_HEIGHT = SPAWN_MIN_Z + SPAWN_MARGIN  # 1.25 m
MIN_ROOM_SIDE = 2 * SPAWN_MARGIN  # 1.0 m
CONTROL_MODES = ("rotor", "ctbr", "attitude", "velocity")
QUAD_PRESETS = ("quadswarm", "crazyflie21_identified")

# ---- physical bounds: every accepted state and airframe stays finite and stable in float32
#: m/s, the largest speed a reset state may give a quad (|v|). Racing quadrotors top out near 50 m/s
#: (180 km/h); a Crazyflie reaches ~20 m/s at full thrust across the default room. At 50 m/s a quad
#: moves 0.25 m per 200 Hz physics sub-step, already 5.4 arms: beyond that no contact or collision
#: model resolves a crossing.
SPEED_LIMIT = 50.0
#: rad/s, the largest body rate per axis a reset state, ``quad.max_omega`` or a collision kick may
#: give (2.5x the default ``max_omega`` 40, above the paper's largest collision kick 20 pi = 62.8;
#: racing quadrotors flip at ~35 rad/s). At 100 rad/s a 200 Hz sub-step turns a quad by 0.5 rad: the
#: rotation is still resolved, and the gyroscopic acceleration |I^-1 (w x I w)| <= ~1e4 rad/s^2 stays
#: far below MuJoCo's instability threshold (1e10).
OMEGA_LIMIT = 100.0
#: rad/s^2, the largest angular acceleration the rotors may give an airframe: 4 arm thrust_max /
#: min(Ixx, Iyy) (roll, pitch: all four rotors at the full arm, an upper bound) and 4 torque_max / Izz
#: (yaw). 2e4 = OMEGA_LIMIT / 5 ms: from rest to the spin limit within one default physics sub-step;
#: stronger airframes are not resolved by the simulation step. The Crazyflie: ~1750 (roll), ~120 (yaw).
MAX_ANGULAR_ACCEL = OMEGA_LIMIT / 0.005
#: The largest thrust-to-weight ratio of an airframe (all rotors at full thrust over the weight, also
#: of the strongest quad the randomization ranges can draw): the strongest racing quadrotors reach
#: ~10 (the Crazyflie 1.9-2.3); beyond, full thrust reaches SPEED_LIMIT within a second.
MAX_THRUST_TO_WEIGHT = 10.0
#: kg, the airframe mass range (a 1 g micro flyer .. a 10 kg heavy-lift multirotor; the Crazyflie 0.028).
MASS_RANGE = (1e-3, 10.0)
#: kg m^2, the range of each principal inertia (a 1 g mass 1 mm off the axis .. 1 kg m^2, a heavy-lift
#: multirotor; the Crazyflie ~1.4e-5, 2.7e-5). MAX_ANGULAR_ACCEL usually binds first.
INERTIA_RANGE = (1e-9, 1.0)
#: m/s^2, the largest gravity (Jupiter's is 24.8).
MAX_GRAVITY = 100.0
#: The largest multiplier of a randomization scale range (``*_scale``) and the smallest of the mass
#: and inertia scales: a 10x heavier or 10x lighter quad is another airframe, not a perturbation.
MAX_RANDOM_SCALE = 10.0
MIN_MASS_INERTIA_SCALE = 0.1
#: The largest ground-effect thrust gain: the Cheeseman-Bennett form reaches 2 at h = r / (2 sqrt 2),
#: well under the rotor radius where no measurement supports it (small rotors measure <= ~1.5).
MAX_GROUND_EFFECT_GAIN = 2.0
#: s, the longest episode: one day (a Crazyflie flies 7 minutes on a battery; the paper's episodes are
#: 15 s). Its control steps must also be <= MAX_EPISODE_STEPS.
MAX_EPISODE_SECONDS = 86400.0
#: The most control steps in an episode, 2^24: the JAX engine counts steps in int32 and takes the
#: time as float32(steps) * control_dt, exact in the step count up to 2^24 (one day at 100 Hz is 8.64e6).
MAX_EPISODE_STEPS = 2**24
#: m, the longest room side: 200 m, the original's "no walls" room (its motor-step recording,
#: tests/reference_data/golden_b_motor0_step.npz). The JAX engine holds positions in float32: 100 m
#: from the room's centre float32 resolves 7.6e-6 m, the distance a quad at 1.5 mm/s moves in a 5 ms
#: sub-step; much larger rooms would freeze slow quads far out. The paper's room is 10 m.
MAX_ROOM_SIDE = 200.0
#: The largest reward scale (every term of ``RewardScales``, ``ObstacleConfig.collision_reward``):
#: 2e5 times the paper's largest (5.0); larger scales only rescale the return, and keep the JAX
#: engine's float32 rewards far from overflow.
MAX_REWARD_SCALE = 1e6


def _is_real(x: Any) -> bool:
    """True for a real number (Python or NumPy int or float), False for bools, strings, complex..."""
    return isinstance(x, numbers.Real) and not isinstance(x, bool) and type(x).__name__ != "bool_"


def _as_int(name: str, value: Any, lo: int, what: str = "") -> int:
    """``value`` as a Python int (NumPy integers accepted) if it is an integer >= ``lo``, else ValueError."""
    if isinstance(value, numbers.Integral) and _is_real(value) and value >= lo:
        return int(value)
    raise ValueError(f"{name} must be an int >= {lo}{what}, got {value!r}")


def _numbers(name: str, value: Any, n: int, what: str) -> tuple[float, ...]:
    """``value`` as a tuple of ``n`` finite floats; ValueError ``"{name} must be {what}, got ..."``
    for strings, bools, non-numbers, a wrong length or NaN/inf."""
    try:
        if isinstance(value, (str, bytes)):
            raise TypeError
        items = list(value)
        if len(items) != n or not all(_is_real(x) for x in items):
            raise TypeError
        out = tuple(float(x) for x in items)
        if not all(math.isfinite(x) for x in out):
            raise TypeError
    except (TypeError, ValueError, OverflowError) as e:
        raise ValueError(f"{name} must be {what}, got {value!r}") from e
    return out


def _check_range(name: str, value: float, lo: float | None = None, hi: float | None = None,
                 lo_open: bool = False) -> None:
    """ValueError naming ``name`` and the allowed range unless ``value`` is a finite real in it."""
    bounds = [f"{'>' if lo_open else '>='} {lo}" if lo is not None else "", f"<= {hi}" if hi is not None else ""]
    rng = " and ".join(b for b in bounds if b)
    try:
        ok = _is_real(value) and math.isfinite(value)
    except OverflowError:  # a Python int beyond the float range
        ok = False
    if ok and lo is not None and (value < lo or (lo_open and value == lo)):
        ok = False
    if ok and hi is not None and value > hi:
        ok = False
    if not ok:
        raise ValueError(f"{name} must be a finite number{' ' + rng if rng else ''}, got {value!r}")


def _check_pair(name: str, pair: Any, lo: float | None = None, hi: float | None = None) -> tuple:
    a, b = _numbers(name, pair, 2, "a (low, high) pair of finite numbers")
    _check_range(f"{name}[0]", a, lo, hi)
    _check_range(f"{name}[1]", b, lo, hi)
    if a > b:
        raise ValueError(f"{name} must satisfy low <= high, got {pair!r}")
    return (a, b)
