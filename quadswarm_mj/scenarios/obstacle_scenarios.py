"""Obstacle scenarios (SPEC_obstacles A.5): ``o_random``, ``o_static_same_goal``,
``o_dynamic_same_goal``, ``o_swap_goals``, ``o_ep_rand_bezier``; ``mix`` with obstacles.

An obstacle-aware scenario has ``accepts_obstacles = True`` and takes the column map as the keyword
``obstacles`` of ``init``/``step``; the ``o_*`` ones also have ``requires_obstacles = True`` and
``approach_goal_metric`` (m). Engines call the dispatch helpers :func:`scenario_num_uniforms`,
:func:`scenario_init`, :func:`scenario_step`, :func:`scenario_spawn` and :func:`scenario_spawn_uniforms`.
Spawns and goals use free cells (:func:`quadswarm_mj.obstacles.free_cells`), one uniform per pick. Pure,
fixed shapes, any batch dims, NumPy or ``jax.numpy``. Rules: docs/model.md ("Scenario interface").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from quadswarm_mj._xp import array_namespace
from quadswarm_mj.obstacles import ObstacleMap, cell_centers, free_cells
from quadswarm_mj.scenarios.base import (
    Scenario,
    ScenarioState,
    clip_goals,
    due,
    empty_state,
    on_event,
    spawn_num_uniforms,
    spawn_state,
    uniform_int,
)
from quadswarm_mj.scenarios.formations import FORMATIONS, formation_offsets, shuffle
from quadswarm_mj.scenarios.registry import register
from quadswarm_mj.scenarios.trajectories import bezier2

#: spawn jitter half-width (m) with obstacles (A.1) and the lowest spawn height (m)
SPAWN_JITTER = 0.1
SPAWN_MIN_Z = 0.75
#: z ranges (m) of the original's placement helpers (A.5)
Z_CELLS = (1.0, 3.0)  # generate_pos_obst_map_2: N distinct free cells
Z_CELL = (0.75, 3.0)  # generate_pos_obst_map: one free cell
Z_SQUARE = (1.5, 3.0)  # max_square_area_center
#: formations of o_swap_goals (Decisions: drawn from the formations that exist)
OBSTACLE_FORMATIONS = ("circle_horizontal", "circle_vertical_xz", "circle_vertical_yz", "sphere", "grid_horizontal",
                       "grid_vertical_xz", "grid_vertical_yz")
_FORMATION_INDEX = np.asarray([FORMATIONS.index(f) for f in OBSTACLE_FORMATIONS])
#: ticks per Bezier segment of o_ep_rand_bezier (6 s at 100 Hz)
BEZIER_TICKS = 600
#: candidate draws per new segment / per dynamic goal jump (the original re-draws until accepted)
BEZIER_TRIES = 32
JUMP_TRIES = 8
JUMP_MAX_DIST = 4.0  # m, o_dynamic_same_goal: a new goal is within this 3D distance of the previous one


def _free(cfg: Any, obstacles: ObstacleMap | None) -> Any:
    if obstacles is None or cfg.obstacles is None:
        raise ValueError("this scenario needs obstacles: EnvConfig(obstacles=ObstacleConfig()) and the column map "
                         "(obstacles=ObstacleMap) passed to init/step")
    return free_cells(cfg.obstacles, obstacles, clearance=cfg.quad.arm + SPAWN_JITTER * math.sqrt(2.0))


def pick_free(free: Any, u: Any) -> Any:
    """K distinct free cells (..., K) int from ``free`` (..., C) bool and uniforms ``u`` (..., K):
    pick k is the floor(u_k * count)-th free cell still unpicked (uniform without replacement)."""
    xp = array_namespace(u, free)
    picks = []
    for k in range(u.shape[-1]):  # static, K = N or 1
        f = free.astype(xp.int32)
        count = xp.sum(f, axis=-1)
        target = xp.minimum(xp.floor(u[..., k] * count), xp.maximum(count - 1, 0)).astype(xp.int32)
        cum = xp.cumsum(f, axis=-1)
        cell = xp.argmax((cum > target[..., None]) & free, axis=-1)  # 0 if none is free
        picks.append(cell)
        free = free & (xp.arange(free.shape[-1]) != cell[..., None])
    return xp.stack(picks, axis=-1).astype(xp.int32)


def cell_points(cfg: Any, cells: Any, uz: Any, zrange: tuple[float, float]) -> Any:
    """(..., K, 3) points (m) at the centres of ``cells`` (..., K) with z = U(zrange) from ``uz``."""
    xp = array_namespace(uz)
    cc = xp.asarray(cell_centers(cfg.obstacles), dtype=uz.dtype)[cells]
    z = zrange[0] + uz * (zrange[1] - zrange[0])
    return xp.concatenate([cc, z[..., None]], axis=-1)


def max_square_cell(cfg: Any, free: Any) -> Any:
    """Flat cell id (...) at the centre of the largest all-free square of cells (A.5, Decisions:
    the classic DP seeded with free = 1): the square ending at (i, j) (bottom-right, row-major
    grid) of the first strict maximum in row-major order has centre (i - (s-1)//2, j - (s-1)//2);
    cell (0, 0) if no cell is free. Vectorized with an integral image over every square size."""
    xp = array_namespace(free)
    gx, gy = cfg.obstacles.grid
    occ = (~free).astype(xp.int32).reshape(free.shape[:-1] + (gy, gx))
    s_int = xp.cumsum(xp.cumsum(occ, axis=-2), axis=-1)
    pad = xp.zeros(free.shape[:-1] + (gy + 1, gx + 1), dtype=xp.int32)
    if xp is np:
        pad[..., 1:, 1:] = s_int
    else:
        pad = pad.at[..., 1:, 1:].set(s_int)
    dp = xp.zeros(occ.shape, dtype=xp.int32)
    ii = np.arange(gy)[:, None]
    jj = np.arange(gx)[None, :]
    for s in range(1, min(gx, gy) + 1):  # static loop over square sizes
        i0, j0 = np.clip(ii - s + 1, 0, None), np.clip(jj - s + 1, 0, None)
        i1, j1 = ii + 1, jj + 1
        total = pad[..., i1, j1] - pad[..., i0, j1] - pad[..., i1, j0] + pad[..., i0, j0]
        fits = (total == 0) & xp.asarray((ii >= s - 1) & (jj >= s - 1))
        dp = xp.where(fits, s, dp)
    flat = dp.reshape(free.shape[:-1] + (gx * gy,))
    best = xp.argmax(flat, axis=-1)
    size = xp.maximum(xp.max(flat, axis=-1), 1)
    i, j = best // gx, best % gx
    half = (size - 1) // 2
    return ((i - half) * gx + (j - half)).astype(xp.int32)


def _ticks(cfg: Any, t: Any) -> Any:
    xp = array_namespace(t)
    return xp.round(t * cfg.control_hz)


def _period_ticks(cfg: Any, u: Any, lo: float = 4.0, hi: float = 6.0) -> Any:
    """int(U(lo, hi) * 100) ticks as seconds (the original's event periods)."""
    xp = array_namespace(u)
    return xp.floor((lo + u * (hi - lo)) * cfg.control_hz) / cfg.control_hz


@dataclass(frozen=True)
class ObstacleScenario(Scenario):
    """Base of the ``o_*`` scenarios; ``step`` keeps the goals (static scenarios)."""

    accepts_obstacles: ClassVar[bool] = True
    requires_obstacles: ClassVar[bool] = True
    approach_goal_metric: ClassVar[float] = 1.0

    def step(self, cfg: Any, state: ScenarioState, t: Any, pos: Any, u: Any,
             obstacles: ObstacleMap | None = None) -> ScenarioState:
        return state


@dataclass(frozen=True)
class ORandom(ObstacleScenario):
    """Each quad's goal: its own distinct free cell, z ~ U(1, 3); never changes.
    Uniforms: init [N cells, N z]."""

    name: str = "o_random"
    approach_goal_metric: ClassVar[float] = 0.5

    def num_uniforms(self, num_quads: int) -> int:
        return 2 * num_quads

    def init(self, cfg: Any, u: Any, obstacles: ObstacleMap | None = None) -> ScenarioState:
        n = cfg.num_quads
        free = _free(cfg, obstacles)
        goals = cell_points(cfg, pick_free(free, u[..., :n]), u[..., n:2 * n], Z_CELLS)
        return empty_state(cfg, u)._replace(goals=clip_goals(cfg, goals))


@dataclass(frozen=True)
class OStaticSameGoal(ObstacleScenario):
    """All quads: the centre of the largest free square, z ~ U(1.5, 3); never changes. Uniforms: [z]."""

    name: str = "o_static_same_goal"

    def num_uniforms(self, num_quads: int) -> int:
        return 1

    def init(self, cfg: Any, u: Any, obstacles: ObstacleMap | None = None) -> ScenarioState:
        xp = array_namespace(u)
        free = _free(cfg, obstacles)
        goal = cell_points(cfg, max_square_cell(cfg, free)[..., None], u[..., :1], Z_SQUARE)
        s = empty_state(cfg, u)
        return s._replace(goals=clip_goals(cfg, xp.zeros_like(s.goals) + goal))


@dataclass(frozen=True)
class ODynamicSameGoal(ObstacleScenario):
    """Shared goal, first at the largest free square's centre (z ~ U(1.5, 3)); at tick 1 and then
    every int(U(4, 6) 100) ticks it jumps to a random free cell, z ~ U(0.75, 3), within 4 m (3D) of
    the previous goal (the first of ``JUMP_TRIES`` candidates that is; else the nearest).
    Uniforms: init [z]; step [JUMP_TRIES x (cell, z), period]."""

    name: str = "o_dynamic_same_goal"

    def num_uniforms(self, num_quads: int) -> int:
        return 2 * JUMP_TRIES + 1

    def init(self, cfg: Any, u: Any, obstacles: ObstacleMap | None = None) -> ScenarioState:
        s = OStaticSameGoal().init(cfg, u[..., :1], obstacles)
        xp = array_namespace(u)
        return s._replace(next_event=xp.full(u.shape[:-1], cfg.control_dt, dtype=u.dtype))

    def step(self, cfg: Any, state: ScenarioState, t: Any, pos: Any, u: Any,
             obstacles: ObstacleMap | None = None) -> ScenarioState:
        xp = array_namespace(u)
        free = _free(cfg, obstacles)

        def jump() -> ScenarioState:
            k = JUMP_TRIES
            cells = xp.stack([pick_free(free, u[..., i:i + 1])[..., 0] for i in range(k)], axis=-1)
            cand = cell_points(cfg, cells, u[..., k:2 * k], Z_CELL)  # (..., K, 3)
            d = xp.sqrt(xp.sum((cand - state.goals[..., :1, :]) ** 2, axis=-1))
            ok = d <= JUMP_MAX_DIST
            idx = xp.where(xp.any(ok, axis=-1), xp.argmax(ok, axis=-1), xp.argmin(d, axis=-1))
            goal = xp.take_along_axis(cand, idx[..., None, None], axis=-2)
            return state._replace(goals=clip_goals(cfg, xp.zeros_like(state.goals) + goal),
                                  next_event=t + _period_ticks(cfg, u[..., 2 * k]))

        return on_event(due(t, state.next_event), jump, state)


@dataclass(frozen=True)
class OSwapGoals(ObstacleScenario):
    """Formation goals (one of ``OBSTACLE_FORMATIONS``, spacing U(0.4, 0.8) m, shuffled) around the
    largest free square's centre (z ~ U(1.5, 3)); every int(U(4, 6) 100) ticks the goals are
    shuffled among the quads. Uniforms: init [type, spacing, N shuffle, z, period]; step [N, period]."""

    name: str = "o_swap_goals"
    spacing: tuple[float, float] = (0.4, 0.8)

    def num_uniforms(self, num_quads: int) -> int:
        return num_quads + 4

    def init(self, cfg: Any, u: Any, obstacles: ObstacleMap | None = None) -> ScenarioState:
        xp = array_namespace(u)
        n = cfg.num_quads
        free = _free(cfg, obstacles)
        kind = xp.asarray(_FORMATION_INDEX)[uniform_int(u[..., 0], len(OBSTACLE_FORMATIONS))]
        spacing = self.spacing[0] + u[..., 1] * (self.spacing[1] - self.spacing[0])
        offsets = shuffle(formation_offsets(n, kind, spacing).astype(u.dtype), u[..., 2:2 + n])
        centre = cell_points(cfg, max_square_cell(cfg, free)[..., None], u[..., 2 + n:3 + n], Z_SQUARE)
        s = empty_state(cfg, u)
        return s._replace(goals=clip_goals(cfg, centre + offsets), offsets=offsets,
                          next_event=_period_ticks(cfg, u[..., 3 + n]))

    def step(self, cfg: Any, state: ScenarioState, t: Any, pos: Any, u: Any,
             obstacles: ObstacleMap | None = None) -> ScenarioState:
        n = cfg.num_quads

        def swap() -> ScenarioState:
            return state._replace(goals=shuffle(state.goals, u[..., :n]), offsets=shuffle(state.offsets, u[..., :n]),
                                  next_event=t + _period_ticks(cfg, u[..., n]))

        return on_event(due(t, state.next_event), swap, state)


@dataclass(frozen=True)
class OEpRandBezier(ObstacleScenario):
    """Shared goal starting at a random free cell (z ~ U(0.75, 3)) and following quadratic Bezier
    segments of 600 ticks: at tick 1 and every multiple of 600 a segment (goal, p1, p2) starts with
    p_k = goal + s unit(a_k), a_k ~ U(-[L/2, W/2, 3], [L/2, W/2, 3]) (Decisions: the intended x, y, z),
    s in {2, 3, 4, 5} shared, accepted when both points are strictly inside x, y in the room shrunk by
    0.5 m and z in (2, 2.5) (the first of ``BEZIER_TRIES`` candidate triples; if none, each point is
    the first accepted among the candidates, else clipped into that box). At other ticks the goal is
    ``curve[tick % 600]`` with ``curve = B(linspace(0, 1, 600))``.
    Uniforms: init [cell, z]; step [BEZIER_TRIES x (a 3, b 3, s 1)].
    ``aux``: [0:3] p0, [3:6] p1, [6:9] p2 (m)."""

    name: str = "o_ep_rand_bezier"
    z_box: tuple[float, float] = (2.0, 2.5)

    def num_uniforms(self, num_quads: int) -> int:
        return max(2, 7 * BEZIER_TRIES)

    def init(self, cfg: Any, u: Any, obstacles: ObstacleMap | None = None) -> ScenarioState:
        xp = array_namespace(u)
        free = _free(cfg, obstacles)
        goal = cell_points(cfg, pick_free(free, u[..., :1]), u[..., 1:2], Z_CELL)[..., 0, :]
        goal = clip_goals(cfg, goal)
        s = empty_state(cfg, u)
        aux = xp.concatenate([goal, goal, goal, s.aux[..., 9:]], axis=-1)
        return s._replace(goals=xp.zeros_like(s.goals) + goal[..., None, :], aux=aux,
                          next_event=xp.full(u.shape[:-1], cfg.control_dt, dtype=u.dtype))

    def _box(self, cfg: Any, xp: Any, dtype: Any) -> tuple[Any, Any]:
        lo = (cfg.room_low[0] + 0.5, cfg.room_low[1] + 0.5, self.z_box[0])
        hi = (cfg.room_high[0] - 0.5, cfg.room_high[1] - 0.5, self.z_box[1])
        return xp.asarray(lo, dtype=dtype), xp.asarray(hi, dtype=dtype)

    def _segment(self, cfg: Any, goal: Any, u: Any) -> tuple[Any, Any]:
        xp = array_namespace(u)
        k = BEZIER_TRIES
        uu = u[..., :7 * k].reshape(u.shape[:-1] + (k, 7))
        half = xp.asarray((cfg.room_size[0] / 2, cfg.room_size[1] / 2, 3.0), dtype=u.dtype)
        a = (2.0 * uu[..., 0:3] - 1.0) * half
        b = (2.0 * uu[..., 3:6] - 1.0) * half
        s = (2 + uniform_int(uu[..., 6], 4)).astype(u.dtype)[..., None]

        def unit(v: Any) -> Any:
            return v / xp.maximum(xp.sqrt(xp.sum(v * v, axis=-1, keepdims=True)), 1e-12)

        g = goal[..., None, :]
        p1, p2 = g + s * unit(a), g + s * unit(b)
        lo, hi = self._box(cfg, xp, u.dtype)

        def inside(p: Any) -> Any:
            return xp.all((p > lo) & (p < hi), axis=-1)

        def first(p: Any, ok: Any, fallback: Any) -> Any:
            idx = xp.argmax(ok, axis=-1)
            sel = xp.take_along_axis(p, idx[..., None, None], axis=-2)[..., 0, :]
            return xp.where(xp.any(ok, axis=-1)[..., None], sel, fallback)

        ok1, ok2 = inside(p1), inside(p2)
        both = ok1 & ok2
        q1 = first(p1, ok1, xp.clip(p1[..., 0, :], lo, hi))
        q2 = first(p2, ok2, xp.clip(p2[..., 0, :], lo, hi))
        any_both = xp.any(both, axis=-1)[..., None]
        return xp.where(any_both, first(p1, both, q1), q1), xp.where(any_both, first(p2, both, q2), q2)

    def step(self, cfg: Any, state: ScenarioState, t: Any, pos: Any, u: Any,
             obstacles: ObstacleMap | None = None) -> ScenarioState:
        xp = array_namespace(u)
        tick = _ticks(cfg, t)

        def new_segment() -> ScenarioState:
            goal = state.goals[..., 0, :]
            p1, p2 = self._segment(cfg, goal, u)
            aux = xp.concatenate([goal, p1, p2, state.aux[..., 9:]], axis=-1)
            nxt = (xp.floor(tick / BEZIER_TICKS) + 1.0) * BEZIER_TICKS / cfg.control_hz
            return state._replace(aux=aux, goal_vel=xp.zeros_like(state.goal_vel), next_event=nxt + 0.0 * t)

        event = due(t, state.next_event)
        s = on_event(event, new_segment, state)
        a = s.aux
        k = xp.mod(tick, BEZIER_TICKS)
        tau = k / (BEZIER_TICKS - 1)
        p, dp = bezier2(a[..., 0:3], a[..., 3:6], a[..., 6:9], tau + 0.0 * a[..., 0])
        moving = (~event) & (tick > 1)
        goals = xp.where(moving[..., None, None], xp.zeros_like(s.goals) + clip_goals(cfg, p)[..., None, :], s.goals)
        vel = dp * cfg.control_hz / (BEZIER_TICKS - 1)
        goal_vel = xp.where(moving[..., None, None], xp.zeros_like(s.goals) + vel[..., None, :], 0.0 * s.goals)
        return s._replace(goals=goals, goal_vel=goal_vel)


O_RANDOM = register(ORandom())
O_STATIC_SAME_GOAL = register(OStaticSameGoal())
O_DYNAMIC_SAME_GOAL = register(ODynamicSameGoal())
O_SWAP_GOALS = register(OSwapGoals())
O_EP_RAND_BEZIER = register(OEpRandBezier())

# ------------------------------------------------------------------------------ dispatch helpers


def accepts_obstacles(scn: Scenario) -> bool:
    return bool(getattr(scn, "accepts_obstacles", False))


def scenario_num_uniforms(scn: Scenario, cfg: Any) -> int:
    """Uniforms one ``init``/``step`` of ``scn`` consumes under ``cfg`` (``mix`` depends on obstacles)."""
    if getattr(scn, "name", "") == "mix":
        return scn.num_uniforms(cfg.num_quads, with_obstacles=cfg.obstacles is not None)  # type: ignore[call-arg]
    return scn.num_uniforms(cfg.num_quads)


def scenario_init(scn: Scenario, cfg: Any, u: Any, obstacles: ObstacleMap | None = None) -> ScenarioState:
    """``scn.init`` with the map for obstacle-aware scenarios."""
    return scn.init(cfg, u, obstacles=obstacles) if accepts_obstacles(scn) else scn.init(cfg, u)  # type: ignore[call-arg]


def scenario_step(scn: Scenario, cfg: Any, state: ScenarioState, t: Any, pos: Any, u: Any,
                  obstacles: ObstacleMap | None = None) -> ScenarioState:
    """``scn.step`` with the map for obstacle-aware scenarios."""
    if accepts_obstacles(scn):
        return scn.step(cfg, state, t, pos, u, obstacles=obstacles)  # type: ignore[call-arg]
    return scn.step(cfg, state, t, pos, u)


def obstacle_spawn_num_uniforms(num_quads: int) -> int:
    return 6 * num_quads


def obstacle_spawn_state(cfg: Any, obstacles: ObstacleMap, u: Any) -> dict[str, Any]:
    """Start state with obstacles (A.1, A.5): N distinct free cells, z ~ U(1, 3), plus
    U(-0.1, 0.1)^3 jitter, z >= 0.75 (and <= room height - 0.5), yaw facing within 60 degrees of the
    room centre. ``u`` (..., 6 N) uniforms: [N cells, N z, 3 N jitter, N yaw]. Returns ``pos``
    (..., N, 3) m and ``yaw`` (..., N) rad."""
    xp = array_namespace(u)
    n = cfg.num_quads
    free = _free(cfg, obstacles)
    pos = cell_points(cfg, pick_free(free, u[..., :n]), u[..., n:2 * n], Z_CELLS)
    jit = u[..., 2 * n:5 * n].reshape(u.shape[:-1] + (n, 3))
    pos = pos + (2.0 * jit - 1.0) * SPAWN_JITTER
    hi_z = max(SPAWN_MIN_Z, cfg.room_size[2] - 0.5)
    pos = xp.concatenate([pos[..., :2], xp.clip(pos[..., 2:], SPAWN_MIN_Z, hi_z)], axis=-1)
    to_center = xp.arctan2(-pos[..., 1], -pos[..., 0])
    yaw = to_center + (u[..., 5 * n:6 * n] * 2.0 - 1.0) * (xp.pi / 3.0)
    return {"pos": pos, "yaw": yaw}


def scenario_spawn_uniforms(cfg: Any) -> int:
    """Uniforms :func:`scenario_spawn` consumes under ``cfg``."""
    n = cfg.num_quads
    return obstacle_spawn_num_uniforms(n) if cfg.obstacles is not None else spawn_num_uniforms(n)


def scenario_spawn(cfg: Any, goals: Any, u: Any, obstacles: ObstacleMap | None = None) -> dict[str, Any]:
    """Spawn positions and yaws: :func:`obstacle_spawn_state` when obstacles are on (any scenario),
    else ``base.spawn_state`` (goal + U(-2, 2)^3)."""
    if cfg.obstacles is not None:
        return obstacle_spawn_state(cfg, obstacles, u)
    return spawn_state(cfg, goals, u)


def approach_threshold(scn: Scenario, cfg: Any, state: ScenarioState, default: float = 0.5) -> Any:
    """Per-world success distance (m) of A.4: ``approach_goal_metric`` of the scenario (``mix``
    with obstacles: of the drawn sub-scenario; scenarios without one: ``default``)."""
    xp = array_namespace(state.goals)
    if getattr(scn, "name", "") == "mix" and cfg.obstacles is not None:
        from quadswarm_mj.scenarios.mix import OBSTACLE_MIX_CHOICES

        thr = xp.asarray([O_BY_NAME[c].approach_goal_metric for c in OBSTACLE_MIX_CHOICES],
                         dtype=state.goals.dtype)
        return xp.where(state.kind >= 0, thr[xp.clip(state.kind, 0, len(OBSTACLE_MIX_CHOICES) - 1)], default)
    return xp.full(state.kind.shape, getattr(scn, "approach_goal_metric", default), dtype=state.goals.dtype)


O_BY_NAME = {s.name: s for s in (O_RANDOM, O_STATIC_SAME_GOAL, O_DYNAMIC_SAME_GOAL, O_SWAP_GOALS, O_EP_RAND_BEZIER)}
