"""The CPU engine shared by every CPU front end: B worlds x N quads stepped by MuJoCo's C engine.

All model math is batched over (B, N) with the pure functions of the package; MuJoCo integrates the
rigid bodies. ``step`` is :func:`quadswarm_mj.core.swarm.step_state` (the control step both engines
call) with :class:`~quadswarm_mj.core.ops.NumpyOps` and the MuJoCo back end as ``physics``; the engine
holds its dynamic state in one :class:`~quadswarm_mj.core.swarm.SwarmState` (``CpuSwarm.state``, leaves
(B, N, ...), replaced every step; the attributes ``u``, ``on_floor``, ``sstate``... are views of it).
``QuadSwarmEnv`` is this engine with B = 1, ``QuadSwarmVectorEnv`` runs several of them (shards of
worlds), ``QuadSwarmParallelEnv`` wraps ``QuadSwarmEnv``.

Two physics back ends hold the B worlds (``backend``: ``"mjdata"``, one ``MjData`` with all worlds, the
default; ``"batch"``, ``mujoco.batch`` chunks; :mod:`quadswarm_mj.physics.mujoco_c`); they give
bit-identical results (with MuJoCo contacts, "mujoco"/"blend", only up to round-off).

Random numbers come from one seeded ``numpy.random.Generator`` in a fixed order, so seeded runs are
bit-identical. Draws whose only use is an event (a new contact, a wall or floor hit) are made only for
the worlds where the event happens, and the event model runs on those worlds only (with B = 1: exactly
when it happens). The per-step speed choices (event gating, the rotation kept for the next step, one
distance matrix per step) change no value: docs/engines.md.
"""

from __future__ import annotations

import operator
from typing import Any

import numpy as np

from quadswarm_mj import metrics as metrics_lib
from quadswarm_mj import pipeline
from quadswarm_mj.actuation import (
    SPIN,
    rotor_positions,
    wrench_matrix,
)
from quadswarm_mj.aerodynamics import aero_draw_spec
from quadswarm_mj.collisions import (
    collision_draw_specs,
)
from quadswarm_mj.config import EnvConfig
from quadswarm_mj.core.ops import ALL as _ALL
from quadswarm_mj.core.ops import NumpyOps
from quadswarm_mj.core.ops import put as _put
from quadswarm_mj.core.reset import reset_state, start_accumulators, start_flags, start_state
from quadswarm_mj.core.swarm import SwarmState, step_state
from quadswarm_mj.downwash import downwash_draw_spec
from quadswarm_mj.observations import obs_bounds, obs_scale, sensor_noise_spec
from quadswarm_mj.perf import numpy_floor
from quadswarm_mj.physics.mujoco_c import (  # noqa: F401  re-exported
    BACKENDS,
    BatchPhysics,
    MjDataPhysics,
    PhysicsInstabilityError,
)
from quadswarm_mj.random_draws import MeanSampler, NumpySampler
from quadswarm_mj.randomization import nominal_draws, randomization_draw_spec
from quadswarm_mj.rewards import zero_terms
from quadswarm_mj.scenarios import get_scenario
from quadswarm_mj.scenarios.obstacle_scenarios import scenario_num_uniforms, scenario_spawn_uniforms
from quadswarm_mj.spatial import rotmat_to_quat


def _put_rows(old: Any, idx: Any, new: Any, B: int) -> Any:
    """``old`` (a (B, ...) leaf, or a dict/tuple/NamedTuple of them; None: zeros) with rows ``idx``
    replaced by ``new`` (:func:`~quadswarm_mj.core.ops.put` per leaf)."""
    if isinstance(new, dict):
        return {k: _put_rows(None if old is None else old[k], idx, v, B) for k, v in new.items()}
    if isinstance(new, tuple):
        vals = [_put_rows(None if old is None else o, idx, v, B) for o, v in zip(old or (None,) * len(new), new)]
        return type(new)(*vals) if hasattr(new, "_fields") else tuple(vals)
    if old is None:
        if isinstance(idx, slice):
            return new
        a = np.asarray(new)
        old = np.zeros((B,) + a.shape[1:], a.dtype)
    return _put(old, idx, new)


def _view(field: str, doc: str) -> property:
    """An attribute that reads (and, assigned, replaces) the field ``field`` of ``self.state``."""
    def set_(self: CpuSwarm, value: Any) -> None:
        self.state = self.state.replace(**{field: value})

    return property(operator.attrgetter(f"state.{field}"), set_, doc=doc)


class CpuSwarm:
    """B worlds of N quads on CPU MuJoCo. State arrays are (B, N, ...), world-local frames.

    The rigid bodies' state is in the physics (``qpos``/``qvel`` views), everything else in ``state``
    (:class:`~quadswarm_mj.core.swarm.SwarmState`). The state changes only through :meth:`reset` and
    :meth:`step` (the engine keeps the rotation matrices of the last step for the next one, and the
    "batch" back end copies qpos/qvel into MuJoCo only after the engine changed them: code that writes
    ``qpos``/``qvel`` directly must call :meth:`state_changed`).
    """

    # views of ``state``'s fields (assigning one replaces the field)
    u = _view("motor_u", "(B, N, 4) normalized rotor speeds.")
    motor_eps = _view("motor_eps", "(B, N, 4) OU motor noise.")
    f_norm = _view("thrust", "(B, N, 4) normalized rotor thrusts.")
    on_floor = _view("on_floor", "(B, N) bool.")
    at_wall = _view("at_wall", "(B, N) bool.")
    at_ceiling = _view("at_ceiling", "(B, N) bool.")
    contact = _view("contact", "(B, N, N) bool pairs in contact at the last step.")
    steps = _view("step", "(B,) int control steps in the episode.")
    total_steps = _view("total_steps", "Control steps across episodes (reward annealing).")
    sstate = _view("scenario", "The scenario state (ScenarioState, (B, ...) leaves).")
    metrics = _view("metrics_acc", "The episode metric accumulators.")
    ctrl_state = _view("ctrl_state", "(B, N, 6) control-mode integrators (None in 'rotor' mode).")
    cmd_s = _view("rotor_cmd", "(B, N, 4) rotor command of the last sub-step (extended actuation only).")
    omap = _view("obstacles", "The column maps (ObstacleMap, (B, M_max, ...) leaves; None without obstacles).")
    obst_contact = _view("obstacle_contact", "(B, N) bool quads touching a column.")
    obst_metrics = _view("obstacle_metrics", "The obstacle metric accumulators.")

    def __init__(self, cfg: EnvConfig, num_worlds: int = 1, backend: str = "mjdata", visual: bool = True,
                 chunk_worlds: int = 64, nthread: int = 1):
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        if not isinstance(num_worlds, (int, np.integer)) or num_worlds < 1:
            raise ValueError(f"num_worlds must be an int >= 1, got {num_worlds!r}")
        self.cfg = cfg
        self.B, self.N = int(num_worlds), cfg.num_quads
        self.backend = backend
        self.phys: Any = (MjDataPhysics(cfg, self.B, visual) if backend == "mjdata"
                          else BatchPhysics(cfg, self.B, chunk_worlds, nthread))
        self.arena, self.model, self.data = self.phys.arena, self.phys.model, self.phys.data
        self.visual = visual
        self.qpos, self.qvel, self.xfrc = self.phys.qpos, self.phys.qvel, self.phys.xfrc  # (B, N, .) views
        self.offsets = self.phys.offsets
        self._offsets_zero = not np.any(self.offsets)
        B, N = self.B, self.N
        self.rotor_pos = rotor_positions(cfg.quad)
        self._mix = wrench_matrix(self.rotor_pos)
        self._zero_terms = zero_terms(cfg)
        self.scenario = get_scenario(cfg.scenario)
        self.paper_floor = cfg.collision_model == "paper"
        self.floor_z = cfg.quad.arm
        low, high = obs_bounds(cfg)
        self.obs_low, self.obs_high = low.astype(np.float64), high.astype(np.float64)
        self.obs_scale = obs_scale(cfg) if cfg.normalize_obs else None
        self.room_low = np.asarray(cfg.room_low)
        self.room_high = np.asarray(cfg.room_high)
        # one compare finds quads outside the walls or above the ceiling (the floor is separate)
        self._out_lo = np.array([cfg.room_low[0], cfg.room_low[1], -np.inf])
        self._out_hi = np.asarray(cfg.room_high, dtype=np.float64)
        self.rng = np.random.default_rng()
        # draw specs, built once
        specs = collision_draw_specs(cfg)
        self._spec_quad, self._spec_wall, self._spec_floor = specs["quad"], specs["wall"], specs["floor"]
        self._spec_down = downwash_draw_spec(N)
        spec_sensor = sensor_noise_spec(cfg)
        self._sensor_on = any(d.std > 0 for d in spec_sensor.values())
        # the three sensor-noise draws as one standard-normal draw (same stream, same values)
        self._sensor_keys = tuple(spec_sensor)
        self._sensor_std = np.array([spec_sensor[k].std for k in self._sensor_keys])[:, None, None, None]
        self._n_scn = scenario_num_uniforms(self.scenario, cfg)
        zeros = np.zeros((B, N))
        params = pipeline.dynamics_params(cfg, nominal_draws(cfg, zeros, (B,)))
        self._params = params  # state.params with gravity, as the model functions read them (set at reset)
        self._act = pipeline.make_substep_actuation(cfg, NumpyOps.wrench)  # None: the paper's chain (no extra work)
        self._modes = cfg.control_mode != "rotor"
        self._torque_spin = params["torque_max"] * SPIN
        self._any_on_floor = False  # a Python mirror of state.on_floor.any()
        z4 = np.zeros((B, N, 4))
        self.state = SwarmState(
            rot=None, motor_u=z4, motor_eps=z4.copy(), thrust=z4.copy(), on_floor=np.zeros((B, N), bool),
            at_wall=np.zeros((B, N), bool), at_ceiling=np.zeros((B, N), bool), contact=np.zeros((B, N, N), bool),
            step=np.zeros(B, np.int64), total_steps=0, scenario=None, metrics_acc=metrics_lib.init(zeros, (B,), N),
            params={k: v for k, v in params.items() if k != "gravity"},
            ctrl_state=np.zeros((B, N, 6)) if self._modes else None, rotor_cmd=z4.copy(), **self._obst_init())
        self._ops = NumpyOps(self)
        # the constants of core.control.control_step
        self._consts = {"act": self._act, "rotor_pos": self.rotor_pos, "mix": self._mix, "obs_low": self.obs_low,
                        "obs_high": self.obs_high, "obs_scale": self.obs_scale, "zero_terms": self._zero_terms}

    # ------------------------------------------------------------------ copy / pickle
    def __getstate__(self) -> dict[str, Any]:
        """For copy/pickle: the state without the aliases of the physics' arrays (views into MuJoCo's
        data, which the physics maps again in the copy): a copy is independent and steps exactly as
        the original from here."""
        return {k: v for k, v in self.__dict__.items()
                if k not in ("arena", "model", "data", "qpos", "qvel", "xfrc", "_visual_arena")}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        p = self.phys
        self.arena, self.model, self.data = p.arena, p.model, p.data
        self.qpos, self.qvel, self.xfrc = p.qpos, p.qvel, p.xfrc

    def visual_arena(self) -> tuple[Any, Any]:
        """(arena, model) to draw this engine with (:class:`quadswarm_mj.render.SwarmRenderer`): its own, or for
        an engine built without the Crazyflie's visual geoms (``visual=False``, which halves MuJoCo's kinematics
        per step) and without columns, a visual arena of the same worlds built on first use (the same bodies
        and qpos layout; the geoms carry no mass, so only the drawing differs)."""
        if self.visual or self.backend != "mjdata" or self.cfg.obstacles is not None:
            return self.arena, self.model
        va = self.__dict__.get("_visual_arena")
        if va is None:
            from quadswarm_mj.arena import build_arena

            va = self._visual_arena = build_arena(self.cfg, self.B)
        return va, va.model

    # ------------------------------------------------------------------ obstacles (SPEC_obstacles A)
    def _obst_init(self) -> dict[str, Any]:
        """The obstacle fields of the state: per-world column maps ``obstacles`` (ObstacleMap (B, M_max,
        2), (B, M_max), (B,)), the previous step's contacts and the metric accumulators ({} without)."""
        o, B, N = self.cfg.obstacles, self.B, self.N
        self._obst_thr: Any = None
        if o is None:
            return {}
        from quadswarm_mj import obstacles as ob

        m = o.slots
        fields = {"obstacles": ob.ObstacleMap(np.zeros((B, m, 2)), np.zeros((B, m), bool), np.full(B, 0.5 * o.size)),
                  "obstacle_contact": np.zeros((B, N), bool),
                  "obstacle_metrics": ob.metrics_init(np.zeros(1), (B,), N)}
        self._spec_obst = ob.response_draw_spec(N)
        self._spec_map = ob.map_draw_spec(o)
        self._obst_respond = self.cfg.collision_model == "paper"  # else MuJoCo's contacts resolve it
        # the success distance of the scenario (per world only for mix, which draws a sub-scenario)
        thr = getattr(self.scenario, "approach_goal_metric", 0.5)
        self._obst_thr = None if self.cfg.scenario == "mix" else np.full(B, float(thr))
        return fields

    def _obst_new_maps(self, idx: Any, M: int, given: Any) -> Any:
        """Maps of the M reset worlds: ``given`` centres ((B, K, 2) or (K, 2) m, world-local), else drawn."""
        from quadswarm_mj import obstacles as ob

        o = self.cfg.obstacles
        if given is None:
            return ob.reset_map(o, NumpySampler(self.rng).draw(self._spec_map, (M,)))
        c = np.asarray(given, dtype=np.float64)
        c = np.broadcast_to(c, (self.B,) + c.shape) if c.ndim == 2 else c
        c = c[idx]
        one = ob.map_from_centres(o, c[0])  # checks the shape and the count
        centres = np.repeat(one.centres[None], M, axis=0)
        centres[:, :c.shape[1]] = c[..., :2]
        return ob.ObstacleMap(centres, np.repeat(one.valid[None], M, axis=0), np.full(M, float(one.radius)))

    def _obstacle_stage(self, pos: np.ndarray, vel: np.ndarray,
                        omega: np.ndarray) -> tuple[np.ndarray, bool, np.ndarray]:
        """Obstacle contacts of this step (pipeline.obstacle_stage, event-gated: the paper model's
        response runs, and draws, only for worlds with a new contact); writes vel/omega in place.
        Returns (new contacts (B, N), whether vel/omega changed, contacts (B, N))."""
        from quadswarm_mj.obstacles import (
            features_from_grid,
            first_hit,
            hits_from_grid,
            obstacle_grid,
            obstacle_response,
        )

        om = self.state.obstacles
        grid = obstacle_grid(pos, om.centres, om.valid)  # one grid: this contact test and the observation's features
        hit = hits_from_grid(grid, om.radius, self.cfg.quad.arm)
        self._obst_feats = features_from_grid(grid, om.radius)  # of the step's final positions (kin["pos"])
        contact = hit.any(-1)
        new = contact & ~self.state.obstacle_contact
        if not (self._obst_respond and np.count_nonzero(new)):
            return new, False, contact
        centre = first_hit(hit, om.centres)[1]
        w = self._worlds(new)
        draws = self._sampler(self.cfg.noise.stochastic_collisions).draw(self._spec_obst, (self._count(w),))
        vel[w], omega[w] = obstacle_response(pos[w], vel[w], omega[w], centre[w], om.radius[w], new[w], draws)
        return new, True, contact

    def obstacle_centres(self, world: int = 0) -> np.ndarray:
        """(M, 2) centres (m, world-local) of the columns in force in ``world`` (empty without obstacles)."""
        if self.omap is None:
            return np.zeros((0, 2))
        return self.omap.centres[world][self.omap.valid[world]].copy()

    # ------------------------------------------------------------------ samplers
    def _sampler(self, stochastic: bool) -> Any:
        return NumpySampler(self.rng) if stochastic else MeanSampler()

    def seed(self, seed: Any) -> None:
        """Reseed the engine's generator (an int, a ``SeedSequence`` or None)."""
        self.rng = np.random.default_rng(seed)

    def state_changed(self) -> None:
        """Tell the engine that ``qpos``/``qvel`` were written from outside."""
        self.state = self.state.replace(rot=None)
        self.phys.touch()

    # ------------------------------------------------------------------ state access
    @property
    def params(self) -> dict[str, np.ndarray]:
        """The per-quad dynamics parameters in force (B, N, ...) with ``gravity`` (the step's; not copies)."""
        return self._params

    def _rotations(self) -> np.ndarray:
        """(B, N, 3, 3) body->world rotations of the current qpos (``state.rot``, made if None)."""
        st = self.state
        if st.rot is None:
            st = self.state = st.replace(rot=NumpyOps.rotmat(self.qpos[..., 3:7]))
        return st.rot

    def kinematics(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(pos, vel, R, omega) copies in world-local frames: pos m, vel m/s world, R body->world,
        omega rad/s body."""
        pos = self.qpos[..., :3] - self.offsets
        return pos, self.qvel[..., :3].copy(), self._rotations().copy(), self.qvel[..., 3:].copy()

    # ------------------------------------------------------------------ reset
    def reset(self, mask: np.ndarray | None = None, state: dict[str, Any] | None = None) -> None:
        """Reset the worlds in ``mask`` (B,) bool (all if None); ``state`` holds (B, N, ...) arrays
        (the rows of the worlds not reset are ignored).

        Draws (randomization, scenario, spawn) are made for the reset worlds only, in world order."""
        cfg, B, N = self.cfg, self.B, self.N
        mask = np.ones(B, bool) if mask is None else np.asarray(mask, bool)
        if mask.shape != (B,):
            raise ValueError(f"mask must have shape ({B},), got {mask.shape}")
        if mask.all():
            idx: Any = _ALL
            M = B
        else:
            idx = np.flatnonzero(mask)
            M = len(idx)
            if M == 0:
                return

        def rows(key: str, tail: tuple[int, ...]) -> np.ndarray | None:
            if state is None or state.get(key) is None:
                return None
            return np.asarray(state[key], dtype=np.float64).reshape((B, N) + tail)[idx]

        # draws in a fixed order (randomization, scenario, spawn), then the shared reset math
        if cfg.randomize:
            draws = NumpySampler(self.rng).draw(randomization_draw_spec(cfg), (M,))
        else:
            draws = nominal_draws(cfg, np.zeros((M, N)), (M,))
        new_map = None if self.omap is None else self._obst_new_maps(idx, M, (state or {}).get("obstacles"))
        scenario_u = self.rng.uniform(size=(M, self._n_scn))
        spawn_u = self.rng.uniform(size=(M, scenario_spawn_uniforms(cfg)))
        overrides: dict[str, Any] = {k: r for k, tail in (("pos", (3,)), ("vel", (3,)), ("rot", (3, 3)),
                                                         ("omega", (3,)), ("goals", (3,)))
                                     if (r := rows(k, tail)) is not None}
        motors: Any = cfg.motor_start if state is None or state.get("motors") is None else state["motors"]
        overrides["motors"] = motors if isinstance(motors, str) else rows("motors", (4,))
        aero_draws = (NumpySampler(self.rng).draw(aero_draw_spec(cfg), (M,)) if cfg.randomize and cfg.aero.any
                      else None)
        init = start_state(cfg, self.scenario, draws, scenario_u, spawn_u, overrides, np, np.float64, aero_draws,
                           omap=new_map)
        # the physics: dynamics parameters, start pose and velocities, column pool
        new_params = init["params"]
        self.phys.write_params(idx, new_params["mass"], new_params["inertia"])
        pos, vel, R, omega = init["pos"], init["vel"], init["rot"], init["omega"]
        offsets = self.offsets if self.offsets.shape[0] == 1 else self.offsets[idx]
        self.qpos[idx, :, :3] = pos + offsets
        self.qpos[idx, :, 3:7] = rotmat_to_quat(R)
        self.qvel[idx, :, :3] = vel
        self.qvel[idx, :, 3:] = omega
        self.phys.touch()
        if new_map is not None:
            self.phys.set_obstacles(cfg, idx, new_map)
        # the state's rows: the start as MuJoCo stores it (the shared reset math, core.reset)
        flags = start_flags(cfg, self.qpos[idx, :, :3] - offsets, np, new_map)
        fresh = start_accumulators(cfg, np.zeros((M, N)), (M,), N)
        start = reset_state(init, flags, fresh, np.zeros(M, np.int64),
                            {k: v for k, v in new_params.items() if k != "gravity"},
                            ctrl_state=np.zeros((M, N, 6)) if self._modes else None, omap=new_map)
        st = self.state
        if isinstance(idx, slice):  # the scenario state of all worlds is the new one (no copy)
            st = st.replace(scenario=None)
        self.state = st.replace(rot=None, **{f: _put_rows(getattr(st, f), idx, v, B)
                                             for f, v in start.__dict__.items() if v is not None})
        self._params = {**self.state.params, "gravity": new_params["gravity"]}
        self._torque_spin = self._params["torque_max"] * SPIN
        self._any_on_floor = np.count_nonzero(self.state.on_floor) > 0
        self.xfrc[...] = 0.0
        self.phys.after_reset(idx)

    # ------------------------------------------------------------------ physics
    def _store(self, k: dict[str, Any], c: dict[str, Any]) -> None:
        """Write the step's rigid-body results into MuJoCo (``c``: after the sub-steps, whose qpos/qvel
        are MuJoCo's own arrays, written there; ``k``: after the stages that follow them)."""
        if not self.paper_floor:
            if k["u"] is not c["u"]:  # the room guard ran
                self.qpos[..., 3:7] = k["quat"]
            self._any_on_floor = np.count_nonzero(k["on_floor"]) > 0  # (the paper's floor: set in the sub-steps)
        if k["changed"] or not self._offsets_zero:  # otherwise qpos/qvel hold these values already
            self.qpos[..., :3] = k["pos"] + self.offsets
            self.qvel[..., :3] = k["vel"]
            self.qvel[..., 3:] = k["omega"]
            self.phys.touch()

    def _worlds(self, flags: np.ndarray) -> Any:
        """Index of the worlds with any flag set: a slice when that is every world (views, no copy)."""
        if self.B == 1:  # callers ask only when some flag is set
            return _ALL
        per_world = flags.reshape(self.B, -1).any(-1)
        return _ALL if per_world.all() else np.flatnonzero(per_world)

    def _count(self, w: Any) -> int:
        return self.B if isinstance(w, slice) else len(w)

    def _floor_impact(self, w: Any, hit_floor: np.ndarray) -> None:
        """:meth:`_floor_rows` on the state's ``motor_u`` and ``on_floor``, which it replaces."""
        u, on_floor = self._floor_rows(w, self.state.motor_u, self.state.on_floor, hit_floor)
        self.state = self.state.replace(motor_u=u, on_floor=on_floor)

    def _floor_rows(self, w: Any, u: np.ndarray, on_floor: np.ndarray,
                    hit_floor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The paper's floor model after a sub-step, on worlds ``w`` (those with a quad at or below
        the floor height or grounded; elsewhere it changes nothing): ``perf.numpy_floor.floor_impact_rows``
        (same bits as the model, signs of zero included) as writes into qpos/qvel (one quad: ``NumpyOps``)
        and ``hit_floor``; returns the new (u, on_floor) (B, N, 4), (B, N)."""
        cfg = self.cfg
        rows = isinstance(w, slice)  # views: write in place; else copies written back
        q, v = self.qpos[w], self.qvel[w]
        offsets = None if self._offsets_zero else self.offsets if self.offsets.shape[0] == 1 else self.offsets[w]
        M, d = self._count(w), self._spec_floor["yaw"]  # = self._sampler(...).draw(self._spec_floor, (M,))["yaw"]
        yaw_draw = (self.rng.uniform(d.low, d.high, size=(M, self.N)) if cfg.noise.stochastic_collisions
                    else np.full((M, self.N), d.mean))
        hit, grounded, any_hit = numpy_floor.floor_impact_rows(q, v, on_floor[w], self.floor_z, offsets, yaw_draw)
        if any_hit:  # a hit zeroes the motors (0.0 * u: signs kept)
            u = _put(u, w, np.where(hit[..., None], 0.0 * u[w], u[w]))
            hit_floor[w] |= hit
        if not rows:
            self.qpos[w], self.qvel[w] = q, v
        self.phys.touch()
        on_floor = _put(on_floor, w, grounded)
        self._any_on_floor = np.count_nonzero(on_floor) > 0
        return u, on_floor

    # ------------------------------------------------------------------ step
    def step(self, action: np.ndarray) -> dict[str, Any]:
        """Advance all worlds one control step with validated actions (B, N, 4) of ``cfg.control_mode``
        (per-rotor in [-1, 1], or physical units clipped into ``control_action_bounds``):
        :func:`quadswarm_mj.core.swarm.step_state` on MuJoCo (``self.phys``) with :class:`NumpyOps`. Returns ``obs``,
        ``rewards``, ``terms``, ``truncated``, ``kin``, ``t`` and ``rows``: a fresh (1 + terms, B, N) block holding
        the rewards and the terms (which are its rows) when the task's fused form made them, else None."""
        st = self.state
        if st.rot is None:  # the rotations of qpos (after a reset or a write from outside)
            st = self.state = st.replace(rot=NumpyOps.rotmat(self.qpos[..., 3:7]))
        consts = self._consts
        consts["torque_spin"] = self._torque_spin  # (drawn at reset)
        new, k, c, r = step_state(self.cfg, self.scenario, st, self.qpos, self.qvel, None, self._params,
                                  action, consts, self.phys, self._ops, self._obst_thr)
        self._store(k, c)
        self.state = new
        k.setdefault("obst_new", None)
        k.setdefault("obst_feats", None)
        return {"obs": r["obs"], "rewards": r["reward"], "terms": r["terms"], "truncated": r["done"], "kin": k,
                "t": r["t"], "rows": r.get("rows")}

    def observe(self, kin: dict[str, Any] | None = None, worlds: Any = None) -> np.ndarray:
        """Observations (B, N, obs_dim) float64 (sensor noise drawn now), or (len(worlds), N,
        obs_dim) for the worlds ``worlds`` (an index array; noise drawn for those only)."""
        st = self.state
        if kin is not None:
            pos, vel, R, omega, dist = kin["pos"], kin["vel"], kin["R"], kin["omega"], kin["dist"]
            goals = st.scenario.goals
        else:
            pos, vel, R, omega = self.kinematics()
            dist, goals = None, st.scenario.goals
            if worlds is not None:
                pos, vel, R, omega, goals = pos[worlds], vel[worlds], R[worlds], omega[worlds], goals[worlds]
        noise = None
        if self._sensor_on:  # = NumpySampler(rng).draw(sensor_noise_spec(cfg), (B,)): 0 + std * N(0, 1)
            z = 0.0 + self._sensor_std * self.rng.standard_normal((3,) + pos.shape)
            noise = dict(zip(self._sensor_keys, z))
        obst, om = None, st.obstacles
        if om is not None:
            obst = tuple(om) if worlds is None or kin is not None else tuple(a[worlds] for a in om)
        feats = kin.get("obst_feats") if kin is not None else None
        deck = None
        if self.cfg.sensors.any and self.cfg.sensors.noise:  # deck sensor noise (quadswarm_mj.sensors)
            from quadswarm_mj.sensors import deck_draw_spec

            deck = NumpySampler(self.rng).draw(deck_draw_spec(self.cfg), pos.shape[:1])
        return self._ops.obs(self.cfg, pos, vel, R, omega, goals, noise, self.obs_low, self.obs_high,
                             self.obs_scale, dist=dist, obstacles=obst, obstacle_feats=feats, deck_draws=deck)

    def state_into(self, out: dict[str, np.ndarray]) -> None:
        """Write :meth:`state_dict`'s arrays into ``out`` (preallocated (B, N, ...) arrays)."""
        np.subtract(self.qpos[..., :3], self.offsets, out=out["pos"])
        out["vel"][...] = self.qvel[..., :3]
        out["rot"][...] = self._rotations()
        out["omega"][...] = self.qvel[..., 3:]
        out["thrust"][...] = self.state.thrust

    def episode_metrics(self) -> dict[str, np.ndarray]:
        """Per-world episode metrics (B,) so far."""
        st = self.state
        t_end = st.step * self.cfg.control_dt
        out = metrics_lib.finalize(st.metrics_acc, t_end[:, None])
        if st.obstacles is not None:
            from quadswarm_mj.obstacles import metrics_finalize

            out.update(metrics_finalize(st.obstacle_metrics, st.metrics_acc["collisions"]))
        return out

    def state_dict(self, kin: dict[str, Any] | None = None) -> dict[str, np.ndarray]:
        """Fresh copies: pos, vel (world), rot (body->world), omega (body), thrust (normalized, (B, N, 4))."""
        pos, vel, R, omega = self.kinematics()
        return {"pos": pos, "vel": vel, "rot": R, "omega": omega, "thrust": self.state.thrust.copy()}

    def params_dict(self) -> dict[str, np.ndarray]:
        """Copies of the per-quad dynamics parameters in force (B, N, ...)."""
        return {k: np.array(v, copy=True) for k, v in self.state.params.items()}
