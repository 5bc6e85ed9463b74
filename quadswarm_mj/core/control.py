"""One control step, written once for both engines: :func:`physics_stage` (the actuation sub-steps of
:mod:`quadswarm_mj.core.substeps`, then :func:`quadswarm_mj.core.step.velocity_stages`) and
:func:`task_step` (scenario, rewards, metrics: :func:`quadswarm_mj.pipeline.task_stage`; then the
observations). ``physics`` is the rigid-body back end (:mod:`quadswarm_mj.physics`), ``ops`` the
engine differences (:mod:`quadswarm_mj.core.ops`). Arrays have leading dims (B, N) on the MuJoCo engine
and (N,) per world on the JAX engine; positions m, velocities m/s world, ``omega`` rad/s body, ``R``
body->world. Where the engines keep the state between steps (``MjData`` and attributes, or the JAX
``State`` pytree) stays with them: they hand the fields below in and store what comes back.
"""

from __future__ import annotations

from typing import Any

from quadswarm_mj.core.step import velocity_stages
from quadswarm_mj.core.substeps import step_inputs, substep_loop
from quadswarm_mj.pipeline import effort_action, task_stage
from quadswarm_mj.rewards import anneal_factor

#: the fields of ``s`` that :func:`physics_stage` reads (``aux``: the back end's own carry or None;
#: ``ctrl``: (last rotor command, controller state) of the extended actuation chain, or None)
PHYSICS_STATE = ("q", "v", "R", "u", "eps", "f_norm", "on_floor", "at_wall", "at_ceiling", "contact", "params",
                 "aux", "ctrl")


def physics_stage(cfg: Any, s: dict[str, Any], action: Any, consts: dict[str, Any], physics: Any,
                  ops: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    """The physics half of a control step on state ``s`` (:data:`PHYSICS_STATE`: ``q``/``v`` in the
    back end's storage, ``R`` the rotation of ``q``; flags of the last step) with ``action`` (..., N, 4)
    and the actuation constants ``consts`` (:func:`~quadswarm_mj.core.substeps.substep_loop`).

    Returns ``(k, c)``: ``k`` :func:`velocity_stages`' result (world-local ``pos``, ``vel``, ``omega``,
    ``R``, ``quat``, ``u``, the event flags, ``dist``, ``changed``) plus ``on_floor``, ``f_norm``,
    ``eps`` (the motor noise after this step) and ``ctrl``; ``c`` the carry after the sub-steps (``q``,
    ``v`` in the back end's storage, ``aux``), which the engine stores where ``k["changed"]`` says."""
    inp = step_inputs(cfg, action, s["eps"], s["params"], ops)
    carry = {"q": s["q"], "v": s["v"], "R": s["R"], "u": s["u"], "f_norm": s["f_norm"], "on_floor": s["on_floor"],
             "hit_floor": ops.zeros_like(s["on_floor"]), "aux": s["aux"], "ctrl": s["ctrl"]}
    c = substep_loop(cfg, carry, inp, consts, physics, ops)
    vel, omega = physics.velocities(c["v"])
    kin = {"pos": physics.local_pos(c["q"]), "vel": vel, "omega": omega, "R": c["R"], "quat": c["q"][..., 3:7],
           "u": c["u"], "on_floor": c["on_floor"], "hit_floor": c["hit_floor"]}
    # the floor flags after the sub-steps (they change there only with the paper's floor, which does not read them)
    prev = {"on_floor": c["on_floor"], "at_wall": s["at_wall"], "at_ceiling": s["at_ceiling"], "contact": s["contact"]}
    fused = getattr(ops, "fused_stages", None)  # an engine's event-free form (None where an event happens)
    k = fused(cfg, kin, prev) if fused is not None else None
    if k is None:
        k = velocity_stages(cfg, kin, prev, ops)
    k.update(f_norm=c["f_norm"], eps=inp["eps"], ctrl=c["ctrl"])
    return k, c


def task_step(cfg: Any, scenario: Any, s: dict[str, Any], k: dict[str, Any], action: Any, consts: dict[str, Any],
              ops: Any) -> dict[str, Any]:
    """The task half of a control step after :func:`physics_stage`'s ``k``: the step count and time,
    :func:`quadswarm_mj.pipeline.task_stage` (scenario, reward terms, metrics), the reward and the
    observations (sensor noise drawn after the scenario's uniforms, deck noise last).

    ``s``: ``steps`` (...,) int control steps so far in the episode, ``total_steps`` (across episodes,
    reward annealing), ``sstate`` (:class:`~quadswarm_mj.scenarios.ScenarioState`), ``f_norm`` (the last
    step's thrusts), ``metrics_acc``, and with obstacles ``omap``, ``obst_metrics``, ``obst_threshold``
    (None: from the scenario). ``consts``: ``obs_low``, ``obs_high``, ``obs_scale`` (None: off) and
    ``zero_terms`` (reward terms that are exactly -0.0, left out of the sum: the same bits).
    Returns ``steps``, ``total_steps``, ``t`` (s), ``sstate``, ``goals``, ``goal_vel``, ``terms``,
    ``reward`` (..., N), ``metrics_acc``, ``obst_metrics``, ``obs`` (..., N, obs_dim) and ``done`` (the
    time limit). The engine's ``ops`` may offer a whole-stage form ``fused_task`` (same values; it returns
    None where it does not apply)."""
    fused = getattr(ops, "fused_task", None)
    if fused is not None and (r := fused(cfg, scenario, s, k, action, consts, ops)) is not None:
        return r
    steps, total_steps = s["steps"] + 1, s["total_steps"] + 1
    t = steps.astype(ops.dtype) * cfg.control_dt
    effort = action if cfg.control_mode == "rotor" else effort_action(cfg, action, k["ctrl"][0])
    omap = s.get("omap")
    r = task_stage(cfg, scenario, s["sstate"], t, k, effort, k["f_norm"], s["f_norm"], k["on_floor"],
                   anneal_factor(cfg, total_steps), ops.draws("scenario", None, None), s["metrics_acc"], omap,
                   s.get("obst_metrics"), s.get("obst_threshold"), ops)
    terms = ops.terms(r["terms"])
    obs = ops.obs(cfg, k["pos"], k["vel"], k["R"], k["omega"], r["goals"], ops.draws("sensor", None, None),
                    consts["obs_low"], consts["obs_high"], consts["obs_scale"], dist=k["dist"],
                    obstacles=None if omap is None else tuple(omap), obstacle_feats=k.get("obst_feats"),
                    deck_draws=ops.draws("deck", None, None))
    return {"steps": steps, "total_steps": total_steps, "t": t, "sstate": r["sstate"], "goals": r["goals"],
            "goal_vel": r["goal_vel"], "terms": terms, "reward": ops.total_reward(terms, consts["zero_terms"]),
            "metrics_acc": r["metrics_acc"], "obst_metrics": r["obst_metrics"], "obs": obs,
            "done": steps >= cfg.episode_steps}


def control_step(cfg: Any, scenario: Any, s: dict[str, Any], action: Any, consts: dict[str, Any], physics: Any,
                 ops: Any) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    """One control step: :func:`physics_stage` then :func:`task_step` (``s`` holds the fields of both,
    ``consts`` the constants of both). Returns ``(k, c, task)``: their results."""
    k, c = physics_stage(cfg, s, action, consts, physics, ops)
    return k, c, task_step(cfg, scenario, s, k, action, consts, ops)
