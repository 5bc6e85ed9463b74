"""The sub-step model functions for exactly one quad (one world), on Python floats.

For a single env with one quad the arrays of :mod:`quadswarm_mj.perf.numpy_small` hold 1 to 9 values,
and NumPy's fixed cost per call (about 1 us) is the whole cost. These forms read the few values out as
Python floats, apply the model's formulas (:mod:`quadswarm_mj.components`, the one body of each) term
by term with the same rounding (IEEE double arithmetic and ``math.sqrt`` round exactly as NumPy's; the
transcendental functions stay NumPy's ufuncs, whose SIMD forms may differ from ``math``'s in the last
bit), and return fresh NumPy arrays of the usual shapes. ``perf.numpy_small`` calls them for
one-element batches; ``tests/test_perf_one_quad.py`` checks the same bits (signs of zero included)
against the array forms. NumPy only.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from quadswarm_mj.constants import FLOOR_TOL

#: set to False for the array forms everywhere (the same-values tests compare the two)
ENABLED = True

_arctan2, _cos, _sin = np.arctan2, np.cos, np.sin


def _max(a: float, b: float) -> float:
    """``np.maximum(a, b)`` on floats: ``b`` when they are equal (signs of zero), NaN from either."""
    return a if (a > b or a != a) else b


def _min(a: float, b: float) -> float:
    """``np.minimum(a, b)`` on floats: ``b`` when they are equal (signs of zero), NaN from either."""
    return a if (a < b or a != a) else b


def wrench_floats(u: list[float], c: list[float], n: list[float], a: float, t: list[float], q: list[float],
                  mix: list[list[float]], r: list[float]) -> tuple[list[float], list[float], list[float], list[float]]:
    """The body of :func:`substep_wrench` on floats: motor state ``u``, command ``c``, noise ``n``, thrust
    ``t`` (N) and yaw torque ``q`` (N m) per rotor, ``a`` alpha, ``mix`` (3, 4) rows, ``r`` the 9 entries of R
    (row-major). Returns (u, f_norm, world force, world torque) as float lists."""
    c0, c1, c2, c3 = c
    n0, n1, n2, n3 = n
    u0, u1, u2, u3 = u
    sqrt = math.sqrt  # correctly rounded, as np.sqrt
    s0, s1, s2, s3 = sqrt(c0), sqrt(c1), sqrt(c2), sqrt(c3)
    u0, u1, u2, u3 = u0 + a * (s0 - u0), u1 + a * (s1 - u1), u2 + a * (s2 - u2), u3 + a * (s3 - u3)
    f = [x if (x > 0.0 or x != x) else 0.0 for x in (u0 * u0 + c0 * n0, u1 * u1 + c1 * n1, u2 * u2 + c2 * n2,
                                                       u3 * u3 + c3 * n3)]  # _max(x, 0.0), inlined
    f0, f1, f2, f3 = [x if (x < 1.0 or x != x) else 1.0 for x in f]  # _min(x, 1.0)
    m0, m1, m2 = mix
    t0, t1, t2, t3 = t
    t0, t1, t2, t3 = t0 * f0, t1 * f1, t2 * f2, t3 * f3
    fz = ((t0 * m0[0] + t1 * m0[1]) + t2 * m0[2]) + t3 * m0[3]
    tx = ((t0 * m1[0] + t1 * m1[1]) + t2 * m1[2]) + t3 * m1[3]
    ty = ((t0 * m2[0] + t1 * m2[1]) + t2 * m2[2]) + t3 * m2[3]
    q0, q1, q2, q3 = q
    tz = ((q0 * f0 + q1 * f1) + q2 * f2) + q3 * f3
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = r
    return ([u0, u1, u2, u3], [f0, f1, f2, f3], [fz * r02, fz * r12, fz * r22],
            [(r00 * tx + r01 * ty) + r02 * tz, (r10 * tx + r11 * ty) + r12 * tz, (r20 * tx + r21 * ty) + r22 * tz])


def substep_wrench(u: Any, cmd: Any, noise: Any, alpha: Any, thrust_max: Any, torque_spin: Any, mix: Any,
                   R: Any) -> tuple[Any, Any, Any, Any]:
    """:func:`quadswarm_mj.actuation.substep_wrench` for one quad in the paper's chain (linear thrust map,
    no rotor gain): ``u``, ``cmd``, ``noise``, ``thrust_max``, ``torque_spin`` (1, 1, 4), ``alpha`` (1, 1),
    ``mix`` (3, 4), ``R`` (1, 1, 3, 3). Returns fresh (u, f_norm) (1, 1, 4) and world (force, torque)
    (1, 1, 3), the bits of ``perf.numpy_small.substep_wrench``."""
    uu, f, fo, to = wrench_floats(u.ravel().tolist(), cmd.ravel().tolist(), noise.ravel().tolist(), alpha.item(),
                                  thrust_max.ravel().tolist(), torque_spin.ravel().tolist(), mix.tolist(),
                                  R.ravel().tolist())
    out = np.array(uu + f + fo + to)  # one fresh buffer
    return out[:4].reshape(1, 1, 4), out[4:8].reshape(1, 1, 4), out[8:11].reshape(1, 1, 3), out[11:].reshape(1, 1, 3)


def rotmat_floats(w: float, x: float, y: float, z: float) -> list[float]:
    """The 9 entries (row-major) of :func:`quat_to_rotmat` of the quaternion (w, x, y, z), on floats."""
    xx, yy, zz, xy, xz, yz, wx, wy, wz = x * x, y * y, z * z, x * y, x * z, y * z, w * x, w * y, w * z
    return [1.0 + (yy * -2.0 + zz * -2.0), 0.0 + (xy * 2.0 + wz * -2.0), 0.0 + (xz * 2.0 + wy * 2.0),
            0.0 + (xy * 2.0 + wz * 2.0), 1.0 + (xx * -2.0 + zz * -2.0), 0.0 + (yz * 2.0 + wx * -2.0),
            0.0 + (xz * 2.0 + wy * -2.0), 0.0 + (yz * 2.0 + wx * 2.0), 1.0 + (xx * -2.0 + yy * -2.0)]


def quat_to_rotmat(q: Any) -> Any:
    """``perf.numpy_small.quat_to_rotmat`` of one quaternion (w, x, y, z) (shape (..., 4) with one row):
    a fresh (..., 3, 3) array, entry by entry ``base + (coef q_a q_b + coef' q_c q_d)`` (the same bits)."""
    return np.array(rotmat_floats(*q.ravel().tolist())).reshape(q.shape[:-1] + (3, 3))


def floor_wrench_floats(force: list[float], torque: list[float], vx: float, vy: float, m: float, gravity: float,
                        friction: float, dt: float) -> tuple[list[float], list[float]]:
    """The body of :func:`floor_wrench` for a grounded quad on floats: world ``force``/``torque`` (3 each),
    horizontal velocity ``vx``, ``vy`` (m/s), mass ``m`` (kg). Returns the new (force, torque) lists."""
    fx, fy, fz = force
    normal = _max(0.0, m * gravity - fz)
    cap = friction * normal
    f_mag = math.sqrt(fx * fx + fy * fy)
    speed = math.sqrt(vx * vx + vy * vy)
    if speed > 1e-9:  # kinetic friction opposes the velocity
        kinetic = _min(cap, m * speed / dt) / speed
        hx, hy = fx - kinetic * vx, fy - kinetic * vy
    else:  # static friction cancels the horizontal force up to the cap
        static = _max(0.0, f_mag - cap) / (f_mag if f_mag > 0 else 1.0)
        hx, hy = fx * static, fy * static
    return [hx, hy, fz + normal], [0.0, 0.0, torque[2]]


def floor_wrench(on_floor: Any, force_w: Any, torque_w: Any, vel: Any, mass: Any, gravity: float,
                 friction: float, dt: float) -> tuple[Any, Any]:
    """:func:`quadswarm_mj.collisions.floor_wrench` for one quad: ``on_floor`` (1, 1) bool, ``force_w``,
    ``torque_w``, ``vel`` (1, 1, 3), ``mass`` (1, 1). Returns fresh (force, torque) (1, 1, 3)."""
    force, torque = force_w.ravel().tolist(), torque_w.ravel().tolist()
    if on_floor.item():
        vx, vy = vel.ravel().tolist()[:2]
        force, torque = floor_wrench_floats(force, torque, vx, vy, mass.item(), gravity, friction, dt)
    out = np.array(force + torque)
    return out[:3].reshape(1, 1, 3), out[3:].reshape(1, 1, 3)


def floor_impact_inplace(q: Any, v: Any, u: Any, on_floor: bool, floor_z: float, offset: Any,
                         yaw_draw: float) -> tuple[bool, bool, Any]:
    """The paper's floor model after a sub-step for one quad, written into ``q`` (7,) = qpos (position
    with the world ``offset`` (3,) added, quaternion) and ``v`` (6,) = qvel (vel, omega) in place: the
    values of ``collisions.floor_impact``'s angle path (``CpuSwarm._floor_impact``'s masked writes). ``u`` (1, 1, 4)
    motor state; ``yaw_draw`` (rad) the upside-down landing's draw. Returns (grounded, hit, u) with ``u``
    a fresh array zeroed (0.0 * u) on a hit, else ``u`` itself."""
    grounded, hit = floor_impact_qv(q, v, on_floor, floor_z, offset.tolist(), yaw_draw)
    return grounded, hit, (0.0 * u if hit else u)


def floor_impact_qv(q: Any, v: Any, on_floor: bool, floor_z: float, offset: list[float],
                    yaw_draw: float) -> tuple[bool, bool]:
    """The body of :func:`floor_impact_inplace` without the motors (the caller zeroes them, 0.0 * u, on a
    hit): writes ``q`` (7,) and ``v`` (6,) in place; ``offset`` the world offset (3 floats). Returns
    (grounded, hit)."""
    ox, oy, oz = offset
    x, y, zq, w, qx, qy, qz = q.tolist()
    z = zq - oz
    hit = z <= floor_z and not on_floor
    staying = on_floor and z <= floor_z + FLOOR_TOL
    if not (hit or staying):
        q[0], q[1], q[2] = (x - ox) + ox, (y - oy) + oy, z + oz
        return False, False
    # R10, R00 (the heading) and R22 (upside down) of quat_to_rotmat, with its rounding
    r10 = 0.0 + (qx * qy * 2.0 + w * qz * 2.0)
    r00 = 1.0 + (qy * qy * -2.0 + qz * qz * -2.0)
    yaw = float(_arctan2(r10, r00))
    if hit:
        r22 = 1.0 + (qx * qx * -2.0 + qy * qy * -2.0)
        yaw = yaw + (yaw_draw if r22 < 0 else 0.0)
    else:
        yaw = yaw + 0.0
    half = 0.5 * yaw
    q[0], q[1], q[2] = (x - ox) + ox, (y - oy) + oy, floor_z + oz
    q[3], q[4], q[5], q[6] = float(_cos(half)), 0.0, 0.0, float(_sin(half))
    if hit:  # vel and omega zeroed (0.0 * x: signs kept)
        v *= 0.0
    else:  # staying: no vertical speed, no roll/pitch rate
        v[2], v[3], v[4] = 0.0, 0.0, 0.0
    return True, hit


def action_to_command(action: Any) -> Any:
    """:func:`quadswarm_mj.actuation.action_to_command` of one quad's float64 (1, 1, 4) ``action``: 0.5 (clip(a,
    -1, 1) + 1) per rotor (the clip as maximum then minimum), a fresh array."""
    c = [a if (a > -1.0 or a != a) else -1.0 for a in action.ravel().tolist()]  # _max(a, -1.0), inlined
    return np.array([0.5 * ((a if (a < 1.0 or a != a) else 1.0) + 1.0) for a in c]).reshape(1, 1, 4)


def motor_noise_step(eps: Any, sigma: Any, theta: float, normal: Any) -> Any:
    """:func:`quadswarm_mj.actuation.motor_noise_step` of one quad: ``eps``, ``normal`` (1, 1, 4), ``sigma``
    (1, 1); (e + theta (0 - e)) + sigma n per rotor, a fresh array."""
    s = sigma.item()
    return np.array([e + theta * (0.0 - e) + s * n for e, n in zip(eps.ravel().tolist(), normal.ravel().tolist())]
                    ).reshape(1, 1, 4)


# ---------------------------------------------------------------- the task stage (reward terms, metrics)
def _norm(v: list[float]) -> float:
    """sqrt(((v0 v0 + v1 v1) + v2 v2) + ...): ``spatial.norm_last``'s rounding."""
    if len(v) == 3:
        a, b, c = v
        return math.sqrt((a * a + b * b) + c * c)
    s = v[0] * v[0] + v[1] * v[1]
    for x in v[2:]:
        s = s + x * x
    return math.sqrt(s)


def reward_plan(factors: tuple, annealed: tuple[str, ...], vel_limit: float = 0.0) -> tuple:
    """The per-config constants of :func:`reward_terms` (made once per engine): from ``factors``
    (``rewards._term_factors``), ``annealed`` (``rewards.ANNEALED``) and ``vel_limit`` (m/s,
    ``RewardScales.vel_limit``) the set of costs needed, the computed terms (key, -dt, base scale,
    annealed), the terms that are exactly -0.0, the keys in order with their rows, and the limit."""
    need = frozenset(k for k, _, base in factors if base is not None)
    live = tuple((k, neg_dt, base, k in annealed) for k, neg_dt, base in factors if base is not None)
    zero_keys = tuple(k for k, _, base in factors if base is None)
    row = {k: i for i, (k, _, _, _) in enumerate(live)}  # each key's row of the output; -0.0 terms: the last
    index = tuple((k, row.get(k, len(live))) for k, _, _ in factors)
    return (need, live, zero_keys, index, bool(need & {"orient", "yaw", "rot"}), float(vel_limit))


def reward_values(plan: tuple, p: list[float], v: list[float], r: list[float], w: list[float], g: list[float],
                  act: list[float], f: list[float], pf: list[float], on: bool, n_contacts: int, hit_floor: bool,
                  hit_wall: bool, hit_ceiling: bool, anneal: Any, goal_dist: float | None) -> list[float]:
    """The body of :func:`reward_terms` on floats: position ``p``, velocity ``v``, omega ``w``, goal ``g`` (3
    each), the 9 entries of R ``r``, the action ``act``, thrusts ``f``/``pf`` (4 each), the flags and the
    count of new quad contacts. Returns the values of the plan's computed terms in order (then -0.0 if
    some term is exactly -0.0)."""
    need, live, zero_keys, index, rot, vel_limit = plan
    c: dict[str, float] = {"crash": 1.0 if on else 0.0, "proximity": 0.0}
    if "pos" in need:
        c["pos"] = goal_dist if goal_dist is not None else _norm([g[0] - p[0], g[1] - p[1], g[2] - p[2]])
    if "effort" in need:
        c["effort"] = _norm([_min(_max(a, -1.0), 1.0) for a in act])
    if "spin" in need:
        c["spin"] = _norm(w)
    if "vel" in need:
        c["vel"] = _norm(v) if vel_limit == 0 else _max(_norm(v) - vel_limit, 0.0)
    if "action_change" in need:
        c["action_change"] = _norm([a - b for a, b in zip(f, pf)])
    if rot:
        c["orient"] = 1.0 if on else -r[8]
        c["yaw"] = -r[0]
        c["rot"] = -(r[0] + r[4] + r[8] - 1.0) / 2.0
    if "quad_collision" in need:
        c["quad_collision"] = float(n_contacts)
    if "floor_hit" in need:
        c["floor_hit"] = 1.0 if hit_floor else 0.0
    if "wall_hit" in need:
        c["wall_hit"] = 1.0 if hit_wall else 0.0
    if "ceiling_hit" in need:
        c["ceiling_hit"] = 1.0 if hit_ceiling else 0.0

    vals = [float(neg_dt * (base * anneal) * c[k]) if ann else neg_dt * base * c[k] for k, neg_dt, base, ann in live]
    if zero_keys:
        vals.append(-0.0)
    return vals


def reward_terms(plan: tuple, pos: Any, vel: Any, R: Any, omega: Any, goals: Any,
                 action: Any, f_norm: Any, prev_f_norm: Any, on_floor: Any, hit_floor: Any, hit_wall: Any,
                 hit_ceiling: Any, new_contact: Any, anneal: Any, goal_dist: Any | None) -> dict[str, Any]:
    """:func:`quadswarm_mj.rewards.reward_terms` for one quad in one world ((1, 1, ...) arrays; ``plan``
    :func:`reward_plan` of its ``_term_factors`` and ``ANNEALED``): the same (1, 1) values, as rows of
    one fresh array (the terms that are exactly -0.0 share one row, as there). With one quad
    ``proximity`` has no other quad (cost 0) and ``quad_collision`` counts the pairs of the (1, 1, 1)
    contact matrix."""
    vals = reward_values(plan, pos.ravel().tolist(), vel.ravel().tolist(), R.ravel().tolist(), omega.ravel().tolist(),
                         goals.ravel().tolist(), action.ravel().tolist(), f_norm.ravel().tolist(),
                         prev_f_norm.ravel().tolist(), bool(on_floor.item()), int(np.count_nonzero(new_contact)),
                         bool(hit_floor.item()), bool(hit_wall.item()), bool(hit_ceiling.item()), anneal,
                         None if goal_dist is None else goal_dist.item())
    rows = np.array(vals).reshape(-1, 1, 1)
    return {k: rows[i] for k, i in plan[3]}


def total_reward(terms: dict[str, Any], keys: list[str]) -> Any:
    """:func:`quadswarm_mj.rewards.total_reward` of (1, 1) terms: the sum in the order of ``keys``, as a
    fresh (1, 1) array."""
    total = terms[keys[0]].item()
    for k in keys[1:]:
        total = total + terms[k].item()
    return np.array([[total]])


def metrics_update(m: dict[str, Any], t: Any, dist_to_goal: Any, new_contact: Any, hit_floor: Any, hit_wall: Any,
                   hit_ceiling: Any, goal_jump: Any, grace_s: float, min_segment_s: float,
                   reach_distance: float) -> dict[str, Any]:
    """:func:`quadswarm_mj.metrics.update` for one quad in one world (float64 accumulators (1, 1), ``steps``
    (1,), ``last_dist`` (1, LAST_STEPS, 1)): the same values, fresh arrays."""
    return metrics_floats(m, t.item(), dist_to_goal.item(), int(np.count_nonzero(new_contact)), bool(hit_floor.item()),
                          bool(hit_wall.item()), bool(hit_ceiling.item()), bool(goal_jump.item()), grace_s,
                          min_segment_s, reach_distance)


def metrics_floats(m: dict[str, Any], tq: float, d: float, n_contacts: int, hit_floor: bool, hit_wall: bool,
                   hit_ceiling: bool, jump: bool, grace_s: float, min_segment_s: float,
                   reach_distance: float) -> dict[str, Any]:
    """The body of :func:`metrics_update` with the step's time ``tq`` (s), goal distance ``d`` (m), count of
    new contacts, flags and goal jump as Python scalars."""
    coll = float(n_contacts) * (1.0 if tq >= grace_s else 0.0)
    start, reached = m["seg_start"].item(), bool(m["seg_reached"].item())
    close = jump and (tq - start >= min_segment_s - 1e-9)
    last = np.empty_like(m["last_dist"])
    last[:, :-1] = m["last_dist"][:, 1:]
    last[:, -1] = d
    f = np.array([m["collisions"].item() + coll, m["floor_hits"].item() + (1.0 if hit_floor else 0.0),
                  m["wall_hits"].item() + (1.0 if hit_wall else 0.0),
                  m["ceiling_hits"].item() + (1.0 if hit_ceiling else 0.0), m["dist_sum"].item() + d,
                  m["seg_count"].item() + (1.0 if close else 0.0),
                  m["seg_success"].item() + (1.0 if close and reached else 0.0), tq if jump else start])
    rows = f.reshape(8, 1, 1)
    return {"collisions": rows[0], "floor_hits": rows[1], "wall_hits": rows[2], "ceiling_hits": rows[3],
            "dist_sum": rows[4], "steps": np.array([m["steps"].item() + 1.0]), "last_dist": last,
            "seg_count": rows[5], "seg_success": rows[6], "seg_start": rows[7],
            "seg_reached": np.array([[d < reach_distance or (reached and not jump)]])}


# ---------------------------------------------------------------- the observation
def build_obs(pos: Any, vel: Any, R: Any, omega: Any, goals: Any, noise: dict[str, Any] | None, low: Any,
              high: Any, scale: Any | None, floor: bool) -> Any:
    """:func:`quadswarm_mj.observations.build_obs` of one quad in one world without neighbours, obstacles
    or deck sensors (``obs_self`` "base", or "floor" with ``floor``): (1, 1, 3) ``pos``, ``vel``, ``omega``,
    ``goals``, (1, 1, 3, 3) ``R``, ``noise`` (the sensor noise of pos, vel, omega, or None), bounds
    ``low``/``high`` and ``scale`` (obs_dim,). A fresh (1, 1, obs_dim) array with the same values."""
    vals = obs_values(pos.ravel().tolist(), vel.ravel().tolist(), R.ravel().tolist(), omega.ravel().tolist(),
                      goals.ravel().tolist(),
                      None if noise is None else [noise[k].ravel().tolist() for k in ("pos", "vel", "omega")],
                      low.tolist(), high.tolist(), None if scale is None else scale.tolist(), floor)
    return np.array(vals).reshape(1, 1, len(vals))


def obs_values(p: list[float], v: list[float], r: list[float], w: list[float], g: list[float],
               noise: list[list[float]] | None, low: list[float], high: list[float], scale: list[float] | None,
               floor: bool) -> list[float]:
    """The body of :func:`build_obs` on floats: ``noise`` the (pos, vel, omega) sensor noise (3 floats each)
    or None; ``low``/``high``/``scale`` the bounds and scales as lists. Returns the observation's values."""
    if noise is not None:
        p = [a + b for a, b in zip(p, noise[0])]
        v = [a + b for a, b in zip(v, noise[1])]
        w = [a + b for a, b in zip(w, noise[2])]
    vals = [p[0] - g[0], p[1] - g[1], p[2] - g[2], *v, *r, *w]
    if floor:
        vals.append(p[2])
    vals = [x if (x > lo or x != x) else lo for x, lo in zip(vals, low)]  # clip as there: _max, inlined
    vals = [x if (x < hi or x != x) else hi for x, hi in zip(vals, high)]  # then _min
    if scale is not None:
        vals = [x / s for x, s in zip(vals, scale)]
    return vals
