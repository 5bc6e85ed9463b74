"""The paper's velocity-based collision model (SPEC §4-5): floor, walls, ceiling, quad-quad.

Pure functions over arrays with leading batch dims (``(N, ...)`` or ``(B, N, ...)``), NumPy or
``jax.numpy``; random draws come in as arrays (see :mod:`quadswarm_mj.random_draws`; with
``MeanSampler`` every draw takes its mean, which is the noise-free model). World frame, SI units;
angular velocity ``omega`` is in the body frame.

* Floor: every physics sub-step. :func:`floor_wrench` (before the step) adds the normal and
  friction forces of a grounded quad; :func:`floor_impact` (after the step) detects a landing.
* Walls, ceiling, quad-quad: once per control step, after the physics.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from quadswarm_mj import components as C
from quadswarm_mj._xp import array_namespace, is_jax_array, safe_normalize
from quadswarm_mj.constants import FLOOR_TOL
from quadswarm_mj.random_draws import DrawSpec, Normal, Uniform
from quadswarm_mj.spatial import norm_last

# ---------------------------------------------------------------------------------------- floor

__all__ = ["FLOOR_TOL"]  # re-exported: its home is quadswarm_mj.constants (a leaf)


def floor_draw_spec(num_quads: int) -> DrawSpec:
    """Yaw offset given to a quad that lands upside down (mean 0: it keeps its yaw)."""
    return {"yaw": Uniform(-3.141592653589793, 3.141592653589793, (num_quads,))}


def floor_wrench(on_floor: Any, force_w: Any, torque_w: Any, vel: Any, mass: Any, gravity: float,
                 friction: float, dt: float) -> tuple[Any, Any]:
    """Add the floor's normal and friction force to a grounded quad's world wrench.

    Normal force N = max(0, m g - F_z), so the vertical acceleration is not negative.
    Horizontal: static friction cancels the horizontal force while it is below mu N and the quad
    is at rest; otherwise kinetic friction mu N opposes the velocity (never reversing it within
    one sub-step). Roll and pitch torques are removed (the quad stays flat, yaw-only). One body:
    :func:`quadswarm_mj.components.floor_wrench` (``perf.numpy_small`` has the small-NumPy form).
    """
    f, t = C.floor_wrench(on_floor, C.split(force_w), C.split(torque_w), C.split(vel), mass, gravity, friction, dt)
    return C.stack(f), C.stack(t)


def floor_impact(pos: Any, vel: Any, omega: Any, quat: Any, R: Any, u: Any, on_floor: Any,
                 floor_z: float, yaw_draw: Any, with_rotmat: bool = True,
                 yaw_draw_cs: tuple[Any, Any] | None = None) -> dict[str, Any]:
    """Floor contact after a physics sub-step (SPEC §4).

    A quad at or below ``floor_z`` that was airborne *hits* the floor: z is set to ``floor_z``,
    linear and angular velocity become 0, the rotation keeps only its yaw (plus ``yaw_draw`` if it
    was upside down), the motor state ``u`` resets to 0. A grounded quad stays grounded (flat,
    z = floor_z, no downward velocity, no roll/pitch rate) until its thrust lifts it above the
    height. Returns a dict with the new ``pos, vel, omega, quat, R, u, on_floor, hit_floor``
    (without ``R`` when ``with_rotmat`` is False, for callers that derive it from ``quat``).

    ``yaw_draw_cs`` (the JAX engine's trig-free path): (cos, sin) of the yaw draws instead of
    ``yaw_draw`` (then ignored); the yaw rotation is built from the heading's cosine and sine
    (:func:`~quadswarm_mj.spatial.yaw_cos_sin`), equal to the angle path up to round-off. One body:
    :func:`quadswarm_mj.components.floor_impact` (``perf.numpy_small`` has the small-NumPy form).
    """
    lead = R.shape[:-2]
    r = C.floor_impact(C.split(pos), C.split(vel), C.split(omega), C.split(quat), C.split(R.reshape(lead + (9,))),
                       C.split(u), on_floor, floor_z, yaw_draw_cs, yaw_draw=yaw_draw)
    out = {k: C.stack(v) if isinstance(v, tuple) else v for k, v in r.items()}
    if with_rotmat:
        out["R"] = out["R"].reshape(lead + (3, 3))
    else:
        del out["R"]
    return out


# ------------------------------------------------------------------------------ walls, ceiling


def wall_draw_spec(num_quads: int, decay: tuple[float, float], kick_omega: tuple[float, float]) -> DrawSpec:
    """Draws of the wall/ceiling bounce for every quad (used only where a quad hits)."""
    n = num_quads
    return {
        "dir": Uniform(-1.0, 1.0, (n, 3)),  # free direction components
        "away": Uniform(0.1, 1.0, (n, 2)),  # |component| along the normal of a wall hit (x, y)
        "down": Uniform(-1.0, -0.5, (n,)),  # vertical component (always downward)
        "decay": Uniform(decay[0], decay[1], (n,)),
        "kick_dir": Normal(0.0, 1.0, (n, 3)),
        "kick_mag": Uniform(kick_omega[0], kick_omega[1], (n,)),
    }


def wall_collisions(pos: Any, vel: Any, omega: Any, prev_wall: Any, prev_ceiling: Any, room_low: Any,
                    room_high: Any, draws: dict[str, Any], speed_limits: tuple[float, float]) -> dict[str, Any]:
    """Clip positions into the room and bounce quads that newly hit a wall or the ceiling.

    The bounce speed is ``decay * |v|`` clipped to ``speed_limits``; its direction points away
    from each wall hit, with a downward z component, and omega gets a random kick. The floor is
    not handled here (see :func:`floor_impact`). Returns a dict with ``pos, vel, omega,
    at_wall, at_ceiling, hit_wall, hit_ceiling``.
    """
    xp = array_namespace(pos, vel)
    lo = xp.asarray(room_low, dtype=pos.dtype)
    hi = xp.asarray(room_high, dtype=pos.dtype)
    low_hit = pos[..., :2] <= lo[:2]
    high_hit = pos[..., :2] >= hi[:2]
    at_wall = xp.any(low_hit | high_hit, axis=-1)
    at_ceiling = pos[..., 2] >= hi[2]
    new_pos = xp.concatenate([xp.clip(pos[..., :2], lo[:2], hi[:2]),
                              xp.minimum(pos[..., 2], hi[2])[..., None]], axis=-1)
    hit_wall = at_wall & ~prev_wall
    hit_ceiling = at_ceiling & ~prev_ceiling
    bounce = hit_wall | hit_ceiling

    away = draws["away"]
    d_xy = xp.where(low_hit, away, xp.where(high_hit, -away, draws["dir"][..., :2]))
    direction = xp.concatenate([d_xy, draws["down"][..., None]], axis=-1)
    direction = safe_normalize(xp, direction)
    speed = xp.sqrt(xp.sum(vel * vel, axis=-1))
    new_speed = xp.clip(draws["decay"] * speed, speed_limits[0], speed_limits[1])
    kick = safe_normalize(xp, draws["kick_dir"]) * draws["kick_mag"][..., None]
    b = bounce[..., None]
    return {
        "pos": new_pos,
        "vel": xp.where(b, new_speed[..., None] * direction, vel),
        "omega": xp.where(b, omega + kick, omega),
        "at_wall": at_wall, "at_ceiling": at_ceiling, "hit_wall": hit_wall, "hit_ceiling": hit_ceiling,
    }


# ------------------------------------------------------------------------------- room guard


def outside_room(pos: Any, room_low: Any, room_high: Any) -> tuple[Any, Any]:
    """(beyond, below) (..., N) masks of quad centres ``pos`` (m, world-local) that have left the
    closed room box: ``beyond`` a wall or above the ceiling, ``below`` the floor (z < room_low z)."""
    xp = array_namespace(pos)
    lo = xp.asarray(room_low, dtype=pos.dtype)
    hi = xp.asarray(room_high, dtype=pos.dtype)
    beyond = xp.any((pos[..., :2] < lo[:2]) | (pos[..., :2] > hi[:2]), axis=-1) | (pos[..., 2] > hi[2])
    return beyond, pos[..., 2] < lo[2]


def room_guard(pos: Any, vel: Any, omega: Any, quat: Any, R: Any, u: Any, room_low: Any, room_high: Any,
               arm: float, wall_draws: dict[str, Any], speed_limits: tuple[float, float], yaw_draw: Any = None,
               yaw_draw_cs: tuple[Any, Any] | None = None) -> dict[str, Any]:
    """Backstop of the MuJoCo-contact collision models ("mujoco", "blend"), once per control step
    after the physics: MuJoCo's soft contacts let a fast quad sink deep into a surface or tunnel
    through a wall within one sub-step; a quad whose *centre* has left the room gets the paper's
    response instead (quads inside are unchanged, so MuJoCo's contacts keep acting on them).

    * beyond a wall or above the ceiling: :func:`wall_collisions` as a new hit, with the room shrunk
      by ``arm`` (the hitbox sphere ends touching the surface, not half inside it): position
      clipped, bounce away from the surface at ``decay * |v|`` within ``speed_limits``, spin kick;
    * below the floor (z < 0): :func:`floor_impact` as a landing at z = ``arm`` (velocity and spin
      0, yaw-only rotation, motor state ``u`` 0).

    ``pos`` m world-local, ``vel`` m/s world, ``omega`` rad/s body, ``quat``/``R`` body->world,
    ``u`` (..., N, 4); ``wall_draws``: :func:`wall_draw_spec`'s draws, ``yaw_draw`` (or its
    ``yaw_draw_cs``) the landing yaw draws, per quad. Returns ``pos, vel, omega, quat, R, u`` and
    the masks ``beyond``, ``below``.
    """
    xp = array_namespace(pos, vel)
    beyond, below = outside_room(pos, room_low, room_high)
    lo = xp.asarray(room_low, dtype=pos.dtype) + arm
    hi = xp.asarray(room_high, dtype=pos.dtype) - arm
    w = wall_collisions(pos, vel, omega, ~beyond, ~beyond, lo, hi, wall_draws, speed_limits)
    b = beyond[..., None]
    pos, vel, omega = xp.where(b, w["pos"], pos), xp.where(b, w["vel"], vel), xp.where(b, w["omega"], omega)
    f = floor_impact(pos, vel, omega, quat, R, u, xp.zeros_like(below), arm, yaw_draw, yaw_draw_cs=yaw_draw_cs)
    d = below[..., None]
    return {"pos": xp.where(d, f["pos"], pos), "vel": xp.where(d, f["vel"], vel),
            "omega": xp.where(d, f["omega"], omega), "quat": xp.where(d, f["quat"], quat),
            "R": xp.where(d[..., None], f["R"], R), "u": xp.where(d, f["u"], u), "beyond": beyond, "below": below}


# ------------------------------------------------------------------------------------ quad-quad


def quad_collision_draw_spec(num_quads: int, tries: int, shared_std: float, own_std: float,
                             decay: tuple[float, float], kick_omega: tuple[float, float]) -> DrawSpec:
    """Pairwise draws: ``tries`` candidate noises per ordered pair, decay per quad, kicks per pair."""
    n = num_quads
    return {
        "shared": Normal(0.0, shared_std, (tries, n, n, 3)),  # antisymmetrized: +c for i, -c for j
        "own": Normal(0.0, own_std, (tries, n, n, 3)),
        "decay": Uniform(decay[0], decay[1], (n,)),
        "kick_dir": Normal(0.0, 1.0, (n, n, 3)),
        "kick_mag": Uniform(kick_omega[0], kick_omega[1], (n, n)),
    }


#: m/s: the normal speed at which a new quad-quad pair separates when the paper's response leaves it
#: none (equal velocities, e.g. two quads started at one point with one velocity: nothing to exchange)
SEPARATION_SPEED = 0.5


@functools.lru_cache(maxsize=64)
def coincident_normals(n: int) -> np.ndarray:
    """(n, n, 3) constant normals of pairs at the same point (zero-length p_i - p_j): +x for i < j,
    -x for i > j (antisymmetric, like unit(p_i - p_j)), 0 on the diagonal."""
    i = np.arange(n)
    out = np.zeros((n, n, 3))
    out[..., 0] = np.sign(i[None, :] - i[:, None])
    out.setflags(write=False)
    return out


def pairwise_contacts(pos: Any, hitbox: float, pair_dist: Any = None) -> tuple[Any, Any]:
    """(..., N, N) contact mask (||p_i - p_j|| <= hitbox, i != j) and distances. ``pair_dist``: an
    optional kernel for one world's (N, 3) JAX ``pos`` computing :func:`_pair_distances_rows_first`'s
    values (the JAX engine's ops pass a faster layout with the same values)."""
    if is_jax_array(pos) and pos.ndim == 2:  # one world under JAX: differentiable on the diagonal
        dist = _pair_distances_jax(pair_dist)(pos)
    else:
        rel = pos[..., :, None, :] - pos[..., None, :, :]
        dist = norm_last(rel)
    return (dist <= hitbox) & off_diagonal(pos.shape[-2]), dist


def _pair_distances_rows_first(xp: Any, pos: Any) -> Any:
    """(N, N, *batch) ||p_i - p_j|| of ``pos`` (N, 3, *batch), summed as norm_last does."""
    rel = pos[:, None] - pos[None, :]  # (N, N, 3, *batch): [i, j] = p_i - p_j
    return xp.sqrt(rel[:, :, 0] * rel[:, :, 0] + rel[:, :, 1] * rel[:, :, 1] + rel[:, :, 2] * rel[:, :, 2])


@functools.lru_cache(maxsize=8)
def _pair_distances_jax(kernel: Any = None) -> Any:
    """:func:`_pair_distances_rows_first` for one world's (N, 3) ``pos`` (computed by ``kernel`` when
    given). Differentiable: d||r|| = r . dr / ||r|| (0 on the diagonal, where autodiff of the norm
    gives NaN)."""
    import jax
    import jax.numpy as jnp

    primal = kernel if kernel is not None else functools.partial(_pair_distances_rows_first, jnp)

    @jax.custom_jvp
    def dist(pos: Any) -> Any:
        return primal(pos)

    @dist.defjvp
    def _jvp(primals: tuple, tangents: tuple) -> tuple[Any, Any]:
        (pos,), (dpos,) = primals, tangents
        d = primal(pos)
        rel, drel = pos[:, None, :] - pos[None, :, :], dpos[:, None, :] - dpos[None, :, :]
        return d, jnp.where(d > 0, jnp.sum(rel * drel, axis=-1) / jnp.where(d > 0, d, 1.0), 0.0)

    return dist


@functools.lru_cache(maxsize=64)
@functools.lru_cache(maxsize=64)
def off_diagonal(n: int) -> np.ndarray:
    """Constant (n, n) bool mask, True off the diagonal (a NumPy constant: also fine under jit; read-only,
    made once per n)."""
    m = ~np.eye(n, dtype=bool)
    m.setflags(write=False)
    return m


def _antisymmetric(xp: Any, x: Any) -> Any:
    """From (..., N, N, 3) keep the upper triangle (i < j) and mirror it with a minus sign."""
    n = x.shape[-2]
    upper = xp.triu(xp.ones((n, n), dtype=bool), k=1)[..., None]
    u = xp.where(upper, x, 0.0)
    return u - xp.swapaxes(u, -2, -3)


def quad_collisions(pos: Any, vel: Any, omega: Any, prev_contact: Any, hitbox: float,
                    draws: dict[str, Any]) -> dict[str, Any]:
    """Velocity response of pairs that newly entered each other's hitbox (SPEC §5).

    For a new pair (i, j) with n = unit(p_i - p_j) (:func:`coincident_normals` for a pair at one
    point): dv = ((v_j.n) - (v_i.n)) n; i gets
    dv + c + e_i, j gets -dv - c + e_j, with the first of the candidate noises that separates the
    pair (the last one if none does). Each involved quad's new speed is scaled by its ``decay``
    draw and capped at the larger pre-collision speed of its pairs; a pair then left without a
    separating normal speed ((v_i' - v_j').n <= 0, e.g. equal velocities with noise off) gets
    +-``SEPARATION_SPEED`` / 2 along n; omega gets +w / -w. A quad in
    several new pairs at once receives the sum of their changes. Returns ``vel, omega, contact,
    new_contact`` (contact masks are (..., N, N), symmetric).
    """
    xp = array_namespace(pos, vel)
    contact, dist = pairwise_contacts(pos, hitbox)
    new = contact & ~prev_contact
    rel = pos[..., :, None, :] - pos[..., None, :, :]
    n = rel / xp.where(dist > 0, dist, 1.0)[..., None]
    n = xp.where((dist == 0)[..., None], xp.asarray(coincident_normals(pos.shape[-2]), dtype=n.dtype), n)
    v_i = vel[..., :, None, :]
    v_j = vel[..., None, :, :]
    vin = xp.sum(v_i * n, axis=-1)
    vjn = xp.sum(v_j * n, axis=-1)
    change = (vjn - vin)[..., None] * n  # (..., N, N, 3), antisymmetric
    shared = _antisymmetric(xp, draws["shared"])  # (..., T, N, N, 3)
    shift = change[..., None, :, :, :] + shared + draws["own"]
    sep = xp.sum((v_i[..., None, :, :, :] + shift) * n[..., None, :, :, :], axis=-1)  # (..., T, N, N)
    ok = (sep > 0) & (xp.swapaxes(sep, -1, -2) > 0)
    tries = ok.shape[-3]
    choice = xp.full(ok.shape[:-3] + ok.shape[-2:], tries - 1)
    for t in range(tries - 2, -1, -1):  # first try that separates (static, tiny loop)
        choice = xp.where(ok[..., t, :, :], t, choice)
    sel = xp.take_along_axis(shift, choice[..., None, :, :, None], axis=-4)[..., 0, :, :, :]
    newf = new[..., None]
    dv = xp.sum(xp.where(newf, sel, 0.0), axis=-2)
    involved = xp.any(new, axis=-1)
    speed = xp.sqrt(xp.sum(vel * vel, axis=-1))
    pair_max = xp.maximum(speed[..., :, None], speed[..., None, :])
    vmax = xp.max(xp.where(new, pair_max, 0.0), axis=-1)
    v_new = (vel + dv) * draws["decay"][..., None]
    s_new = xp.sqrt(xp.sum(v_new * v_new, axis=-1))
    scale = xp.minimum(1.0, vmax / xp.where(s_new > 0, s_new, 1.0))
    v_new = v_new * scale[..., None]
    # a pair the response leaves without a separating normal speed (equal velocities: nothing to
    # exchange) gets +-SEPARATION_SPEED / 2 along n
    dv_rel = v_new[..., :, None, :] - v_new[..., None, :, :]
    stuck = new & (xp.sum(dv_rel * n, axis=-1) <= 0.0)
    push = xp.sum(xp.where(stuck[..., None], (0.5 * SEPARATION_SPEED) * n, 0.0), axis=-2)
    v_new = xp.where(xp.any(stuck, axis=-1)[..., None], v_new + push, v_new)
    kick = _antisymmetric(xp, safe_normalize(xp, draws["kick_dir"]) * draws["kick_mag"][..., None])
    d_omega = xp.sum(xp.where(newf, kick, 0.0), axis=-2)
    inv = involved[..., None]
    return {"vel": xp.where(inv, v_new, vel), "omega": xp.where(inv, omega + d_omega, omega),
            "contact": contact, "new_contact": new}


def collision_draw_specs(cfg: Any) -> dict[str, DrawSpec]:
    """The draw specs of the paper's collision models for one world of ``cfg`` (an EnvConfig):
    ``{"quad": ..., "wall": ..., "floor": ...}``; built once by each front end."""
    n, c = cfg.num_quads, cfg.collision
    return {
        "quad": quad_collision_draw_spec(n, c.tries, c.shared_noise_std, c.own_noise_std, cfg.collision_decay,
                                         c.kick_omega),
        "wall": wall_draw_spec(n, cfg.collision_decay, c.kick_omega),
        "floor": floor_draw_spec(n),
    }


# ------------------------------------------------------------------------------- draw budgets
# The JAX engine's bounded draws (see :func:`quadswarm_mj.random_draws.event_slots`): per step it
# draws the collision noise of QUAD_PAIR_BUDGET new quad-quad pairs, WALL_BUDGET wall/ceiling
# bounces and FLOOR_BUDGET floor landings per sub-step, and expands them to the dense draws the
# model functions take. Ranking rule: new pairs (i < j) in row-major order, quads in index order;
# the r-th event takes slot r mod budget (beyond the budget, events repeat an earlier event's draws
# of the same step; each event's own draws keep SPEC §5's distributions exactly).

QUAD_PAIR_BUDGET = 2
WALL_BUDGET = 2
FLOOR_BUDGET = 2


def quad_collision_slot_spec(tries: int, slots: int, shared_std: float, own_std: float, num_quads: int,
                             decay: tuple[float, float], kick_omega: tuple[float, float]) -> DrawSpec:
    """Per-slot draws of new quad-quad pairs (i < j): ``shared`` c, ``own_i`` e_i, ``own_j`` e_j per
    try, the pair's spin kick, and the per-quad ``decay`` (as :func:`quad_collision_draw_spec`)."""
    return {
        "shared": Normal(0.0, shared_std, (tries, slots, 3)),
        "own_i": Normal(0.0, own_std, (tries, slots, 3)),
        "own_j": Normal(0.0, own_std, (tries, slots, 3)),
        "kick_dir": Normal(0.0, 1.0, (slots, 3)),
        "kick_mag": Uniform(kick_omega[0], kick_omega[1], (slots,)),
        "decay": Uniform(decay[0], decay[1], (num_quads,)),
    }


def wall_bounces(pos: Any, prev_wall: Any, prev_ceiling: Any, room_low: Any, room_high: Any) -> Any:
    """(N,) mask of the quads that newly hit a wall or the ceiling (as :func:`wall_collisions`)."""
    xp = array_namespace(pos, prev_wall)
    lo = xp.asarray(room_low, dtype=pos.dtype)
    hi = xp.asarray(room_high, dtype=pos.dtype)
    at_wall = xp.any((pos[..., :2] <= lo[:2]) | (pos[..., :2] >= hi[:2]), axis=-1)
    return (at_wall & ~prev_wall) | ((pos[..., 2] >= hi[2]) & ~prev_ceiling)


def expand_per_quad(mask: Any, slots: dict[str, Any]) -> dict[str, Any]:
    """Dense per-quad draws (N, *shape) from per-slot draws (S, *shape) for the quads in ``mask``."""
    from quadswarm_mj.random_draws import event_slots, spread

    xp = array_namespace(mask, *slots.values())
    S = next(iter(slots.values())).shape[0]
    if xp is not np and mask.ndim == 1:  # one world under jax: pick the slot rows by S - 1 selects
        n = mask.shape[0]
        before = np.arange(n)[None, :] < np.arange(n)[:, None]  # [q, p] = p < q
        slot = xp.sum((mask[None, :] & before).astype(xp.int32), axis=-1) % S  # events before q (no cumsum)
        out = {}
        for k, v in slots.items():
            lead = (-1,) + (1,) * (v.ndim - 1)
            picked = xp.broadcast_to(v[0], mask.shape + v.shape[1:])
            for s in range(1, S):
                picked = xp.where((slot == s).reshape(lead), v[s], picked)
            out[k] = xp.where(mask.reshape(lead), picked, 0.0)
        return out
    hot = event_slots(xp, mask, S)
    return {k: spread(xp, hot, v) for k, v in slots.items()}


def quad_collisions_budgeted(pos: Any, vel: Any, omega: Any, prev_contact: Any, hitbox: float,
                             slots: dict[str, Any], pair_dist: Any = None, pair_events: Any = None) -> dict[str, Any]:
    """:func:`quad_collisions` of ONE world (``pos`` (N, 3)) computed only on the budgeted pairs (the
    JAX engine's path; O(S) response work instead of (T, N, N, 3) tensors).

    ``slots`` are the per-slot draws of :func:`quad_collision_slot_spec` (S slots). The new pairs
    (i < j) are ranked row-major; the first S take slots 0..S-1 and get exactly the response that
    :func:`quad_collisions` gives them with the slots' draws spread densely (the same formulas per pair,
    summed per quad; tests/test_draw_budget.py). New pairs beyond the budget are *deferred*: they get no response
    this step and are left out of the returned ``contact`` (and ``new_contact``), so they are new
    pairs again at the next control step. Returns ``vel, omega, contact, new_contact`` as
    :func:`quad_collisions` (``new_contact``: the resolved pairs, symmetric). ``pair_dist``, ``pair_events``:
    optional JAX kernels with the values of :func:`pairwise_contacts`' distances and of
    :func:`_pair_events_rows_first` (``pair_events(pos, prev_contact, hitbox, slots)``, one world).
    """
    xp = array_namespace(pos, vel)
    S = slots["kick_mag"].shape[-1]
    dist = pairwise_contacts(pos, hitbox, pair_dist)[1]
    if xp is np or pair_events is None:
        events = _pair_events_rows_first(xp, pos[..., None], prev_contact[..., None], hitbox, S)
        contact, res, hi, hj = (e[..., 0] for e in events)
    else:
        import jax

        contact, res, hi, hj = pair_events(jax.lax.stop_gradient(pos), prev_contact, xp.asarray(hitbox, pos.dtype), S)

    def gather(x: Any, h: Any) -> Any:  # (N, D) rows of the slots' quads -> (S, D)
        return xp.sum(xp.where(h[:, :, None], x[:, None, :], 0.0), axis=0)

    def scatter(x: Any, h: Any) -> Any:  # (S, D) -> (N, D), summed over the quad's slots
        return xp.sum(xp.where(h[:, :, None], x[None, :, :], 0.0), axis=1)

    p_i, p_j, v_i, v_j = gather(pos, hi), gather(pos, hj), gather(vel, hi), gather(vel, hj)
    rel = p_i - p_j
    d = xp.sqrt(xp.sum(rel * rel, axis=-1))
    nrm = rel / xp.where(d > 0, d, 1.0)[:, None]  # (S, 3) unit(p_i - p_j)
    nrm = xp.where((d == 0)[:, None], xp.asarray(coincident_normals(2)[0, 1], dtype=nrm.dtype), nrm)  # i < j: +x
    vin = xp.sum(v_i * nrm, axis=-1)
    vjn = xp.sum(v_j * nrm, axis=-1)
    change = (vjn - vin)[:, None] * nrm
    shift_i = change + slots["shared"] + slots["own_i"]  # (T, S, 3)
    shift_j = -change - slots["shared"] + slots["own_j"]
    sep_i = xp.sum((v_i + shift_i) * nrm, axis=-1)  # (T, S)
    sep_j = -xp.sum((v_j + shift_j) * nrm, axis=-1)
    ok = (sep_i > 0) & (sep_j > 0)
    tries = ok.shape[0]
    sel_i, sel_j = shift_i[tries - 1], shift_j[tries - 1]
    for t in range(tries - 2, -1, -1):  # first try that separates (static, tiny loop)
        sel_i = xp.where(ok[t][:, None], shift_i[t], sel_i)
        sel_j = xp.where(ok[t][:, None], shift_j[t], sel_j)
    dv = scatter(sel_i, hi) + scatter(sel_j, hj)
    s_pair = xp.maximum(xp.sqrt(xp.sum(v_i * v_i, axis=-1)), xp.sqrt(xp.sum(v_j * v_j, axis=-1)))  # (S,)
    h_any = hi | hj
    involved = xp.any(h_any, axis=-1)
    vmax = xp.max(xp.where(h_any, s_pair[None, :], 0.0), axis=-1)
    v_new = (vel + dv) * slots["decay"][:, None]
    s_new = xp.sqrt(xp.sum(v_new * v_new, axis=-1))
    scale = xp.minimum(1.0, vmax / xp.where(s_new > 0, s_new, 1.0))
    v_new = v_new * scale[:, None]
    # as quad_collisions: a resolved pair left without a separating normal speed gets +-SEPARATION_SPEED / 2
    used = xp.any(hi, axis=0)  # (S,) slots holding a pair
    stuck = used & (xp.sum((gather(v_new, hi) - gather(v_new, hj)) * nrm, axis=-1) <= 0.0)
    push = xp.where(stuck[:, None], (0.5 * SEPARATION_SPEED) * nrm, 0.0)
    any_stuck = xp.any((hi | hj) & stuck[None, :], axis=-1)
    v_new = xp.where(any_stuck[:, None], v_new + (scatter(push, hi) - scatter(push, hj)), v_new)
    kick = safe_normalize(xp, slots["kick_dir"]) * slots["kick_mag"][:, None]  # (S, 3): +w for i, -w for j
    d_omega = scatter(kick, hi) - scatter(kick, hj)
    inv = involved[:, None]
    return {"vel": xp.where(inv, v_new, vel), "omega": xp.where(inv, omega + d_omega, omega),
            "contact": contact, "new_contact": res, "dist": dist}


def _pair_events_rows_first(xp: Any, pos: Any, prev_contact: Any, hitbox: Any, slots: int) -> tuple:
    """The budget's pair events of ``pos`` (N, 3, *batch) with the batch axes LAST and
    ``prev_contact`` (N, N, *batch) and ``hitbox`` (m; a float or an array broadcasting against
    (N, N, *batch)): the new pairs (i < j) in row-major order, the first ``slots`` of them resolved
    (slot s = the s-th new pair), the rest deferred.

    Returns ``contact`` (N, N, *batch, symmetric; deferred pairs left out, so they are new again at
    the next step), ``resolved`` (N, N, *batch, symmetric) and ``hi``, ``hj`` (N, S, *batch): quad q
    is i / j of slot s. The s-th new pair is found as the smallest remaining flat index, S times
    (O(S N^2) compares and minimums instead of a cumulative sum's rank)."""
    n = pos.shape[0]
    tail = (1,) * (pos.ndim - 2)
    dist = _pair_distances_rows_first(xp, pos)
    contact = (dist <= hitbox) & off_diagonal(n).reshape((n, n) + tail)
    new_u = contact & ~prev_contact & np.triu(np.ones((n, n), bool), k=1).reshape((n, n) + tail)
    flat = new_u.reshape((n * n,) + new_u.shape[2:])
    index = np.arange(n * n, dtype=np.int32).reshape((n * n,) + tail)
    hot = []
    for _ in range(slots):  # static, tiny loop
        first = xp.min(xp.where(flat, index, n * n), axis=0)  # n * n where no new pair is left
        h = index == first[None]
        hot.append(h.reshape((n, n) + h.shape[1:]))
        flat = flat & ~h
    hot3 = xp.stack(hot, axis=2)  # (N, N, S, *batch)
    resolved = xp.any(hot3, axis=2)
    deferred = new_u & ~resolved
    drop = deferred | xp.swapaxes(deferred, 0, 1)
    return contact & ~drop, resolved | xp.swapaxes(resolved, 0, 1), xp.any(hot3, axis=1), xp.any(hot3, axis=0)
