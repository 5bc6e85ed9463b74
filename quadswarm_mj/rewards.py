"""Reward terms (SPEC §8). Every term is a reward: r_term = -control_dt * scale * cost.

Terms (keys of ``info["reward_terms"]``) and their costs per quad:

* ``pos`` ||goal - p||; ``effort`` ||a_raw||; ``spin`` ||omega||; ``crash`` 1 while on the floor;
  ``orient`` -R_22 in the air, 1 on the floor; ``vel`` ||v||; ``action_change``
  ||f_t - f_{t-1}|| (normalized thrusts); ``yaw`` -R_00; ``rot`` -(tr R - 1) / 2;
* ``quad_collision`` number of pairs the quad is in whose contact started this step;
  ``proximity`` sum over other quads within the falloff of (1 - d / falloff);
* ``floor_hit``, ``wall_hit``, ``ceiling_hit`` 1 on the step of the hit.

The collision and proximity scales are multiplied by an annealing factor in [0, 1].
The per-quad reward is the exact sum of the terms. Pure, any batch dims, NumPy or ``jax.numpy``.
"""

from __future__ import annotations

from typing import Any

from quadswarm_mj._xp import array_namespace
from quadswarm_mj.config import EnvConfig, RewardScales

TERMS = RewardScales.TERMS
ANNEALED = ("quad_collision", "proximity")


def _norm(xp: Any, x: Any) -> Any:
    return xp.sqrt(xp.sum(x * x, axis=-1))


def reward_terms(cfg: EnvConfig, pos: Any, vel: Any, R: Any, omega: Any, goals: Any, action: Any,
                 f_norm: Any, prev_f_norm: Any, on_floor: Any, hit_floor: Any, hit_wall: Any,
                 hit_ceiling: Any, new_contact: Any, dist: Any, anneal: Any = 1.0) -> dict[str, Any]:
    """Dict term -> (..., N) rewards for one control step. ``dist`` is the (..., N, N) distance matrix."""
    xp = array_namespace(pos, vel)
    s = cfg.rewards
    dt = cfg.control_dt
    fl = on_floor.astype(pos.dtype)
    n = pos.shape[-2]
    falloff = s.proximity_falloff_arms * cfg.quad.arm
    others = ~xp.eye(n, dtype=bool)
    prox = xp.sum(xp.where(others & (dist < falloff), 1.0 - dist / falloff, 0.0), axis=-1)
    costs = {
        "pos": _norm(xp, goals - pos),
        "effort": _norm(xp, action),
        "spin": _norm(xp, omega),
        "crash": fl,
        "orient": xp.where(on_floor, 1.0, -R[..., 2, 2]),
        "vel": _norm(xp, vel),
        "action_change": _norm(xp, f_norm - prev_f_norm),
        "yaw": -R[..., 0, 0],
        "rot": -(R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0) / 2.0,
        "quad_collision": xp.sum(new_contact.astype(pos.dtype), axis=-1),
        "proximity": prox,
        "floor_hit": hit_floor.astype(pos.dtype),
        "wall_hit": hit_wall.astype(pos.dtype),
        "ceiling_hit": hit_ceiling.astype(pos.dtype),
    }
    out = {}
    for k in TERMS:
        scale = getattr(s, k) * (anneal if k in ANNEALED else 1.0)
        out[k] = -dt * scale * costs[k]
    return out


def total_reward(terms: dict[str, Any]) -> Any:
    """Sum of the terms, in the fixed order of ``TERMS`` (so sums are reproducible)."""
    total = terms[TERMS[0]]
    for k in TERMS[1:]:
        total = total + terms[k]
    return total


def anneal_factor(cfg: EnvConfig, total_steps: Any) -> Any:
    """Collision-term annealing: ramps linearly 0 -> 1 over ``rewards.anneal_steps`` steps."""
    if cfg.rewards.anneal_steps <= 0:
        return 1.0
    xp = array_namespace(total_steps)
    return xp.minimum(1.0, total_steps / cfg.rewards.anneal_steps)
