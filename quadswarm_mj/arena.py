"""Build the MuJoCo world for N quads (and B worlds side by side) with MjSpec.

The room (``quadswarm_mj/assets/arenas/room.xml``, package data read with ``importlib.resources``;
``assets/`` at the top of the repository links to it) is rescaled to ``EnvConfig.room_size`` and one
Crazyflie (``quadswarm_mj/assets/crazyflie2.xml``) is attached per quad, named ``q{i}`` (``w{b}q{i}`` when
several worlds share the model). Quad bodies are contiguous, world-major, so their state in
``MjData`` is a plain (B, N, ...) view. Contacts are disabled in the "paper" collision model
(the paper's own floor/wall/quad-quad models run instead); in "mujoco" and "blend" each quad's
hitbox sphere and the room geoms collide, and worlds are placed apart along x so they never touch.
With obstacles (``EnvConfig.obstacles``) each world also holds a fixed pool of column geoms
(mocap bodies, :func:`add_obstacle_geoms`), moved onto the map at every reset (:func:`place_obstacles`).

Several worlds in one model (contacts on): the floor is a MuJoCo ``plane``, which is infinite, so
all worlds share world 0's floor plane (z = 0) and only the finite geoms (the walls and ceiling,
boxes) are copied per world, ``L + 2`` m apart along x. Every quad therefore touches exactly one
floor, one set of walls and one ceiling, as in a one-world model, and a multi-world run equals
single-world runs up to round-off (contact positions carry the world offset). A copy of the floor
per world would put B planes at z = 0 under every quad (B times the floor contacts).
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from importlib.resources.abc import Traversable
from typing import Any

import mujoco
import numpy as np

from quadswarm_mj.config import EnvConfig

#: The MJCF files shipped as package data (``importlib.resources`` traversables; they reference no other file).
ASSETS_DIR = resources.files("quadswarm_mj") / "assets"
CRAZYFLIE_XML = ASSETS_DIR / "crazyflie2.xml"
ROOM_XML = ASSETS_DIR / "arenas" / "room.xml"


def load_spec(asset: Traversable) -> mujoco.MjSpec:
    """Parse one shipped MJCF file (read as text, so it also works from a zipped install)."""
    try:
        xml = asset.read_text(encoding="utf-8")
    except FileNotFoundError as e:
        raise FileNotFoundError(f"quadswarm_mj asset {asset} is missing from the installation "
                                "(package data not installed?)") from e
    return mujoco.MjSpec.from_string(xml)
ROOM_GEOMS = ("floor", "wall_px", "wall_nx", "wall_py", "wall_ny", "ceiling")
WALL_THICKNESS = 0.05  # half thickness, m


@dataclass(frozen=True)
class Arena:
    """A compiled world and the indices the simulator needs (looked up once)."""

    model: mujoco.MjModel
    num_worlds: int
    num_quads: int
    body_ids: np.ndarray  # (B, N) body ids of the quads
    first_body: int  # body id of world 0, quad 0; quads occupy [first_body, first_body + B*N)
    qpos_start: int  # qpos address of the first quad's free joint; 7 per quad, contiguous
    qvel_start: int  # qvel address of the first quad; 6 per quad, contiguous
    world_offsets: np.ndarray  # (B, 3) origin of each world in the MuJoCo frame (m)
    obstacle_geom_ids: np.ndarray | None = None  # (B, M_max) geom ids of the column pool (None: no obstacles)
    obstacle_mocap_ids: np.ndarray | None = None  # (B, M_max) mocap ids (rows of data.mocap_pos) of the columns
    obstacle_park: np.ndarray | None = None  # (3,) world-local position (m) of unused columns (below the floor)

    def obstacle_name(self, world: int, k: int) -> str:
        return obstacle_geom_name(self.num_worlds, world, k)


# ------------------------------------------------------------------------------ obstacle columns

#: colour of the obstacle columns (opaque warm grey)
OBSTACLE_RGBA = (0.62, 0.56, 0.5, 1.0)
#: collision bit of the columns (room geoms and hitboxes use bit 1)
OBSTACLE_BIT = 2


def obstacle_geom_name(num_worlds: int, world: int, k: int) -> str:
    """``obst{k}`` in a one-world model, ``w{b}obst{k}`` otherwise."""
    return f"obst{k}" if num_worlds == 1 else f"w{world}obst{k}"


def obstacle_park(cfg: EnvConfig) -> np.ndarray:
    """World-local parking position (m) of unused columns: centred below the floor, so a parked
    column (half height room_h / 2) ends 1 m under it (never seen, never touched)."""
    return np.array([0.0, 0.0, -0.5 * cfg.room_size[2] - 1.0])


def add_obstacle_geoms(spec: mujoco.MjSpec, cfg: EnvConfig, offsets: np.ndarray, contacts: bool) -> None:
    """Add the fixed pool of ``M_max`` columns per world (SPEC_obstacles A.1), parked.

    Each column is a mocap body ``obst{k}`` / ``w{b}obst{k}`` holding a vertical cylinder geom of
    the same name, of the largest drawable radius and the room's height. Mocap bodies move
    through ``data.mocap_pos`` (no recompilation; MuJoCo's mid-phase keeps static world geoms in a
    precomputed tree, so moving world geoms would break contacts; on MJX ``mocap_pos`` is per
    world data). They collide with the quad hitbox spheres only, when MuJoCo resolves contacts
    (``contacts``: collision_model "mujoco"/"blend"; bits: see :func:`obstacle_hitbox_bits`); in
    "paper" they never collide (the paper's model runs instead). World 0's columns are visible
    (group 0); other worlds' columns are in group 4 like their room copies. :func:`place_obstacles` (CPU) /
    :func:`obstacle_mocap_pos` (MJX) move them onto a map at reset.
    """
    o = cfg.obstacles
    if o is None:
        return
    H = cfg.room_size[2]
    park = obstacle_park(cfg)
    aff = OBSTACLE_BIT if contacts else 0
    for b in range(offsets.shape[0]):
        for k in range(o.slots):
            name = obstacle_geom_name(offsets.shape[0], b, k)
            body = spec.worldbody.add_body(name=name, pos=park + offsets[b], mocap=True)
            body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=(0.5 * o.max_size, 0.5 * H, 0.0),
                          contype=0, conaffinity=aff, group=0 if b == 0 else 4, rgba=OBSTACLE_RGBA)


def obstacle_hitbox_bits(hitbox: mujoco.MjsGeom, cfg: EnvConfig, contacts: bool) -> None:
    """Let the quad hitbox sphere collide with the columns: its contype gains ``OBSTACLE_BIT``.
    Columns have contype 0 and conaffinity ``OBSTACLE_BIT``, so they pair with the hitboxes only,
    never with the room geoms or each other (MJX has no cylinder-box collision)."""
    if contacts and cfg.obstacles is not None:
        hitbox.contype = int(hitbox.contype) | OBSTACLE_BIT


def _obstacle_ids(model: mujoco.MjModel, cfg: EnvConfig, num_worlds: int) -> tuple[Any, Any]:
    """(geom ids, mocap ids), each (B, M_max), or (None, None) without obstacles."""
    if cfg.obstacles is None:
        return None, None
    names = [[obstacle_geom_name(num_worlds, b, k) for k in range(cfg.obstacles.slots)] for b in range(num_worlds)]
    geoms = np.array([[model.geom(n).id for n in row] for row in names], dtype=np.int64)
    mocap = np.array([[model.body_mocapid[model.body(n).id] for n in row] for row in names], dtype=np.int64)
    return geoms, mocap


def obstacle_positions(arena: Arena, centres: Any, valid: Any, room_h: float, worlds: Any = None) -> np.ndarray:
    """(W, M_max, 3) MuJoCo-frame positions of the column bodies of the worlds ``worlds`` (default
    all) for maps ``centres`` (W, M_max, 2) m world-local and ``valid`` (W, M_max)."""
    from quadswarm_mj.obstacles import geom_positions

    off = arena.world_offsets if worlds is None else arena.world_offsets[worlds]
    off = np.asarray(off).reshape(-1, 3)
    m = arena.obstacle_mocap_ids.shape[-1]
    c = np.asarray(centres, dtype=np.float64).reshape(-1, m, 2)
    v = np.asarray(valid, dtype=bool).reshape(-1, m)
    return geom_positions(c, v, room_h, arena.obstacle_park) + off[:, None, :]


def place_obstacles(arena: Arena, mocap_pos: np.ndarray, centres: Any, valid: Any, room_h: float,
                    worlds: Any = None) -> None:
    """Move the column pool of the given worlds onto maps (CPU): writes ``mocap_pos`` (the
    ``data.mocap_pos`` array, (nmocap, 3)) in place. ``centres`` (W, M_max, 2) m world-local,
    ``valid`` (W, M_max) bool; ``worlds`` selects the W worlds (default: all)."""
    if arena.obstacle_mocap_ids is None:
        raise ValueError("this arena has no obstacle columns (EnvConfig.obstacles is None)")
    ids = arena.obstacle_mocap_ids if worlds is None else arena.obstacle_mocap_ids[worlds]
    mocap_pos[np.asarray(ids).reshape(-1)] = obstacle_positions(arena, centres, valid, room_h, worlds).reshape(-1, 3)


def set_obstacle_radius(model: mujoco.MjModel, arena: Arena, radius: Any, worlds: Any = None) -> None:
    """Column radius per world (W,) m (size randomization): writes ``model.geom_size``; at most the
    compiled radius (the largest drawable), so broad-phase bounds stay conservative."""
    ids = arena.obstacle_geom_ids if worlds is None else arena.obstacle_geom_ids[worlds]
    ids = np.asarray(ids).reshape(-1, arena.obstacle_geom_ids.shape[-1])
    r = np.broadcast_to(np.asarray(radius, dtype=np.float64).reshape(-1), (ids.shape[0],))
    h = model.geom_size[ids[:, 0], 1]
    r0 = np.sqrt(np.maximum(model.geom_rbound[ids[:, 0]] ** 2 - h**2, 0.0))  # the compiled radius
    if np.any(r > r0 + 1e-9) or np.any(r <= 0):
        raise ValueError(f"column radius must be in (0, {float(r0.min()):.6g}] m (the compiled radius), got {r}")
    model.geom_size[ids, 0] = r[:, None]


def obstacle_mocap_pos(mocap_pos: Any, ids: np.ndarray, centres: Any, valid: Any, room_h: float, park: Any,
                       offset: Any = None) -> Any:
    """MJX: ``mocap_pos`` (nmocap, 3) with the column pool ``ids`` (M_max,) (``Arena.obstacle_mocap_ids``
    of the world) moved onto one world's map (``centres`` (..., M_max, 2), ``valid`` (..., M_max));
    returns (..., nmocap, 3), to use as ``mjx_data.replace(mocap_pos=...)`` (per world data).
    Pure NumPy / jax.numpy."""
    from quadswarm_mj._xp import array_namespace
    from quadswarm_mj.obstacles import geom_positions

    xp = array_namespace(centres, mocap_pos)
    p = geom_positions(centres, valid, room_h, park)
    if offset is not None:
        p = p + xp.asarray(offset, dtype=p.dtype)
    base = xp.broadcast_to(xp.asarray(mocap_pos, dtype=p.dtype), p.shape[:-2] + tuple(np.shape(mocap_pos)))
    if xp is np:
        out = base.copy()
        out[..., ids, :] = p
        return out
    return base.at[..., ids, :].set(p)


def _room_geoms(spec: mujoco.MjSpec, cfg: EnvConfig) -> None:
    """Resize the room geoms of ``room.xml`` to ``cfg.room_size``."""
    L, W, H = cfg.room_size
    t = WALL_THICKNESS
    layout = {
        "floor": ((0, 0, 0), (L / 2, W / 2, 0.05)),
        "wall_px": ((L / 2 + t, 0, H / 2), (t, W / 2, H / 2)),
        "wall_nx": ((-L / 2 - t, 0, H / 2), (t, W / 2, H / 2)),
        "wall_py": ((0, W / 2 + t, H / 2), (L / 2, t, H / 2)),
        "wall_ny": ((0, -W / 2 - t, H / 2), (L / 2, t, H / 2)),
        "ceiling": ((0, 0, H + t), (L / 2, W / 2, t)),
    }
    for name, (pos, size) in layout.items():
        g = spec.geom(name)
        g.pos = pos
        g.size = size


def _attach_quads(spec: mujoco.MjSpec, cf_body: mujoco.MjsBody, offsets: np.ndarray, n: int) -> None:
    """Attach ``n`` Crazyflies per world (``offsets`` (B, 3)) to ``spec``, world-major, named ``q{i}``
    (``w{b}q{i}`` with several worlds), each element of quad ``name`` prefixed ``name/``.

    Why in chunks: MuJoCo's ``MjSpec`` re-serializes the whole spec at every added or attached
    element (its signature; google-deepmind/mujoco#3397), so attaching T quads one by one into the
    model costs O(T^2) (1,000 quads 13 s, 4,000 212 s). The quads are attached instead into small
    specs of about sqrt(T) quads each (named without their leading letter), and each small spec is
    attached once into the model with the prefix ``"q"``/``"w"``: O(T^1.5) in all (1,000 quads
    ~2 s on one core; MuJoCo's compile of such a model then dominates), and the compiled model is
    identical (same elements, order and names)."""
    B = offsets.shape[0]
    total = B * n
    chunk = max(1, int(np.ceil(np.sqrt(total))))
    lead = "q" if B == 1 else "w"
    for start in range(0, total, chunk):
        sub = mujoco.MjSpec()
        sub.copy_during_attach = True
        for t in range(start, min(total, start + chunk)):
            b, i = divmod(t, n)
            name = f"q{i}" if B == 1 else f"w{b}q{i}"
            frame = sub.worldbody.add_frame(pos=offsets[b] + np.array([0.0, 0.0, 1.0 + 0.2 * i]))
            body = frame.attach_body(cf_body, f"{name[1:]}/", "")
            body.name = name[1:]
        spec.attach(sub, prefix=lead, frame=spec.worldbody.add_frame())


def build_arena(cfg: EnvConfig, num_worlds: int = 1, visual: bool = True) -> Arena:
    """Compile a model with ``num_worlds`` rooms of ``cfg.num_quads`` Crazyflies each.

    ``visual=False`` drops the Crazyflie's visual geoms and sites (the dynamics are unchanged: they
    carry no mass); MuJoCo's kinematics then cost half as much per step (used by the vector env)."""
    if num_worlds < 1:
        raise ValueError(f"num_worlds must be >= 1, got {num_worlds}")
    contacts = cfg.collision_model in ("mujoco", "blend")
    spec = load_spec(ROOM_XML)
    spec.modelname = "quadswarm"
    spec.copy_during_attach = True
    spec.option.timestep = cfg.sim_dt
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_EULER
    spec.option.gravity = (0.0, 0.0, -cfg.quad.gravity)
    if not contacts:
        spec.option.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    _room_geoms(spec, cfg)
    L, W, H = cfg.room_size
    spacing = L + 2.0 if contacts else 0.0
    offsets = np.zeros((num_worlds, 3))
    offsets[:, 0] = spacing * np.arange(num_worlds)
    if contacts:
        for name in ROOM_GEOMS:
            g = spec.geom(name)
            g.contype, g.conaffinity = 1, 1
        # Extra worlds get invisible copies of the finite room geoms; a plane (the floor) is infinite
        # and already under every world (see the module doc).
        finite = [name for name in ROOM_GEOMS if spec.geom(name).type != mujoco.mjtGeom.mjGEOM_PLANE]
        for b in range(1, num_worlds):
            for name in finite:
                src = spec.geom(name)
                spec.worldbody.add_geom(name=f"w{b}{name}", type=src.type, size=src.size,
                                        pos=np.asarray(src.pos) + offsets[b], contype=1, conaffinity=1,
                                        group=4, rgba=(0, 0, 0, 0))
    # Overview camera framing the room.
    cam = spec.camera("overview")
    cam.pos = (0.0, -0.95 * W - 0.3 * L, 0.75 * H)

    cf = load_spec(CRAZYFLIE_XML)
    cf_body = cf.body("crazyflie")
    if not visual:
        for el in [g for g in cf.geoms if g.group == 2] + list(cf.sites):
            cf.delete(el)
    hit = cf.geom("hitbox")
    hit.size = (cfg.quad.arm, 0, 0)
    if contacts:
        hit.contype, hit.conaffinity = 1, 1
    obstacle_hitbox_bits(hit, cfg, contacts)
    n = cfg.num_quads
    _attach_quads(spec, cf_body, offsets, n)
    # columns: after the quads (their bodies stay first and contiguous); a lean arena (visual=False) of
    # the paper model has none (they would only cost kinematics: no contacts, nothing to render)
    columns = visual or contacts
    if columns:
        add_obstacle_geoms(spec, cfg, offsets, contacts)
    total = num_worlds * n
    if total > 256:
        spec.memory = int(4e6 + 60_000 * total)  # bytes; large worlds need more arena memory
    model = spec.compile()
    names = [[f"q{i}" if num_worlds == 1 else f"w{b}q{i}" for i in range(n)] for b in range(num_worlds)]
    body_ids = np.array([[model.body(nm).id for nm in row] for row in names], dtype=np.int64)
    first = int(body_ids[0, 0])
    if not np.array_equal(body_ids.ravel(), np.arange(first, first + total)):
        raise RuntimeError("quad bodies are not contiguous in the compiled model")
    jnt = model.body_jntadr[first]
    qpos_start, qvel_start = int(model.jnt_qposadr[jnt]), int(model.jnt_dofadr[jnt])
    if model.nq != qpos_start + 7 * total or model.nv != qvel_start + 6 * total:
        raise RuntimeError("quad free joints are not contiguous in the compiled model")
    obst_geoms, obst_mocap = _obstacle_ids(model, cfg, num_worlds) if columns else (None, None)
    return Arena(model=model, num_worlds=num_worlds, num_quads=n, body_ids=body_ids, first_body=first,
                 qpos_start=qpos_start, qvel_start=qvel_start, world_offsets=offsets,
                 obstacle_geom_ids=obst_geoms, obstacle_mocap_ids=obst_mocap,
                 obstacle_park=None if cfg.obstacles is None else obstacle_park(cfg))
