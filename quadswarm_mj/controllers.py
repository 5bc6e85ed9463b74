"""Baseline geometric position controller: goals -> normalized per-rotor actions.

:class:`PositionController` is a Lee / Mellinger style controller on SE(3): a saturated position loop
(world frame) -> collective thrust along body z -> geometric attitude loop -> the inverse rotor mixing of
:func:`quadswarm_mj.actuation.body_wrench` (attitude first) -> actions ``2 f - 1`` in [-1, 1]. Stateless and
vectorized: arrays (..., N, ...) with any leading batch dims, NumPy or ``jax.numpy``. Units SI;
``pos``/``vel``/goals in the world frame (m, m/s), ``rot`` body to world, ``omega`` body frame (rad/s).
The loop equations: docs/model.md ("The baseline controller").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

from quadswarm_mj._xp import array_namespace
from quadswarm_mj.actuation import SPIN, inverse_thrust_map, rotor_positions
from quadswarm_mj.config import EnvConfig, QuadParams


def _check_positive(name: str, value: float, allow_zero: bool = False) -> None:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < 0 or (value == 0 and not allow_zero):
        op = ">=" if allow_zero else ">"
        raise ValueError(f"controller gain {name} must be a finite number {op} 0, got {value!r}")


@dataclass(frozen=True)
class ControllerGains:
    """Gains and limits of :class:`PositionController` (SI units).

    Position gains are accelerations per metre (kp, 1/s^2) and per m/s (kv, 1/s); attitude gains
    are angular accelerations per unit attitude error (kR, 1/s^2) and per rad/s (kw, 1/s), scaled by
    the inertia inside the controller, so they do not depend on the airframe.
    """

    kp: tuple[float, float, float] = (6.0, 6.0, 8.0)  # 1/s^2, per world axis x, y, z
    kv: tuple[float, float, float] = (4.0, 4.0, 5.0)  # 1/s
    kR: tuple[float, float, float] = (500.0, 500.0, 60.0)  # 1/s^2, per body axis
    kw: tuple[float, float, float] = (38.0, 38.0, 12.0)  # 1/s
    max_pos_error: float = 1.0  # m, norm of the position error fed to the loop
    max_tilt_deg: float = 35.0  # deg, tilt of the commanded thrust from vertical
    max_up_acc: float = 8.0  # m/s^2, commanded vertical acceleration above g
    max_down_acc: float = 6.0  # m/s^2, commanded vertical deceleration (< g keeps thrust > 0)
    max_thrust_fraction: float = 0.95  # collective limit, fraction of sum(thrust_max)
    avoid_radius: float = 0.0  # m, neighbours closer than this repel (0: no collision avoidance)
    avoid_acc: float = 6.0  # m/s^2, repulsion at zero distance (falls linearly to 0 at avoid_radius)
    avoid_swirl: float = 0.5  # sideways (right-hand) share of the repulsion, breaks head-on deadlocks
    avoid_damping: float = 4.0  # 1/s, brakes the closing speed of neighbours within avoid_radius
    obstacle_radius: float = 0.0  # m from a column's surface within which it repels (0: columns ignored)
    obstacle_gain: float = 8.0  # m/s^2, horizontal repulsion at the surface (falls linearly to 0 at obstacle_radius)
    obstacle_swirl: float = 0.6  # tangential share of the repulsion (side of the current motion): slides around
    obstacle_damping: float = 4.0  # 1/s, brakes the approach speed toward columns within obstacle_radius
    column_radius: float = 0.3  # m, column radius used when ``obstacles`` is a plain (..., M, 2) array

    def __post_init__(self) -> None:
        for n in ("kp", "kv", "kR", "kw"):
            v = getattr(self, n)
            if isinstance(v, (int, float)):
                v = (v, v, v)
            try:
                v = tuple(float(x) for x in v)
            except TypeError as e:
                raise ValueError(f"controller gain {n} must be a number or 3 numbers, got {v!r}") from e
            if len(v) != 3:
                raise ValueError(f"controller gain {n} must be a number or 3 numbers, got {v!r}")
            for x in v:
                _check_positive(n, x, allow_zero=n in ("kv", "kw"))
            object.__setattr__(self, n, v)
        for f in fields(self):
            if f.name not in ("kp", "kv", "kR", "kw"):
                _check_positive(f.name, getattr(self, f.name), allow_zero=f.name.startswith(("avoid", "obstacle")))
        if not self.max_tilt_deg < 89.0:
            raise ValueError(f"controller max_tilt_deg must be < 89, got {self.max_tilt_deg!r}")
        if self.max_thrust_fraction > 1.0:
            raise ValueError(f"controller max_thrust_fraction must be <= 1, got {self.max_thrust_fraction!r}")


def _cross(xp: Any, a: Any, b: Any) -> Any:
    return xp.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def _normalize(xp: Any, v: Any, fallback: Any) -> Any:
    n = xp.sqrt(xp.sum(v * v, axis=-1, keepdims=True))
    return xp.where(n > 1e-9, v / xp.maximum(n, 1e-9), fallback)


def _max_scale(a: Any, b: Any, g: Any) -> Any:
    """Largest s in [0, 1] such that rotor thrusts ``k g + a + s b`` fit in [0, 1] for some k.

    ``a``, ``b``, ``g`` are (..., 4); ``g > 0`` is the collective direction (rotor thrust per N of
    collective). Feasible iff for every pair (i, j): -(a_i + s b_i)/g_i <= (1 - a_j - s b_j)/g_j,
    i.e. s (b_j/g_j - b_i/g_i) <= 1/g_j - a_j/g_j + a_i/g_i.
    """
    xp = array_namespace(a, b, g)
    an, bn, inv = a / g, b / g, 1.0 / g
    coef = bn[..., None, :] - bn[..., :, None]  # [i, j] = b_j/g_j - b_i/g_i
    rhs = inv[..., None, :] - an[..., None, :] + an[..., :, None]
    pos = coef > 1e-12
    ratio = xp.where(pos, rhs / xp.where(pos, coef, 1.0), xp.inf)
    s = xp.min(xp.min(ratio, axis=-1), axis=-1)
    return xp.clip(s, 0.0, 1.0)


class PositionController:
    """Geometric position + attitude controller for N quads (equations: docs/model.md).

    ``PositionController(cfg)`` with an :class:`EnvConfig` (or a :class:`QuadParams`) and optional
    :class:`ControllerGains`; call it as ``ctrl(state, goals, goal_vel=None, params=None)``:

    * ``state``: the ``info["state"]`` dict of the envs, arrays (..., N, ...): ``pos`` (m, world),
      ``vel`` (m/s, world), ``rot`` (body -> world), ``omega`` (rad/s, body); other keys ignored;
    * ``goals`` (..., N, 3) m and ``goal_vel`` (..., N, 3) m/s (feed-forward; zero if None);
    * ``params``: optional per-quad dynamics parameters, e.g. ``info["params"]``; any of
      ``mass`` (..., N) kg, ``inertia`` (..., N, 3) kg m^2, ``thrust_max`` and ``torque_max``
      (..., N, 4) N and N m per rotor. Missing keys take the nominal airframe of ``cfg``.

    Returns actions (..., N, 4) in [-1, 1] (same namespace as ``state["pos"]``) of the "rotor"
    control mode (an ``EnvConfig`` with another ``control_mode`` raises ValueError); for airframes
    with a nonlinear thrust map (``QuadParams.thrust_map_quadratic``, e.g. the
    "crazyflie21_identified" preset) the rotor thrusts go through ``inverse_thrust_map``.
    ``yaw`` (rad, scalar or (..., N)) sets a heading to hold; None (default) keeps the current
    heading and only damps the yaw rate (the position loop does not need a heading).
    ``obstacles``: optional columns to steer around (an ``ObstacleMap``, or the (..., M, 2) centres
    of ``info["obstacles"]`` with radius ``gains.column_radius``); active when
    ``gains.obstacle_radius > 0`` (:meth:`obstacle_acceleration`).
    """

    def __init__(self, cfg: EnvConfig | QuadParams | None = None, gains: ControllerGains | dict | None = None,
                 yaw: Any = None):
        if cfg is None:
            quad, gravity = QuadParams(), QuadParams().gravity
        elif isinstance(cfg, EnvConfig):
            if cfg.control_mode != "rotor":
                raise ValueError(f"PositionController returns per-rotor actions: it needs control_mode='rotor', "
                                 f"got control_mode={cfg.control_mode!r} (the 'velocity' mode is a built-in "
                                 f"velocity controller)")
            quad, gravity = cfg.quad, cfg.quad.gravity
        elif isinstance(cfg, QuadParams):
            quad, gravity = cfg, cfg.gravity
        else:
            raise ValueError(f"cfg must be an EnvConfig or QuadParams, got {type(cfg).__name__}")
        if gains is None:
            gains = ControllerGains()
        elif isinstance(gains, dict):
            gains = ControllerGains(**gains)
        elif not isinstance(gains, ControllerGains):
            raise ValueError(f"gains must be a ControllerGains or a dict, got {type(gains).__name__}")
        self.quad, self.gains, self.gravity, self.yaw = quad, gains, float(gravity), yaw
        self.rotor_pos = rotor_positions(quad)  # (4, 3) body frame, m
        self.spin = SPIN.copy()

    # ------------------------------------------------------------------ mixing
    def mixer(self, thrust_max: Any, torque_max: Any) -> Any:
        """(..., 4, 4) matrix mapping normalized rotor thrusts f to (T, tau_x, tau_y, tau_z) (N, N m),
        the linear map of :func:`quadswarm_mj.actuation.body_wrench`."""
        xp = array_namespace(thrust_max, torque_max)
        rx, ry = self.rotor_pos[:, 0], self.rotor_pos[:, 1]
        return xp.stack([thrust_max, ry * thrust_max, -rx * thrust_max, self.spin * torque_max], axis=-2)

    def _avoidance(self, xp: Any, pos: Any, vel: Any) -> Any:
        """Repulsive acceleration (..., N, 3) from neighbours within ``avoid_radius`` (world frame):
        linear in the penetration, along the separation plus a right-hand sideways share, and a
        brake on the closing speed."""
        g = self.gains
        rel = pos[..., :, None, :] - pos[..., None, :, :]  # (..., N, N, 3), i minus j
        d = xp.sqrt(xp.sum(rel * rel, axis=-1) + 1e-12)
        n = pos.shape[-2]
        near = (d < g.avoid_radius) & ~xp.eye(n, dtype=bool)
        w = xp.where(near, g.avoid_acc * (1.0 - d / g.avoid_radius), 0.0)[..., None]
        unit = rel / d[..., None]
        side = _cross(xp, xp.zeros_like(unit) + xp.asarray([0.0, 0.0, 1.0], dtype=pos.dtype), unit)
        closing = -xp.sum((vel[..., :, None, :] - vel[..., None, :, :]) * unit, axis=-1)  # > 0: approaching
        brake = xp.where(near, g.avoid_damping * xp.maximum(closing, 0.0), 0.0)[..., None]
        return xp.sum(w * (unit + g.avoid_swirl * side) + brake * unit, axis=-2)

    def obstacle_acceleration(self, pos: Any, vel: Any, centres: Any, valid: Any = None, radius: Any = None) -> Any:
        """Horizontal potential-field acceleration (..., N, 3) (m/s^2, world frame) away from the columns
        (``centres`` (..., M, 2) m, ``valid`` (..., M) bool or None = all, ``radius`` (...,) m or None =
        ``column_radius``) within ``obstacle_radius`` of their surface: ``obstacle_gain (1 - s / R)``
        along the outward normal plus an ``obstacle_swirl`` share tangentially (on the side the quad
        already moves to, so it slides around the column), and a brake on the approach speed."""
        xp = array_namespace(pos, centres)
        g = self.gains
        c = xp.asarray(centres, dtype=pos.dtype)
        r = g.column_radius if radius is None else xp.asarray(radius, dtype=pos.dtype)[..., None, None]
        rel = pos[..., :, None, :2] - c[..., None, :, :]  # (..., N, M, 2)
        d = xp.sqrt(xp.sum(rel * rel, axis=-1) + 1e-12)
        s = d - r  # distance to the surface
        near = s < g.obstacle_radius
        if valid is not None:
            near = near & xp.asarray(valid)[..., None, :]
        w = xp.where(near, g.obstacle_gain * (1.0 - xp.maximum(s, 0.0) / g.obstacle_radius), 0.0)[..., None]
        unit = rel / d[..., None]
        tangent = xp.stack([-unit[..., 1], unit[..., 0]], axis=-1)  # normal rotated +90 deg about z
        v = vel[..., :, None, :2]
        side = xp.where(xp.sum(v * tangent, axis=-1, keepdims=True) < 0, -1.0, 1.0)
        closing = xp.maximum(-xp.sum(v * unit, axis=-1), 0.0)[..., None]  # > 0: approaching
        brake = xp.where(near[..., None], g.obstacle_damping * closing, 0.0)
        h = xp.sum(w * (unit + g.obstacle_swirl * side * tangent) + brake * unit, axis=-2)
        return xp.concatenate([h, xp.zeros_like(h[..., :1])], axis=-1)

    def allocate(self, thrust: Any, torque: Any, thrust_max: Any, torque_max: Any) -> Any:
        """Normalized rotor thrusts f (..., 4) in [0, 1] for collective ``thrust`` (...,) N and body
        ``torque`` (..., 3) N m, with per-rotor ``thrust_max``/``torque_max`` (..., 4).

        Exact (``mixer(f) == (thrust, torque)``) when feasible. Otherwise attitude comes first: the
        roll/pitch torque is scaled down (direction kept) only if it alone does not fit, the yaw
        torque is scaled into the room left, and the collective is moved to the nearest value that
        keeps every rotor in [0, 1].
        """
        xp = array_namespace(thrust, torque, thrust_max)
        Minv = xp.linalg.inv(self.mixer(thrust_max, torque_max))
        gcol = Minv[..., :, 0]  # f per N of collective (> 0)
        zero = xp.zeros_like(thrust)
        f_rp = xp.einsum("...ij,...j->...i", Minv, xp.stack([zero, torque[..., 0], torque[..., 1], zero], -1))
        f_y = xp.einsum("...ij,...j->...i", Minv, xp.stack([zero, zero, zero, torque[..., 2]], -1))
        f_rp = f_rp * _max_scale(xp.zeros_like(f_rp), f_rp, gcol)[..., None]
        f_att = f_rp + f_y * _max_scale(f_rp, f_y, gcol)[..., None]
        k_lo = xp.max(-f_att / gcol, axis=-1)
        k_hi = xp.min((1.0 - f_att) / gcol, axis=-1)
        k = xp.minimum(xp.maximum(thrust, k_lo), k_hi)
        return xp.clip(k[..., None] * gcol + f_att, 0.0, 1.0)

    def _params(self, params: dict[str, Any] | None, like: Any) -> tuple[Any, Any, Any, Any]:
        xp = array_namespace(like)
        batch = tuple(like.shape)  # (..., N)
        q = self.quad
        p = params or {}

        def get(key: str, default: Any, tail: tuple[int, ...]) -> Any:
            v = p.get(key)
            v = default if v is None else v
            return xp.broadcast_to(xp.asarray(v, dtype=like.dtype), batch + tail)

        mass = get("mass", q.mass, ())
        inertia = get("inertia", q.inertia, (3,))
        thrust_max = get("thrust_max", q.thrust_max, (4,))
        torque_max = get("torque_max", q.torque_max, (4,))
        return mass, inertia, thrust_max, torque_max

    # ------------------------------------------------------------------ control law
    def __call__(self, state: dict[str, Any], goals: Any, goal_vel: Any = None,
                 params: dict[str, Any] | None = None, obstacles: Any = None) -> Any:
        try:
            pos, vel, R, omega = state["pos"], state["vel"], state["rot"], state["omega"]
        except (KeyError, TypeError) as e:
            raise ValueError("state must be a dict with 'pos', 'vel', 'rot', 'omega' (info['state'])") from e
        xp = array_namespace(pos)
        pos, vel, R, omega = (xp.asarray(x) for x in (pos, vel, R, omega))
        goals = xp.asarray(goals, dtype=pos.dtype)
        if goals.shape != pos.shape:
            raise ValueError(f"goals must have the shape of state['pos'] {tuple(pos.shape)}, got {tuple(goals.shape)}")
        gv = xp.zeros_like(pos) if goal_vel is None else xp.asarray(goal_vel, dtype=pos.dtype)
        if gv.shape != pos.shape:
            raise ValueError(f"goal_vel must have the shape of state['pos'] {tuple(pos.shape)}, got {tuple(gv.shape)}")
        gains, g = self.gains, self.gravity
        mass, inertia, thrust_max, torque_max = self._params(params, pos[..., 0])
        kp, kv = xp.asarray(gains.kp, dtype=pos.dtype), xp.asarray(gains.kv, dtype=pos.dtype)
        kR, kw = xp.asarray(gains.kR, dtype=pos.dtype), xp.asarray(gains.kw, dtype=pos.dtype)

        # 1. position loop -> desired acceleration (world frame, gravity compensated)
        e_p = pos - goals
        n_ep = xp.sqrt(xp.sum(e_p * e_p, axis=-1, keepdims=True))
        e_p = e_p * xp.minimum(1.0, gains.max_pos_error / xp.maximum(n_ep, 1e-9))
        acc = -kp * e_p - kv * (vel - gv)
        if gains.avoid_radius > 0 and pos.shape[-2] > 1:
            acc = acc + self._avoidance(xp, pos, vel)
        if obstacles is not None and gains.obstacle_radius > 0:
            if hasattr(obstacles, "centres"):  # an ObstacleMap (centres, valid, radius)
                acc = acc + self.obstacle_acceleration(pos, vel, obstacles.centres, obstacles.valid, obstacles.radius)
            else:  # (..., M, 2) column centres, e.g. info["obstacles"]
                acc = acc + self.obstacle_acceleration(pos, vel, obstacles)
        az = xp.clip(acc[..., 2], -gains.max_down_acc, gains.max_up_acc) + g
        h = acc[..., :2]
        h_max = az * math.tan(math.radians(gains.max_tilt_deg))
        n_h = xp.sqrt(xp.sum(h * h, axis=-1))
        h = h * xp.minimum(1.0, h_max / xp.maximum(n_h, 1e-9))[..., None]
        acc = xp.concatenate([h, az[..., None]], axis=-1)  # az >= g - max_down_acc > 0

        # 2. collective thrust along the current body z axis
        b3 = R[..., :, 2]
        thrust = mass * xp.sum(acc * b3, axis=-1)  # N, may be < 0 when upside down

        # 3. attitude loop
        b3_d = _normalize(xp, acc, xp.zeros_like(acc) + xp.asarray([0.0, 0.0, 1.0], dtype=pos.dtype))
        if self.yaw is None:
            heading = R[..., :, 0]
        else:
            yaw = xp.asarray(self.yaw, dtype=pos.dtype) + xp.zeros_like(pos[..., 0])
            heading = xp.stack([xp.cos(yaw), xp.sin(yaw), xp.zeros_like(yaw)], axis=-1)
        b2_d = _normalize(xp, _cross(xp, b3_d, heading), R[..., :, 1])
        b1_d = _cross(xp, b2_d, b3_d)
        R_d = xp.stack([b1_d, b2_d, b3_d], axis=-1)
        E = xp.einsum("...ki,...kj->...ij", R_d, R) - xp.einsum("...ki,...kj->...ij", R, R_d)
        e_R = 0.5 * xp.stack([E[..., 2, 1], E[..., 0, 2], E[..., 1, 0]], axis=-1)
        if self.yaw is None:  # hold the heading: no yaw attitude error, only rate damping
            e_R = e_R * xp.asarray([1.0, 1.0, 0.0], dtype=pos.dtype)
        J_w = inertia * omega
        torque = inertia * (-kR * e_R - kw * omega) + _cross(xp, omega, J_w)

        # 4. inverse mixing with attitude priority and thrust limits
        t_max = gains.max_thrust_fraction * xp.sum(thrust_max, axis=-1)
        f = self.allocate(xp.clip(thrust, 0.0, t_max), torque, thrust_max, torque_max)

        # 5. rotor thrust -> motor command through the inverse static thrust map (identity for the
        # paper's linear map) -> raw action (steady state f_norm = cmd)
        q = self.quad.thrust_map_quadratic
        return 2.0 * (f if q == 0.0 else inverse_thrust_map(f, q)) - 1.0
