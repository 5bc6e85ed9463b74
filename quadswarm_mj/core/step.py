"""The once-per-control-step stages after the physics sub-steps, written once for both engines.

Order (docs/engines.md): walls and ceiling (the paper's floor model) or, with MuJoCo contacts, the room
guard and the surface flags -> quad-quad -> obstacles -> downwash. :func:`velocity_stages` spells it
with ``ops`` (:mod:`quadswarm_mj.core.ops`) holding the only engine differences: which worlds an
event model runs on (the CPU engine: only worlds with an event, and not at all without one; the JAX
engine: every world, always) and where its random draws come from (per event from a NumPy
``Generator``, or the step's budgeted slots spread over the events). Arrays have leading dims (B, N)
on the CPU engine, (N,) per world on the JAX engine; positions m world-local, velocities m/s world,
``omega`` rad/s body, ``R``/``quat`` body->world.
"""

from __future__ import annotations

from typing import Any

from quadswarm_mj.collisions import outside_room, room_guard, wall_bounces, wall_collisions
from quadswarm_mj.downwash import apply_downwash, downwash_mask


def surface_flags(cfg: Any, pos: Any, room_low: Any, room_high: Any) -> tuple[Any, Any, Any]:
    """(on_floor, at_wall, at_ceiling) (..., N) with MuJoCo contacts: within the hitbox radius (arm)
    plus 5 mm of the floor, a wall or the ceiling."""
    margin = cfg.quad.arm + 0.005
    on_floor = pos[..., 2] <= margin
    xy = pos[..., :2]
    at_wall = ((xy <= room_low[:2] + margin) | (xy >= room_high[:2] - margin)).any(-1)
    return on_floor, at_wall, pos[..., 2] >= room_high[2] - margin


def velocity_stages(cfg: Any, k: dict[str, Any], prev: dict[str, Any], ops: Any) -> dict[str, Any]:
    """The stages after the sub-steps on ``k`` (``pos``, ``vel``, ``omega``, ``R``, ``quat``, ``u``,
    ``hit_floor`` of the sub-steps) with the previous flags ``prev`` (``on_floor``, ``at_wall``,
    ``at_ceiling``, ``contact``). Returns ``k`` updated (new arrays; the inputs are not written) with
    ``at_wall``, ``at_ceiling``, ``on_floor``, ``hit_wall``, ``hit_ceiling``, ``contact``,
    ``new_contact``, ``dist`` (pair distances m) and ``changed`` (a Python bool: whether pos, vel,
    omega or the rotations may differ from the input)."""
    k = dict(k)
    lo, hi = ops.room
    changed = False
    if cfg.collision_model == "paper":  # the paper's walls and ceiling (the floor is in the sub-steps)
        at_wall, at_ceiling = prev["at_wall"], prev["at_ceiling"]
        w = ops.wall_gate(k["pos"], at_wall, at_ceiling)  # worlds whose wall/ceiling state may change
        hit_wall = hit_ceiling = ops.zeros_like(at_wall)
        if w is not None:
            draws = ops.draws("wall", lambda: wall_bounces(k["pos"], at_wall, at_ceiling, lo, hi), w)
            r = wall_collisions(k["pos"][w], k["vel"][w], k["omega"][w], at_wall[w], at_ceiling[w], lo, hi, draws,
                                cfg.collision.wall_speed_limits)
            for name in ("pos", "vel", "omega"):
                k[name] = ops.put(k[name], w, r[name])
            hit_wall, hit_ceiling = ops.put(hit_wall, w, r["hit_wall"]), ops.put(hit_ceiling, w, r["hit_ceiling"])
            at_wall, at_ceiling = ops.put(at_wall, w, r["at_wall"]), ops.put(at_ceiling, w, r["at_ceiling"])
            changed = True
        k.update(at_wall=at_wall, at_ceiling=at_ceiling, hit_wall=hit_wall, hit_ceiling=hit_ceiling)
    else:  # MuJoCo resolves floor, walls and ceiling; the room guard is the backstop, flags from proximity
        beyond, below = outside_room(k["pos"], lo, hi)
        w = ops.gate(lambda: beyond | below)
        if w is not None:
            wall_draws = ops.draws("wall", lambda: beyond, w)
            yaw = ops.draws("yaw", lambda: below, w)  # {"yaw_draw": rad} or {"yaw_draw_cs": (cos, sin)}
            g = room_guard(k["pos"][w], k["vel"][w], k["omega"][w], k["quat"][w], k["R"][w], k["u"][w], lo, hi,
                           cfg.quad.arm, wall_draws, cfg.collision.wall_speed_limits, **yaw)
            for name, key in (("pos", "pos"), ("vel", "vel"), ("omega", "omega"), ("quat", "quat"), ("R", "R"),
                              ("u", "u")):
                k[name] = ops.put(k[name], w, g[key])
            changed = True
        on_floor, at_wall, at_ceiling = surface_flags(cfg, k["pos"], lo, hi)
        k.update(on_floor=on_floor, at_wall=at_wall, at_ceiling=at_ceiling, hit_floor=on_floor & ~prev["on_floor"],
                 hit_wall=at_wall & ~prev["at_wall"], hit_ceiling=at_ceiling & ~prev["at_ceiling"])
    contact, dist = ops.pairwise_contacts(k["pos"], cfg.hitbox)
    k.update(contact=contact, new_contact=contact & ~prev["contact"], dist=dist)
    if cfg.collision_model in ("paper", "blend"):  # the paper's quad-quad response
        q = ops.quad_quad(k["pos"], k["vel"], k["omega"], prev["contact"], contact, k["new_contact"])
        if q is not None:
            k.update(vel=q["vel"], omega=q["omega"], new_contact=q["new_contact"], contact=q["contact"])
            changed = True
    if cfg.obstacles is not None:
        o = ops.obstacles(k["pos"], k["vel"], k["omega"])
        changed = changed or o.pop("changed")
        k.update(o)
    if cfg.downwash:
        draws = ops.draws("down", lambda: downwash_mask(k["pos"], k["R"])[0], None)
        k["vel"], k["omega"] = apply_downwash(k["pos"], k["vel"], k["omega"], k["R"], cfg.control_dt, draws)
        changed = True
    k["changed"] = changed
    return k
