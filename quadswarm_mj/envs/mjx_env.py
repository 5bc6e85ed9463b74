"""``MjxQuadSwarmEnv``: the quadswarm simulator on MJX, jit-compiled and vmapped over worlds.

Shaped like MuJoCo Playground's ``MjxEnv``: one env object describes ONE world of N quads with
pure functions ``reset(key, init_state=None) -> State`` and ``step(state, action) -> State``;
batch with ``jax.vmap`` and compile with ``jax.jit``::

    import jax, jax.numpy as jnp
    from quadswarm_mj import EnvConfig
    from quadswarm_mj.envs.mjx_env import AutoResetWrapper, MjxQuadSwarmEnv

    env = AutoResetWrapper(MjxQuadSwarmEnv(EnvConfig(num_quads=8, randomize=True)))
    reset = jax.jit(jax.vmap(env.reset))
    step = jax.jit(env.vstep)          # = jax.jit(jax.vmap(env.step)), resets computed only when due
    state = reset(jax.random.split(jax.random.key(0), 64))      # 64 worlds
    action = jnp.full((64, 8, 4), env.cfg.quad.hover_action)   # (worlds, N, 4) in [-1, 1]
    state = step(state, action)                                  # state.obs (64, 8, obs_dim)

The model is the package's single definition: actuation, the paper's floor/wall/ceiling and
quad-quad collisions, downwash, scenarios, observations, rewards and episode metrics are the very
functions :mod:`quadswarm_mj.envs.cpu_core` calls, here on ``jax.numpy`` with random draws from
:class:`FusedJaxSampler` (a :class:`~quadswarm_mj.random_draws.JaxSampler` that makes all draws of
one reset or one step with one uniform and one normal call) or a ``MeanSampler`` where a
``cfg.noise.stochastic_*`` flag is off. Rigid-body integration is ``mjx.step`` in a ``lax.scan``
over the ``cfg.substeps`` physics sub-steps of one control step, in the same order as
``CpuSwarm._physics``. Without noise, MJX (float32) and the CPU env (float64) agree to well under
2 mm over 150 control steps (``tests/test_mjx_env.py``).

The CPU engine skips a model function when nothing can happen (no quad near the floor, no new
contact); here every function is always evaluated, which gives the same values because each one
leaves unaffected quads unchanged (no Python ``if`` on array values under ``jit``). Random streams
differ from the CPU env's (``jax.random`` vs NumPy), so only noise-free runs are comparable.

Per-world domain randomization: at every ``reset`` (``cfg.randomize=True``) the dynamics parameters
are drawn under ``jit`` into ``state.info["params"]``; ``step`` writes mass and inertia into the
quad rows of the MJX model with ``model.replace`` (so a batched state carries a batched model) and
passes thrust, torque and motor constants to the actuation functions.

``State`` fields (one world; a vmapped state has a leading worlds axis on every leaf):

* ``data``: ``mjx.Data``. Quad ``i``'s free joint is ``qpos[7 i: 7 i + 7]`` (position m, world;
  quaternion w, x, y, z body->world) and ``qvel[6 i: 6 i + 6]`` (linear m/s world, angular rad/s
  body). Derived fields (``xpos``...) are those of the last physics sub-step; after ``reset`` and
  the once-per-control-step velocity models they lag ``qpos``/``qvel`` until the next ``mjx.step``.
* ``obs`` (N, obs_dim), ``reward`` (N,) per quad, ``done`` () bool (time limit; there is no
  termination), ``metrics`` {"reward/<term>": (N,)} for every term of
  :data:`quadswarm_mj.rewards.TERMS` (they sum to ``reward``).
* ``info``: ``state`` {pos (N, 3) m world, vel (N, 3) m/s world, rot (N, 3, 3) body->world,
  omega (N, 3) rad/s body, thrust (N, 4) normalized rotor thrusts} as the CPU env's
  ``info["state"]``; ``params`` (per-quad dynamics parameters, see
  :mod:`quadswarm_mj.randomization`; gravity excluded); ``goals``, ``goal_vel`` (N, 3); ``motor_u``
  (N, 4) normalized rotor speed; ``motor_eps`` (N, 4) OU motor noise; ``on_floor``, ``at_wall``,
  ``at_ceiling`` (N,) bool; ``contact`` (N, N) bool (pairs inside the hitbox);
  ``scenario`` (:class:`~quadswarm_mj.scenarios.ScenarioState`); ``metrics_acc`` (accumulators of
  :mod:`quadswarm_mj.metrics`); ``episode_metrics`` (episode metrics so far, per world);
  ``last_action`` (N, 4); ``step`` () int control steps in this episode; ``time`` () s;
  ``total_steps`` () int across episodes (reward annealing; kept by :class:`AutoResetWrapper`);
  ``truncation`` () float (1.0 at the time limit); ``rng`` (the key for the next step's draws).

Not supported on MJX (``ValueError``): ``collision_model`` "mujoco" and "blend" (contacts through
MJX's solver); use the CPU env for those.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from quadswarm_mj import metrics as metrics_lib
from quadswarm_mj.actuation import (
    action_to_command,
    hover_motor_state,
    motor_noise_draw_spec,
    motor_noise_step,
    rotor_positions,
    substep_wrench,
)
from quadswarm_mj.arena import build_arena
from quadswarm_mj.collisions import (
    collision_draw_specs,
    floor_impact,
    floor_wrench,
    pairwise_contacts,
    quad_collisions,
    wall_collisions,
)
from quadswarm_mj.config import EnvConfig
from quadswarm_mj.downwash import apply_downwash, downwash_draw_spec
from quadswarm_mj.observations import build_obs, obs_bounds, obs_scale, sensor_noise_spec
from quadswarm_mj.random_draws import DrawSpec, JaxSampler, MeanSampler, Normal, Uniform
from quadswarm_mj.randomization import nominal_draws, params_from_draws, randomization_draw_spec
from quadswarm_mj.rewards import TERMS, anneal_factor, reward_terms, total_reward
from quadswarm_mj.scenarios import get_scenario
from quadswarm_mj.scenarios.base import spawn_num_uniforms, spawn_state
from quadswarm_mj.spatial import quat_to_rotmat, rotmat_to_quat, yaw_rotmat

INIT_STATE_KEYS = ("pos", "vel", "rot", "omega", "motors", "goals")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class State:
    """Environment state of one world (a pytree; see the module docstring for the fields)."""

    data: mjx.Data
    obs: jax.Array
    reward: jax.Array
    done: jax.Array
    metrics: dict[str, jax.Array]
    info: dict[str, Any]

    def replace(self, **changes: Any) -> State:
        return dataclasses.replace(self, **changes)


def _float() -> Any:
    """JAX's default float dtype (float32, or float64 with ``jax_enable_x64``)."""
    return jnp.asarray(0.0).dtype


def _prefixed(prefix: str, spec: DrawSpec, lead: tuple[int, ...] = ()) -> DrawSpec:
    """``spec`` with names ``prefix/name`` and per-item shapes ``lead + shape``."""
    return {f"{prefix}/{k}": dataclasses.replace(d, shape=tuple(lead) + tuple(d.shape)) for k, d in spec.items()}


def _sub(draws: dict[str, Any], prefix: str) -> dict[str, Any]:
    """The draws named ``prefix/...`` with the prefix removed."""
    p = prefix + "/"
    return {k[len(p):]: v for k, v in draws.items() if k.startswith(p)}


class FusedJaxSampler(JaxSampler):
    """A :class:`~quadswarm_mj.random_draws.JaxSampler` that draws a whole spec with ONE
    ``jax.random.uniform`` and ONE ``jax.random.normal`` call (sliced per entry) instead of one
    call per entry: same distributions, far less to compile (each threefry call is a large graph on
    XLA:CPU) and fewer small kernels to run. Used under ``jit`` only."""

    def draw(self, spec: DrawSpec, batch_shape: tuple[int, ...] = ()) -> dict[str, Any]:
        self.key, k_u, k_n = jax.random.split(self.key, 3)
        out: dict[str, Any] = {}
        for kind, key in ((Uniform, k_u), (Normal, k_n)):
            items = [(name, d, tuple(batch_shape) + tuple(d.shape)) for name, d in spec.items() if isinstance(d, kind)]
            if not items:
                continue
            sizes = [int(np.prod(shape)) for _, _, shape in items]
            flat = (jax.random.uniform if kind is Uniform else jax.random.normal)(key, (sum(sizes),), self.dtype)
            start = 0
            for (name, d, shape), size in zip(items, sizes):
                x = flat[start:start + size].reshape(shape)
                start += size
                out[name] = d.low + (d.high - d.low) * x if kind is Uniform else d.mean + d.std * x
        return out


class MjxQuadSwarmEnv:
    """One world of ``cfg.num_quads`` Crazyflies on MJX; pure ``reset``/``step`` (jit, vmap).

    The model is ``quadswarm_mj.arena.build_arena(cfg, 1)`` put on the default device with
    ``mjx.put_model``. ``action`` is (N, 4) raw per-rotor commands in [-1, 1] (clipped; -1 no
    thrust, 1 full thrust). Actions are not validated under ``jit``: a NaN action yields NaN state.
    """

    def __init__(self, cfg: EnvConfig | None = None):
        cfg = EnvConfig() if cfg is None else cfg
        if not isinstance(cfg, EnvConfig):
            raise ValueError(f"cfg must be an EnvConfig, got {type(cfg).__name__}")
        if cfg.collision_model != "paper":
            raise ValueError(f"MjxQuadSwarmEnv supports collision_model='paper' only, got "
                             f"{cfg.collision_model!r}; use the CPU env (QuadSwarmEnv) for 'mujoco'/'blend'")
        self.cfg = cfg
        self.N = n = cfg.num_quads
        self.arena = build_arena(cfg, 1)
        self.mj_model = self.arena.model
        self.mjx_model = mjx.put_model(self.mj_model)
        self._data0 = mjx.make_data(self.mjx_model)
        self._qs, self._vs = self.arena.qpos_start, self.arena.qvel_start
        self._fb = self.arena.first_body
        self.scenario = get_scenario(cfg.scenario)
        self._n_scn = self.scenario.num_uniforms(n)
        self._rotor_pos = rotor_positions(cfg.quad)
        low, high = obs_bounds(cfg)
        self._obs_low, self._obs_high = np.asarray(low, np.float64), np.asarray(high, np.float64)
        self._obs_scale = obs_scale(cfg) if cfg.normalize_obs else None
        specs = collision_draw_specs(cfg)
        self._spec_quad, self._spec_wall, self._spec_floor = specs["quad"], specs["wall"], specs["floor"]
        self._spec_down = downwash_draw_spec(n)
        self._spec_motor = motor_noise_draw_spec(n)
        self._spec_sensor = sensor_noise_spec(cfg)
        self._sensor_on = any(d.std > 0 for d in self._spec_sensor.values())
        # All random numbers of one reset / one step come from one fused draw of these specs;
        # sources whose cfg.noise.stochastic_* flag is off take their means instead.
        stoch_coll, stoch_down = cfg.noise.stochastic_collisions, cfg.noise.stochastic_downwash
        floor_spec = _prefixed("floor", self._spec_floor, (cfg.substeps,))  # one yaw draw per sub-step
        self._reset_spec = {
            **(_prefixed("rand", randomization_draw_spec(cfg)) if cfg.randomize else {}),
            "scenario": Uniform(0.0, 1.0, (self._n_scn,)),
            "spawn": Uniform(0.0, 1.0, (spawn_num_uniforms(n),)),
            **(_prefixed("sensor", self._spec_sensor) if self._sensor_on else {}),
        }
        coll_spec = {**floor_spec, **_prefixed("wall", self._spec_wall), **_prefixed("quad", self._spec_quad)}
        down_spec = _prefixed("down", self._spec_down) if cfg.downwash else {}
        self._step_spec = {
            **(_prefixed("motor", self._spec_motor) if cfg.noise.motor_noise_ratio > 0 else {}),
            **(coll_spec if stoch_coll else {}),
            **(down_spec if stoch_down else {}),
            "scenario": Uniform(0.0, 1.0, (self._n_scn,)),
            **(_prefixed("sensor", self._spec_sensor) if self._sensor_on else {}),
        }
        self._step_mean_spec = {**({} if stoch_coll else coll_spec), **({} if stoch_down else down_spec)}

    # ------------------------------------------------------------------ properties
    @property
    def observation_size(self) -> int:
        return self.cfg.obs_dim

    @property
    def action_size(self) -> int:
        """Actions per quad (4 rotors); the full action is (N, 4)."""
        return 4

    @property
    def num_quads(self) -> int:
        return self.N

    @property
    def episode_length(self) -> int:
        """Control steps per episode."""
        return self.cfg.episode_steps

    @property
    def dt(self) -> float:
        return self.cfg.control_dt

    # ------------------------------------------------------------------ helpers
    def _draw(self, spec: DrawSpec, key: jax.Array, mean_spec: DrawSpec | None = None) -> dict[str, jax.Array]:
        """Random draws of ``spec`` (one fused threefry call per distribution type) and the means
        of ``mean_spec``, in one flat dict."""
        out = FusedJaxSampler(key, _float()).draw(spec) if spec else {}
        if mean_spec:
            out.update(MeanSampler(dtype=_float(), xp=jnp).draw(mean_spec))
        return out

    def _kinematics(self, data: mjx.Data) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array, jax.Array]:
        """(pos m world, quat wxyz, vel m/s world, omega rad/s body) of the quads, and R body->world."""
        n = self.N
        q = data.qpos[self._qs:self._qs + 7 * n].reshape(n, 7)
        v = data.qvel[self._vs:self._vs + 6 * n].reshape(n, 6)
        return q[:, :3], q[:, 3:7], v[:, :3], v[:, 3:], quat_to_rotmat(q[:, 3:7])

    def _write(self, data: mjx.Data, pos: Any = None, quat: Any = None, vel: Any = None, omega: Any = None) -> mjx.Data:
        n = self.N
        q = data.qpos[self._qs:self._qs + 7 * n].reshape(n, 7)
        v = data.qvel[self._vs:self._vs + 6 * n].reshape(n, 6)
        q = jnp.concatenate([q[:, :3] if pos is None else pos, q[:, 3:7] if quat is None else quat], axis=-1)
        v = jnp.concatenate([v[:, :3] if vel is None else vel, v[:, 3:] if omega is None else omega], axis=-1)
        return data.replace(qpos=data.qpos.at[self._qs:self._qs + 7 * n].set(q.ravel().astype(data.qpos.dtype)),
                            qvel=data.qvel.at[self._vs:self._vs + 6 * n].set(v.ravel().astype(data.qvel.dtype)))

    def _params(self, info: dict[str, Any]) -> dict[str, Any]:
        return {**info["params"], "gravity": self.cfg.quad.gravity}

    def _model(self, params: dict[str, Any]) -> mjx.Model:
        """The MJX model with this world's drawn mass and inertia in the quad rows."""
        m, sl = self.mjx_model, slice(self._fb, self._fb + self.N)
        return m.replace(body_mass=m.body_mass.at[sl].set(params["mass"].astype(m.body_mass.dtype)),
                         body_inertia=m.body_inertia.at[sl].set(params["inertia"].astype(m.body_inertia.dtype)))

    def _observe(self, pos: Any, vel: Any, R: Any, omega: Any, goals: Any, draws: dict[str, Any]) -> jax.Array:
        f = _float()
        noise = _sub(draws, "sensor") if self._sensor_on else None
        scale = None if self._obs_scale is None else jnp.asarray(self._obs_scale, f)
        return build_obs(self.cfg, pos, vel, R, omega, goals, noise, jnp.asarray(self._obs_low, f),
                         jnp.asarray(self._obs_high, f), scale)

    def _surface_flags(self, pos: Any, vel: Any, omega: Any) -> tuple[Any, Any, Any]:
        """(on_floor, at_wall, at_ceiling) of quads at ``pos``, from the collision functions
        themselves: ``floor_impact`` of a grounded quad keeps it grounded exactly while it is at the
        floor height, ``wall_collisions`` reports contact with walls and ceiling."""
        cfg, n, f = self.cfg, self.N, pos.dtype
        yes = jnp.ones((n,), bool)
        zero_u = jnp.zeros((n, 4), f)
        eye = jnp.broadcast_to(jnp.eye(3, dtype=f), (n, 3, 3))
        quat = jnp.broadcast_to(jnp.asarray([1.0, 0.0, 0.0, 0.0], f), (n, 4))
        fl = floor_impact(pos, vel, omega, quat, eye, zero_u, yes, cfg.quad.arm, jnp.zeros((n,), f))
        w = wall_collisions(pos, vel, omega, yes, yes, jnp.asarray(cfg.room_low, f), jnp.asarray(cfg.room_high, f),
                            MeanSampler(dtype=f, xp=jnp).draw(self._spec_wall), cfg.collision.wall_speed_limits)
        return fl["on_floor"], w["at_wall"], w["at_ceiling"]

    # ------------------------------------------------------------------ reset
    def reset(self, key: jax.Array, init_state: dict[str, Any] | None = None) -> State:
        """Start an episode of one world from PRNG ``key``.

        ``init_state`` is the CPU env's ``options["state"]``: optional ``pos`` (N, 3) m, ``vel``
        (N, 3) m/s, ``rot`` (N, 3, 3) body->world, ``omega`` (N, 3) rad/s body, ``goals`` (N, 3)
        m and ``motors``: "zero" or "hover" (a Python string, so static: known at trace time,
        e.g. close over it), or (N, 4) normalized rotor thrusts in [0, 1]. Missing keys take the
        defaults (scenario goals, spawn near the goals at rest, ``cfg.motor_start``).
        """
        cfg, n = self.cfg, self.N
        f = _float()
        init_state = {} if init_state is None else {k: v for k, v in init_state.items() if v is not None}
        unknown = set(init_state) - set(INIT_STATE_KEYS)
        if unknown:
            raise ValueError(f"init_state has unknown keys {sorted(unknown)}; allowed: {list(INIT_STATE_KEYS)}")
        motors = init_state.get("motors", cfg.motor_start)
        if isinstance(motors, str) and motors not in ("zero", "hover"):
            raise ValueError(f"init_state['motors'] must be 'zero', 'hover' or an (N, 4) array, got {motors!r}")
        for name, tail in (("pos", (3,)), ("vel", (3,)), ("rot", (3, 3)), ("omega", (3,)), ("goals", (3,)),
                           ("motors", (4,))):
            v = init_state.get(name)
            if v is not None and not isinstance(v, str) and tuple(np.shape(v)) != (n,) + tail:
                raise ValueError(f"init_state['{name}'] has the wrong shape: expected {(n,) + tail}, "
                                 f"got {tuple(np.shape(v))}")
        k_draw, k_next = jax.random.split(key)
        rnd = self._draw(self._reset_spec, k_draw)
        # 1. dynamics parameters (drawn at every reset, under jit)
        draws = _sub(rnd, "rand") if cfg.randomize else nominal_draws(cfg, jnp.zeros((n,), f))
        params = params_from_draws(cfg, draws)
        # 2. scenario
        sstate = self.scenario.init(cfg, rnd["scenario"])
        if init_state.get("goals") is not None:
            sstate = sstate._replace(goals=jnp.asarray(init_state["goals"], f).reshape(n, 3))
        goals = sstate.goals
        # 3. start state
        sp = spawn_state(cfg, goals, rnd["spawn"])
        pos, R = sp["pos"], yaw_rotmat(sp["yaw"])
        vel, omega = jnp.zeros((n, 3), f), jnp.zeros((n, 3), f)
        pos = jnp.asarray(init_state.get("pos", pos), f).reshape(n, 3)
        vel = jnp.asarray(init_state.get("vel", vel), f).reshape(n, 3)
        R = jnp.asarray(init_state.get("rot", R), f).reshape(n, 3, 3)
        omega = jnp.asarray(init_state.get("omega", omega), f).reshape(n, 3)
        if isinstance(motors, str):
            u0 = hover_motor_state(params).astype(f) if motors == "hover" else jnp.zeros((n, 4), f)
        else:
            u0 = jnp.sqrt(jnp.clip(jnp.asarray(motors, f).reshape(n, 4), 0.0, 1.0))
        data = self._write(self._data0, pos, rotmat_to_quat(R), vel, omega)
        data = data.replace(time=jnp.zeros_like(data.time))
        pos, quat, vel, omega, R = self._kinematics(data)  # as stored (quaternion round trip), like the CPU env
        pos, vel, omega, R = pos.astype(f), vel.astype(f), omega.astype(f), R.astype(f)
        on_floor, at_wall, at_ceiling = self._surface_flags(pos, vel, omega)
        contact, _ = pairwise_contacts(pos, cfg.hitbox)
        acc = metrics_lib.init(jnp.zeros((n,), f), (), n)
        f_norm = u0 * u0
        obs = self._observe(pos, vel, R, omega, goals, rnd)
        zero_n = jnp.zeros((n,), f)
        info = {
            "state": {"pos": pos, "vel": vel, "rot": R, "omega": omega, "thrust": f_norm},
            "params": {k: jnp.asarray(v, f) for k, v in params.items() if k != "gravity"},
            "goals": goals, "goal_vel": sstate.goal_vel,
            "motor_u": u0, "motor_eps": jnp.zeros((n, 4), f),
            "on_floor": on_floor, "at_wall": at_wall, "at_ceiling": at_ceiling, "contact": contact,
            "scenario": sstate, "metrics_acc": acc,
            "episode_metrics": metrics_lib.finalize(acc, jnp.zeros((), f)),
            "last_action": jnp.zeros((n, 4), f),
            "step": jnp.zeros((), jnp.int32), "time": jnp.zeros((), f), "total_steps": jnp.zeros((), jnp.int32),
            "truncation": jnp.zeros((), f), "rng": k_next,
        }
        metrics = {f"reward/{k}": zero_n for k in TERMS}
        return State(data=data, obs=obs, reward=zero_n, done=jnp.zeros((), bool), metrics=metrics, info=info)

    # ------------------------------------------------------------------ physics
    def _physics(self, data: mjx.Data, info: dict[str, Any], action: jax.Array,
                 rnd: dict[str, Any]) -> tuple[mjx.Data, dict[str, Any]]:
        """One control step of the simulator, in the order of ``CpuSwarm._physics``."""
        cfg, n = self.cfg, self.N
        f = _float()
        params = self._params(info)
        model = self._model(params)
        rotor_pos = jnp.asarray(self._rotor_pos, f)
        cmd = action_to_command(action)
        eps = info["motor_eps"]
        if cfg.noise.motor_noise_ratio > 0:
            eps = motor_noise_step(eps, params["motor_sigma"], cfg.noise.motor_noise_theta, rnd["motor/motor"])
        max_w = cfg.quad.max_omega

        def substep(carry: tuple, yaw: jax.Array) -> tuple[tuple, None]:
            data, u, f_norm, on_floor, hit_floor = carry
            _, _, vel, _, R = self._kinematics(data)
            u, f_norm, force, torque = substep_wrench(u, cmd, eps, params, R, rotor_pos)
            force, torque = floor_wrench(on_floor, force, torque, vel, params["mass"], params["gravity"],
                                         cfg.collision.floor_friction, cfg.sim_dt)
            wrench = jnp.concatenate([force, torque], axis=-1).astype(data.xfrc_applied.dtype)
            data = data.replace(xfrc_applied=data.xfrc_applied.at[self._fb:self._fb + n].set(wrench))
            data = mjx.step(model, data)
            pos, quat, vel, omega, R = self._kinematics(data)
            omega = jnp.clip(omega, -max_w, max_w)
            r = floor_impact(pos, vel, omega, quat, R, u, on_floor, cfg.quad.arm, yaw)
            data = self._write(data, r["pos"], r["quat"], r["vel"], r["omega"])
            return (data, r["u"], f_norm, r["on_floor"], hit_floor | r["hit_floor"]), None

        carry0 = (data, info["motor_u"], info["state"]["thrust"], info["on_floor"], jnp.zeros((n,), bool))
        (data, u, f_norm, on_floor, hit_floor), _ = jax.lax.scan(
            substep, carry0, rnd["floor/yaw"])
        # once per control step: walls, ceiling, quad-quad, downwash (velocity-level models)
        pos, _, vel, omega, R = self._kinematics(data)
        pos, vel, omega, R = pos.astype(f), vel.astype(f), omega.astype(f), R.astype(f)
        w = wall_collisions(pos, vel, omega, info["at_wall"], info["at_ceiling"], jnp.asarray(cfg.room_low, f),
                            jnp.asarray(cfg.room_high, f), _sub(rnd, "wall"),
                            cfg.collision.wall_speed_limits)
        pos, vel, omega = w["pos"], w["vel"], w["omega"]
        q = quad_collisions(pos, vel, omega, info["contact"], cfg.hitbox,
                            _sub(rnd, "quad"))
        vel, omega = q["vel"], q["omega"]
        _, dist = pairwise_contacts(pos, cfg.hitbox)
        if cfg.downwash:
            vel, omega = apply_downwash(pos, vel, omega, R, cfg.control_dt, _sub(rnd, "down"))
        data = self._write(data, pos, None, vel, omega)
        k = {"pos": pos, "vel": vel, "R": R, "omega": omega, "dist": dist, "new_contact": q["new_contact"],
             "contact": q["contact"], "hit_floor": hit_floor, "hit_wall": w["hit_wall"],
             "hit_ceiling": w["hit_ceiling"], "at_wall": w["at_wall"], "at_ceiling": w["at_ceiling"],
             "on_floor": on_floor, "u": u, "f_norm": f_norm, "eps": eps}
        return data, k

    # ------------------------------------------------------------------ step
    def step(self, state: State, action: jax.Array) -> State:
        """Advance one control step with raw actions (N, 4) in [-1, 1]."""
        cfg, n = self.cfg, self.N
        f = _float()
        info = state.info
        if tuple(jnp.shape(action)) != (n, 4):
            raise ValueError(f"action has the wrong shape: expected shape {(n, 4)} per world, "
                             f"got shape {tuple(jnp.shape(action))}")
        action = jnp.asarray(action, f)
        k_draw, k_next = jax.random.split(info["rng"])
        rnd = self._draw(self._step_spec, k_draw, self._step_mean_spec)
        prev_f_norm = info["state"]["thrust"]
        data, k = self._physics(state.data, info, action, rnd)
        steps = info["step"] + 1
        total_steps = info["total_steps"] + 1
        t = steps.astype(f) * cfg.control_dt
        prev_goals = info["scenario"].goals
        sstate = self.scenario.step(cfg, info["scenario"], t, k["pos"], rnd["scenario"])
        goals, goal_vel = sstate.goals, sstate.goal_vel
        jump = metrics_lib.goal_jump(prev_goals, goals, goal_vel, cfg.control_dt)
        terms = reward_terms(cfg, k["pos"], k["vel"], k["R"], k["omega"], goals, action, k["f_norm"], prev_f_norm,
                             k["on_floor"], k["hit_floor"], k["hit_wall"], k["hit_ceiling"], k["new_contact"],
                             k["dist"], anneal_factor(cfg, total_steps))
        # explicit dtype: a zero-scale term may come back weakly typed, and a state whose leaf types
        # change between reset and step would make jit compile step twice
        terms = {name: v.astype(f) for name, v in terms.items()}
        reward = total_reward(terms)
        dist_goal = jnp.sqrt(jnp.sum((goals - k["pos"]) ** 2, axis=-1))
        acc = metrics_lib.update(info["metrics_acc"], t, dist_goal, k["new_contact"], k["hit_floor"], k["hit_wall"],
                                 k["hit_ceiling"], jump, cfg.grace_period_s)
        obs = self._observe(k["pos"], k["vel"], k["R"], k["omega"], goals, rnd)
        done = steps >= cfg.episode_steps
        new_info = {
            "state": {"pos": k["pos"], "vel": k["vel"], "rot": k["R"], "omega": k["omega"], "thrust": k["f_norm"]},
            "params": info["params"],
            "goals": goals, "goal_vel": goal_vel,
            "motor_u": k["u"], "motor_eps": k["eps"],
            "on_floor": k["on_floor"], "at_wall": k["at_wall"], "at_ceiling": k["at_ceiling"],
            "contact": k["contact"], "scenario": sstate, "metrics_acc": acc,
            "episode_metrics": metrics_lib.finalize(acc, t),
            "last_action": action,
            "step": steps, "time": t, "total_steps": total_steps,
            "truncation": done.astype(f), "rng": k_next,
        }
        metrics = {f"reward/{name}": terms[name] for name in TERMS}
        return State(data=data, obs=obs, reward=reward, done=done, metrics=metrics, info=new_info)


class AutoResetWrapper:
    """Resets a finished world completely: physics data, dynamics parameters (redrawn), motor
    state and noise, goals and scenario timers, flags, contacts, metrics and step counters.

    (Brax's and Playground's default auto-reset restore only the physics data and observation
    and keep ``info``, which here would keep the old goals, motors and timers.)

    At a step that ends an episode the returned state is the fresh episode's first state, except
    ``done`` (True), ``reward`` and ``metrics`` (the last step's) and ``info["episode_metrics"]``
    (the finished episode's). ``info["total_steps"]`` carries over (reward annealing).

    ``step`` is per world (vmap it): the fresh episode is computed every step and selected with
    ``where``. ``vstep`` steps a batch of worlds (leading axis) and computes the resets only on
    steps where some world finished (``lax.cond`` outside the vmap), which saves about a fifth of
    the step time; :class:`~quadswarm_mj.envs.sharding.ShardedEnv`, :func:`benchmark_mjx` and the
    Brax front end use it.
    """

    def __init__(self, env: MjxQuadSwarmEnv):
        self.env = env

    def __getattr__(self, name: str) -> Any:
        return getattr(self.env, name)

    def reset(self, key: jax.Array, init_state: dict[str, Any] | None = None) -> State:
        return self.env.reset(key, init_state)

    def step(self, state: State, action: jax.Array) -> State:
        """One world: (State, (N, 4)) -> State."""
        return self._renew(self.env.step(state, action))

    def vstep(self, state: State, action: jax.Array) -> State:
        """A batch of worlds: (State with leading axis W, (W, N, 4)) -> State."""
        s = jax.vmap(self.env.step)(state, action)
        return jax.lax.cond(jnp.any(s.done), jax.vmap(self._renew), lambda x: x, s)

    def _renew(self, s: State) -> State:
        """Replace a finished world's state by a fresh episode (identity where not done)."""
        # A finished world continues from the fresh episode's key; the others keep their key (the
        # discarded reset drew from a key derived from it), so vstep's no-reset branch is the same.
        fresh = self.env.reset(jax.random.fold_in(s.info["rng"], 1))
        fresh_info = {**fresh.info, "total_steps": s.info["total_steps"],
                      "episode_metrics": s.info["episode_metrics"], "truncation": s.info["truncation"]}

        def pick(a: Any, b: Any) -> Any:
            return _select(s.done, a, b)

        info = jax.tree.map(pick, fresh_info, s.info)
        return s.replace(data=jax.tree.map(pick, fresh.data, s.data), obs=pick(fresh.obs, s.obs), info=info)


def _select(pred: jax.Array, a: Any, b: Any) -> Any:
    """``where(pred, a, b)`` that also handles typed PRNG key arrays."""
    if jax.dtypes.issubdtype(a.dtype, jax.dtypes.prng_key):
        data = jnp.where(pred, jax.random.key_data(a), jax.random.key_data(b))
        return jax.random.wrap_key_data(data, impl=jax.random.key_impl(a))
    return jnp.where(pred, a, b)


# ---------------------------------------------------------------------------------- benchmark


def benchmark_mjx(cfg: EnvConfig, num_worlds: int, num_steps: int, seed: int = 0) -> dict[str, float]:
    """Time ``num_steps`` control steps of ``num_worlds`` worlds (auto-reset, hover actions).

    Worlds are sharded over all JAX devices when their number divides ``num_worlds``. The rollout
    is one jitted ``lax.scan``; ``compile_s`` is the time to trace and compile it (reset and
    rollout), ``samples_per_s`` counts quad-steps (worlds x quads x steps) per second of the
    compiled rollout (median of 3 runs). Returns also ``steps_per_s`` (world-steps per second),
    ``num_worlds``, ``num_quads``, ``num_steps``, ``devices``.
    """
    from quadswarm_mj.envs.sharding import WorldSharding

    if num_worlds < 1 or num_steps < 1:
        raise ValueError(f"num_worlds and num_steps must be >= 1, got {num_worlds}, {num_steps}")
    env = AutoResetWrapper(MjxQuadSwarmEnv(cfg))
    shard = WorldSharding(num_worlds)
    hover = jnp.full((num_worlds, cfg.num_quads, 4), cfg.quad.hover_action, _float())

    def rollout(state: State) -> State:
        def body(s: State, _: Any) -> tuple[State, None]:
            return shard.map_batched(env.vstep)(s, hover), None

        return jax.lax.scan(body, state, None, length=num_steps)[0]

    keys = jax.random.split(jax.random.key(seed), num_worlds)
    t0 = time.perf_counter()
    reset = jax.jit(shard.vmap_reset(env), in_shardings=shard.sharding, out_shardings=shard.sharding)
    run = jax.jit(rollout, in_shardings=shard.sharding, out_shardings=shard.sharding)
    keys = jax.device_put(keys, shard.sharding)
    state = jax.block_until_ready(reset(keys))
    run_c = run.lower(state).compile()
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(3):
        t1 = time.perf_counter()
        state = jax.block_until_ready(run_c(state))
        times.append(time.perf_counter() - t1)
    dt = float(np.median(times))
    return {"samples_per_s": num_worlds * cfg.num_quads * num_steps / dt, "compile_s": compile_s,
            "steps_per_s": num_worlds * num_steps / dt, "num_worlds": num_worlds, "num_quads": cfg.num_quads,
            "num_steps": num_steps, "devices": shard.num_devices}
