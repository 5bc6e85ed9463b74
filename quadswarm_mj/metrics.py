"""Episode metrics (SPEC §8), accumulated per quad with pure array updates (any batch dims).

``info["episode_metrics"]`` at the end of an episode holds, per world (means over quads):
``success``, ``collisions``, ``collision_rate`` (fraction of quads with at least one collision after
the grace period), ``floor_hits``, ``wall_hits``, ``ceiling_hits``, ``mean_distance``,
``goal_reach_rate`` (see :func:`finalize`); with obstacles also ``obstacle_collisions``, and
``collision_rate``/``success`` count obstacle contacts too
(:func:`quadswarm_mj.obstacles.metrics_finalize`, :func:`metric_keys`).
"""

from __future__ import annotations

from typing import Any

from quadswarm_mj._xp import array_namespace
from quadswarm_mj.spatial import norm_last

SUCCESS_DISTANCE = 0.5  # m, mean over the last LAST_STEPS steps
LAST_STEPS = 5
REACH_DISTANCE = 0.3  # m
MIN_SEGMENT_S = 3.0  # s, shorter goal segments are not counted in goal_reach_rate
METRIC_KEYS = ("success", "collisions", "collision_rate", "floor_hits", "wall_hits", "ceiling_hits",
               "mean_distance", "goal_reach_rate")
#: added with obstacles on (``success`` and ``collision_rate`` then also count obstacle contacts; SPEC_obstacles A.4)
OBSTACLE_METRIC_KEYS = ("obstacle_collisions",)


def metric_keys(cfg: Any) -> tuple[str, ...]:
    """Keys of ``info["episode_metrics"]`` of an env with ``cfg``."""
    return METRIC_KEYS + (OBSTACLE_METRIC_KEYS if getattr(cfg, "obstacles", None) is not None else ())


def init(like: Any, batch_shape: tuple[int, ...], n: int) -> dict[str, Any]:
    """Zeroed accumulators; ``like`` fixes the namespace and float dtype."""
    xp = array_namespace(like)
    f = like.dtype
    z = xp.zeros(tuple(batch_shape) + (n,), dtype=f)
    b = tuple(batch_shape)
    return {"collisions": z, "floor_hits": z, "wall_hits": z, "ceiling_hits": z, "dist_sum": z,
            "steps": xp.zeros(b, dtype=f), "last_dist": xp.zeros(b + (LAST_STEPS, n), dtype=f),
            "seg_start": z, "seg_reached": xp.zeros(z.shape, dtype=bool), "seg_count": z, "seg_success": z}


def goal_jump(prev_goals: Any, goals: Any, goal_vel: Any, dt: float) -> Any:
    """(..., N) True where a goal moved by more than its velocity explains over one control step
    (dt in s; goals m, goal_vel m/s): a new goal segment starts."""
    moved = norm_last(goals - prev_goals)
    speed = norm_last(goal_vel)
    return moved > 1e-3 + 2.0 * speed * dt


def update(m: dict[str, Any], t: Any, dist_to_goal: Any, new_contact: Any, hit_floor: Any, hit_wall: Any,
           hit_ceiling: Any, goal_jump: Any, grace_s: float) -> dict[str, Any]:
    """Accumulate one control step at time ``t`` (s, after the step). ``goal_jump`` (..., N) marks
    quads whose goal jumped this step (a new goal segment starts at ``t``)."""
    xp = array_namespace(dist_to_goal)
    f = dist_to_goal.dtype
    after_grace = (t >= grace_s)
    coll = new_contact.sum(axis=-1, dtype=f) * after_grace  # a count: exact in any float
    seg_len = t - m["seg_start"]
    close = goal_jump & (seg_len >= MIN_SEGMENT_S - 1e-9)
    reached = m["seg_reached"]
    near = dist_to_goal < REACH_DISTANCE
    last = xp.concatenate([m["last_dist"][..., 1:, :], dist_to_goal[..., None, :]], axis=-2)
    return {  # float + bool adds 0 or 1 exactly (bools promote to the float dtype)
        "collisions": m["collisions"] + coll,
        "floor_hits": m["floor_hits"] + hit_floor,
        "wall_hits": m["wall_hits"] + hit_wall,
        "ceiling_hits": m["ceiling_hits"] + hit_ceiling,
        "dist_sum": m["dist_sum"] + dist_to_goal,
        "steps": m["steps"] + 1.0,
        "last_dist": last,
        "seg_count": m["seg_count"] + close,
        "seg_success": m["seg_success"] + (close & reached),
        "seg_start": xp.where(goal_jump, t, m["seg_start"]),
        "seg_reached": near | (reached & ~goal_jump),  # a jump starts a new segment: reached = near
    }


def finalize(m: dict[str, Any], t_end: Any) -> dict[str, Any]:
    """Episode metrics per world (..., ) as means over quads."""
    xp = array_namespace(m["dist_sum"])
    f = m["dist_sum"].dtype
    steps = xp.maximum(m["steps"], 1.0)
    close = (t_end - m["seg_start"]) >= MIN_SEGMENT_S - 1e-9
    count = xp.sum(m["seg_count"] + close.astype(f), axis=-1)
    succ = xp.sum(m["seg_success"] + (close & m["seg_reached"]).astype(f), axis=-1)
    final_d = xp.mean(m["last_dist"], axis=-2)
    success = (m["collisions"] == 0) & (final_d < SUCCESS_DISTANCE)
    return {
        "success": xp.mean(success.astype(f), axis=-1),
        "collisions": xp.mean(m["collisions"], axis=-1),
        "collision_rate": xp.mean((m["collisions"] > 0).astype(f), axis=-1),
        "floor_hits": xp.mean(m["floor_hits"], axis=-1),
        "wall_hits": xp.mean(m["wall_hits"], axis=-1),
        "ceiling_hits": xp.mean(m["ceiling_hits"], axis=-1),
        "mean_distance": xp.mean(m["dist_sum"], axis=-1) / steps,
        "goal_reach_rate": xp.where(count > 0, succ / xp.maximum(count, 1.0), xp.nan),
    }
