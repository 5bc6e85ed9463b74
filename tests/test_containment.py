"""The room contains every quad (issue 32, item 1) and coincident quads separate (item 8).

Every collision model on both engines: a quad driven into a wall, the ceiling or the floor at any
speed that ``reset`` accepts (up to ~50 m/s) or the dynamics reach (full thrust) stays inside the
room, and its observation still tells where it is. All cases run as the worlds of one batch (one
vector env per collision model on the CPU engine, one compiled rollout per physics on the JAX
engine), so the JAX compiles stay few.
"""

from __future__ import annotations

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, QuadSwarmEnv, QuadSwarmVectorEnv
from quadswarm_mj.observations import obs_scale

N = 2  # quads per world: the second one is parked in the room's far corner unless a case moves it
STEPS = 200
SPEED = 49.5  # m/s: just under the reset speed bound (50 m/s)
HOVER = EnvConfig().quad.hover_action
FLIP = np.diag([1.0, -1.0, -1.0])  # upside down (rolled by pi)
PARK = [-4.0, 4.0, 5.0]


def _unit(*v: float) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def _case(pos0, vel0, action=HOVER, rot0=None, pos1=PARK, vel1=(0.0, 0.0, 0.0), action1=HOVER) -> dict:
    rot = np.tile(np.eye(3), (N, 1, 1))
    if rot0 is not None:
        rot[0] = rot0
    return {"pos": np.array([pos0, pos1], float), "vel": np.array([vel0, vel1], float), "rot": rot,
            "action": np.array([[action] * 4, [action1] * 4], float)}


#: name -> start state and constant action of one world (quad 0 is the one driven at the room)
CASES = {
    "wall_15": _case([3.0, 0.0, 2.0], [15.0, 0.0, 0.0]),
    "wall_50": _case([3.0, 0.0, 2.0], [SPEED, 0.0, 0.0]),
    "walls_diagonal": _case([-3.0, -3.0, 2.0], SPEED * _unit(-1.0, -1.0, 0.0)),
    "ceiling_corner_diagonal": _case([3.0, 3.0, 8.0], SPEED * _unit(1.0, 1.0, 1.0)),
    "floor_corner_diagonal": _case([3.0, -3.0, 1.0], SPEED * _unit(1.0, -1.0, -1.0)),
    "head_on_pair_x": _case([-1.0, 0.0, 2.0], [SPEED, 0.0, 0.0], pos1=[1.0, 0.0, 2.0], vel1=[-SPEED, 0.0, 0.0]),
    "head_on_pair_z": _case([0.0, 0.0, 1.0], [0.0, 0.0, SPEED], pos1=[0.0, 0.0, 9.0], vel1=[0.0, 0.0, -SPEED]),
    "ceiling_full_thrust": _case([0.0, 2.0, 8.0], [0.0, 0.0, SPEED], action=1.0),
    "floor_full_thrust_upside_down": _case([0.0, -2.0, 1.0], [0.0, 0.0, -SPEED], action=1.0, rot0=FLIP),
    "floor_full_thrust_from_rest": _case([2.0, 2.0, 0.3], [0.0, 0.0, 0.0], action=1.0, rot0=FLIP),
    "tilted_full_thrust": _case([0.0, 0.0, 2.0], [0.0, 0.0, 0.0], action=1.0,
                                rot0=np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])),
    # item 8: two quads at one point with one velocity (moving, at rest): the pair must separate
    "coincident_moving": _case([0.0, 3.0, 2.0], [1.0, 0.0, 0.0], pos1=[0.0, 3.0, 2.0], vel1=[1.0, 0.0, 0.0]),
    "coincident_at_rest": _case([0.0, -3.0, 2.0], [0.0, 0.0, 0.0], pos1=[0.0, -3.0, 2.0]),
}
NAMES = list(CASES)
COINCIDENT = [NAMES.index("coincident_moving"), NAMES.index("coincident_at_rest")]
W = len(CASES)


def _batched(key: str) -> np.ndarray:
    return np.stack([CASES[name][key] for name in NAMES])


def _check_inside(cfg: EnvConfig, pos: np.ndarray, tol: float, where: str) -> None:
    """Every quad centre inside the closed room box [room_low, room_high] (floor z = 0)."""
    lo, hi = np.asarray(cfg.room_low), np.asarray(cfg.room_high)
    assert np.isfinite(pos).all(), where
    out = (pos < lo - tol) | (pos > hi + tol)
    if out.any():
        w, q, _ = np.argwhere(out)[0]
        raise AssertionError(f"{where}: world {NAMES[w]!r} quad {q} left the room at {pos[w, q]}")


def _check_obs_sees_position(cfg: EnvConfig, obs: np.ndarray, pos: np.ndarray, goals: np.ndarray, atol: float,
                             where: str) -> None:
    """The observation's first block is p - goal, unsaturated (noise off): a policy can tell where it is."""
    rel = obs[..., :3] * (obs_scale(cfg)[:3] if cfg.normalize_obs else 1.0)
    np.testing.assert_allclose(rel, pos - goals, rtol=0, atol=atol, err_msg=where)


def _check_separated(cfg: EnvConfig, pos: np.ndarray) -> None:
    """The coincident pairs have left each other's hitbox."""
    d = np.linalg.norm(pos[COINCIDENT, 0] - pos[COINCIDENT, 1], axis=-1)
    assert (d > cfg.hitbox).all(), d


# ------------------------------------------------------------------------------------- CPU engine


@pytest.mark.parametrize("collision_model", ["paper", "mujoco", "blend"])
def test_room_contains_every_quad_cpu(collision_model):
    """CPU engine (multi-world vector env): 200 steps of every case, every quad inside the room
    after every control step, observations unsaturated. Before the fix, "mujoco"/"blend" let a quad
    at 15 m/s through the wall (x = 17.4 m after 200 steps) and full thrust sank it into the floor."""
    cfg = EnvConfig(num_quads=N, collision_model=collision_model).without_noise()
    vec = QuadSwarmVectorEnv(cfg, num_envs=W, num_shards=1)
    try:
        state = {k: _batched(k) for k in ("pos", "vel", "rot")}
        state["omega"] = np.zeros((W, N, 3))
        state["motors"] = "hover"
        vec.reset(seed=0, options={"state": state})
        action = _batched("action")
        for t in range(STEPS):
            obs, _, _, _, info = vec.step(action)
            pos = info["state"]["pos"]
            _check_inside(cfg, pos, 1e-9, f"{collision_model} step {t}")
            _check_obs_sees_position(cfg, obs, pos, info["goals"], 1e-4, f"{collision_model} step {t}")
        _check_separated(cfg, pos)
    finally:
        vec.close()


@pytest.mark.parametrize("collision_model", ["mujoco", "blend"])
def test_single_env_wall_reproduction(collision_model):
    """The issue's reproduction through QuadSwarmEnv: pos [[3, 0, 2]], vel [[15, 0, 0]], 200 hover steps."""
    env = QuadSwarmEnv(EnvConfig(num_quads=1, collision_model=collision_model).without_noise())
    env.reset(seed=0, options={"state": {"pos": [[3.0, 0.0, 2.0]], "vel": [[15.0, 0.0, 0.0]], "motors": "hover"}})
    xs = []
    for _ in range(STEPS):
        info = env.step(np.full(4, HOVER))[4]
        xs.append(info["state"]["pos"][0, 0])
    assert max(xs) <= env.cfg.room_high[0]
    assert min(xs) >= env.cfg.room_low[0]


# ------------------------------------------------------------------------------------- JAX engine

#: (physics, collision model); MJX with "blend" differs from "mujoco" only by the quad-quad response
#: (covered on the CPU engine): slow
ENGINES = [pytest.param(("freebody", "paper"), id="freebody-paper"), pytest.param(("mjx", "mujoco"), id="mjx-mujoco"),
           pytest.param(("mjx", "blend"), id="mjx-blend", marks=pytest.mark.slow)]


@pytest.fixture(scope="module", params=ENGINES)
def jax_rollout(request):
    """One compiled reset and 200-step rollout of every case (worlds) per (physics, collision model)."""
    jax = pytest.importorskip("jax")
    pytest.importorskip("mujoco.mjx")
    import jax.numpy as jnp

    from quadswarm_mj.envs.mjx_env import MjxQuadSwarmEnv

    physics, model = request.param
    cfg = EnvConfig(num_quads=N, collision_model=model).without_noise()
    env = MjxQuadSwarmEnv(cfg, physics=physics)
    init = {k: jnp.asarray(_batched(k), jnp.float32) for k in ("pos", "vel", "rot")}
    init["omega"] = jnp.zeros((W, N, 3), jnp.float32)
    reset = jax.vmap(lambda k, st: env.reset(k, {**st, "motors": "hover"}))
    step = jax.vmap(env.step)

    def run(keys, init, action):
        def body(s, _):
            s = step(s, action)
            return s, (s.info["state"]["pos"], s.obs, s.info["goals"])
        return jax.lax.scan(body, reset(keys, init), None, length=STEPS)[1]

    pos, obs, goals = jax.jit(run)(jax.random.split(jax.random.key(0), W), init,
                                   jnp.asarray(_batched("action"), jnp.float32))
    return cfg, np.asarray(pos, np.float64), np.asarray(obs, np.float64), np.asarray(goals, np.float64)


def test_room_contains_every_quad_jax(jax_rollout):
    """JAX engine (free-body physics with the paper's model; MJX contacts with "mujoco"/"blend"):
    every quad inside the room after every control step (float32: 1e-5 m), observations unsaturated."""
    cfg, pos, obs, goals = jax_rollout
    for t in range(STEPS):
        _check_inside(cfg, pos[t], 1e-5, f"{cfg.collision_model} step {t}")
        _check_obs_sees_position(cfg, obs[t], pos[t], goals[t], 1e-3, f"{cfg.collision_model} step {t}")
    _check_separated(cfg, pos[-1])


# --------------------------------------------------------------------- coincident quads (item 8)

COINCIDENT_VEL = [(1.0, 0.0, 0.0), (0.0, 0.0, 0.0)]  # m/s, the same for both quads


def _coincident_state(v) -> dict:
    return {"pos": [[0.0, 0.0, 2.0], [0.0, 0.0, 2.0]], "vel": [v, v], "motors": "hover"}


@pytest.mark.parametrize("noise", [False, True], ids=["noise_free", "noisy"])
@pytest.mark.parametrize("v", COINCIDENT_VEL, ids=["moving", "at_rest"])
def test_coincident_quads_are_separated_cpu(v, noise):
    """Two quads started at the same point with the same velocity: the paper's model takes the pair
    as a new contact at the first step (none is 'already colliding' at reset) and separates it,
    with noise off too (a deterministic normal for the zero-length one, a minimum separating speed).
    Before, they flew overlapping (no response ever; motor noise alone drifted them 5 mm in 20 steps)."""
    cfg = EnvConfig(num_quads=2)
    cfg = cfg if noise else cfg.without_noise()
    env = QuadSwarmEnv(cfg)
    env.reset(seed=3, options={"state": _coincident_state(v)})
    hits = 0
    for _ in range(40):
        _, _, _, _, info = env.step(np.full((2, 4), HOVER))
        hits += int(info["new_collisions"].any())
    p = info["state"]["pos"]
    assert hits == 1  # one response, at the first step
    assert np.linalg.norm(p[0] - p[1]) > cfg.hitbox


def test_room_guard_leaves_quads_inside_unchanged():
    """The guard acts only on quad centres outside the room: the others (touching or slightly
    penetrating surfaces, which MuJoCo's contacts handle) keep their state bit for bit."""
    from quadswarm_mj.collisions import room_guard, wall_draw_spec
    from quadswarm_mj.random_draws import MeanSampler
    from quadswarm_mj.spatial import yaw_quat, yaw_rotmat

    cfg = EnvConfig()
    arm = cfg.quad.arm
    pos = np.array([[0.0, 0.0, 2.0], [5.0 - 0.5 * arm, 0.0, 2.0], [0.0, 0.0, 0.5 * arm], [5.2, -5.3, 1.0],
                    [1.0, 1.0, -0.05], [0.0, 0.0, 10.4]])
    n = len(pos)
    vel = np.tile([3.0, -2.0, 1.0], (n, 1))
    omega = np.tile([0.1, 0.2, 0.3], (n, 1))
    yaw = np.linspace(-1.0, 1.0, n)
    R, quat, u = yaw_rotmat(yaw), yaw_quat(yaw), np.full((n, 4), 0.7)
    R[4] = R[4] @ FLIP  # the one below the floor is upside down
    draws = MeanSampler().draw(wall_draw_spec(n, cfg.collision_decay, cfg.collision.kick_omega))
    r = room_guard(pos, vel, omega, quat, R, u, cfg.room_low, cfg.room_high, arm, draws,
                   cfg.collision.wall_speed_limits, np.zeros(n))
    inside = np.array([True, True, True, False, False, False])
    np.testing.assert_array_equal(r["beyond"], [False, False, False, True, False, True])
    np.testing.assert_array_equal(r["below"], [False, False, False, False, True, False])
    for k, v in (("pos", pos), ("vel", vel), ("omega", omega), ("quat", quat), ("R", R), ("u", u)):
        np.testing.assert_array_equal(r[k][inside], v[inside], err_msg=k)
    lo, hi = np.asarray(cfg.room_low) + arm, np.asarray(cfg.room_high) - arm
    np.testing.assert_allclose(r["pos"][3], [hi[0], lo[1], 1.0])  # the sphere touches both walls
    assert r["vel"][3, 0] < 0 < r["vel"][3, 1] and r["vel"][3, 2] < 0  # bounced away, downward (SPEC §4)
    np.testing.assert_allclose(r["pos"][4], [1.0, 1.0, arm])  # landed: at the arm height, at rest, upright
    np.testing.assert_array_equal(r["vel"][4], 0.0)
    np.testing.assert_array_equal(r["u"][4], 0.0)
    assert r["R"][4][2, 2] == pytest.approx(1.0)
    assert r["pos"][5, 2] == pytest.approx(hi[2]) and r["vel"][5, 2] < 0
