"""One control step's physics half, free-body physics, run with NumPy and with ``jax.numpy`` (jit,
float64) on identical inputs: the two agree to round-off (1e-12) and every event flag is equal.

``physics_half`` below is the control step's physics as the package has it today, chained from the
leaf functions in the order of ``CpuSwarm._physics`` / ``MjxQuadSwarmEnv._physics``: motor noise;
per sub-step the actuation (``substep_wrench``, or the control-mode and aerodynamics chain of
``pipeline.make_substep_actuation``), the paper's floor wrench, ``freebody_step`` (angular velocity
clipped), the floor impact; then once per step walls and ceiling (or the MuJoCo-contact models' room
guard and surface flags), quad-quad, obstacles, downwash. Every draw is given dense (for every quad),
so the same numbers reach both namespaces. The start states put quads into every event (landing
upside down, grounded, wall, ceiling, a colliding pair, a column, one under another's downwash).

Measured (3 chained steps; ``python -m pytest -q -m "" tests/test_numpy_jax_step.py``, errors relative to
max(1, |value|)): the rotor cases agree to 2e-15, the "ctbr" case to 1e-8 (see ``TOL_SQRT``).

``STEP`` is the package's one control step's physics half, :func:`quadswarm_mj.core.control.physics_stage`
(the sub-step loop and the stages after it, written once for both engines), with the free-body physics
:class:`quadswarm_mj.physics.freebody.FreeBodyPhysics` and the dense-draw ops
:class:`dense_ops.DenseOps` (tests/dense_ops.py) in either namespace: the NumPy and JAX runs of it must
agree, and in NumPy it must agree with ``physics_half`` (the leaf chain) to round-off. The whole
:func:`quadswarm_mj.core.control.control_step` (plus scenario, rewards, metrics, observations) is run
the same way by ``test_the_whole_control_step_numpy_equals_jax_float64``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, ObstacleConfig, pipeline
from quadswarm_mj.actuation import (
    SPIN,
    action_to_command,
    motor_noise_step,
    rotor_positions,
    substep_wrench,
    wrench_matrix,
)
from quadswarm_mj.collisions import (
    collision_draw_specs,
    floor_impact,
    floor_wrench,
    pairwise_contacts,
    quad_collisions,
    room_guard,
    wall_collisions,
)
from quadswarm_mj.control_modes import control_action_bounds
from quadswarm_mj.downwash import apply_downwash, downwash_draw_spec
from quadswarm_mj.freebody import freebody_step
from quadswarm_mj.obstacles import map_from_centres, response_draw_spec
from quadswarm_mj.random_draws import NumpySampler
from quadswarm_mj.randomization import randomization_draw_spec
from quadswarm_mj.spatial import quat_to_rotmat, rotmat_to_quat

jax = pytest.importorskip("jax")
jnp = jax.numpy

B, N = 2, 9
STEPS = 3  # control steps chained (the outputs of one are the inputs of the next)
TOL = 1e-12  # relative to max(1, |value|)
#: The control modes' allocation clips rotor commands at 0, where XLA's fused operations leave ~1e-18
#: that NumPy computes as 0 (or the converse); the motor lag's sqrt(cmd) turns that into ~1e-9 in the
#: motor state u (sqrt has an infinite slope at 0): an inherent sensitivity of the model, not a
#: difference of formulas. Bound for those cases: a few sqrt(float64 eps) = 1.5e-8.
TOL_SQRT = 1e-7
COLS = np.array([[0.0, 0.0], [2.0, -1.0]])  # m, column centres (diameter 0.6 m)


def _cfg(**kw: Any) -> EnvConfig:
    return EnvConfig(num_quads=N, downwash=True, randomize=True, obstacles=ObstacleConfig(density=0.2), **kw)


CASES = {
    "paper_rotor": _cfg(),
    "paper_ctbr_aero": _cfg(control_mode="ctbr", aero={"ground_effect": True, "drag": True}),
    "blend_rotor": _cfg(collision_model="blend"),
}
#: (case, floor impact path) compared: the angle path (the CPU engine's) on each case, the trig-free path
#: (the JAX engine's) on the default model; each JAX case takes 12-22 s (mostly compiling, on 2 loaded
#: cores), two of them run only with -m slow
COMPARED = [pytest.param("paper_rotor", False, id="paper_rotor-floor_angle"),
            pytest.param("paper_ctbr_aero", False, id="paper_ctbr_aero-floor_angle"),
            pytest.param("paper_rotor", True, id="paper_rotor-floor_cos_sin", marks=pytest.mark.slow),
            pytest.param("blend_rotor", False, id="blend_rotor-floor_angle", marks=pytest.mark.slow)]


# ------------------------------------------------------------------------------------ the step under test
def physics_half(xp: Any, cfg: EnvConfig, s: dict[str, Any], action: Any, params: dict[str, Any],
                 d: dict[str, Any], yaw_cs: bool) -> dict[str, Any]:
    """One control step's physics with free-body physics in namespace ``xp`` (NumPy or jax.numpy).

    ``s``: state (B, N, ...) ``q`` [pos m, quat wxyz], ``v`` [vel m/s world, omega rad/s body], ``u``,
    ``eps``, ``f_norm`` (B, N, 4), ``ctrl`` (B, N, 6), flags ``on_floor``, ``at_wall``, ``at_ceiling``,
    ``obst_contact`` (B, N), ``contact`` (B, N, N); ``d``: every draw of the step, dense; ``yaw_cs``:
    the floor impact's trig-free path (cos, sin of the yaw draws) instead of the angle path.
    Returns the new state plus this step's event masks."""
    paper = cfg.collision_model == "paper"
    rotor_pos = xp.asarray(rotor_positions(cfg.quad))
    mix = wrench_matrix(rotor_positions(cfg.quad))  # NumPy constant (3, 4) for both, as the engines
    spin = params["torque_max"] * xp.asarray(SPIN)
    act = pipeline.make_substep_actuation(cfg)
    cmd = action_to_command(action) if cfg.control_mode == "rotor" else None
    eps = motor_noise_step(s["eps"], params["motor_sigma"], cfg.noise.motor_noise_theta, d["motor"])
    g = xp.asarray([0.0, 0.0, -params["gravity"]])
    q, v, u, f_norm, ctrl, on_floor = s["q"], s["v"], s["u"], s["f_norm"], s["ctrl"], s["on_floor"]
    hit_floor = xp.zeros(on_floor.shape, dtype=bool)
    floor_z = cfg.quad.arm
    for k in range(cfg.substeps):
        R = quat_to_rotmat(q[..., 3:7])
        if act is None:
            u, f_norm, force, torque = substep_wrench(u, cmd, eps, params, R, rotor_pos, mix, spin)
        else:
            u, f_norm, force, torque, _, ctrl = act(u, action, cmd, eps, params, q[..., :3], v[..., :3], R,
                                                    v[..., 3:], ctrl, rotor_pos, mix, spin)
        if paper:
            force, torque = floor_wrench(on_floor, force, torque, v[..., :3], params["mass"], params["gravity"],
                                         cfg.collision.floor_friction, cfg.sim_dt)
        q, v = freebody_step(q, v, xp.concatenate([force, torque], -1), params["mass"], params["inertia"], None,
                             None, g, cfg.sim_dt, max_omega=cfg.quad.max_omega)
        if paper:
            R = quat_to_rotmat(q[..., 3:7])
            yaw = d["yaw"][k]
            kw = {"yaw_draw_cs": (xp.cos(yaw), xp.sin(yaw))} if yaw_cs else {}
            r = floor_impact(q[..., :3], v[..., :3], v[..., 3:], q[..., 3:7], R, u, on_floor, floor_z,
                             None if yaw_cs else yaw, **kw)
            q = xp.concatenate([r["pos"], r["quat"]], -1)
            v = xp.concatenate([r["vel"], r["omega"]], -1)
            u, on_floor, hit_floor = r["u"], r["on_floor"], hit_floor | r["hit_floor"]
    R = quat_to_rotmat(q[..., 3:7])
    pos, vel, omega = q[..., :3], v[..., :3], v[..., 3:]
    lo, hi = xp.asarray(cfg.room_low), xp.asarray(cfg.room_high)
    if paper:
        w = wall_collisions(pos, vel, omega, s["at_wall"], s["at_ceiling"], lo, hi, d["wall"],
                            cfg.collision.wall_speed_limits)
        pos, vel, omega = w["pos"], w["vel"], w["omega"]
        at_wall, at_ceiling, hit_wall, hit_ceiling = w["at_wall"], w["at_ceiling"], w["hit_wall"], w["hit_ceiling"]
    else:  # room guard, then flags from proximity to the surfaces
        yaw = d["yaw"][-1]
        kw = {"yaw_draw_cs": (xp.cos(yaw), xp.sin(yaw))} if yaw_cs else {"yaw_draw": yaw}
        gd = room_guard(pos, vel, omega, q[..., 3:7], R, u, lo, hi, cfg.quad.arm, d["wall"],
                        cfg.collision.wall_speed_limits, **kw)
        pos, vel, omega, R, u = gd["pos"], gd["vel"], gd["omega"], gd["R"], gd["u"]
        q = xp.concatenate([pos, gd["quat"]], -1)
        margin = cfg.quad.arm + 0.005
        now_floor = pos[..., 2] <= margin
        at_wall = xp.any((pos[..., :2] <= lo[:2] + margin) | (pos[..., :2] >= hi[:2] - margin), -1)
        at_ceiling = pos[..., 2] >= hi[2] - margin
        hit_floor, hit_wall = now_floor & ~s["on_floor"], at_wall & ~s["at_wall"]
        hit_ceiling = at_ceiling & ~s["at_ceiling"]
        on_floor = now_floor
    qc = quad_collisions(pos, vel, omega, s["contact"], cfg.hitbox, d["quad"])
    vel, omega = qc["vel"], qc["omega"]
    ob = pipeline.obstacle_stage(pos, vel, omega, s["obst_contact"], d["omap"], cfg.quad.arm, d["obst"], paper)
    vel, omega = ob["vel"], ob["omega"]
    _, dist = pairwise_contacts(pos, cfg.hitbox)
    vel, omega = apply_downwash(pos, vel, omega, R, cfg.control_dt, d["down"])
    q = xp.concatenate([pos, q[..., 3:7]], -1)
    return {"q": q, "v": xp.concatenate([vel, omega], -1), "u": u, "eps": eps, "f_norm": f_norm, "ctrl": ctrl,
            "on_floor": on_floor, "at_wall": at_wall, "at_ceiling": at_ceiling, "contact": qc["contact"],
            "obst_contact": ob["contact"], "R": R, "dist": dist, "hit_floor": hit_floor, "hit_wall": hit_wall,
            "hit_ceiling": hit_ceiling, "new_contact": qc["new_contact"], "obst_new": ob["new_contact"]}


def control_step_physics(xp: Any, cfg: EnvConfig, s: dict[str, Any], action: Any, params: dict[str, Any],
                         d: dict[str, Any], yaw_cs: bool) -> dict[str, Any]:
    """``physics_half``'s contract through the package's ``core.control.physics_stage``."""
    from dense_ops import DenseOps

    from quadswarm_mj.core.control import physics_stage
    from quadswarm_mj.physics.freebody import FreeBodyPhysics

    act = pipeline.make_substep_actuation(cfg)
    physics = FreeBodyPhysics(params["mass"], params["inertia"], xp.asarray([0.0, 0.0, -params["gravity"]]),
                              cfg.sim_dt, cfg.quad.max_omega)
    ops = DenseOps(cfg, d, xp, yaw_cs, omap=d["omap"], obst_contact=s["obst_contact"])
    consts = {"act": act, "rotor_pos": xp.asarray(rotor_positions(cfg.quad)),
              "mix": wrench_matrix(rotor_positions(cfg.quad)), "torque_spin": params["torque_max"] * xp.asarray(SPIN)}
    state = {**{k: s[k] for k in ("q", "v", "u", "eps", "f_norm", "on_floor", "at_wall", "at_ceiling", "contact")},
             "R": quat_to_rotmat(s["q"][..., 3:7]), "params": params, "aux": None,
             "ctrl": None if act is None else (xp.zeros_like(s["u"]), s["ctrl"])}
    k, _ = physics_stage(cfg, state, action, consts, physics, ops)
    return {"q": xp.concatenate([k["pos"], k["quat"]], -1), "v": xp.concatenate([k["vel"], k["omega"]], -1),
            "u": k["u"], "eps": k["eps"], "f_norm": k["f_norm"], "ctrl": s["ctrl"] if act is None else k["ctrl"][1],
            **{key: k[key] for key in ("on_floor", "at_wall", "at_ceiling", "contact", "obst_contact", "R", "dist",
                                       "hit_floor", "hit_wall", "hit_ceiling", "new_contact", "obst_new")}}


STEP = control_step_physics
STATE_KEYS = ("q", "v", "u", "eps", "f_norm", "ctrl", "on_floor", "at_wall", "at_ceiling", "contact", "obst_contact")


# ------------------------------------------------------------------------------------ inputs
def _rot(rng: np.random.Generator, tilt: float, flip: np.ndarray) -> np.ndarray:
    """(B, N, 3, 3) rotations: random yaw, roll/pitch up to ``tilt`` rad, upside down where ``flip``."""
    yaw, roll, pitch = rng.uniform(-math.pi, math.pi, (B, N)), *rng.uniform(-tilt, tilt, (2, B, N))
    roll = np.where(flip, roll + math.pi, roll)
    cy, sy, cr, sr, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    Rz = np.stack([cy, -sy, 0 * cy, sy, cy, 0 * cy, 0 * cy, 0 * cy, 1 + 0 * cy], -1).reshape(B, N, 3, 3)
    Ry = np.stack([cp, 0 * cp, sp, 0 * cp, 1 + 0 * cp, 0 * cp, -sp, 0 * cp, cp], -1).reshape(B, N, 3, 3)
    Rx = np.stack([1 + 0 * cr, 0 * cr, 0 * cr, 0 * cr, cr, -sr, 0 * cr, sr, cr], -1).reshape(B, N, 3, 3)
    return Rz @ Ry @ Rx


def start_state(cfg: EnvConfig, seed: int = 0) -> dict[str, np.ndarray]:
    """Quads in every event: 0/1 a pair inside the hitbox, closing; 2 upside down 2 mm above the floor,
    falling; 3 grounded (on_floor, flat); 4 at the +x wall; 5 at the ceiling; 6 at the column at (0, 0);
    8 0.4 m below 7 (flat; 8 in 7's downwash). World 1: the same moved by up to 3 mm, other draws."""
    rng = np.random.default_rng(seed)
    arm, (L, _, H) = cfg.quad.arm, cfg.room_size
    pos = np.array([[-2.0, -2.0, 2.0], [-1.95, -2.0, 2.0], [-3.0, 3.0, arm + 0.002], [3.0, -3.0, arm],
                    [L / 2 - 0.01, 1.0, 3.0], [1.0, 3.0, H - 0.01], [-0.34, 0.0, 2.0], [2.5, 2.5, 3.0],
                    [2.5, 2.5, 2.6]])
    pos = np.stack([pos, pos + rng.uniform(-0.003, 0.003, pos.shape) * [1.0, 1.0, 0.0]])
    vel = rng.uniform(-0.3, 0.3, (B, N, 3))
    vel[:, :2, 0] += [[1.0, -1.0]]
    vel[:, 2] = [0.2, 0.0, -1.5]
    vel[:, 3] = 0.0
    vel[:, 4, 0] += 2.0
    vel[:, 5, 2] += 2.0
    vel[:, 6, 0] += 1.0
    R = _rot(rng, 0.3, np.arange(N) == 2)
    flat = np.isin(np.arange(N), (3, 7, 8))
    R[:, flat] = _rot(rng, 0.0, np.zeros(N, bool))[:, flat]
    omega = rng.uniform(-5.0, 5.0, (B, N, 3))
    omega[:, flat] = [0.0, 0.0, 0.5]
    on_floor = np.zeros((B, N), bool)
    on_floor[:, 3] = True
    return {"q": np.concatenate([pos, rotmat_to_quat(R)], -1), "v": np.concatenate([vel, omega], -1),
            "u": rng.uniform(0.3, 0.9, (B, N, 4)), "eps": rng.normal(0.0, 0.01, (B, N, 4)),
            "f_norm": np.zeros((B, N, 4)), "ctrl": np.zeros((B, N, 6)), "on_floor": on_floor,
            "at_wall": np.zeros((B, N), bool), "at_ceiling": np.zeros((B, N), bool),
            "contact": np.zeros((B, N, N), bool), "obst_contact": np.zeros((B, N), bool)}


def step_inputs(cfg: EnvConfig, seed: int) -> tuple[dict[str, Any], list[np.ndarray], list[dict[str, Any]]]:
    """(params, actions per step, draws per step): NumPy float64, drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    sample = NumpySampler(rng).draw
    params = pipeline.dynamics_params(cfg, sample(randomization_draw_spec(cfg), (B,)))
    lo, hi = control_action_bounds(cfg)
    mid = np.full(4, cfg.quad.hover_action) if cfg.control_mode == "rotor" else 0.5 * (lo + hi)
    if cfg.control_mode == "ctbr":
        mid[0] = cfg.quad.mass * cfg.quad.gravity
    omap = map_from_centres(cfg.obstacles, COLS)
    omap = type(omap)(*(np.broadcast_to(a, (B,) + np.shape(a)).copy() for a in omap))
    specs = collision_draw_specs(cfg)
    actions, draws = [], []
    for _ in range(STEPS):
        actions.append(np.clip(mid + 0.3 * (hi - lo) * rng.standard_normal((B, N, 4)), lo, hi))
        draws.append({"motor": rng.standard_normal((B, N, 4)),
                      "yaw": rng.uniform(-math.pi, math.pi, (cfg.substeps, B, N)),
                      "wall": sample(specs["wall"], (B,)), "quad": sample(specs["quad"], (B,)),
                      "obst": sample(response_draw_spec(N), (B,)), "down": sample(downwash_draw_spec(N), (B,)),
                      "omap": omap})
    return params, actions, draws


def _to_jax(tree: Any) -> Any:
    return jax.tree.map(lambda a: jnp.asarray(a) if isinstance(a, np.ndarray) else a, tree)


def rollout(xp: Any, cfg: EnvConfig, yaw_cs: bool, seed: int = 1, step: Any = None) -> list[dict[str, np.ndarray]]:
    """``STEPS`` chained control steps of ``step`` (default ``STEP``) in ``xp`` (jax.numpy: jitted,
    float64); NumPy outputs."""
    step = STEP if step is None else step
    params, actions, draws = step_inputs(cfg, seed)
    state = start_state(cfg, seed)
    if xp is np:
        fn = lambda s, a, p, d: step(np, cfg, s, a, p, d, yaw_cs)  # noqa: E731
    else:
        fn = jax.jit(lambda s, a, p, d: step(jnp, cfg, s, a, p, d, yaw_cs))
        state, actions, draws, params = _to_jax((state, actions, draws, params))
    out = []
    for a, d in zip(actions, draws):
        r = fn(state, a, params, d)
        state = {k: r[k] for k in STATE_KEYS}
        out.append(jax.tree.map(np.asarray, r))
    return out


# ------------------------------------------------------------------------------------ tests
def _max_err(ref: dict[str, np.ndarray], got: dict[str, np.ndarray]) -> tuple[float, str]:
    """Largest |got - ref| / max(1, |ref|) over the float outputs, and its key; bool outputs must be equal."""
    worst, where = 0.0, ""
    for k, r in ref.items():
        g = got[k]
        assert g.shape == r.shape, (k, g.shape, r.shape)
        if r.dtype == bool:
            np.testing.assert_array_equal(g, r, err_msg=k)
            continue
        assert g.dtype == np.float64, (k, g.dtype)
        e = float(np.max(np.abs(g - r) / np.maximum(1.0, np.abs(r)))) if r.size else 0.0
        if e > worst:
            worst, where = e, k
    return worst, where


@pytest.mark.parametrize("case, yaw_cs", COMPARED)
def test_numpy_equals_jax_float64(case: str, yaw_cs: bool) -> None:
    cfg = CASES[case]
    tol = TOL if cfg.control_mode == "rotor" else TOL_SQRT
    ref = rollout(np, cfg, yaw_cs)
    with jax.enable_x64(True):
        got = rollout(jnp, cfg, yaw_cs)
    for t, (r, g) in enumerate(zip(ref, got)):
        err, key = _max_err(r, g)
        assert err <= tol, f"step {t}: {key} differs by {err:.3g} (relative) between NumPy and JAX"


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("yaw_cs", [False, True])
def test_the_control_step_is_the_leaf_chain(case: str, yaw_cs: bool) -> None:
    """``core.control.physics_stage`` (NumPy, free-body physics, dense draws) computes what the leaf
    functions chained in the documented order compute (``physics_half``), to round-off: the control
    step's order is the model's."""
    cfg = CASES[case]
    tol = TOL if cfg.control_mode == "rotor" else TOL_SQRT
    ref = rollout(np, cfg, yaw_cs, step=physics_half)
    got = rollout(np, cfg, yaw_cs)
    for t, (r, g) in enumerate(zip(ref, got)):
        err, key = _max_err(_w_positive(r), _w_positive(g))
        assert err <= tol, f"step {t}: {key} differs by {err:.3g} (relative) from the leaf chain"


def _w_positive(out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``out`` with each quaternion of ``q`` as the one of its pair (q, -q) with w >= 0."""
    q = out["q"].copy()
    q[..., 3:7] *= np.where(q[..., 3:4] < 0, -1.0, 1.0)
    return {**out, "q": q}


@pytest.mark.parametrize("case", sorted(CASES))
def test_the_floor_impact_paths_agree(case: str) -> None:
    """The angle path and the trig-free (cos, sin) path of the floor impact give the same step to
    round-off, up to the sign of the quaternion: the angle path's yaw quaternion (cos(yaw/2), 0, 0,
    sin(yaw/2)) has w < 0 when the landing yaw (heading + draw) is beyond +-pi, the trig-free one has
    w >= 0 (the same rotation; seen in the room guard of "blend_rotor")."""
    for t, (r, g) in enumerate(zip(rollout(np, CASES[case], False), rollout(np, CASES[case], True))):
        err, key = _max_err(_w_positive(r), _w_positive(g))
        assert err <= TOL, f"step {t}: {key} differs by {err:.3g}"


@pytest.mark.parametrize("case", sorted(CASES))
def test_the_inputs_exercise_every_event(case: str) -> None:
    """The comparison above covers each stage: in each world a landing, a wall and a ceiling hit, a new
    quad-quad pair, a column contact and a quad in another's downwash, and a grounded quad."""
    from quadswarm_mj.downwash import downwash_mask

    out = rollout(np, CASES[case], False)
    anyof = {k: np.any([o[k] for o in out], axis=0).reshape(B, -1).any(-1)
             for k in ("hit_floor", "hit_wall", "hit_ceiling", "new_contact", "obst_new")}
    for k, per_world in anyof.items():
        assert per_world.all(), (k, per_world)
    assert out[0]["on_floor"][:, 3].all()
    mask, _ = downwash_mask(out[0]["q"][..., :3], out[0]["R"])
    assert mask[:, 7, 8].all()


# ------------------------------------------------------------------------------------ the whole control step
def _task_inputs(cfg: EnvConfig, seed: int) -> tuple[dict[str, Any], list[dict[str, Any]], dict[str, Any]]:
    """(the task state of ``B`` worlds at reset, per-step task draws, observation constants): NumPy."""
    from quadswarm_mj.core.reset import start_accumulators, start_state
    from quadswarm_mj.observations import obs_bounds, obs_scale, sensor_noise_spec
    from quadswarm_mj.randomization import nominal_draws
    from quadswarm_mj.scenarios import get_scenario
    from quadswarm_mj.scenarios.obstacle_scenarios import scenario_num_uniforms, scenario_spawn_uniforms

    rng = np.random.default_rng(seed + 7)
    scenario = get_scenario(cfg.scenario)
    n_scn = scenario_num_uniforms(scenario, cfg)
    omap = step_inputs(cfg, seed)[2][0]["omap"]
    init = start_state(cfg, scenario, nominal_draws(cfg, np.zeros((B, N)), (B,)), rng.uniform(size=(B, n_scn)),
                       rng.uniform(size=(B, scenario_spawn_uniforms(cfg))), {}, np, np.float64, omap=omap)
    task = {"steps": np.zeros(B, np.int64), "total_steps": np.asarray(0), "sstate": init["scenario"],
            "omap": omap, **start_accumulators(cfg, np.zeros((B, N)), (B,), N)}
    spec = sensor_noise_spec(cfg)
    draws = [{"scenario": rng.uniform(size=(B, n_scn)), "sensor": NumpySampler(rng).draw(spec, (B,))}
             for _ in range(STEPS)]
    low, high = obs_bounds(cfg)
    consts = {"obs_low": low.astype(np.float64), "obs_high": high.astype(np.float64),
              "obs_scale": obs_scale(cfg) if cfg.normalize_obs else None, "zero_terms": ()}
    return task, draws, consts


def whole_step(xp: Any, cfg: EnvConfig, s: dict[str, Any], action: Any, params: dict[str, Any], d: dict[str, Any],
               consts: dict[str, Any]) -> dict[str, Any]:
    """``core.control.control_step`` (free-body physics, dense draws) on ``s``: the physics state of
    ``control_step_physics`` plus the task state; returns the next state and the step's outputs."""
    from dense_ops import DenseOps

    from quadswarm_mj.core.control import control_step
    from quadswarm_mj.physics.freebody import FreeBodyPhysics
    from quadswarm_mj.scenarios import get_scenario

    physics = FreeBodyPhysics(params["mass"], params["inertia"], xp.asarray([0.0, 0.0, -params["gravity"]]),
                              cfg.sim_dt, cfg.quad.max_omega)
    ops = DenseOps(cfg, d, xp, False, omap=s["omap"], obst_contact=s["obst_contact"])
    consts = {**consts, "act": None, "rotor_pos": xp.asarray(rotor_positions(cfg.quad)),
              "mix": wrench_matrix(rotor_positions(cfg.quad)), "torque_spin": params["torque_max"] * xp.asarray(SPIN)}
    state = {**s, "R": quat_to_rotmat(s["q"][..., 3:7]), "params": params, "aux": None, "ctrl": None}
    k, _, r = control_step(cfg, get_scenario(cfg.scenario), state, action, consts, physics, ops)
    nxt = {"q": xp.concatenate([k["pos"], k["quat"]], -1), "v": xp.concatenate([k["vel"], k["omega"]], -1),
           "u": k["u"], "eps": k["eps"], "f_norm": k["f_norm"], "obst_contact": k["obst_contact"],
           **{key: k[key] for key in ("on_floor", "at_wall", "at_ceiling", "contact")},
           "steps": r["steps"], "total_steps": r["total_steps"], "sstate": r["sstate"], "omap": s["omap"],
           "metrics_acc": r["metrics_acc"], "obst_metrics": r["obst_metrics"]}
    return {"state": nxt, "out": {"obs": r["obs"], "reward": r["reward"], "terms": r["terms"], "t": r["t"]}}


def test_the_whole_control_step_numpy_equals_jax_float64() -> None:
    """``core.control.control_step`` (sub-steps, stages, scenario, rewards, metrics, observations) with
    the free-body physics and dense draws: NumPy and jitted JAX (float64) agree on every output and
    accumulator over chained steps (default rotor model, every event happening, sensor noise on)."""
    cfg = CASES["paper_rotor"]
    params, actions, draws = step_inputs(cfg, 1)
    task, task_draws, consts = _task_inputs(cfg, 1)
    s0 = {**{k: v for k, v in start_state(cfg, 1).items() if k != "ctrl"}, **task}
    outs: dict[str, list] = {"numpy": [], "jax": []}
    for name in ("numpy", "jax"):
        state, ds = s0, [{**d, **t} for d, t in zip(draws, task_draws)]
        p, acts = params, actions
        with jax.enable_x64(name == "jax"):
            if name == "jax":
                fn = jax.jit(lambda s, a, p_, d: whole_step(jnp, cfg, s, a, p_, d, _to_jax(consts)))
                state, acts, ds, p = _to_jax((state, acts, ds, p))
            else:
                fn = lambda s, a, p_, d: whole_step(np, cfg, s, a, p_, d, consts)  # noqa: E731
            for a, d in zip(acts, ds):
                r = fn(state, a, p, d)
                state = r["state"]
                outs[name].append(jax.tree.map(np.asarray, (r["out"], state["metrics_acc"], state["obst_metrics"],
                                                            state["sstate"].goals)))
    for t, (ref, got) in enumerate(zip(outs["numpy"], outs["jax"])):
        for path, rv in jax.tree_util.tree_leaves_with_path(ref):
            gv = dict(jax.tree_util.tree_leaves_with_path(got))[path]
            assert gv.shape == rv.shape, (t, path)
            if rv.dtype == bool:
                np.testing.assert_array_equal(gv, rv, err_msg=f"step {t} {path}")
            else:
                err = float(np.max(np.abs(gv - rv) / np.maximum(1.0, np.abs(rv)))) if rv.size else 0.0
                assert err <= TOL, f"step {t}: {jax.tree_util.keystr(path)} differs by {err:.3g} (relative)"
    assert np.any(outs["numpy"][-1][0]["reward"] != 0.0)
