"""Obstacles (SPEC_obstacles A.1-A.4): column maps, distance features, contacts, response, metrics.

Columns are vertical cylinders from floor to ceiling; everything here is 2D (x, y), world frame, SI units.
A world holds ``M_max = ObstacleConfig.slots`` column slots with a validity mask (static shapes under
``jax.jit``); an :class:`ObstacleMap` is ``centres`` (..., M_max, 2) m, ``valid`` (..., M_max) bool and
``radius`` (...,) m. Pure functions over NumPy or ``jax.numpy`` (leading batch dims allowed); random draws
come in as arrays (:func:`map_draw_spec`, :func:`response_draw_spec`). The engines' stage functions are
:func:`obstacle_step` and :func:`obstacle_features`. Cell indexing and how the engines wire these in:
docs/model.md ("Obstacles").
"""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from quadswarm_mj._xp import array_namespace, safe_normalize
from quadswarm_mj.obstacle_config import ObstacleConfig
from quadswarm_mj.random_draws import DrawSpec, Normal, Uniform
from quadswarm_mj.spatial import norm_last

if TYPE_CHECKING:  # annotations only: quadswarm_mj.config imports the scenarios, which import this module
    from quadswarm_mj.config import EnvConfig

#: spacing (m) of the 3 x 3 grid of sample points of the distance features (A.2)
SDF_RESOLUTION = 0.1
NUM_FEATURES = 9
CENTRE_FEATURE = 4  # the quad's own point among the 9 (x-major 3 x 3 grid)
#: distance (m) used when a world has no column (the original's placeholder; the radius is subtracted)
NO_OBSTACLE_DIST = 100.0
NEAR_RANGE = 1.0  # m: feature_form="near" sees columns whose surface is closer than this
NEAR_MAX = 2.0  # its proximity's cap (1 at the surface; a quad's centre is never 1 m inside a column)
#: normal of a quad exactly on a column axis: divided by this instead of 0 (A.3 step 1)
NORMAL_EPS = 1e-5
#: decay range U(low, high) of the obstacle response (A.3 step 4); the inside branch uses 1.0
OBSTACLE_DECAY = (0.2, 0.8)
#: omega kick magnitude range (rad/s) of the obstacle response (A.3 step 5)
OBSTACLE_KICK = (0.5 * math.pi, math.pi)
#: std of the two Gaussian parts of the direction noise, and the number of tries (A.3 step 3)
ETA_STDS = (0.1, 0.05)
ETA_TRIES = 3
#: grace period (s) of the obstacle metrics (A.4: tick >= 150 at 100 Hz)
GRACE_S = 1.5


class ObstacleMap(NamedTuple):
    """Columns of one or more worlds (see the module docstring)."""

    centres: Any  # (..., M_max, 2) m
    valid: Any  # (..., M_max) bool
    radius: Any  # (...,) m


# ------------------------------------------------------------------------------------ the map


@functools.lru_cache(maxsize=32)
def cell_centers(ocfg: ObstacleConfig) -> np.ndarray:
    """(gx * gy, 2) centres (m) of the cells, indexed by flat cell id (module docstring)."""
    gx, gy = ocfg.grid
    k = np.arange(gx * gy)
    r, c = k // gx, k % gx
    out = np.stack([(c + 0.5 - gx / 2) * ocfg.cell, (gy - 1 - r + 0.5 - gy / 2) * ocfg.cell], axis=-1)
    out.setflags(write=False)
    return out


def map_draw_spec(ocfg: ObstacleConfig) -> DrawSpec:
    """Uniforms of one map: one per cell (the permutation that picks the cells without replacement),
    one for the density and one for the size (used only when randomized). These are always drawn
    from the generator (they are not noise: ``without_noise`` keeps random maps)."""
    return {"cells": Uniform(0.0, 1.0, (ocfg.num_cells,)), "density": Uniform(0.0, 1.0), "size": Uniform(0.0, 1.0)}


def _pick(xp: Any, u: Any, values: tuple[float, ...]) -> Any:
    """values[int(u * len)] for uniforms u (...), as an array."""
    idx = xp.clip(xp.floor(u * len(values)), 0, len(values) - 1).astype(xp.int32)
    return xp.asarray(np.asarray(values, dtype=np.float64))[idx], idx


def generate_map(ocfg: ObstacleConfig, draws: dict[str, Any]) -> tuple[ObstacleMap, Any]:
    """A random map from :func:`map_draw_spec` draws (A.1, A.6): ``int(cells * density)`` distinct
    cells, uniformly without replacement (the first cells of the permutation sorting ``cells``),
    one column at each cell centre. Returns ``(map, cell_ids)`` with ``cell_ids`` (..., M_max) int.
    """
    u = draws["cells"]
    xp = array_namespace(u)
    m = ocfg.slots
    perm = xp.argsort(u, axis=-1)[..., :m]
    batch = u.shape[:-1]
    if ocfg.density_random:
        counts = np.asarray([ocfg.num_columns(d) for d in ocfg.density_values])
        _, i = _pick(xp, draws["density"], ocfg.density_values)
        count = xp.asarray(counts)[i]
    else:
        count = xp.full(batch, ocfg.num_columns(), dtype=xp.int32)
    if ocfg.size_random:
        size, _ = _pick(xp, draws["size"], ocfg.size_values)
        radius = (0.5 * size).astype(u.dtype)
    else:
        radius = xp.full(batch, 0.5 * ocfg.size, dtype=u.dtype)
    valid = xp.arange(m) < count[..., None]
    centres = xp.asarray(cell_centers(ocfg), dtype=u.dtype)[perm]
    return ObstacleMap(centres=centres, valid=valid, radius=radius), perm


def map_from_centres(ocfg: ObstacleConfig, centres: Any, radius: Any = None, xp: Any = np) -> ObstacleMap:
    """A map with the given columns (M, 2) m (M <= M_max), padded to the M_max slots; ``radius``
    defaults to ``ocfg.size / 2``. Used by ``reset(options={"obstacles": ...})``."""
    c = xp.asarray(centres, dtype=xp.float64 if xp is np else None)
    if c.ndim != 2 or c.shape[-1] not in (2, 3):
        raise ValueError(f"obstacles must be an (M, 2) array of column centres (x, y) in m, got shape {c.shape}")
    c = c[:, :2]
    m, slots = c.shape[0], ocfg.slots
    if m > slots:
        raise ValueError(f"obstacles: {m} columns given, more than the {slots} column slots per world "
                         f"(raise ObstacleConfig.max_columns, at most {ocfg.num_cells})")
    if xp is np and not np.all(np.isfinite(c)):
        raise ValueError("obstacles must hold finite column centres (m)")
    pad = xp.zeros((slots - m, 2), dtype=c.dtype)
    full = xp.concatenate([c, pad], axis=0)
    valid = xp.arange(slots) < m
    r = 0.5 * ocfg.size if radius is None else radius
    return ObstacleMap(centres=full, valid=valid, radius=xp.asarray(r, dtype=full.dtype))


def reset_map(ocfg: ObstacleConfig, draws: dict[str, Any], centres: Any = None, xp: Any = np) -> ObstacleMap:
    """The map of a reset: the given columns ``centres`` (M, 2) m (``reset(options={"obstacles": ...})``,
    radius ``size / 2``), else a random map from ``draws`` (:func:`map_draw_spec`, any batch dims)."""
    if centres is not None:
        return map_from_centres(ocfg, centres, xp=xp)
    return generate_map(ocfg, draws)[0]


def active_centres(omap: ObstacleMap) -> np.ndarray:
    """(M, 2) centres of the valid columns of one world (NumPy; for ``info["obstacles"]``)."""
    return np.asarray(omap.centres)[np.asarray(omap.valid)]


def free_cells(ocfg: ObstacleConfig, omap: ObstacleMap, clearance: float = 0.0) -> Any:
    """(..., gx * gy) bool: cells whose centre is farther than ``radius + clearance`` (m) from
    every column axis (2D). On a generated map these are the cells without a column."""
    xp = array_namespace(omap.centres)
    cc = xp.asarray(cell_centers(ocfg), dtype=omap.centres.dtype)
    d = _dist2d(xp, cc[..., :, None, :], omap.centres[..., None, :, :])  # (..., C, M)
    d = xp.where(omap.valid[..., None, :], d, xp.inf)
    return xp.min(d, axis=-1) > (omap.radius[..., None] + clearance)


def _dist2d(xp: Any, a: Any, b: Any) -> Any:
    d = a - b
    return xp.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1])


# ------------------------------------------------------------------------------- features


def obstacle_grid(pos: Any, centres: Any, valid: Any) -> Any:
    """(..., N, 3, 3, M) squared xy distances (m^2) from the 3 x 3 sample points ``p + (dx, dy)`` of
    each quad (A.2; dx, dy in (-0.1, 0, 0.1) m, x-major) to the valid column axes (inf for unused
    slots). The centre point [..., 1, 1, :] is the quad itself: :func:`hits_from_grid` gives the
    contact test from it, :func:`features_from_grid` the 9 features (one grid for both)."""
    xp = array_namespace(pos, centres)
    # separable: squared x and y distances per offset (..., N, 3, M), summed to (..., N, 3, 3, M)
    off = xp.asarray(np.array([-SDF_RESOLUTION, 0.0, SDF_RESOLUTION]), dtype=pos.dtype)[:, None]
    dx = (pos[..., :, None, None, 0] + off) - centres[..., None, None, :, 0]
    dy = (pos[..., :, None, None, 1] + off) - centres[..., None, None, :, 1]
    dx2 = xp.where(valid[..., None, None, :], dx * dx, xp.inf)  # invalid slots: never the nearest
    return dx2[..., :, :, None, :] + (dy * dy)[..., :, None, :, :]


def features_from_grid(d2: Any, radius: Any) -> Any:
    """The 9 features (..., N, 9) from :func:`obstacle_grid` (see :func:`obstacle_features`)."""
    xp = array_namespace(d2)
    # the same values as the 9 points' distances (sqrt is monotonic: sqrt of the min = min of the sqrt)
    dmin = xp.sqrt(xp.min(d2, axis=-1)).reshape(d2.shape[:-3] + (NUM_FEATURES,))  # x-major: 3 i + j
    dmin = xp.where(xp.isinf(dmin), NO_OBSTACLE_DIST, dmin)
    r = xp.asarray(radius, dtype=d2.dtype)
    return dmin - r[..., None, None]


def hits_from_grid(d2: Any, radius: Any, arm: float) -> Any:
    """:func:`contact_hits` from :func:`obstacle_grid` (the same comparison on the same values)."""
    xp = array_namespace(d2)
    lim = arm + xp.asarray(radius, dtype=d2.dtype)
    return d2[..., 1, 1, :] <= (lim * lim)[..., None, None]


def obstacle_features(pos: Any, centres: Any, valid: Any, radius: Any) -> Any:
    """The 9 distance features (..., N, 9) of each quad (A.2): at the 3 x 3 xy points
    ``p + (dx, dy)``, dx, dy in (-0.1, 0, 0.1) m, x-major (index 3 i + j, i over dx, j over dy; the
    centre is index 4), the 2D distance to the nearest valid column axis minus the radius (negative
    inside a column; ``100 - radius`` without any column). ``pos`` (..., N, 3) are the TRUE
    positions (m, world frame; no sensor noise); ``centres`` (..., M, 2), ``valid`` (..., M),
    ``radius`` (...,). No clipping. Goes LAST in each quad's observation.
    """
    return features_from_grid(obstacle_grid(pos, centres, valid), radius)


def observed_features(features: Any, form: str, near_range: float = NEAR_RANGE, speed_reach: float = 0.0,
                      vel: Any = None) -> Any:
    """The features as observed (``ObstacleConfig.feature_form``): ``"grid"`` returns them unchanged;
    ``"slopes"`` keeps the centre distance (m, index 4) and replaces each other point's distance by its
    difference from the centre divided by the 0.1 m grid step (dimensionless, within +-sqrt(2): the
    distance to the nearest column is 1-Lipschitz). An invertible linear map: the same information,
    but the direction to the column no longer hides in ~1 % differences of nine nearly equal inputs.
    ``"near"`` is bounded and local: the centre is the proximity ``w = clip(1 - d / reach, 0, NEAR_MAX)``
    (0 from ``reach`` m away, 1 at the surface) and the slopes are multiplied by ``w``, so in open space all
    9 are 0 and a policy's hover point does not depend on how far the nearest column is. The reach (m) is
    ``near_range + speed_reach * closing``, ``closing`` the speed (m/s) of ``vel`` (..., N, 3) towards the
    nearest column (:func:`closing_speed`; ``speed_reach`` in s, 0: a fixed reach and ``vel`` unused)."""
    if form == "grid":
        return features
    xp = array_namespace(features)
    centre = features[..., CENTRE_FEATURE:CENTRE_FEATURE + 1]
    slopes = (features - centre) / SDF_RESOLUTION
    if form == "near":
        reach = near_range
        if speed_reach:
            if vel is None:
                raise ValueError("observed_features: speed_reach > 0 needs the velocities vel (..., N, 3) (m/s)")
            reach = near_range + speed_reach * closing_speed(features, vel)[..., None]
        centre = xp.clip(1.0 - centre / reach, 0.0, NEAR_MAX)
        slopes = slopes * centre
    return xp.concatenate([slopes[..., :CENTRE_FEATURE], centre, slopes[..., CENTRE_FEATURE + 1:]], axis=-1)


def closing_speed(features: Any, vel: Any) -> Any:
    """(..., N) speed (m/s) towards the nearest column, ``max(-v_xy . grad d, 0)``, from the 9 features
    (..., N, 9) (m) and the velocities (..., N, 3) (m/s); grad d is the features' central differences over the
    3 x 3 grid (the unit vector away from the nearest column, up to the grid's resolution)."""
    xp = array_namespace(features, vel)
    gx = (features[..., 7] - features[..., 1]) / (2.0 * SDF_RESOLUTION)  # x-major: index 3 i + j
    gy = (features[..., 5] - features[..., 3]) / (2.0 * SDF_RESOLUTION)
    return xp.maximum(-(vel[..., 0] * gx + vel[..., 1] * gy), 0.0)


def feature_bounds(cfg: EnvConfig) -> tuple[np.ndarray, np.ndarray]:
    """Finite (low, high) float32 bounds (9,) of the observed features: +- max(room diagonal + 1 m,
    100 m) for a distance, so no reachable value (nor the no-column placeholder) is ever clipped, and
    +-1.5 for a slope (``feature_form="slopes"``, whose slopes lie within +-sqrt(2)); ``"near"``: +-NEAR_MAX
    for its proximity, +-1.5 NEAR_MAX for a weighted slope."""
    b = max(math.sqrt(sum(x * x for x in cfg.room_size)) + 1.0, NO_OBSTACLE_DIST)
    hi = np.full(NUM_FEATURES, b, dtype=np.float32)
    form = cfg.obstacles.feature_form if cfg.obstacles is not None else "grid"
    if form == "slopes":
        hi[:] = 1.5
        hi[CENTRE_FEATURE] = b
    elif form == "near":
        hi[:] = 1.5 * NEAR_MAX
        hi[CENTRE_FEATURE] = NEAR_MAX
    return -hi, hi


# ------------------------------------------------------------------------------ detection


def contact_hits(pos: Any, centres: Any, valid: Any, radius: Any, arm: float) -> Any:
    """(..., N, M) bool: quad n touches valid column m, ``||p_xy - o_xy|| <= arm + radius`` (at any
    height; compared squared)."""
    xp = array_namespace(pos, centres)
    dx = pos[..., :, None, 0] - centres[..., None, :, 0]
    dy = pos[..., :, None, 1] - centres[..., None, :, 1]
    lim = arm + xp.asarray(radius, dtype=pos.dtype)
    return ((dx * dx + dy * dy) <= (lim * lim)[..., None, None]) & valid[..., None, :]


def first_hit(hit: Any, centres: Any) -> tuple[Any, Any]:
    """``index`` (..., N) of the first column hit (index order; 0 without contact) and its centre (..., N, 2)."""
    xp = array_namespace(centres)
    if xp is np:
        index = xp.argmax(hit, axis=-1)
        cx = xp.take_along_axis(centres[..., 0], index, axis=-1)
        cy = xp.take_along_axis(centres[..., 1], index, axis=-1)
        return index, xp.stack([cx, cy], axis=-1)
    # under XLA: selects from the last column to the first (M static) instead of an argmax and two
    # gathers over the short column axis; the same index and centre (column 0's without a hit)
    m_cols = centres.shape[-2]
    index = xp.zeros(hit.shape[:-1], dtype=np.int32)
    cx = xp.broadcast_to(centres[..., None, 0, 0], hit.shape[:-1])
    cy = xp.broadcast_to(centres[..., None, 0, 1], hit.shape[:-1])
    for m in range(m_cols - 1, -1, -1):
        h = hit[..., m]
        index = xp.where(h, np.int32(m), index)
        cx = xp.where(h, centres[..., None, m, 0], cx)
        cy = xp.where(h, centres[..., None, m, 1], cy)
    return index, xp.stack([cx, cy], axis=-1)


def detect(pos: Any, centres: Any, valid: Any, radius: Any, arm: float) -> tuple[Any, Any, Any]:
    """Contacts (A.3): a quad touches column m if ``||p_xy - o_xy|| <= arm + radius`` (at any
    height). Columns are scanned in index order and only the first hit is kept. Returns
    ``contact`` (..., N) bool, ``index`` (..., N) int (0 without contact) and that column's centre
    (..., N, 2) (:func:`contact_hits`, :func:`first_hit`)."""
    hit = contact_hits(pos, centres, valid, radius, arm)
    index, centre = first_hit(hit, centres)
    return hit.any(axis=-1), index, centre


def new_contacts(contact: Any, prev_contact: Any) -> Any:
    """Quads in contact now and not at the previous control step (A.3: a quad that stays in
    contact, even sliding onto another column, gets no new penalty or kick)."""
    return contact & ~prev_contact


# ------------------------------------------------------------------------------- response


#: the JAX engine's draw budget for the obstacle response: draws for at most this many NEW column contacts
#: per world and control step (more simultaneous new contacts reuse the slots' draws, as wall bounces and
#: landings do; each contact's draws keep their distribution). The CPU engine draws per contact.
OBSTACLE_BUDGET = 2


def response_draw_spec(num_quads: int, decay: tuple[float, float] = OBSTACLE_DECAY,
                       kick_omega: tuple[float, float] = OBSTACLE_KICK) -> DrawSpec:
    """Draws of the obstacle response per quad (budget: at most one column per quad per step):
    ``eta_a``/``eta_b`` the two Gaussian parts of the direction noise for each of the 3 tries,
    ``decay``, and the omega kick's uniform-cube direction and magnitude. With every draw at its
    mean: no direction noise, decay 0.5, no kick."""
    n = num_quads
    return {
        "eta_a": Normal(0.0, ETA_STDS[0], (n, ETA_TRIES, 3)),
        "eta_b": Normal(0.0, ETA_STDS[1], (n, ETA_TRIES, 3)),
        "decay": Uniform(decay[0], decay[1], (n,)),
        "kick_dir": Uniform(-1.0, 1.0, (n, 3)),
        "kick_mag": Uniform(kick_omega[0], kick_omega[1], (n,)),
    }


def collision_normal(pos: Any, centre: Any) -> Any:
    """Horizontal unit normal (..., 3) from the column axis ``centre`` (..., 2) to ``pos`` (..., 3)
    (A.3 step 1; exactly on the axis the difference is divided by 1e-5: the normal is 0)."""
    xp = array_namespace(pos, centre)
    d = pos[..., :2] - centre
    n = xp.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1])
    d = d / xp.where(n > 0, n, NORMAL_EPS)[..., None]
    return xp.concatenate([d, xp.zeros_like(d[..., :1])], axis=-1)


def obstacle_response(pos: Any, vel: Any, omega: Any, centre: Any, radius: Any, hit: Any,
                      draws: dict[str, Any]) -> tuple[Any, Any]:
    """Velocity response of quads with a new contact (A.3 steps 1-5); others unchanged.

    ``v_ref = |v| n``; the direction noise ``eta`` is the first of 3 tries with
    ``(v_ref + eta) . n > 0`` (0 if none); ``v_new = unit(v_ref + eta) min(|v_ref + eta| decay, |v|)``
    with ``decay`` = the draw, or 1.0 when the quad's centre is inside the column (2D distance
    < radius; Decisions); ``omega += unit(kick_dir) kick_mag`` (body frame, rad/s).
    ``centre`` (..., N, 2) is each quad's column, ``radius`` (...,), ``hit`` (..., N) bool.
    Returns ``(vel, omega)``.
    """
    xp = array_namespace(pos, vel)
    n = collision_normal(pos, centre)
    speed = xp.sqrt(xp.sum(vel * vel, axis=-1))
    v_ref = speed[..., None] * n
    eta = draws["eta_a"] + draws["eta_b"]  # (..., N, T, 3)
    ok = xp.sum((v_ref[..., None, :] + eta) * n[..., None, :], axis=-1) > 0  # (..., N, T)
    chosen = xp.zeros_like(vel)
    found = xp.zeros(ok.shape[:-1], dtype=bool)
    for t in range(eta.shape[-2]):  # first accepted try (static, tiny loop)
        take = ok[..., t] & ~found
        chosen = xp.where(take[..., None], eta[..., t, :], chosen)
        found = found | take
    w = v_ref + chosen
    wn = xp.sqrt(xp.sum(w * w, axis=-1))
    d2 = xp.sqrt(xp.sum((pos[..., :2] - centre) ** 2, axis=-1))
    r = xp.asarray(radius, dtype=pos.dtype)[..., None]
    decay = xp.where(d2 < r, 1.0, draws["decay"])
    new_speed = xp.minimum(wn * decay, speed)
    v_new = w * (new_speed / xp.where(wn > 0, wn, 1.0))[..., None]
    kick = safe_normalize(xp, draws["kick_dir"]) * draws["kick_mag"][..., None]
    h = hit[..., None]
    return xp.where(h, v_new, vel), xp.where(h, omega + kick, omega)


def obstacle_step(pos: Any, vel: Any, omega: Any, prev_contact: Any, centres: Any, valid: Any, radius: Any,
                  arm: float, draws: dict[str, Any] | None, respond: bool = True) -> dict[str, Any]:
    """The obstacle stage of a control step (paper model, SPEC_obstacles A.3).

    Once per control step, right after the quad-quad response (order: docs/model.md, "Obstacles").

    Per world state: ``centres`` (M_max, 2), ``valid`` (M_max,), ``radius`` () of the map in force
    and ``prev_contact`` (N,) bool (False at reset, or the contacts of the start state), all with
    the engine's leading batch dims. ``pos`` (..., N, 3) m, ``vel`` (..., N, 3) m/s (world),
    ``omega`` (..., N, 3) rad/s (body). ``draws``: :func:`response_draw_spec` draws (a
    ``MeanSampler`` when ``noise.stochastic_collisions`` is False). ``respond=False`` (MuJoCo
    contacts, collision_model "mujoco"/"blend") only detects (``draws`` may be None).

    Returns ``vel``, ``omega`` (after the response), ``contact`` (..., N) bool (the next step's
    ``prev_contact``), ``new_contact`` (..., N) bool (penalty, metrics), ``index`` (..., N) the
    column touched. The env exposes ``info["obstacles"]`` (M, 2) (valid centres) after reset and
    every step, the reward term ``"obstacle_collision"`` (:func:`obstacle_penalty`) in
    ``info["reward_terms"]`` and the episode metrics of :func:`metrics_finalize`.
    """
    contact, index, centre = detect(pos, centres, valid, radius, arm)
    new = new_contacts(contact, prev_contact)
    if respond:
        vel, omega = obstacle_response(pos, vel, omega, centre, radius, new, draws)
    return {"vel": vel, "omega": omega, "contact": contact, "new_contact": new, "index": index}


# --------------------------------------------------------------------------- reward, metrics


def obstacle_penalty(new_contact: Any, scale: float, anneal: Any = 1.0) -> Any:
    """Reward term ``obstacle_collision`` (..., N): ``-scale`` on the step of each new contact (A.4:
    not multiplied by dt, no grace period; one per contact however long it lasts). ``anneal``
    multiplies the scale like the other collision terms."""
    xp = array_namespace(new_contact, anneal)
    return xp.where(new_contact, -scale * anneal, 0.0)


def obstacle_proximity(clearance: Any, scale: float, falloff: float, control_dt: float) -> Any:
    """Reward term ``obstacle_proximity`` (..., N) of the clearances (m): the xy distances from the quads'
    centres to the nearest column surface, the centre feature ``obstacle_features(...)[..., CENTRE_FEATURE]``:
    ``-control_dt * scale * max(1 - clearance / falloff, 0)`` (a shaping term; the original has none)."""
    xp = array_namespace(clearance)
    return -(control_dt * scale) * xp.maximum(1.0 - clearance / falloff, 0.0)


def obstacle_approach(features: Any, vel: Any, scale: float, falloff: float, control_dt: float) -> Any:
    """Reward term ``obstacle_approach`` (..., N) from the 9 features (..., N, 9) (m) and the velocities
    (..., N, 3) (m/s): ``-control_dt * scale * max(-v_xy . grad d, 0) * max(1 - d / falloff, 0)``, d the
    centre feature and grad d its central differences over the 3 x 3 grid (the unit vector away from
    the nearest column, up to the grid's resolution): the speed towards the nearest column within the
    falloff; sliding around a column costs nothing (a shaping term; the original has none)."""
    xp = array_namespace(features, vel)
    closing = closing_speed(features, vel)
    near = xp.maximum(1.0 - features[..., CENTRE_FEATURE] / falloff, 0.0)
    return -(control_dt * scale) * closing * near


#: clearance (m) added to a column's radius for the path around it (:func:`around_distance`)
AROUND_MARGIN = 0.1


def around_distance(pos: Any, goals: Any, centres: Any, valid: Any, radius: Any, margin: float = AROUND_MARGIN) -> Any:
    """(..., N) length (m) of the path from ``pos`` to ``goals`` (..., N, 3) around the column nearest to
    ``pos``: in xy the straight segment, or, when it passes within ``radius + margin`` of that column's
    axis, the two tangents to that circle and the arc between them; z adds in quadrature (the columns
    span floor to ceiling). Continuous: equal to the straight distance where the segment just touches
    the circle. A position inside the circle counts as on it. ``centres`` (..., M, 2), ``valid`` (..., M),
    ``radius`` (...,) as :func:`obstacle_features`; without a valid column the straight distance."""
    xp = array_namespace(pos, centres)
    p, g = pos[..., :2], goals[..., :2]
    d_all = norm_last(p[..., None, :] - centres[..., None, :, :])  # (..., N, M)
    d_all = xp.where(valid[..., None, :], d_all, xp.inf)
    j = xp.argmin(d_all, axis=-1)  # (..., N) the nearest column
    c = xp.take_along_axis(centres, j[..., None] * xp.ones((1, 2), dtype=j.dtype), axis=-2)  # (..., N, 2)
    any_col = xp.isfinite(xp.min(d_all, axis=-1))
    r = (radius[..., None] + margin) * xp.ones_like(p[..., 0])  # (..., N)
    a, b = p - c, g - c
    da = xp.maximum(norm_last(a), r)
    db = xp.maximum(norm_last(b), r)
    ab = b - a
    t = xp.clip(-xp.sum(a * ab, axis=-1) / xp.maximum(xp.sum(ab * ab, axis=-1), 1e-12), 0.0, 1.0)
    blocked = any_col & (norm_last(a + t[..., None] * ab) < r)
    phi = xp.arctan2(xp.abs(a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]), xp.sum(a * b, axis=-1))
    arc = xp.maximum(phi - xp.arccos(xp.minimum(r / da, 1.0)) - xp.arccos(xp.minimum(r / db, 1.0)), 0.0)
    around = xp.sqrt(xp.maximum(da * da - r * r, 0.0)) + xp.sqrt(xp.maximum(db * db - r * r, 0.0)) + r * arc
    l_xy = xp.where(blocked, around, norm_last(g - p))
    dz = goals[..., 2] - pos[..., 2]
    return xp.sqrt(l_xy * l_xy + dz * dz)


def metrics_init(like: Any, batch_shape: tuple[int, ...], n: int) -> dict[str, Any]:
    """Zeroed obstacle accumulators (per quad): all new contacts, those after the grace period,
    and the latched goal-reached flag."""
    xp = array_namespace(like)
    z = xp.zeros(tuple(batch_shape) + (n,), dtype=like.dtype)
    return {"obstacle_contacts": z, "obstacle_collisions": z, "reached": xp.zeros(z.shape, dtype=bool)}


def metrics_update(om: dict[str, Any], t: Any, new_contact: Any, last_dist: Any, steps: Any, threshold: Any,
                   grace_s: float = GRACE_S, last_steps: int = 5) -> dict[str, Any]:
    """Accumulate one control step at time ``t`` (s, after the step; (..., 1) or broadcastable).

    ``new_contact`` (..., N) new obstacle contacts; ``last_dist`` (..., 5, N) the true distances to
    the goals of the last steps (``metrics`` accumulator ``last_dist``, after its update), ``steps``
    (...,) steps so far; ``threshold`` (...,) or scalar: the scenario's approach distance (m).
    ``reached`` latches once the mean of the last 5 distances is below the threshold (A.4)."""
    xp = array_namespace(last_dist)
    f = last_dist.dtype
    after = (t >= grace_s - 1e-9)
    thr = xp.asarray(threshold, dtype=f)[..., None]
    full = (xp.asarray(steps) >= last_steps)[..., None]
    near = full & (xp.mean(last_dist, axis=-2) < thr)
    return {"obstacle_contacts": om["obstacle_contacts"] + new_contact,
            "obstacle_collisions": om["obstacle_collisions"] + (new_contact & after),
            "reached": om["reached"] | near}


def metrics_finalize(om: dict[str, Any], quad_collisions: Any) -> dict[str, Any]:
    """Episode metrics per world (means over quads) with obstacles: ``obstacle_collisions`` (new
    contacts after the grace period per quad), ``collision_rate`` (fraction of quads with at least
    one quad-quad or obstacle collision after the grace period) and ``success`` (fraction that
    reached the goal and had no collision of either kind). ``quad_collisions`` (..., N) is the
    ``metrics`` accumulator ``collisions`` (quad-quad, after the grace period)."""
    xp = array_namespace(quad_collisions)
    f = quad_collisions.dtype
    collided = (om["obstacle_collisions"] > 0) | (quad_collisions > 0)
    return {"obstacle_collisions": xp.mean(om["obstacle_collisions"], axis=-1),
            "collision_rate": xp.mean(collided.astype(f), axis=-1),
            "success": xp.mean((om["reached"] & ~collided).astype(f), axis=-1)}


# ------------------------------------------------------------------------------------ arena


def geom_positions(centres: Any, valid: Any, room_h: float, park: Any) -> Any:
    """(..., M_max, 3) positions (m, world-local) of the column geoms: valid columns at
    ``(x, y, room_h / 2)``, the others at ``park`` (3,) (out of the room)."""
    xp = array_namespace(centres)
    z = xp.full(centres.shape[:-1] + (1,), 0.5 * room_h, dtype=centres.dtype)
    p = xp.concatenate([centres, z], axis=-1)
    return xp.where(valid[..., None], p, xp.asarray(park, dtype=centres.dtype))
