"""Typed, frozen, validated configuration (SPEC §1-11 defaults).

Every config error is a ``ValueError`` naming the field and the allowed values.
Nested configs may be given as dicts, e.g. ``EnvConfig(noise={"sensor_pos_std": 0.0})``.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass, field, fields, replace
from typing import Any

from quadswarm_mj.config_checks import (  # noqa: F401  (re-exported: the limits are part of the config's API)
    COLLISION_MODELS,
    CONTROL_MODES,
    INERTIA_RANGE,
    MASS_RANGE,
    MAX_ANGULAR_ACCEL,
    MAX_EPISODE_SECONDS,
    MAX_EPISODE_STEPS,
    MAX_GRAVITY,
    MAX_GROUND_EFFECT_GAIN,
    MAX_RANDOM_SCALE,
    MAX_REWARD_SCALE,
    MAX_ROOM_SIDE,
    MAX_THRUST_TO_WEIGHT,
    MIN_MASS_INERTIA_SCALE,
    MIN_ROOM_HEIGHT,
    MIN_ROOM_SIDE,
    MOTOR_STARTS,
    NEIGHBOR_FORMS,
    NEIGHBOR_SORTS,
    OBS_SELF_VARIANTS,
    OMEGA_LIMIT,
    QUAD_PRESETS,
    SPAWN_MARGIN,
    SPAWN_MIN_Z,
    SPEED_LIMIT,
    _as_int,
    _check_pair,
    _check_range,
    _is_real,
    _numbers,
)
from quadswarm_mj.obstacle_config import OBSTACLE_DENSITY_VALUES, OBSTACLE_SIZE_VALUES, ObstacleConfig  # noqa: F401
from quadswarm_mj.scenarios import get_scenario
from quadswarm_mj.sensor_config import SensorConfig


@dataclass(frozen=True)
class QuadParams:
    """Nominal Crazyflie 2.x airframe (SPEC §1). SI units; body frame x forward, y left, z up."""

    mass: float = 0.028  # kg
    inertia: tuple[float, float, float] = (1.3669232142857e-05, 1.4356732142857e-05, 2.6561583333333e-05)
    arm: float = 0.04596194  # m, COM to rotor in xy
    rotor_z: float = -0.0034286  # m, rotor plane below the COM
    thrust_to_weight: float = 1.9  # all four rotors
    torque_to_thrust: float = 0.006  # N m per N
    motor_settling_time: float = 0.15  # s, 2 % settling (4 time constants)
    max_omega: float = 40.0  # rad/s, per body axis
    gravity: float = 9.81  # m/s^2
    #: q in [0, 1] of the static thrust map thrust / thrust_max = (1 - q) f + q f^2 of the normalized
    #: motor output f (PWM fraction); 0 (default) is the paper's linear model and is never evaluated.
    thrust_map_quadratic: float = 0.0

    def __post_init__(self) -> None:
        for n in ("arm", "torque_to_thrust", "motor_settling_time"):
            _check_range(f"quad.{n}", getattr(self, n), 0.0, lo_open=True)
        _check_range("quad.mass", self.mass, *MASS_RANGE)  # kg
        _check_range("quad.thrust_to_weight", self.thrust_to_weight, 0.0, MAX_THRUST_TO_WEIGHT, lo_open=True)
        _check_range("quad.max_omega", self.max_omega, 0.0, OMEGA_LIMIT, lo_open=True)  # rad/s
        _check_range("quad.gravity", self.gravity, 0.0, MAX_GRAVITY, lo_open=True)  # m/s^2
        _check_range("quad.thrust_map_quadratic", self.thrust_map_quadratic, 0.0, 1.0)
        if self.arm >= SPAWN_MARGIN:
            raise ValueError(f"quad.arm must be < {SPAWN_MARGIN} m (the spawn margin from walls and ceiling), "
                             f"got {self.arm!r}")
        _check_range("quad.rotor_z", self.rotor_z, -self.arm, self.arm)
        lo, hi = INERTIA_RANGE
        what = f"3 finite numbers >= {lo:g} and <= {hi:g} (kg m^2, Ixx, Iyy, Izz)"
        inertia = _numbers("quad.inertia", self.inertia, 3, what)
        if not all(lo <= i <= hi for i in inertia):
            raise ValueError(f"quad.inertia must be {what}, got {self.inertia!r}")
        object.__setattr__(self, "inertia", inertia)
        check_angular_accel(self, "quad")

    def angular_accel(self, thrust_scale: float = 1.0, torque_scale: float = 1.0,
                      inertia_scale: float = 1.0) -> tuple[float, float]:
        """Upper bounds (rad/s^2) of the (roll/pitch, yaw) angular acceleration the rotors can give:
        4 arm thrust_max / min(Ixx, Iyy) and 4 torque_max / Izz, with thrust_max, torque_max and the
        inertia multiplied by the given scales (the extremes of the randomization ranges)."""
        t = self.thrust_max * thrust_scale
        Ixx, Iyy, Izz = (i * inertia_scale for i in self.inertia)
        return 4.0 * self.arm * t / min(Ixx, Iyy), 4.0 * self.torque_to_thrust * torque_scale * t / Izz

    @property
    def thrust_max(self) -> float:
        """Max thrust per rotor (N), from the nominal mass and thrust-to-weight."""
        return self.gravity * self.mass * self.thrust_to_weight / 4.0

    @property
    def torque_max(self) -> float:
        """Max yaw reaction torque per rotor (N m)."""
        return self.torque_to_thrust * self.thrust_max

    @property
    def hover_command(self) -> float:
        """Normalized per-rotor command whose static thrust balances gravity (0.5263158 nominal)."""
        f, q = 1.0 / self.thrust_to_weight, self.thrust_map_quadratic
        if q == 0.0:
            return f
        return 2.0 * f / ((1.0 - q) + math.sqrt((1.0 - q) ** 2 + 4.0 * q * f))  # inverse of the thrust map

    @classmethod
    def preset(cls, name: str, **changes: Any) -> QuadParams:
        """A named airframe (``QUAD_PRESETS``), optionally with fields changed.

        * ``"quadswarm"``: the paper's constants (SPEC §1, the default ``QuadParams()``).
        * ``"crazyflie21_identified"``: the Crazyflie 2.x from published measurements and its system
          identification, sources in ``tests/reference_data/crazyflie2_thrust.json``: mass 0.027 kg
          (firmware ``CF_MASS``), inertia diag(16.571710, 16.655602, 29.261652) e-6 kg m^2 (Förster
          2015, as in the firmware's controller_sjc.c), arm 0.046 m (firmware ``ARM_LENGTH``),
          torque-to-thrust 0.005964552 m (firmware ``thrustToTorque``), motor settling time 0.18 s
          (Bitcraze: 0 to 25k rpm in about 180 ms), and the static thrust curve
          thrust = thrust_max ((1 - q) p + q p^2) of the PWM fraction p fitted (minimax relative error)
          to Bitcraze's PWM-to-thrust table over 12.5-93.75 % PWM: thrust_max = 0.15485 N per rotor
          (thrust-to-weight 2.339), q = 0.4302. (The firmware's own fit a p^2 + b p, a = 0.091492681 N,
          b = 0.067673604 N, misses that table by up to 18 % at low PWM; tests/test_thrust_curve.py.)
        """
        if name == "quadswarm":
            base = cls()
        elif name == "crazyflie21_identified":
            thrust_max, mass, g = 0.15485, 0.027, 9.81  # N per rotor, kg, m/s^2
            base = cls(mass=mass, inertia=(16.571710e-6, 16.655602e-6, 29.261652e-6), arm=0.046,
                       thrust_to_weight=4.0 * thrust_max / (mass * g), torque_to_thrust=0.005964552,
                       motor_settling_time=0.18, gravity=g, thrust_map_quadratic=0.4302)
        else:
            raise ValueError(f"quad preset must be one of {QUAD_PRESETS}, got {name!r}")
        return replace(base, **changes) if changes else base

    @property
    def hover_action(self) -> float:
        """Raw action in [-1, 1] whose command is the hover thrust."""
        return 2.0 * self.hover_command - 1.0


def check_angular_accel(quad: QuadParams, where: str, thrust_scale: float = 1.0, torque_scale: float = 1.0,
                        inertia_scale: float = 1.0) -> None:
    """ValueError unless the airframe's angular accelerations (:meth:`QuadParams.angular_accel`) are
    <= MAX_ANGULAR_ACCEL; ``where`` says which ranges gave the scales."""
    roll, yaw = quad.angular_accel(thrust_scale, torque_scale, inertia_scale)
    if roll > MAX_ANGULAR_ACCEL:
        raise ValueError(f"{where}: quad.inertia {quad.inertia} kg m^2 is too small for quad.arm, quad.mass and "
                         f"quad.thrust_to_weight: the roll/pitch angular acceleration reaches {roll:.4g} rad/s^2 "
                         f"(4 arm thrust_max / min(Ixx, Iyy)); it must be <= MAX_ANGULAR_ACCEL = "
                         f"{MAX_ANGULAR_ACCEL:g} rad/s^2 (from rest to the spin limit within one 5 ms sub-step)")
    if yaw > MAX_ANGULAR_ACCEL:
        raise ValueError(f"{where}: quad.torque_to_thrust {quad.torque_to_thrust!r} m with quad.inertia[2] "
                         f"{quad.inertia[2]!r} kg m^2 gives a yaw angular acceleration up to {yaw:.4g} rad/s^2 "
                         f"(4 torque_max / Izz); it must be <= MAX_ANGULAR_ACCEL = {MAX_ANGULAR_ACCEL:g} rad/s^2")


@dataclass(frozen=True)
class NoiseConfig:
    """Noise sources (SPEC §2, §5-7). ``EnvConfig.without_noise()`` turns all of them off."""

    motor_noise_ratio: float = 0.05  # OU sigma = 0.2 * ratio
    motor_noise_theta: float = 0.15
    sensor_pos_std: float = 0.005  # m
    sensor_vel_std: float = 0.01  # m/s
    sensor_omega_std: float = 1.75e-4  # rad/s
    neighbor_obs_noise: bool = False  # the original leaves neighbour observations noise-free
    stochastic_collisions: bool = True  # False: every collision draw takes its mean
    stochastic_downwash: bool = True  # False: downwash draws take their means

    def __post_init__(self) -> None:
        # bounds: a motor noise beyond the thrust range, or a sensor noise beyond the largest value the
        # quantity can take (room side, SPEED_LIMIT, OMEGA_LIMIT), is no longer a perturbation
        for n, hi in (("motor_noise_ratio", 1.0), ("sensor_pos_std", MAX_ROOM_SIDE), ("sensor_vel_std", SPEED_LIMIT),
                      ("sensor_omega_std", OMEGA_LIMIT)):
            _check_range(f"noise.{n}", getattr(self, n), 0.0, hi)
        _check_range("noise.motor_noise_theta", self.motor_noise_theta, 0.0, 1.0)


@dataclass(frozen=True)
class RandomizationConfig:
    """Per-reset, per-quad ranges (SPEC §11); used when ``EnvConfig.randomize`` is True."""

    mass_scale: tuple[float, float] = (0.8, 1.2)
    inertia_scale: tuple[float, float] = (0.8, 1.2)
    thrust_to_weight: tuple[float, float] = (1.7, 2.1)
    torque_to_thrust_scale: tuple[float, float] = (0.8, 1.2)
    motor_settling_time: tuple[float, float] = (0.15, 0.2)
    rotor_thrust_scale: tuple[float, float] = (0.9, 1.1)
    motor_noise_ratio: tuple[float, float] = (0.01, 0.05)

    def __post_init__(self) -> None:
        bounds = {"mass_scale": (MIN_MASS_INERTIA_SCALE, MAX_RANDOM_SCALE),
                  "inertia_scale": (MIN_MASS_INERTIA_SCALE, MAX_RANDOM_SCALE),
                  "thrust_to_weight": (0.0, MAX_THRUST_TO_WEIGHT), "torque_to_thrust_scale": (0.0, MAX_RANDOM_SCALE),
                  "rotor_thrust_scale": (0.0, MAX_RANDOM_SCALE), "motor_noise_ratio": (0.0, 1.0)}
        for f in fields(self):
            lo, hi = bounds.get(f.name, (0.0, None))
            object.__setattr__(self, f.name, _check_pair(f"randomization.{f.name}",
                                                         getattr(self, f.name), lo, hi))
        for n in ("mass_scale", "inertia_scale", "thrust_to_weight", "motor_settling_time",
                  "rotor_thrust_scale"):
            if getattr(self, n)[0] <= 0:
                raise ValueError(f"randomization.{n} must be > 0, got {getattr(self, n)!r}")


#: the largest ``rewards.vel_limit`` (m/s): the velocity observation's bound
MAX_VEL_LIMIT = 20.0


@dataclass(frozen=True)
class RewardScales:
    """Reward-term scales (SPEC §8, paper baseline), time-scaled as the original: the state terms
    (pos ... rot) give r = -sim_dt * scale * cost, ``proximity`` r = -control_dt * scale * cost, and the
    event terms (quad_collision, floor_hit, wall_hit, ceiling_hit) r = -scale * count (not time-scaled:
    a new collision at the baseline 5.0 costs 5.0 per quad involved)."""

    pos: float = 1.0
    effort: float = 0.05
    spin: float = 0.1
    crash: float = 1.0
    orient: float = 1.0
    vel: float = 0.0
    action_change: float = 0.0
    yaw: float = 0.0
    rot: float = 0.0
    quad_collision: float = 5.0
    proximity: float = 10.0
    floor_hit: float = 0.0
    wall_hit: float = 0.0
    ceiling_hit: float = 0.0
    proximity_falloff_arms: float = 4.0  # falloff = this * arm
    vel_limit: float = 0.0  # m/s: the vel cost is the speed above it, max(||v|| - vel_limit, 0) (0: ||v||)
    anneal_steps: int = 0  # control steps over which collision terms ramp from 0 (0: no annealing)

    TERMS = ("pos", "effort", "spin", "crash", "orient", "vel", "action_change", "yaw", "rot",
             "quad_collision", "proximity", "floor_hit", "wall_hit", "ceiling_hit")

    def __post_init__(self) -> None:
        for n in self.TERMS:
            _check_range(f"rewards.{n}", getattr(self, n), 0.0, MAX_REWARD_SCALE)
        _check_range("rewards.proximity_falloff_arms", self.proximity_falloff_arms, 0.0, lo_open=True)
        _check_range("rewards.vel_limit", self.vel_limit, 0.0, MAX_VEL_LIMIT)
        object.__setattr__(self, "anneal_steps", _as_int("rewards.anneal_steps", self.anneal_steps, 0))

    @classmethod
    def paper_baseline(cls) -> RewardScales:
        """The scales of the paper's baseline (the defaults)."""
        return cls()


@dataclass(frozen=True)
class AeroConfig:
    """Aerodynamic effects beyond the paper (off by default), see :mod:`quadswarm_mj.aerodynamics`.

    * ground effect: per-rotor thrust gain 1 / (1 - (r / 4 h)^2) at rotor height h above the floor
      (Cheeseman & Bennett 1955), r = ``rotor_radius`` (the Crazyflie's 46.2 mm props: 0.0231 m;
      gym-pybullet-drones ``cf2x.urdf`` prop_radius 2.31348e-2 m), clipped at ``ground_effect_max_gain``
      (4/3 = the form at h = r / 2, the lower end of its validity);
    * rotor (blade) drag: body-frame force -diag(``drag_coeff``) * (sum of rotor speeds, rad/s) * v_body,
      drag_coeff in N / (m/s) / (rad/s) from gym-pybullet-drones ``cf2x.urdf`` (drag_coeff_xy 9.1785e-7,
      drag_coeff_z 10.311e-7, after Förster 2015); rotor speeds from the rotor thrust by
      F = ``thrust_coeff`` * w^2 (3.16e-10 N/rpm^2 = 2.8816e-8 N/(rad/s)^2, the same source).

    ``*_scale`` are per-quad randomization ranges (multipliers, drawn per reset when
    ``EnvConfig.randomize``).
    """

    ground_effect: bool = False
    drag: bool = False
    rotor_radius: float = 0.0231  # m
    ground_effect_max_gain: float = 4.0 / 3.0
    drag_coeff: tuple[float, float, float] = (9.1785e-7, 9.1785e-7, 10.311e-7)  # N/(m/s)/(rad/s), body x, y, z
    thrust_coeff: float = 3.16e-10 * (60.0 / (2.0 * math.pi)) ** 2  # N/(rad/s)^2
    rotor_radius_scale: tuple[float, float] = (0.9, 1.1)
    drag_scale: tuple[float, float] = (0.5, 1.5)

    def __post_init__(self) -> None:
        for n in ("ground_effect", "drag"):
            if not isinstance(getattr(self, n), bool):
                raise ValueError(f"aero.{n} must be a bool, got {getattr(self, n)!r}")
        _check_range("aero.rotor_radius", self.rotor_radius, 0.0, lo_open=True)
        _check_range("aero.ground_effect_max_gain", self.ground_effect_max_gain, 1.0, MAX_GROUND_EFFECT_GAIN,
                     lo_open=True)
        _check_range("aero.thrust_coeff", self.thrust_coeff, 0.0, lo_open=True)
        d = _numbers("aero.drag_coeff", self.drag_coeff, 3, "3 numbers >= 0")
        for i, x in enumerate(d):
            _check_range(f"aero.drag_coeff[{i}]", x, 0.0)
        object.__setattr__(self, "drag_coeff", d)
        for n in ("rotor_radius_scale", "drag_scale"):
            object.__setattr__(self, n, _check_pair(f"aero.{n}", getattr(self, n), 0.0))

    @property
    def any(self) -> bool:
        """True if any aerodynamic effect is on."""
        return self.ground_effect or self.drag


@dataclass(frozen=True)
class CollisionParams:
    """Constants of the paper's collision model (SPEC §4-5)."""

    hitbox_arms: float = 2.0  # hitbox = hitbox_arms * arm
    tries: int = 3
    shared_noise_std: float = 0.8
    own_noise_std: float = 0.15
    kick_omega: tuple[float, float] = (10 * math.pi, 20 * math.pi)  # rad/s
    wall_speed_limits: tuple[float, float] = (0.1, 6.0)  # m/s
    floor_friction: float = 0.6

    def __post_init__(self) -> None:
        _check_range("collision.hitbox_arms", self.hitbox_arms, 0.0, lo_open=True)
        object.__setattr__(self, "tries", _as_int("collision.tries", self.tries, 1))
        _check_range("collision.shared_noise_std", self.shared_noise_std, 0.0)
        _check_range("collision.own_noise_std", self.own_noise_std, 0.0)
        object.__setattr__(self, "kick_omega", _check_pair("collision.kick_omega", self.kick_omega, 0.0, OMEGA_LIMIT))
        object.__setattr__(self, "wall_speed_limits",
                           _check_pair("collision.wall_speed_limits", self.wall_speed_limits, 0.0, SPEED_LIMIT))
        _check_range("collision.floor_friction", self.floor_friction, 0.0)


#: the supported maximum of ``EnvConfig.num_quads`` (quads in one world): building the MuJoCo model grows
#: faster than linearly in the quads (about 4 s at 1,000 on one core, MuJoCo's compile dominating) and every
#: step holds (N, N) pair arrays (distances, contacts)
MAX_QUADS = 1024

_NESTED = {"quad": QuadParams, "noise": NoiseConfig, "randomization": RandomizationConfig,
           "rewards": RewardScales, "collision": CollisionParams, "aero": AeroConfig, "sensors": SensorConfig}


@dataclass(frozen=True)
class EnvConfig:
    """Everything that defines a quadswarm_mj environment.

    Units: SI. ``room_size`` is (length x, width y, height z) in m; the room is the box
    [-L/2, L/2] x [-W/2, W/2] x [0, H]. ``num_quads`` is at most :data:`MAX_QUADS` (1024).
    """

    num_quads: int = 8
    scenario: str = "static_same_goal"
    room_size: tuple[float, float, float] = (10.0, 10.0, 10.0)
    control_hz: int = 100
    sim_hz: int = 200
    episode_seconds: float = 15.0
    downwash: bool = False
    collision_model: str = "paper"
    collision_decay: tuple[float, float] = (0.2, 0.8)
    num_neighbors: int | None = None  # None: min(6, num_quads - 1)
    motor_start: str = "zero"
    randomize: bool = False
    obs_self: str = "base"  # "base" (18), "floor" (19: + z), "wall" (24: + wall distances)
    neighbor_sort: str = "distance"  # "distance" or "original" (d + unit(r).dv, d >= 0.01)
    neighbor_vel_clip: float = 6.0  # m/s, clip of neighbour relative velocity
    neighbor_form: str = "raw"  # "raw" (p_j - p_i, v_j - v_i) or "near" (0 beyond neighbor_near_range; observations)
    neighbor_near_range: float = 1.0  # m, the reach of neighbor_form="near"
    normalize_obs: bool = False
    formation_center: tuple[float, float, float] = (0.0, 0.0, 2.0)
    grace_period_s: float = 1.5  # s, collisions before this are not counted in the episode metrics (the reward
    # penalizes every collision)
    quad: QuadParams = field(default_factory=QuadParams)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    randomization: RandomizationConfig = field(default_factory=RandomizationConfig)
    rewards: RewardScales = field(default_factory=RewardScales)
    collision: CollisionParams = field(default_factory=CollisionParams)
    control_mode: str = "rotor"  # "rotor", "ctbr", "attitude", "velocity" (quadswarm_mj.control_modes)
    aero: AeroConfig = field(default_factory=AeroConfig)
    obstacles: ObstacleConfig | None = None  # None: no obstacles (SPEC_obstacles)
    info_mode: str = "nested"  # "nested" (info["state"]["pos"]) or "flat" ("state/pos", quadswarm_mj.envs.flat_info)
    sensors: SensorConfig = field(default_factory=SensorConfig)  # deck sensors, all off (quadswarm_mj.sensors)

    def __post_init__(self) -> None:
        if isinstance(self.quad, str):  # a preset name
            object.__setattr__(self, "quad", QuadParams.preset(self.quad))
        for name, cls in _NESTED.items():
            v = getattr(self, name)
            if isinstance(v, dict):
                try:
                    v = cls(**v)
                except TypeError as e:
                    raise ValueError(f"{name}: {e}") from e
                object.__setattr__(self, name, v)
            elif not isinstance(v, cls):
                raise ValueError(f"{name} must be a {cls.__name__} or a dict, got {type(v).__name__}")
        object.__setattr__(self, "num_quads", _as_int("num_quads", self.num_quads, 1))
        room = _numbers("room_size", self.room_size, 3, f"3 numbers (m), the room's length x, width y and height z, "
                                                        f"each in (0, {MAX_ROOM_SIDE:g}]")
        if not all(x > 0 for x in room):
            raise ValueError(f"room_size must be 3 positive finite numbers (m), got {self.room_size!r}")
        if max(room) > MAX_ROOM_SIDE:
            raise ValueError(f"room_size sides must be <= {MAX_ROOM_SIDE:g} m (MAX_ROOM_SIDE: the JAX engine holds "
                             f"positions in float32), got {self.room_size!r}")
        if room[2] < MIN_ROOM_HEIGHT:
            raise ValueError(f"room_size[2] (height) must be >= {MIN_ROOM_HEIGHT} m (quads spawn at z >= "
                             f"{SPAWN_MIN_Z} m and {SPAWN_MARGIN} m below the ceiling), got {room[2]!r}")
        if min(room[:2]) < MIN_ROOM_SIDE:
            raise ValueError(f"room_size[0] and room_size[1] (length, width) must be >= {MIN_ROOM_SIDE} m "
                             f"(quads spawn {SPAWN_MARGIN} m from the walls), got {self.room_size!r}")
        object.__setattr__(self, "room_size", room)
        for n in ("control_hz", "sim_hz"):
            v = getattr(self, n)
            if not (isinstance(v, numbers.Integral) and _is_real(v) and v >= 1):
                raise ValueError(f"{n} must be a positive int (hz), got {v!r}")
            object.__setattr__(self, n, int(v))
        if self.sim_hz % self.control_hz != 0:
            raise ValueError(f"sim_hz must be a multiple of control_hz, got sim_hz={self.sim_hz}, "
                             f"control_hz={self.control_hz}")
        self._check_episode_seconds()
        for n, choices in (("collision_model", COLLISION_MODELS), ("motor_start", MOTOR_STARTS),
                           ("obs_self", OBS_SELF_VARIANTS), ("control_mode", CONTROL_MODES),
                           ("info_mode", ("nested", "flat")), ("neighbor_sort", NEIGHBOR_SORTS),
                           ("neighbor_form", NEIGHBOR_FORMS)):
            if getattr(self, n) not in choices:
                raise ValueError(f"{n} must be one of {choices}, got {getattr(self, n)!r}")
        # a collision never speeds a quad up (decay multiplies the speed)
        object.__setattr__(self, "collision_decay", _check_pair("collision_decay", self.collision_decay, 0.0, 1.0))
        if self.num_quads > MAX_QUADS:
            raise ValueError(f"num_quads must be at most MAX_QUADS = {MAX_QUADS} (the supported maximum per world: "
                             f"MuJoCo's model build grows faster than linearly and each step holds (N, N) pair "
                             f"arrays), got {self.num_quads!r}; use more worlds (QuadSwarmVectorEnv) instead")
        if self.num_neighbors is not None:
            k = self.num_neighbors
            if not (isinstance(k, numbers.Integral) and _is_real(k) and 0 <= k <= self.num_quads - 1):
                raise ValueError(f"num_neighbors must be an int in [0, num_quads - 1] = [0, {self.num_quads - 1}] "
                                 f"(each quad has num_quads - 1 neighbors), got {k!r}")
            object.__setattr__(self, "num_neighbors", int(k))
        # two quads at SPEED_LIMIT close at 2 SPEED_LIMIT; a grace period longer than the longest episode means
        # nothing; the formation centre is a point of a room no side of which exceeds MAX_ROOM_SIDE
        _check_range("neighbor_vel_clip", self.neighbor_vel_clip, 0.0, 2 * SPEED_LIMIT, lo_open=True)
        _check_range("neighbor_near_range", self.neighbor_near_range, 0.0, 10.0, lo_open=True)
        _check_range("grace_period_s", self.grace_period_s, 0.0, MAX_EPISODE_SECONDS)
        fc = _numbers("formation_center", self.formation_center, 3, "3 finite numbers (m)")
        if max(abs(x) for x in fc) > MAX_ROOM_SIDE:
            raise ValueError(f"formation_center must be 3 numbers (m) within +-{MAX_ROOM_SIDE:g} m (MAX_ROOM_SIDE), "
                             f"got {self.formation_center!r}")
        object.__setattr__(self, "formation_center", fc)
        for n in ("downwash", "randomize", "normalize_obs"):
            if not isinstance(getattr(self, n), bool):
                raise ValueError(f"{n} must be a bool, got {getattr(self, n)!r}")
        self._check_obstacles()
        self._check_airframe_ranges()
        scn = get_scenario(self.scenario)
        if getattr(scn, "requires_obstacles", False) and self.obstacles is None:
            raise ValueError(f"scenario {self.scenario!r} needs obstacles, which are off (obstacles=None); turn them "
                             f"on with EnvConfig(scenario={self.scenario!r}, obstacles=ObstacleConfig()) "
                             f"(or obstacles={{}} for the defaults)")

    def _check_episode_seconds(self) -> None:
        """At least one control step, at most MAX_EPISODE_SECONDS and MAX_EPISODE_STEPS control steps."""
        v, dt = self.episode_seconds, 1.0 / self.control_hz
        _check_range("episode_seconds", v, 0.0, MAX_EPISODE_SECONDS, lo_open=True)
        if v < dt:
            raise ValueError(f"episode_seconds must be at least one control step (1 / control_hz = {dt:g} s) and "
                             f"<= {MAX_EPISODE_SECONDS:g} s, got {v!r}")
        steps = int(round(v * self.control_hz))
        if steps > MAX_EPISODE_STEPS:
            raise ValueError(f"episode_seconds * control_hz = {steps} control steps must be <= 2^24 = "
                             f"{MAX_EPISODE_STEPS} (the JAX engine's float32 step time is exact up to 2^24 steps); "
                             f"got episode_seconds={v!r}, control_hz={self.control_hz}")

    def _check_airframe_ranges(self) -> None:
        """Bounds on the strongest airframe the randomization ranges can draw (``randomize``) and on the
        rotor drag's explicit step (``aero.drag``)."""
        q, r = self.quad, self.randomization
        thrust_hi = r.thrust_to_weight[1] / q.thrust_to_weight * r.rotor_thrust_scale[1] if self.randomize else 1.0
        mass_lo = r.mass_scale[0] if self.randomize else 1.0
        if self.randomize:
            ttw = q.thrust_to_weight * thrust_hi / mass_lo
            if ttw > MAX_THRUST_TO_WEIGHT:
                raise ValueError(f"randomization: the strongest quad the ranges can draw has thrust-to-weight "
                                 f"{ttw:.4g} (thrust_to_weight[1] * rotor_thrust_scale[1] / mass_scale[0]); it must "
                                 f"be <= MAX_THRUST_TO_WEIGHT = {MAX_THRUST_TO_WEIGHT:g}")
            if q.mass * mass_lo < MASS_RANGE[0] or min(q.inertia) * r.inertia_scale[0] < INERTIA_RANGE[0]:
                raise ValueError(f"randomization: quad.mass * mass_scale[0] must be >= {MASS_RANGE[0]:g} kg and "
                                 f"quad.inertia * inertia_scale[0] >= {INERTIA_RANGE[0]:g} kg m^2")
            check_angular_accel(q, "randomization (the strongest quad the ranges can draw)", thrust_hi,
                                r.torque_to_thrust_scale[1], r.inertia_scale[0])
        a = self.aero
        if a.drag:
            gain = a.ground_effect_max_gain if a.ground_effect else 1.0
            drag_hi = max(a.drag_coeff) * (a.drag_scale[1] if self.randomize else 1.0)
            rotor_speed = math.sqrt(q.thrust_max * thrust_hi * gain / a.thrust_coeff)  # rad/s, full thrust
            rate = drag_hi * 4.0 * rotor_speed / (q.mass * mass_lo)  # 1/s, dv/dt = -rate v
            if rate * self.sim_dt > 1.0:
                raise ValueError(f"aero.drag_coeff {a.drag_coeff} and aero.thrust_coeff {a.thrust_coeff!r} give a "
                                 f"rotor-drag rate up to {rate:.4g} 1/s (drag_coeff * sum of rotor speeds / mass); "
                                 f"rate * sim_dt ({self.sim_dt:g} s) must be <= 1, beyond which the explicit drag "
                                 f"step overshoots and diverges: lower aero.drag_coeff or raise aero.thrust_coeff "
                                 f"or sim_hz")

    def _check_obstacles(self) -> None:
        o = self.obstacles
        if o is None:
            return
        if isinstance(o, dict):
            try:
                o = ObstacleConfig(**o)
            except TypeError as e:
                raise ValueError(f"obstacles: {e}") from e
            object.__setattr__(self, "obstacles", o)
        elif not isinstance(o, ObstacleConfig):
            raise ValueError(f"obstacles must be an ObstacleConfig, a dict or None, got {type(o).__name__}")
        L, W, _ = self.room_size
        for i, (a, r) in enumerate(zip(o.area, (L, W))):
            if a > r:
                raise ValueError(f"obstacles.area[{i}] = {a} m must fit inside the room (room_size[{i}] = {r} m)")
        free = o.num_cells - o.columns_needed
        if free < self.num_quads:
            raise ValueError(f"obstacles: {o.num_cells} cells with up to {o.columns_needed} columns leave {free} free "
                             f"cells, fewer than num_quads = {self.num_quads} (spawns need distinct free cells); "
                             f"lower obstacles.density or enlarge obstacles.area")

    # ---- derived quantities ----
    @property
    def sim_dt(self) -> float:
        return 1.0 / self.sim_hz

    @property
    def control_dt(self) -> float:
        return 1.0 / self.control_hz

    @property
    def substeps(self) -> int:
        return self.sim_hz // self.control_hz

    @property
    def episode_steps(self) -> int:
        return int(round(self.episode_seconds * self.control_hz))

    @property
    def neighbors(self) -> int:
        """Resolved K: ``num_neighbors`` or min(6, num_quads - 1)."""
        return min(6, self.num_quads - 1) if self.num_neighbors is None else self.num_neighbors

    @property
    def self_obs_dim(self) -> int:
        return {"base": 18, "floor": 19, "wall": 24}[self.obs_self]

    @property
    def obs_dim(self) -> int:
        """Self block + 6 per neighbour (+ 9 obstacle distance features when obstacles are on and
        ``obstacles.observe_features``) (+ the deck sensors' ``sensors.obs_dim`` readings, last)."""
        features = self.obstacles.feature_dim if self.obstacles is not None else 0
        return self.self_obs_dim + 6 * self.neighbors + features + self.sensors.obs_dim

    @property
    def hitbox(self) -> float:
        return self.collision.hitbox_arms * self.quad.arm

    @property
    def room_low(self) -> tuple[float, float, float]:
        L, W, _ = self.room_size
        return (-L / 2, -W / 2, 0.0)

    @property
    def room_high(self) -> tuple[float, float, float]:
        L, W, H = self.room_size
        return (L / 2, W / 2, H)

    def replace(self, **changes: Any) -> EnvConfig:
        """Copy with fields changed (validated again)."""
        return replace(self, **changes)

    def without_noise(self) -> EnvConfig:
        """Copy with every noise source and randomization off, and the collision and
        downwash draws replaced by their means (SPEC §5, §6). Obstacles are kept (their
        response's draws take their means too, through ``noise.stochastic_collisions``); the deck
        sensors read noise-free (``sensors.noise`` False)."""
        noise = replace(self.noise, motor_noise_ratio=0.0, sensor_pos_std=0.0, sensor_vel_std=0.0,
                        sensor_omega_std=0.0, neighbor_obs_noise=False, stochastic_collisions=False,
                        stochastic_downwash=False)
        return replace(self, noise=noise, randomize=False, sensors=replace(self.sensors, noise=False))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)
