"""The reset math of both engines, written once: :func:`start_state` (dynamics parameters, scenario,
spawn and the given overrides: :func:`quadswarm_mj.pipeline.initial_state`; the motors' derived state)
before the start is written into the physics, and :func:`start_flags` after it, on the positions as the
physics stores them (both engines read the start back: the quaternion round trip). The engines make the
draws (a seeded NumPy ``Generator`` in a fixed order, or one fused JAX draw) and keep the results
(rows of the reset worlds, or a new ``State``): :func:`reset_state` gathers the start into the
:class:`~quadswarm_mj.core.swarm.SwarmState` of the reset worlds. Arrays have leading dims (..., N)."""

from __future__ import annotations

from typing import Any

from quadswarm_mj import metrics as metrics_lib
from quadswarm_mj.core.swarm import SwarmState
from quadswarm_mj.pipeline import initial_flags, initial_state


def start_state(cfg: Any, scenario: Any, rand_draws: dict[str, Any], scenario_u: Any, spawn_u: Any,
                overrides: dict[str, Any], xp: Any, dtype: Any, aero_draws: dict[str, Any] | None = None,
                omap: Any = None) -> dict[str, Any]:
    """:func:`~quadswarm_mj.pipeline.initial_state` (``params``, ``scenario``, ``pos`` m, ``vel`` m/s,
    ``rot``, ``omega`` rad/s body, ``u0``; same arguments) plus ``f_norm`` = u0^2 (the normalized rotor
    thrusts of the start) and ``eps`` (zero motor noise) (..., N, 4)."""
    init = initial_state(cfg, scenario, rand_draws, scenario_u, spawn_u, overrides, xp, dtype, aero_draws,
                         obstacles=omap)
    u0 = init["u0"]
    return {**init, "f_norm": u0 * u0, "eps": xp.zeros(u0.shape, dtype=dtype)}


def start_flags(cfg: Any, pos: Any, xp: Any, omap: Any = None) -> dict[str, Any]:
    """The event flags of quads starting at ``pos`` (..., N, 3) m world-local (as the physics stores
    them): ``on_floor``, ``at_wall``, ``at_ceiling`` (:func:`~quadswarm_mj.pipeline.initial_flags`),
    ``contact`` (..., N, N) all False (no pair is 'already colliding' at the start: one overlapping at
    reset is a new contact at the first step, which the paper's response separates, as in the original)
    and, with obstacles, ``obst_contact`` (..., N) (quads touching a column of ``omap``)."""
    on_floor, at_wall, at_ceiling = initial_flags(cfg, pos, xp)
    n = pos.shape[-2]
    out = {"on_floor": on_floor, "at_wall": at_wall, "at_ceiling": at_ceiling,
           "contact": xp.zeros(pos.shape[:-1] + (n,), dtype=bool)}
    if omap is not None:
        from quadswarm_mj.obstacles import detect

        out["obst_contact"] = detect(pos, *omap, cfg.quad.arm)[0]
    return out


def start_accumulators(cfg: Any, like: Any, lead: tuple[int, ...], n: int) -> dict[str, Any]:
    """Zeroed episode accumulators of ``lead`` worlds of ``n`` quads: ``metrics_acc``
    (:func:`quadswarm_mj.metrics.init`) and, with obstacles, ``obst_metrics``; ``like`` fixes the
    namespace and float dtype."""
    out: dict[str, Any] = {"metrics_acc": metrics_lib.init(like, lead, n)}
    if cfg.obstacles is not None:
        from quadswarm_mj.obstacles import metrics_init

        out["obst_metrics"] = metrics_init(like, lead, n)
    return out


def reset_state(init: dict[str, Any], flags: dict[str, Any], fresh: dict[str, Any], step: Any, params: dict[str, Any],
                rot: Any = None, ctrl_state: Any = None, omap: Any = None, total_steps: Any = None) -> SwarmState:
    """The :class:`~quadswarm_mj.core.swarm.SwarmState` of the reset worlds from :func:`start_state`'s
    ``init``, :func:`start_flags`' ``flags`` and :func:`start_accumulators`' ``fresh``: motors at
    ``init["u0"]`` (thrust u0^2, no noise), the start's flags, no contact, zeroed accumulators, ``step``
    (the zero step count), ``params`` (gravity excluded), ``rot`` (None: recompute from the physics),
    ``ctrl_state`` (zeroed control-mode integrators or None), the column map ``omap`` or None and
    ``total_steps`` (None: the engine keeps its count)."""
    return SwarmState(rot=rot, motor_u=init["u0"], motor_eps=init["eps"], thrust=init["f_norm"],
                      on_floor=flags["on_floor"], at_wall=flags["at_wall"], at_ceiling=flags["at_ceiling"],
                      contact=flags["contact"], step=step, total_steps=total_steps, scenario=init["scenario"],
                      metrics_acc=fresh["metrics_acc"], params=params, ctrl_state=ctrl_state, obstacles=omap,
                      obstacle_contact=flags.get("obst_contact"), obstacle_metrics=fresh.get("obst_metrics"))
