"""The component-form (structure-of-arrays) sub-step functions of ``quadswarm_mj.components``: the
model's one body of each sub-step function (the array-of-structures functions split, call them and
stack); ``quadswarm_mj.perf.numpy_small`` keeps a fewest-calls form for small NumPy arrays (the CPU
engine's); both forms give the same bits (small arrays compared directly, large arrays against the
small form chunk by chunk). The trig-free floor impact against
the angle path, and the JAX engine's component sub-step loop against its general loop, within
round-off."""

from __future__ import annotations

import numpy as np
import pytest

from quadswarm_mj import actuation, collisions, spatial
from quadswarm_mj import components as C
from quadswarm_mj.actuation import SPIN, rotor_positions, wrench_matrix
from quadswarm_mj.collisions import floor_impact
from quadswarm_mj.config import EnvConfig, QuadParams
from quadswarm_mj.freebody import freebody_step, freebody_step_components
from quadswarm_mj.perf import numpy_small as small
from quadswarm_mj.perf.xla_cpu import kernel_boundary
from quadswarm_mj.spatial import quat_to_rotmat, quat_to_rotmat_components

# (worlds, quads): a small batch takes perf.numpy_small's own form, a large one (>= spatial.BIG
# elements) its delegation to the model's body (the component functions)
SHAPES = [(3, 8), (200, 8)]


def _chunked(fn, *arrays, rows: int = 3):
    """``fn`` applied to row chunks of the leading axis (each below spatial.BIG: perf's small NumPy form),
    outputs concatenated: an independent reference for the large-array (component) path."""
    n = arrays[0].shape[0]
    outs = [fn(*(a[i:i + rows] for a in arrays)) for i in range(0, n, rows)]
    return tuple(np.concatenate([o[k] for o in outs]) for k in range(len(outs[0])))


def _random_rotations(rng: np.random.Generator, lead: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    q = rng.normal(size=lead + (4,))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return q, quat_to_rotmat(q)


def _same(a: np.ndarray, b: np.ndarray) -> None:
    """Bit-identical, including the sign of zeros."""
    np.testing.assert_array_equal(np.signbit(a), np.signbit(b))
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("lead", SHAPES)
def test_rotor_wrench_matches_substep_wrench_bitwise(lead):
    rng = np.random.default_rng(0)
    quad = QuadParams()
    u, cmd = rng.uniform(0, 1, lead + (4,)), rng.uniform(0, 1, lead + (4,))
    noise = rng.normal(0, 0.1, lead + (4,))
    params = {"alpha": rng.uniform(0.2, 1, lead), "thrust_max": rng.uniform(0.1, 0.2, lead + (4,)),
              "torque_max": rng.uniform(0.001, 0.003, lead + (4,))}
    _, R = _random_rotations(rng, lead)
    mix = wrench_matrix(rotor_positions(quad))
    spin = params["torque_max"] * SPIN
    def aos(u, cmd, noise, alpha, thrust_max, torque_max, R, fn=small.substep_wrench):
        p = {"alpha": alpha, "thrust_max": thrust_max, "torque_max": torque_max}
        return fn(u, cmd, noise, p, R, rotor_positions(quad), mix, torque_max * SPIN)

    ref = _chunked(aos, u, cmd, noise, params["alpha"], params["thrust_max"], params["torque_max"], R)
    got = C.rotor_wrench(C.split(u), C.split(cmd), C.split(noise), params["alpha"], C.split(params["thrust_max"]),
                         C.split(spin), mix, C.split(R.reshape(lead + (9,))))
    args = (u, cmd, noise, params["alpha"], params["thrust_max"], params["torque_max"], R)
    for a, b, c, d in zip(ref, got, aos(*args), aos(*args, fn=actuation.substep_wrench)):
        _same(a, C.stack(b))
        _same(a, c)  # perf's function at this size (its small form, or its delegation)
        _same(a, d)  # the model's AoS function (split, the component body, stack)


@pytest.mark.parametrize("lead", SHAPES)
def test_rotor_wrench_with_thrust_map_and_gain_matches_bitwise(lead):
    """The thrust map and a rotor gain (control modes, ground effect) in both forms."""
    rng = np.random.default_rng(10)
    quad = QuadParams()
    u, cmd = rng.uniform(0, 1, lead + (4,)), rng.uniform(0, 1, lead + (4,))
    noise, gain = rng.normal(0, 0.1, lead + (4,)), rng.uniform(1.0, 1.3, lead + (4,))
    params = {"alpha": rng.uniform(0.2, 1, lead), "thrust_max": rng.uniform(0.1, 0.2, lead + (4,)),
              "torque_max": rng.uniform(0.001, 0.003, lead + (4,))}
    _, R = _random_rotations(rng, lead)
    args = (u, cmd, noise, params, R, rotor_positions(quad))
    for a, b in zip(small.substep_wrench(*args, thrust_quadratic=0.3, rotor_gain=gain),
                    actuation.substep_wrench(*args, thrust_quadratic=0.3, rotor_gain=gain)):
        _same(a, b)


@pytest.mark.parametrize("lead", SHAPES)
def test_floor_wrench_matches_bitwise(lead):
    rng = np.random.default_rng(1)
    on_floor = rng.uniform(size=lead) < 0.6
    force, torque = rng.normal(0, 0.3, lead + (3,)), rng.normal(0, 0.01, lead + (3,))
    vel = rng.normal(0, 1, lead + (3,)) * (rng.uniform(size=lead + (1,)) < 0.5)  # half at rest
    force[..., :2] *= rng.uniform(size=lead + (1,)) < 0.7  # some without horizontal force
    mass = rng.uniform(0.025, 0.035, lead)
    def aos(on_floor, force, torque, vel, mass, fn=small.floor_wrench):
        return fn(on_floor, force, torque, vel, mass, 9.81, 0.3, 0.005)

    ref = _chunked(aos, on_floor, force, torque, vel, mass)
    got = C.floor_wrench(on_floor, C.split(force), C.split(torque), C.split(vel), mass, 9.81, 0.3, 0.005)
    args = (on_floor, force, torque, vel, mass)
    for a, b, c, d in zip(ref, got, aos(*args), aos(*args, fn=collisions.floor_wrench)):
        _same(a, C.stack(b))
        _same(a, c)
        _same(a, d)


@pytest.mark.parametrize("lead", SHAPES)
def test_floor_impact_angle_path_without_rotmat_drops_only_R(lead):
    """The floor impact's angle path (the CPU engine's reference; its in-place forms are checked against it
    below and in tests/test_perf_one_quad.py): ``with_rotmat=False`` leaves out R and nothing else."""
    rng = np.random.default_rng(12)
    arm = 0.046
    pos = rng.uniform(-1, 1, lead + (3,))
    pos[..., 2] = rng.choice([arm - 0.01, arm, arm + 5e-7, arm + 0.01, 1.0], size=lead)
    on_floor = rng.uniform(size=lead) < 0.5
    vel, omega = rng.normal(size=lead + (3,)), rng.normal(size=lead + (3,))
    quat, R = _random_rotations(rng, lead)
    u = rng.uniform(size=lead + (4,))
    yaw = rng.uniform(-np.pi, np.pi, lead)
    args = (pos, vel, omega, quat, R, u, on_floor, arm, yaw)
    ref, got = collisions.floor_impact(*args), collisions.floor_impact(*args, with_rotmat=False)
    assert (ref["hit_floor"] & (R[..., 2, 2] < 0)).any()  # an upside-down landing takes its yaw draw
    assert set(ref) - set(got) == {"R"}
    for key in got:
        _same(ref[key], got[key])


def test_yaw_entries_are_quat_to_rotmats_bitwise():
    rng = np.random.default_rng(13)
    q, _ = _random_rotations(rng, (6, 8))
    q[0, :4] = np.eye(4)  # exact zeros, of both signs
    q[1, :4] = -np.eye(4)
    R = small.quat_to_rotmat(q)
    qpos = np.concatenate([np.zeros(q.shape[:-1] + (3,)), q], axis=-1)
    _same(small.yaw_entries_qpos(qpos), np.stack([R[..., 1, 0], R[..., 0, 0], R[..., 2, 2]], axis=-1))


@pytest.mark.parametrize("worlds", ["all", "some"])
def test_engine_floor_impact_is_the_small_form_bitwise(worlds):
    """The CPU engine's in-place floor impact (masked writes into qpos/qvel) = the model's angle path."""
    import copy

    from quadswarm_mj.envs.cpu_core import CpuSwarm

    B, N = 3, 8
    core = CpuSwarm(EnvConfig(num_quads=N), num_worlds=B, visual=False)
    core.seed(5)
    core.reset()
    rng = np.random.default_rng(14)
    arm = core.floor_z
    z = rng.choice([arm - 0.01, arm, arm + 5e-7, arm + 0.01, 1.0], size=(B, N))
    core.qpos[..., 2] = z + core.offsets[..., 2]
    quat, _ = _random_rotations(rng, (B, N))
    core.qpos[..., 3:7] = quat
    core.qvel[...] = rng.normal(size=(B, N, 6))
    core.qvel[0, 0] = -0.0
    core.on_floor = rng.uniform(size=(B, N)) < 0.5
    core.u = rng.uniform(size=(B, N, 4))
    core.state_changed()
    w = slice(None) if worlds == "all" else np.array([0, 2])
    q, v, u, on, off = (core.qpos[w].copy(), core.qvel[w].copy(), core.u[w].copy(), core.on_floor[w].copy(),
                        core.offsets[w] if core.offsets.shape[0] > 1 else core.offsets)
    d = core._spec_floor["yaw"]
    yaw = copy.deepcopy(core.rng).uniform(d.low, d.high, size=q.shape[:2])
    ref = collisions.floor_impact(q[..., :3] - off, v[..., :3], v[..., 3:], q[..., 3:7],
                                  small.quat_to_rotmat(q[..., 3:7]), u, on, arm, yaw)
    assert (ref["hit_floor"] & (small.quat_to_rotmat(q[..., 3:7])[..., 2, 2] < 0)).any()
    hit_floor = np.zeros((B, N), bool)
    core._floor_impact(w, hit_floor)
    _same(core.qpos[w][..., :3], ref["pos"] + off)
    _same(core.qpos[w][..., 3:7], ref["quat"])
    _same(core.qvel[w][..., :3], ref["vel"])
    _same(core.qvel[w][..., 3:], ref["omega"])
    _same(core.u[w], ref["u"])
    np.testing.assert_array_equal(core.on_floor[w], ref["on_floor"])
    np.testing.assert_array_equal(hit_floor[w], ref["hit_floor"])
    assert core._any_on_floor == bool(core.on_floor.any())


@pytest.mark.parametrize("lead", SHAPES)
def test_floor_impact_trig_free_matches_the_angle_path(lead):
    """The trig-free floor impact (defined once, in component form; ``collisions.floor_impact`` with
    ``yaw_draw_cs`` delegates to it) against the angle path with the same yaw draws: the same flags,
    positions, velocities and motors exactly, the yaw-only rotations within round-off."""
    rng = np.random.default_rng(2)
    arm = 0.046
    pos = rng.uniform(-1, 1, lead + (3,))
    pos[..., 2] = rng.choice([arm - 0.01, arm, arm + 5e-7, arm + 0.01, 1.0], size=lead)
    on_floor = rng.uniform(size=lead) < 0.5
    vel, omega = rng.normal(size=lead + (3,)), rng.normal(size=lead + (3,))
    quat, R = _random_rotations(rng, lead)
    u = rng.uniform(size=lead + (4,))
    yaw = rng.uniform(-np.pi, np.pi, lead)
    cs = (np.cos(yaw), np.sin(yaw))
    ref = floor_impact(pos, vel, omega, quat, R, u, on_floor, arm, yaw)  # the angle path
    got = floor_impact(pos, vel, omega, quat, R, u, on_floor, arm, None, yaw_draw_cs=cs)
    assert ref["hit_floor"].any() and (ref["on_floor"] & ~ref["hit_floor"]).any()  # both branches exercised
    flipped = ref["hit_floor"] & (R[..., 2, 2] < 0)
    assert flipped.any()  # an upside-down landing takes its yaw draw
    for key in ("pos", "vel", "omega", "u", "on_floor", "hit_floor"):
        _same(ref[key], got[key])
    np.testing.assert_allclose(got["R"], ref["R"], rtol=0, atol=1e-12)
    # quaternions: the same rotation (q and -q), within round-off
    dots = np.abs(np.sum(got["quat"] * ref["quat"], axis=-1))
    np.testing.assert_allclose(dots, 1.0, rtol=0, atol=1e-12)


def test_quat_to_rotmat_components_is_the_body_and_the_gather_the_same_values():
    rng = np.random.default_rng(3)
    q, _ = _random_rotations(rng, (2000,))  # >= spatial.BIG elements: perf delegates to the body
    _same(quat_to_rotmat(q), C.stack(quat_to_rotmat_components(*C.split(q))).reshape(-1, 3, 3))
    _same(small.quat_to_rotmat(q), spatial.quat_to_rotmat(q))
    q = np.concatenate([q[:8], np.eye(4)[:, [0, 1, 2, 3]]])  # small: the gather (zeros may differ in sign)
    np.testing.assert_array_equal(small.quat_to_rotmat(q), spatial.quat_to_rotmat(q))


def test_freebody_components_is_freebody_step():
    rng = np.random.default_rng(4)
    n = 8
    q, _ = _random_rotations(rng, (n,))
    qpos = np.concatenate([rng.normal(size=(n, 3)), q], -1)
    qvel = rng.normal(size=(n, 6))
    xfrc = rng.normal(0, 0.1, (n, 6))
    mass, inertia = rng.uniform(0.02, 0.04, n), rng.uniform(1e-5, 3e-5, (n, 3))
    g = np.array([0.0, 0.0, -9.81])
    qp, qv = freebody_step(qpos, qvel, xfrc, mass, inertia, None, None, g, 0.005)
    p, quat, v, w = freebody_step_components(C.split(qpos[:, :3]), C.split(qpos[:, 3:]), C.split(qvel[:, :3]),
                                             C.split(qvel[:, 3:]), C.split(xfrc[:, :3]), C.split(xfrc[:, 3:]), mass,
                                             C.split(inertia), None, None, C.split(g), 0.005)
    _same(qp, C.stack(p + quat))
    _same(qv, C.stack(v + w))


def test_jax_component_substeps_match_the_general_loop():
    """The JAX engine's default sub-step loop (components) and its general loop (the AoS functions)
    agree within float32 round-off over 25 control steps with floor landings, flips and spins."""
    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv

    cfg = EnvConfig(num_quads=8, scenario="static_same_goal")
    fast, general = MjxQuadSwarmEnv(cfg), MjxQuadSwarmEnv(cfg)
    assert fast._component_substeps
    general._component_substeps = False
    rng = np.random.default_rng(5)
    n = 8
    quat, R = _random_rotations(rng, (n,))
    pos = np.concatenate([rng.uniform(-1, 1, (n, 2)), np.full((n, 1), 0.12)], -1)
    pos[:, 0] = np.linspace(-1.5, 1.5, n)  # apart: no quad-quad contacts
    init = {"pos": pos, "vel": np.concatenate([rng.normal(0, 0.5, (n, 2)), np.full((n, 1), -2.0)], -1),
            "rot": R, "omega": rng.normal(0, 5, (n, 3)), "motors": "hover"}
    actions = jnp.asarray(rng.uniform(-1, 1, (25, n, 4)), jnp.float32)

    def rollout(env):
        def body(s, a):
            s = env.step(s, a)
            return s, (s.info["state"]["pos"], s.info["state"]["rot"], s.info["state"]["vel"], s.info["on_floor"])
        s0 = env.reset(jax.random.key(0), init)
        return jax.lax.scan(body, s0, actions)[1]

    a, b = jax.jit(lambda: rollout(fast))(), jax.jit(lambda: rollout(general))()
    floor_a = np.asarray(a[3])
    assert floor_a.any() and not floor_a.all()  # landings happen, not everywhere
    np.testing.assert_array_equal(floor_a, np.asarray(b[3]))
    for x, y in zip(a[:3], b[:3]):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), atol=2e-5, rtol=0)


def test_kernel_boundary_is_an_exact_identity_that_xla_keeps() -> None:
    """perf.xla_cpu.kernel_boundary: the same bits (division by exactly 1.0), and the division survives
    compilation when ``one`` is a run-time value (folded away, it would not make a kernel boundary)."""
    import jax
    import jax.numpy as jnp

    x = jnp.asarray([0.0, -0.0, 1e-37, -3.5, 1e30, np.inf, -np.inf, 0.1], jnp.float32)

    def f(x: jax.Array, i: jax.Array) -> jax.Array:
        return kernel_boundary((x,), 1.0 + 0.0 * i.astype(jnp.float32))[0]

    out = jax.jit(f)(x, jnp.int32(5))
    np.testing.assert_array_equal(np.asarray(out).view(np.uint32), np.asarray(x).view(np.uint32))
    assert "divide(" in jax.jit(f).lower(x, jnp.int32(5)).compile().as_text()
