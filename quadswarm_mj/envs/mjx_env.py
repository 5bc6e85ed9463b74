"""``MjxQuadSwarmEnv``: the quadswarm simulator on MJX, jit-compiled and vmapped over worlds.

Shaped like MuJoCo Playground's ``MjxEnv``: one env object describes ONE world of N quads with pure
``reset(key, init_state=None) -> State`` and ``step(state, action) -> State``; batch with ``jax.vmap``,
compile with ``jax.jit``, renew finished worlds with :class:`AutoResetWrapper` (README, "JAX engine").

``step`` is :func:`quadswarm_mj.core.control.control_step` with :class:`~quadswarm_mj.core.ops.JaxOps`
(always-on stages, budgeted draws: ``tests/test_draw_budget.py``); the reset math is
:func:`quadswarm_mj.pipeline.initial_state`, shared with the CPU engine. ``physics``: the exact free-body
step or ``mjx.step`` (MuJoCo contacts). Random numbers: ``jax.random`` (or :mod:`quadswarm_mj.perf.fused_draws`
with ``draws="fused"``), made one step ahead into the state; per-world
randomization is redrawn at every ``reset`` into ``info["params"]`` and reaches ``mjx.step`` through
``model.replace``. ``State``'s fields: :class:`quadswarm_mj.core.state.State`; design: docs/engines.md.
Without noise this engine (float32) and the CPU engine (float64) agree to well under 2 mm over 150
control steps (``tests/test_mjx_env.py``).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from quadswarm_mj import metrics as metrics_lib
from quadswarm_mj import pipeline
from quadswarm_mj.actuation import (
    SPIN,
    motor_noise_draw_spec,
    rotor_positions,
    wrench_matrix,
)
from quadswarm_mj.aerodynamics import aero_draw_spec
from quadswarm_mj.arena import build_arena
from quadswarm_mj.collisions import (
    FLOOR_BUDGET,
    QUAD_PAIR_BUDGET,
    WALL_BUDGET,
    collision_draw_specs,
    expand_per_quad,
    floor_draw_spec,
    pairwise_contacts,
    quad_collision_slot_spec,
    wall_draw_spec,
)
from quadswarm_mj.config import EnvConfig
from quadswarm_mj.core.ops import JaxOps, jax_deck_part
from quadswarm_mj.core.ops import sub as _sub
from quadswarm_mj.core.reset import reset_state, start_accumulators, start_flags, start_state
from quadswarm_mj.core.state import State
from quadswarm_mj.core.swarm import SwarmState, from_info, step_state, to_info
from quadswarm_mj.devices import check_mjx_batch
from quadswarm_mj.downwash import DOWNWASH_BUDGET, downwash_slot_spec
from quadswarm_mj.envs.autoreset import AutoResetWrapper
from quadswarm_mj.envs.validation import check_obstacles, check_state
from quadswarm_mj.observations import build_obs, obs_bounds, obs_scale, sensor_noise_spec
from quadswarm_mj.perf import xla_cpu
from quadswarm_mj.perf.fused_draws import (  # noqa: F401  re-exported (their home is perf/)
    FusedJaxSampler,
    erf_inv_f32,
    step_key_and_numbers,
    step_words,
    threefry_2x32_unrolled,
    tof_numbers,
)
from quadswarm_mj.perf.jax_substeps import ComponentLoop
from quadswarm_mj.physics.mjx import MjxPhysics
from quadswarm_mj.random_draws import DrawSpec, JaxSampler, MeanSampler, Uniform, jax_unit_numbers
from quadswarm_mj.randomization import nominal_draws, randomization_draw_spec
from quadswarm_mj.rewards import env_terms
from quadswarm_mj.scenarios import get_scenario
from quadswarm_mj.scenarios.obstacle_scenarios import scenario_num_uniforms, scenario_spawn_uniforms
from quadswarm_mj.sensors import tof_from_words
from quadswarm_mj.spatial import quat_to_rotmat, rotmat_to_quat

PHYSICS = ("freebody", "mjx")
DRAWS = ("jax", "fused")


def _obst_lib() -> Any:
    """:mod:`quadswarm_mj.obstacles` (imported where obstacles are on)."""
    from quadswarm_mj import obstacles

    return obstacles


def _float() -> Any:
    """JAX's default float dtype (float32, or float64 with ``jax_enable_x64``)."""
    return jnp.asarray(0.0).dtype


def _prefixed(prefix: str, spec: DrawSpec, lead: tuple[int, ...] = ()) -> DrawSpec:
    """``spec`` with names ``prefix/name`` and per-item shapes ``lead + shape``."""
    return {f"{prefix}/{k}": dataclasses.replace(d, shape=tuple(lead) + tuple(d.shape)) for k, d in spec.items()}


_DECK_U = "deck/range_u"  # the deck rays' uniforms in the step's draws (quadswarm_mj.sensors.deck_draw_spec)


def _deck_spec(cfg: EnvConfig) -> DrawSpec:
    """The deck sensors' draws of one step (quadswarm_mj.sensors.deck_draw_spec; {} when off)."""
    from quadswarm_mj.sensors import deck_draw_spec

    return deck_draw_spec(cfg)


class MjxQuadSwarmEnv:
    """One world of ``cfg.num_quads`` Crazyflies on MJX; pure ``reset``/``step`` (jit, vmap).

    The model is ``quadswarm_mj.arena.build_arena(cfg, 1)`` put on the default device with
    ``mjx.put_model``. ``action`` is (N, 4): in the default "rotor" control mode raw per-rotor
    commands in [-1, 1] (clipped; -1 no thrust, 1 full thrust), in the other modes
    (``cfg.control_mode``) physical units within :attr:`action_bounds` (clipped; README "Beyond the
    paper"). Actions are not validated under ``jit``: a NaN action yields NaN state.

    ``physics`` chooses the rigid-body integrator of the sub-steps: ``"freebody"`` (the default
    where it is available: :func:`quadswarm_mj.freebody.freebody_step`, MuJoCo's Euler step of
    contact-free free bodies, exact) or ``"mjx"`` (``mjx.step``, generic: builds and factors the
    dense mass matrix). Both keep ``mjx.Data`` as the state; with "freebody" the derived fields
    (``xpos``...) are not recomputed (``mjx.get_data`` + ``mj_forward`` for rendering). ``draws``:
    ``"jax"`` (the default: a step's numbers from ``jax.random.bits``/``normal``,
    :func:`~quadswarm_mj.random_draws.jax_unit_numbers`) or ``"fused"`` (opt-in: one unrolled threefry
    hash and its own erfinv, :mod:`quadswarm_mj.perf.fused_draws`; 1.04x the samples/s at 512 x 8, 1.4-1.7x
    at 16 x 8: below the 1.3x a hand-written default needs on the standard run, docs/engines.md, "What pays").
    """

    def __init__(self, cfg: EnvConfig | None = None, physics: str | None = None, draws: str = "jax"):
        cfg = EnvConfig() if cfg is None else cfg
        if not isinstance(cfg, EnvConfig):
            raise ValueError(f"cfg must be an EnvConfig, got {type(cfg).__name__}")
        if draws not in DRAWS:
            raise ValueError(f"draws must be one of {DRAWS}, got {draws!r}")
        self.draws = draws
        if physics is None:
            physics = "freebody" if cfg.collision_model == "paper" else "mjx"
        if physics not in PHYSICS:
            raise ValueError(f"physics must be one of {PHYSICS}, got {physics!r}")
        if physics == "freebody" and cfg.collision_model != "paper":
            raise ValueError(f"physics='freebody' has no contacts: collision_model must be 'paper' with it, got "
                             f"{cfg.collision_model!r}; use physics='mjx' for 'mujoco'/'blend'")
        # which events the paper's model handles (the others are MuJoCo contacts, as in CpuSwarm)
        self._paper_floor = cfg.collision_model == "paper"
        self.physics = physics
        self.cfg = cfg
        self.N = n = cfg.num_quads
        self.arena = build_arena(cfg, 1)
        self.mj_model = self.arena.model
        self.mjx_model = mjx.put_model(self.mj_model, device=(dev := jax.local_devices()[0]))  # this process's:
        self._data0 = mjx.make_data(self.mjx_model, device=dev)  # mjx's default, jax.devices()[0], is process 0's
        self._mjx_physics = MjxPhysics(self.arena, self.mjx_model, n, cfg.collision_model == "paper")
        self.scenario = get_scenario(cfg.scenario)
        self._n_scn = scenario_num_uniforms(self.scenario, cfg)
        self._terms = env_terms(cfg)
        self._obst = cfg.obstacles
        self._obst_respond = cfg.collision_model == "paper"  # else MuJoCo's contacts resolve the columns
        self._rotor_pos = rotor_positions(cfg.quad)
        self._mix = wrench_matrix(self._rotor_pos)
        low, high = obs_bounds(cfg)
        self._obs_low, self._obs_high = np.asarray(low, np.float64), np.asarray(high, np.float64)
        self._obs_scale = obs_scale(cfg) if cfg.normalize_obs else None
        self._spec_wall = collision_draw_specs(cfg)["wall"]
        self._spec_sensor = sensor_noise_spec(cfg)
        self._sensor_on = any(d.std > 0 for d in self._spec_sensor.values())
        # All random numbers of one reset / one step come from one fused draw of these specs;
        # sources whose cfg.noise.stochastic_* flag is off take their means instead. Event models
        # draw for a bounded number of events per step (the draw budget, see collisions.py).
        stoch_coll, stoch_down = cfg.noise.stochastic_collisions, cfg.noise.stochastic_downwash
        c = cfg.collision
        self._reset_spec = {
            **(_prefixed("rand", randomization_draw_spec(cfg)) if cfg.randomize else {}),
            "scenario": Uniform(0.0, 1.0, (self._n_scn,)),
            "spawn": Uniform(0.0, 1.0, (scenario_spawn_uniforms(cfg),)),
            **(_prefixed("omap", _obst_lib().map_draw_spec(self._obst)) if self._obst is not None else {}),
            **(_prefixed("sensor", self._spec_sensor) if self._sensor_on else {}),
            **(_prefixed("aero", aero_draw_spec(cfg)) if cfg.randomize and cfg.aero.any else {}),
            **_prefixed("deck", _deck_spec(cfg)),  # deck sensor noise (quadswarm_mj.sensors); {} when off
        }
        self._act = pipeline.make_substep_actuation(cfg)  # None: the paper's chain (no extra work)
        # the default configuration's sub-steps run on tuples of components (quadswarm_mj.components)
        self._component_substeps = self._act is None and self._paper_floor and physics == "freebody"
        if physics == "freebody":
            from quadswarm_mj.freebody import freebody_constants

            self._fb_constants = freebody_constants(self.mj_model, self.arena)  # checks the model's assumptions
        self._modes = cfg.control_mode != "rotor"
        coll_spec = {
            **_prefixed("floor", floor_draw_spec(FLOOR_BUDGET), (cfg.substeps,)),  # slots per sub-step
            **_prefixed("wall", wall_draw_spec(WALL_BUDGET, cfg.collision_decay, c.kick_omega)),
            **_prefixed("quad", quad_collision_slot_spec(c.tries, QUAD_PAIR_BUDGET, c.shared_noise_std,
                                                         c.own_noise_std, n, cfg.collision_decay, c.kick_omega)),
            # obstacle response: slots for at most OBSTACLE_BUDGET new column contacts per step
            **(_prefixed("obst", _obst_lib().response_draw_spec(_obst_lib().OBSTACLE_BUDGET))
               if self._obst is not None and self._obst_respond else {}),
        }
        down_spec = _prefixed("down", downwash_slot_spec(DOWNWASH_BUDGET)) if cfg.downwash else {}
        self._step_spec = {
            **(_prefixed("motor", motor_noise_draw_spec(n)) if cfg.noise.motor_noise_ratio > 0 else {}),
            **(coll_spec if stoch_coll else {}),
            **(down_spec if stoch_down else {}),
            "scenario": Uniform(0.0, 1.0, (self._n_scn,)),
            **(_prefixed("sensor", self._spec_sensor) if self._sensor_on else {}),
            **_prefixed("deck", _deck_spec(cfg)),  # deck sensor noise (quadswarm_mj.sensors); {} when off
        }
        self._step_mean_spec = {**({} if stoch_coll else coll_spec), **({} if stoch_down else down_spec)}
        # The next step's random numbers are made at the end of a step (and by reset) and carried in
        # info["step_numbers"]: computed once into the state instead of inside the step, where XLA fuses
        # the normals' erf_inv into every consumer (or needs a loop to materialize them).
        self._carry_numbers = bool(self._step_spec) and (draws == "jax"
                                                         or FusedJaxSampler.fused(jax.random.key(0), _float()))
        # the deck rays' uniforms are carried as their ToF noise (NaN: lost), which build_obs takes as
        # draws["deck/range_z"]: sensors.tof_from_words (jax), perf.fused_draws.tof_numbers (fused)
        self._tof_mask = FusedJaxSampler.entry_mask(self._step_spec, _DECK_U) if self._carry_numbers else None
        if self._tof_mask is not None and not self._tof_mask.any():
            self._tof_mask = None

    # ------------------------------------------------------------------ properties
    @property
    def observation_size(self) -> int:
        return self.cfg.obs_dim

    @property
    def action_size(self) -> int:
        """Actions per quad (4 rotors); the full action is (N, 4)."""
        return 4

    @property
    def action_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(low (4,), high (4,)) per quad: :func:`quadswarm_mj.control_modes.control_action_bounds`."""
        from quadswarm_mj.control_modes import control_action_bounds

        return control_action_bounds(self.cfg)

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
        """Random draws of ``spec`` (:class:`~quadswarm_mj.random_draws.JaxSampler`, or with ``draws="fused"``
        :class:`~quadswarm_mj.perf.fused_draws.FusedJaxSampler`) and the means of ``mean_spec``, in one flat dict."""
        sampler = FusedJaxSampler if self.draws == "fused" else JaxSampler
        out = sampler(key, _float()).draw(spec) if spec else {}
        if mean_spec:
            out.update(MeanSampler(dtype=_float(), xp=jnp).draw(mean_spec))
        return out

    def _next_numbers(self, key: jax.Array) -> dict[str, jax.Array]:
        """``{"rng": next key, "step_numbers": the next step's unit numbers}`` from ``key`` (``jax.random``, or
        with ``draws="fused"`` one unrolled threefry hash); empty where the numbers are not carried."""
        if not self._carry_numbers:
            return {}
        normal_mask, dropout = FusedJaxSampler.normal_mask(self._step_spec), self.cfg.sensors.dropout
        if self.draws == "fused":
            k_next, numbers = step_key_and_numbers(key, normal_mask, self._tof_mask, dropout)
            return {"rng": k_next, "step_numbers": numbers}
        # the deck rays' ToF noise (NaN: lost) from 16 random bits each (sensors.tof_noise_table)
        rays = 0 if self._tof_mask is None else int(self._tof_mask.sum())
        k_next, numbers = jax_unit_numbers(key, normal_mask, _float(), self._tof_mask,
                                           lambda words: tof_from_words(words, rays, dropout), (rays + 1) // 2)
        return {"rng": k_next, "step_numbers": numbers}

    def _read(self, data: mjx.Data) -> tuple[jax.Array, jax.Array]:
        return self._mjx_physics.read(data)

    def _write(self, data: mjx.Data, q: jax.Array, v: jax.Array) -> mjx.Data:
        return self._mjx_physics.write(data, q, v)

    def _params(self, state: SwarmState) -> dict[str, Any]:
        return {**state.params, "gravity": self.cfg.quad.gravity}

    def _substep_physics(self, params: dict[str, Any], obstacle_radius: Any = None) -> Any:
        """The ``physics`` of :func:`quadswarm_mj.core.substeps.substep_loop`: the whole loop on components
        in the default configuration (:class:`~quadswarm_mj.perf.jax_substeps.ComponentLoop`), else one
        integrator sub-step at a time (:meth:`~quadswarm_mj.physics.mjx.MjxPhysics.substep_physics`)."""
        if self._component_substeps:
            return ComponentLoop(self._fb_constants, self._mix)
        return self._mjx_physics.substep_physics(self.physics, params, self.cfg.quad.max_omega, obstacle_radius)

    def _observe(self, pos: Any, vel: Any, R: Any, omega: Any, goals: Any, draws: dict[str, Any],
                 dist: Any = None, omap: Any = None) -> jax.Array:
        f = _float()
        noise = _sub(draws, "sensor") if self._sensor_on else None
        scale = None if self._obs_scale is None else jnp.asarray(self._obs_scale, f)
        deck = _sub(draws, "deck") or None  # deck sensor noise (quadswarm_mj.sensors), None: noise-free
        return build_obs(self.cfg, pos, vel, R, omega, goals, noise, jnp.asarray(self._obs_low, f),
                         jnp.asarray(self._obs_high, f), scale, dist=dist,
                         obstacles=None if omap is None else tuple(omap), deck_draws=deck,
                         rank_fn=xla_cpu.neighbor_rank(), deck_fn=jax_deck_part())

    def _deck_info(self, obs: jax.Array) -> dict[str, jax.Array]:
        """``multiranger``, ``flow``, ``depth`` (and their ``*_valid`` flags) from the observation's deck
        part (quadswarm_mj.sensors.deck_info); {} with the deck sensors off."""
        if not self.cfg.sensors.any:
            return {}
        from quadswarm_mj.sensors import deck_info

        return deck_info(self.cfg, obs, self._obs_scale)

    def _episode_metrics(self, state: SwarmState, t: Any) -> dict[str, Any]:
        """Episode metrics at ``t`` s: the standard ones, then with obstacles obstacle_collisions,
        collision_rate, success."""
        acc = state.metrics_acc
        out = metrics_lib.finalize(acc, t)
        if state.obstacles is not None:
            out.update(_obst_lib().metrics_finalize(state.obstacle_metrics, acc["collisions"]))
        return out

    # ------------------------------------------------------------------ reset
    def reset(self, key: jax.Array, init_state: dict[str, Any] | None = None) -> State:
        """Start an episode of one world from PRNG ``key``.

        ``init_state`` is the CPU env's ``options["state"]``: optional ``pos`` (N, 3) m, ``vel``
        (N, 3) m/s, ``rot`` (N, 3, 3) body->world, ``omega`` (N, 3) rad/s body, ``goals`` (N, 3)
        m and ``motors``: "zero" or "hover" (a Python string, so static: known at trace time,
        e.g. close over it), or (N, 4) normalized rotor thrusts in [0, 1]. Missing keys take the
        defaults (scenario goals, spawn near the goals at rest, ``cfg.motor_start``). With obstacles
        on, ``obstacles`` (M, 2) column centres (x, y m, M <= the column slots) replace the random map.

        ``init_state`` is checked as the CPU env checks it (:func:`~quadswarm_mj.envs.validation.
        check_state`: keys, shapes, finite values, proper rotations, ``pos`` and ``goals`` inside
        the room), raising ValueError naming the key; values that are tracers (``init_state``
        passed through ``jit``/``vmap``) get the shape checks only.
        """
        cfg, n = self.cfg, self.N
        f = _float()
        init_state = dict({} if init_state is None else init_state)
        given_obst = init_state.pop("obstacles", None)
        if given_obst is not None:
            given_obst = check_obstacles(given_obst, cfg, name="init_state['obstacles']")
        init_state = check_state(init_state, n, name="init_state", room=(cfg.room_low, cfg.room_high))
        k_draw, k_next = jax.random.split(key)
        rnd = self._draw(self._reset_spec, k_draw)
        draws = _sub(rnd, "rand") if cfg.randomize else nominal_draws(cfg, jnp.zeros((n,), f))
        aero_draws = _sub(rnd, "aero") if cfg.randomize and cfg.aero.any else None
        omap = None
        if self._obst is not None:
            ob = _obst_lib()
            omap = ob.reset_map(self._obst, _sub(rnd, "omap"), given_obst, xp=jnp)
            omap = ob.ObstacleMap(omap.centres.astype(f), omap.valid, jnp.asarray(omap.radius, f))
        init = start_state(cfg, self.scenario, draws, rnd["scenario"], rnd["spawn"], init_state, jnp, f, aero_draws,
                           omap=omap)
        params, sstate, goals = init["params"], init["scenario"], init["scenario"].goals
        pos, vel, R, omega = init["pos"], init["vel"], init["rot"], init["omega"]
        data = self._write(self._data0, jnp.concatenate([pos, rotmat_to_quat(R)], -1),
                           jnp.concatenate([vel, omega], -1))
        data = data.replace(time=jnp.zeros_like(data.time))
        if omap is not None:  # move the column pool (MuJoCo contacts with physics="mjx"; rendering)
            from quadswarm_mj.arena import obstacle_mocap_pos

            a = self.arena
            data = data.replace(mocap_pos=obstacle_mocap_pos(data.mocap_pos, a.obstacle_mocap_ids[0], omap.centres,
                                                             omap.valid, cfg.room_size[2], a.obstacle_park
                                                             ).astype(data.mocap_pos.dtype))
        q, v = self._read(data)  # as stored (quaternion round trip), like the CPU env
        pos, vel, omega = q[:, :3].astype(f), v[:, :3].astype(f), v[:, 3:].astype(f)
        R = quat_to_rotmat(q[:, 3:7]).astype(f)
        flags = start_flags(cfg, pos, jnp, omap)
        _, dist = pairwise_contacts(pos, cfg.hitbox, xla_cpu.pair_distances())
        fresh = start_accumulators(cfg, jnp.zeros((n,), f), (), n)
        obs = self._observe(pos, vel, R, omega, goals, rnd, dist, omap)
        zero_n, zero_i, zero_t = jnp.zeros((n,), f), jnp.zeros((), jnp.int32), jnp.zeros((), f)
        params = {k: jnp.asarray(v, f) for k, v in params.items() if k != "gravity"}
        ctrl_state = jnp.zeros((n, 6), f) if self._modes else None  # control-mode integrators
        ss = reset_state(init, flags, fresh, zero_i, params, R, ctrl_state, omap, total_steps=zero_i)
        nxt = self._next_numbers(k_next)
        ss = ss.replace(rng=nxt.get("rng", k_next), step_numbers=nxt.get("step_numbers"))
        readouts = {"state": {"pos": pos, "vel": vel, "omega": omega}, "goals": goals, "goal_vel": sstate.goal_vel,
                    "episode_metrics": self._episode_metrics(ss, zero_t), "time": zero_t, "truncation": zero_t,
                    **self._deck_info(obs)}  # deck sensor readings ({} when off)
        metrics = {f"reward/{k}": zero_n for k in self._terms}
        return State(data=data, obs=obs, reward=zero_n, done=jnp.zeros((), bool), metrics=metrics,
                     info=to_info(ss, readouts))

    # ------------------------------------------------------------------ physics
    def _step_inputs(self, ss: SwarmState, rnd: dict[str, Any]) -> tuple[dict, dict, Any, Any]:
        """(dynamics parameters, constants, physics, ops) of :func:`quadswarm_mj.core.swarm.step_state` for
        one world in state ``ss`` with the step's draws ``rnd``."""
        cfg, f = self.cfg, _float()
        params = self._params(ss)
        obst = None if self._obst is None else functools.partial(self._obstacles, ss, rnd)
        consts = {"act": self._act, "rotor_pos": jnp.asarray(self._rotor_pos, f), "mix": jnp.asarray(self._mix, f),
                  "torque_spin": params["torque_max"] * jnp.asarray(SPIN, f), "obs_low": jnp.asarray(self._obs_low, f),
                  "obs_high": jnp.asarray(self._obs_high, f),
                  "obs_scale": None if self._obs_scale is None else jnp.asarray(self._obs_scale, f), "zero_terms": ()}
        radius = None if ss.obstacles is None else ss.obstacles.radius
        return params, consts, self._substep_physics(params, radius), JaxOps(cfg, rnd, f, obst)

    def _obstacles(self, ss: SwarmState, rnd: dict[str, Any], pos: Any, vel: Any, omega: Any) -> dict[str, Any]:
        """The obstacle stage (after quad-quad): the budgeted response slots spread over this step's new
        column contacts (paper model), or detection only (MuJoCo contacts)."""
        omap, draws = ss.obstacles, None
        if self._obst_respond:
            new = _obst_lib().detect(pos, *omap, self.cfg.quad.arm)[0] & ~ss.obstacle_contact
            draws = expand_per_quad(new, _sub(rnd, "obst"))
        r = pipeline.obstacle_stage(pos, vel, omega, ss.obstacle_contact, omap, self.cfg.quad.arm, draws,
                                    self._obst_respond)
        return {"vel": r["vel"], "omega": r["omega"], "obst_new": r["new_contact"], "obst_contact": r["contact"],
                "changed": True}

    # ------------------------------------------------------------------ step
    def step(self, state: State, action: jax.Array) -> State:
        """Advance one control step with actions (N, 4) of ``cfg.control_mode`` (rotor: [-1, 1])."""
        cfg, n = self.cfg, self.N
        f = _float()
        ss = from_info(state.info)
        if tuple(jnp.shape(action)) != (n, 4):
            raise ValueError(f"action has the wrong shape: expected shape {(n, 4)} per world, "
                             f"got shape {tuple(jnp.shape(action))}")
        action = jnp.asarray(action, f)
        k_next = ss.rng
        if ss.step_numbers is not None:  # made by the previous step (or reset); the next ones at the end
            rnd = FusedJaxSampler.from_numbers(self._step_spec, ss.step_numbers)
            if self._tof_mask is not None:  # the deck rays' ToF noise (NaN: lost), not their uniforms
                del rnd[_DECK_U]
                rnd["deck/range_z"] = FusedJaxSampler.raw_entry(self._step_spec, ss.step_numbers, _DECK_U)
            if self._step_mean_spec:
                rnd.update(MeanSampler(dtype=f, xp=jnp).draw(self._step_mean_spec))
        else:
            k_draw, k_next = jax.random.split(ss.rng)
            rnd = self._draw(self._step_spec, k_draw, self._step_mean_spec)
        if self._act is not None:  # nothing reads the rotor command before the first sub-step writes it
            ss = ss.replace(rotor_cmd=jnp.zeros_like(ss.motor_eps))
        params, consts, physics, ops = self._step_inputs(ss, rnd)
        q0, v0 = self._read(state.data)
        aux = state.data if self.physics == "mjx" else None
        new, k, c, r = step_state(cfg, self.scenario, ss, q0.astype(f), v0.astype(f), aux, params, action, consts,
                                  physics, ops)
        data = state.data if c["aux"] is None else c["aux"]  # mjx.step's data, else the state's
        q, v = jnp.concatenate([k["pos"], k["quat"]], -1), jnp.concatenate([k["vel"], k["omega"]], -1)
        data = self._write(data, q, v)
        if c["aux"] is None:
            data = data.replace(time=data.time + cfg.control_dt)
        t, done, obs = r["t"], r["done"], r["obs"]
        nxt = self._next_numbers(k_next) if ss.step_numbers is not None else {}
        new = new.replace(rotor_cmd=None, rng=nxt.get("rng", k_next), step_numbers=nxt.get("step_numbers"))
        readouts = {"state": {"pos": k["pos"], "vel": k["vel"], "omega": k["omega"]}, "goals": r["goals"],
                    "goal_vel": r["goal_vel"], "episode_metrics": self._episode_metrics(new, t), "time": t,
                    "truncation": done.astype(f), **self._deck_info(obs)}  # deck sensor readings ({} when off)
        metrics = {f"reward/{name}": r["terms"][name] for name in self._terms}
        return State(data=data, obs=obs, reward=r["reward"], done=done, metrics=metrics, info=to_info(new, readouts))


# ---------------------------------------------------------------------------------- benchmark


def benchmark_mjx(cfg: EnvConfig, num_worlds: int, num_steps: int, seed: int = 0,
                  physics: str | None = None, devices: int | None = None, draws: str = "jax") -> dict[str, float]:
    """Time ``num_steps`` control steps of ``num_worlds`` worlds (auto-reset, hover actions).

    Worlds are sharded over all JAX devices when their number divides ``num_worlds``. The rollout
    is one jitted ``lax.scan``; ``compile_s`` is the time to trace and compile it (reset and
    rollout), ``samples_per_s`` counts quad-steps (worlds x quads x steps) per second of the
    compiled rollout (median of 3 runs), ``cpu_samples_per_s`` the same per second of this process's
    CPU time (all its threads: steadier on a shared machine). Returns also ``steps_per_s`` (world-steps per second),
    ``num_worlds``, ``num_quads``, ``num_steps``, ``devices``. ``physics``: see
    :class:`MjxQuadSwarmEnv` (None: its default). ``devices``: use at most that many of
    ``jax.devices()`` (None: all; :func:`quadswarm_mj.use_cpu_cores` gives one CPU device per core).
    ``draws``: see :class:`MjxQuadSwarmEnv`.
    """
    from quadswarm_mj.envs.sharding import WorldSharding, world_devices

    if num_worlds < 1 or num_steps < 1:
        raise ValueError(f"num_worlds and num_steps must be >= 1, got {num_worlds}, {num_steps}")
    if devices is not None and (not isinstance(devices, int) or devices < 1):
        raise ValueError(f"devices must be an int >= 1 or None, got {devices!r}")
    env = AutoResetWrapper(MjxQuadSwarmEnv(cfg, physics=physics, draws=draws))
    check_mjx_batch(env.env.physics, num_worlds)  # a clear error where jax >= 0.10 would hang (devices.py)
    shard = WorldSharding(num_worlds, world_devices(num_worlds, jax.devices()[:devices]))
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
    times, cpu = [], []
    for _ in range(3):
        t1, c1 = time.perf_counter(), time.process_time()
        state = jax.block_until_ready(run_c(state))
        times.append(time.perf_counter() - t1)
        cpu.append(time.process_time() - c1)
    dt = float(np.median(times))
    return {"samples_per_s": num_worlds * cfg.num_quads * num_steps / dt, "compile_s": compile_s,
            "cpu_samples_per_s": num_worlds * cfg.num_quads * num_steps / max(float(np.median(cpu)), 1e-9),
            "steps_per_s": num_worlds * num_steps / dt, "num_worlds": num_worlds, "num_quads": cfg.num_quads,
            "num_steps": num_steps, "devices": shard.num_devices}
