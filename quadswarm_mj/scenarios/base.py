"""Scenario machinery: fixed-shape state, the Scenario base class, spawning.

A scenario is a small frozen object with two pure functions over a fixed-shape :class:`ScenarioState`
(leading batch dims allowed, NumPy or ``jax.numpy``): ``init(cfg, u)`` and ``step(cfg, state, t, pos, u)``,
``u`` U(0, 1) draws, ``t`` s since the episode start, ``pos`` (..., N, 3) m; goals in the world frame (m),
``goal_vel`` m/s. Events fire at the first step with ``t >= next_event - EVENT_EPS`` and are selected per
world with ``where`` (:func:`on_event`, :func:`select_state`), so every scenario runs under
``jax.jit``/``jax.vmap`` with any batch shape. The interface in full: docs/model.md ("Scenario interface").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from quadswarm_mj._xp import array_namespace, is_jax_array

#: Length of the float scratch vector ``ScenarioState.aux``.
AUX_SIZE = 24
#: Goals keep this distance (m) from walls and ceiling, and at least this height.
GOAL_MARGIN = 0.5
MIN_GOAL_Z = 0.25
#: s; an event is due when t >= next_event - EVENT_EPS (absorbs rounding of t = steps * dt).
EVENT_EPS = 1e-4
#: s; range of the random period of the U(4, 6) s events (SPEC §10).
EVENT_PERIOD = (4.0, 6.0)


class ScenarioState(NamedTuple):
    """Fixed-shape scenario state shared by every scenario (so ``mix`` can switch among them)."""

    goals: Any  # (..., N, 3) m, world frame
    goal_vel: Any  # (..., N, 3) m/s
    offsets: Any  # (..., N, 3) formation offsets or stored goals, scenario-specific
    aux: Any  # (..., AUX_SIZE) scratch floats, scenario-specific
    next_event: Any  # (...,) s, time of the next scheduled goal change (inf if none)
    kind: Any  # (...,) int32, index into MIX_CHOICES of the active sub-scenario (mix), else -1
    slots: Any  # (..., N) int32, scenario-specific per-quad indices (run_away: formation slot)


@dataclass(frozen=True)
class Scenario:
    """Base class; subclasses override ``num_uniforms``, ``init`` and ``step``."""

    name: str = "base"

    def num_uniforms(self, num_quads: int) -> int:
        """How many U(0, 1) draws one call of ``init`` or ``step`` consumes."""
        return 4

    def init(self, cfg: Any, u: Any) -> ScenarioState:  # pragma: no cover - abstract
        raise NotImplementedError

    def step(self, cfg: Any, state: ScenarioState, t: Any, pos: Any, u: Any) -> ScenarioState:
        return state


def empty_state(cfg: Any, u: Any) -> ScenarioState:
    """A state with all goals at the formation centre, zero velocity and no events."""
    xp = array_namespace(u)
    batch = u.shape[:-1]
    n = cfg.num_quads
    center = xp.asarray(cfg.formation_center, dtype=u.dtype)
    goals = xp.zeros(batch + (n, 3), dtype=u.dtype) + center
    return ScenarioState(goals=goals, goal_vel=xp.zeros_like(goals), offsets=xp.zeros_like(goals),
                         aux=xp.zeros(batch + (AUX_SIZE,), dtype=u.dtype),
                         next_event=xp.full(batch, float("inf"), dtype=u.dtype),
                         kind=xp.full(batch, -1, dtype=xp.int32),
                         slots=xp.zeros(batch + (n,), dtype=xp.int32) + xp.arange(n, dtype=xp.int32))


def room_bounds(cfg: Any, margin: float = GOAL_MARGIN) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(low, high) corners (m) of the region goals may occupy: the room shrunk by ``margin`` at
    the walls and ceiling and raised to at least ``MIN_GOAL_Z`` above the floor. In a room too
    small for the margins an axis collapses to the middle of its allowed span, so the region is
    never empty and always inside the room."""
    lo, hi = cfg.room_low, cfg.room_high
    low = [lo[0] + margin, lo[1] + margin, lo[2] + MIN_GOAL_Z]
    high = [hi[0] - margin, hi[1] - margin, hi[2] - margin]
    for i in range(3):
        if low[i] > high[i]:
            mid = min(max(0.5 * (low[i] + high[i]), lo[i]), hi[i])
            if i == 2:  # keep the floor clearance if the room allows it
                mid = min(max(lo[2] + MIN_GOAL_Z, lo[2] + 0.5 * (hi[2] - lo[2])), hi[2])
            low[i] = high[i] = mid
    return tuple(low), tuple(high)


def clip_goals(cfg: Any, goals: Any) -> Any:
    """Clip goals (..., 3) into the room with the goal margin."""
    xp = array_namespace(goals)
    low, high = room_bounds(cfg)
    return xp.clip(goals, xp.asarray(low, dtype=goals.dtype), xp.asarray(high, dtype=goals.dtype))


def inner_bounds(cfg: Any, inset: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """:func:`room_bounds` shrunk by ``inset`` m on every side (an axis too short collapses to
    its middle)."""
    low, high = room_bounds(cfg)
    lo = [a + inset for a in low]
    hi = [b - inset for b in high]
    for i in range(3):
        if lo[i] > hi[i]:
            lo[i] = hi[i] = 0.5 * (low[i] + high[i])
    return tuple(lo), tuple(hi)


def uniform_point(cfg: Any, u3: Any, inset: float = 0.0) -> Any:
    """Map (..., 3) uniforms to a point uniform in :func:`inner_bounds` (``cfg``, ``inset``) (m)."""
    xp = array_namespace(u3)
    low, high = inner_bounds(cfg, inset)
    lo = xp.asarray(low, dtype=u3.dtype)
    hi = xp.asarray(high, dtype=u3.dtype)
    return lo + u3 * (hi - lo)


def uniform_int(u: Any, n: int) -> Any:
    """Map U(0, 1) draws (...) to ints uniform in {0, ..., n - 1} (int32); n >= 1 is static."""
    xp = array_namespace(u)
    return xp.clip(xp.floor(u * n), 0, max(n - 1, 0)).astype(xp.int32)


def event_period(u: Any, period: tuple[float, float] = EVENT_PERIOD) -> Any:
    """Map U(0, 1) draws to a random event period (s), uniform in ``period``."""
    return period[0] + u * (period[1] - period[0])


def due(t: Any, next_event: Any) -> Any:
    """True (batch shape) where the scheduled event is due at time ``t`` (s)."""
    return t >= next_event - EVENT_EPS


def select_state(cond: Any, new: ScenarioState, old: ScenarioState) -> ScenarioState:
    """Field by field ``new`` where ``cond`` (batch shape bool) else ``old``."""
    xp = array_namespace(new.goals, old.goals, cond)

    def sel(a: Any, b: Any) -> Any:
        c = cond.reshape(cond.shape + (1,) * (a.ndim - cond.ndim))
        return xp.where(c, a, b)

    return ScenarioState(*(sel(a, b) for a, b in zip(new, old)))


def on_event(cond: Any, make_new: Callable[[], ScenarioState], old: ScenarioState) -> ScenarioState:
    """``make_new()`` in the worlds where ``cond`` (batch shape bool) holds, ``old`` elsewhere.

    Under JAX (``cond`` a traced array) ``make_new`` is always evaluated and selected with
    ``where``. On NumPy, where ``cond`` is concrete, ``make_new`` is skipped when no world has an
    event: the result is the same, without computing a discarded event every control step.
    """
    if not is_jax_array(cond) and not bool(np.any(cond)):
        return old
    return select_state(cond, make_new(), old)


def place_formation(cfg: Any, center: Any, offsets: Any) -> tuple[Any, Any]:
    """Goals (..., N, 3) of a formation with ``offsets`` (..., N, 3) around ``center`` (..., 3), m.

    The centre is moved (as little as possible, per axis) so that the whole formation fits in
    :func:`room_bounds`; a formation larger than the room on some axis is centred on that axis
    and clipped. Returns ``(goals, center_used)``.
    """
    xp = array_namespace(center, offsets)
    low, high = room_bounds(cfg)
    lo = xp.asarray(low, dtype=offsets.dtype)
    hi = xp.asarray(high, dtype=offsets.dtype)
    omin = xp.min(offsets, axis=-2)
    omax = xp.max(offsets, axis=-2)
    fits = (omax - omin) <= (hi - lo)
    c_fit = xp.minimum(xp.maximum(center, lo - omin), hi - omax)
    c_mid = 0.5 * (lo + hi) - 0.5 * (omin + omax)
    c = xp.where(fits, c_fit, c_mid)
    return clip_goals(cfg, c[..., None, :] + offsets), c


def spawn_num_uniforms(num_quads: int) -> int:
    return 4 * num_quads


def spawn_state(cfg: Any, goals: Any, u: Any) -> dict[str, Any]:
    """Start state near the goals (SPEC §9): goal + U(-2, 2)^3, z >= 0.75, inside the room,
    at rest, yaw facing within 60 degrees of the room centre.

    ``u`` is (..., 4 N) uniforms. Returns ``pos`` (..., N, 3) and ``yaw`` (..., N) in rad.
    """
    xp = array_namespace(u)
    n = cfg.num_quads
    uu = u.reshape(u.shape[:-1] + (n, 4))
    pos = goals + (uu[..., :3] * 4.0 - 2.0)
    lo, hi = cfg.room_low, cfg.room_high
    m = 0.5
    low = xp.asarray((lo[0] + m, lo[1] + m, max(0.75, lo[2])), dtype=u.dtype)
    high = xp.asarray((hi[0] - m, hi[1] - m, max(0.75, hi[2] - m)), dtype=u.dtype)
    pos = xp.clip(pos, low, high)
    to_center = xp.arctan2(-pos[..., 1], -pos[..., 0])
    yaw = to_center + (uu[..., 3] * 2.0 - 1.0) * (xp.pi / 3.0)
    return {"pos": pos, "yaw": yaw}
