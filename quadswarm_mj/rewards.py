"""Reward terms (SPEC §8), per quad and control step, with the original's time scaling:

* state terms (``STATE_TERMS``): r = -sim_dt * scale * cost (sim_dt = 0.005 s by default, as the original
  scales although it computes the reward once per control step);
* ``proximity``: r = -control_dt * scale * cost (0.01 s);
* event terms (``EVENT_TERMS``): r = -scale * count, not time-scaled.

The terms (keys of ``info["reward_terms"]``), their costs and baseline scales are tabled in docs/model.md
("Rewards and episode metrics"). ``effort`` sees ``a_raw``, the "rotor" mode's per-rotor action clipped
into [-1, 1]; the physical-unit control modes pass the equivalent raw action 2 cmd - 1 of the mode
controller's last rotor command (:func:`quadswarm_mj.pipeline.effort_action`), so its scale means the
same in every mode. The collision and proximity scales are multiplied by an annealing factor in [0, 1].
The per-quad reward is the exact sum of the terms. Pure, any batch dims, NumPy or ``jax.numpy``.
"""

from __future__ import annotations

import functools
from typing import Any

from quadswarm_mj._xp import array_namespace
from quadswarm_mj.collisions import off_diagonal
from quadswarm_mj.config import EnvConfig, RewardScales
from quadswarm_mj.spatial import norm_last

TERMS = RewardScales.TERMS
ANNEALED = ("quad_collision", "proximity")
#: Terms scaled by the simulation step, by the control step, and not time-scaled (counts of events).
STATE_TERMS = ("pos", "effort", "spin", "crash", "orient", "vel", "action_change", "yaw", "rot")
CONTROL_DT_TERMS = ("proximity", "obstacle_proximity", "obstacle_approach")
EVENT_TERMS = ("quad_collision", "obstacle_collision", "floor_hit", "wall_hit", "ceiling_hit")
#: Terms present only with obstacles on (``cfg.obstacles``; ``obstacle_proximity`` and ``obstacle_approach``
#: only with their scale > 0): summed after ``TERMS`` by :func:`total_reward`.
OBSTACLE_TERMS = ("obstacle_collision", "obstacle_proximity", "obstacle_approach")


def env_terms(cfg: EnvConfig) -> tuple[str, ...]:
    """The reward terms of an env with ``cfg`` (keys of ``info["reward_terms"]``, MJX
    ``metrics["reward/<term>"]``): ``TERMS``, plus ``obstacle_collision`` with obstacles on (and
    ``obstacle_proximity``/``obstacle_approach`` with ``cfg.obstacles.proximity_reward``/``approach_reward`` > 0)."""
    o = cfg.obstacles
    if o is None:
        return TERMS
    on = {"obstacle_collision": True, "obstacle_proximity": o.proximity_reward > 0,
          "obstacle_approach": o.approach_reward > 0}
    return TERMS + tuple(k for k in OBSTACLE_TERMS if on[k])


def term_dt(cfg: EnvConfig, term: str) -> float:
    """The time factor of ``term`` (s): sim_dt, control_dt, or 1.0 for event terms (SPEC §8)."""
    if term in STATE_TERMS:
        return cfg.sim_dt
    if term in CONTROL_DT_TERMS:
        return cfg.control_dt
    if term in EVENT_TERMS:
        return 1.0
    raise ValueError(f"unknown reward term {term!r}; known: {TERMS}")


#: Terms whose cost is never negative: with a zero scale they are exactly -0.0 and are not computed.
NONNEGATIVE = ("pos", "effort", "spin", "crash", "vel", "action_change", "quad_collision", "proximity",
               "floor_hit", "wall_hit", "ceiling_hit")


def reward_terms(cfg: EnvConfig, pos: Any, vel: Any, R: Any, omega: Any, goals: Any, action: Any,
                 f_norm: Any, prev_f_norm: Any, on_floor: Any, hit_floor: Any, hit_wall: Any,
                 hit_ceiling: Any, new_contact: Any, dist: Any, anneal: Any = 1.0,
                 goal_dist: Any | None = None) -> dict[str, Any]:
    """Dict term -> (..., N) rewards for one control step. ``dist`` is the (..., N, N) distance matrix;
    ``goal_dist`` optionally passes ||goals - pos|| (..., N) when the caller has it already.

    Each term is -term_dt(cfg, term) * scale * cost (see the module doc). A term with a zero scale
    whose cost cannot be negative is -0.0 (= -dt * 0 * cost) without computing the cost: all such
    terms are one shared (..., N) array of -0.0 (read-only by convention, as every term)."""
    s = cfg.rewards
    xp = array_namespace(pos, vel)
    n = pos.shape[-2]
    falloff = s.proximity_falloff_arms * cfg.quad.arm
    dtype = pos.dtype
    cost_fns = {
        "pos": lambda: norm_last(goals - pos) if goal_dist is None else goal_dist,
        "effort": lambda: norm_last(xp.minimum(xp.maximum(action, -1.0), 1.0)),  # the clipped action
        "spin": lambda: norm_last(omega),
        "crash": lambda: on_floor.astype(dtype),
        "orient": lambda: xp.where(on_floor, 1.0, -R[..., 2, 2]),
        "vel": lambda: (norm_last(vel) if s.vel_limit == 0 else  # the speed above the limit (m/s)
                        xp.maximum(norm_last(vel) - s.vel_limit, 0.0)),
        "action_change": lambda: norm_last(f_norm - prev_f_norm),
        "yaw": lambda: -R[..., 0, 0],
        "rot": lambda: -(R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0) / 2.0,
        "quad_collision": lambda: new_contact.sum(axis=-1, dtype=dtype),  # a count: exact in any float
        # sum over the others within the falloff of (1 - d / falloff); max(., 0) does the masking
        "proximity": lambda: xp.maximum(1.0 - xp.where(off_diagonal(n), dist, xp.inf) / falloff, 0.0).sum(axis=-1),
        "floor_hit": lambda: hit_floor.astype(dtype),
        "wall_hit": lambda: hit_wall.astype(dtype),
        "ceiling_hit": lambda: hit_ceiling.astype(dtype),
    }
    out = {}
    zero = None
    for k, neg_dt, base in _term_factors(s, cfg.sim_dt, cfg.control_dt):
        if base is None:
            if zero is None:
                zero = -0.0 * on_floor  # a fresh (..., N) array of -0.0 (default float type)
            out[k] = zero
        elif k in ANNEALED:
            out[k] = neg_dt * (base * anneal) * cost_fns[k]()
        else:
            out[k] = neg_dt * base * cost_fns[k]()  # = -term_dt(cfg, k) * scale * cost
    return out


@functools.lru_cache(maxsize=64)
def _term_factors(scales: RewardScales, sim_dt: float, control_dt: float
                  ) -> tuple[tuple[str, float, float | None], ...]:
    """(term, -term_dt, base scale) of each of ``TERMS`` in order; base None for a term that is exactly
    -0.0 (zero scale, cost never negative). Depends on the config only: computed once per config."""
    dt = {**dict.fromkeys(STATE_TERMS, sim_dt), **dict.fromkeys(CONTROL_DT_TERMS, control_dt)}
    out = []
    for k in TERMS:
        base = getattr(scales, k)
        out.append((k, -dt.get(k, 1.0), None if base == 0 and k in NONNEGATIVE else base))
    return tuple(out)


def zero_terms(cfg: EnvConfig) -> tuple[str, ...]:
    """The terms :func:`reward_terms` returns as exactly -0.0 (zero scale, cost never negative)."""
    return tuple(k for k in TERMS if k in NONNEGATIVE and getattr(cfg.rewards, k) == 0)


def total_reward(terms: dict[str, Any], skip: tuple[str, ...] = ()) -> Any:
    """Sum of the terms, in the fixed order of ``TERMS`` then ``OBSTACLE_TERMS`` present in ``terms``
    (so sums are reproducible). ``skip`` may name terms that are exactly -0.0 (:func:`zero_terms`):
    adding -0.0 changes nothing."""
    keys = [k for k in TERMS if k not in skip] + [k for k in OBSTACLE_TERMS if k in terms]
    total = terms[keys[0]]
    for k in keys[1:]:
        total = total + terms[k]
    return total


def anneal_factor(cfg: EnvConfig, total_steps: Any) -> Any:
    """Collision-term annealing: ramps linearly 0 -> 1 over ``rewards.anneal_steps`` steps."""
    if cfg.rewards.anneal_steps <= 0:
        return 1.0
    xp = array_namespace(total_steps)
    return xp.minimum(1.0, total_steps / cfg.rewards.anneal_steps)
