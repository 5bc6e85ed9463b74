"""Build the MuJoCo world for N quads (and B worlds side by side) with MjSpec.

The room (``assets/arenas/room.xml``) is rescaled to ``EnvConfig.room_size`` and one
Crazyflie (``assets/crazyflie2.xml``) is attached per quad, named ``q{i}`` (``w{b}q{i}`` when
several worlds share the model). Quad bodies are contiguous, world-major, so their state in
``MjData`` is a plain (B, N, ...) view. Contacts are disabled in the "paper" collision model
(the paper's own floor/wall/quad-quad models run instead); in "mujoco" and "blend" each quad's
hitbox sphere and the room geoms collide, and worlds are placed apart along x so they never touch.

Several worlds in one model (contacts on): the floor is a MuJoCo ``plane``, which is infinite, so
all worlds share world 0's floor plane (z = 0) and only the finite geoms (the walls and ceiling,
boxes) are copied per world, ``L + 2`` m apart along x. Every quad therefore touches exactly one
floor, one set of walls and one ceiling, as in a one-world model, and a multi-world run equals
single-world runs up to round-off (contact positions carry the world offset). A copy of the floor
per world would put B planes at z = 0 under every quad (B times the floor contacts).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from quadswarm_mj.config import EnvConfig

ASSETS_DIR = Path(__file__).resolve().parent.parent / "assets"
CRAZYFLIE_XML = ASSETS_DIR / "crazyflie2.xml"
ROOM_XML = ASSETS_DIR / "arenas" / "room.xml"
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

    def quad_name(self, world: int, quad: int) -> str:
        return f"q{quad}" if self.num_worlds == 1 else f"w{world}q{quad}"


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


def build_arena(cfg: EnvConfig, num_worlds: int = 1, visual: bool = True) -> Arena:
    """Compile a model with ``num_worlds`` rooms of ``cfg.num_quads`` Crazyflies each.

    ``visual=False`` drops the Crazyflie's visual geoms and sites (the dynamics are unchanged: they
    carry no mass); MuJoCo's kinematics then cost half as much per step (used by the vector env)."""
    if num_worlds < 1:
        raise ValueError(f"num_worlds must be >= 1, got {num_worlds}")
    contacts = cfg.collision_model in ("mujoco", "blend")
    spec = mujoco.MjSpec.from_file(str(ROOM_XML))
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

    cf = mujoco.MjSpec.from_file(str(CRAZYFLIE_XML))
    cf_body = cf.body("crazyflie")
    if not visual:
        for el in [g for g in cf.geoms if g.group == 2] + list(cf.sites):
            cf.delete(el)
    hit = cf.geom("hitbox")
    hit.size = (cfg.quad.arm, 0, 0)
    if contacts:
        hit.contype, hit.conaffinity = 1, 1
    n = cfg.num_quads
    for b in range(num_worlds):
        for i in range(n):
            frame = spec.worldbody.add_frame(pos=offsets[b] + np.array([0.0, 0.0, 1.0 + 0.2 * i]))
            name = f"q{i}" if num_worlds == 1 else f"w{b}q{i}"
            body = frame.attach_body(cf_body, f"{name}/", "")
            body.name = name
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
    return Arena(model=model, num_worlds=num_worlds, num_quads=n, body_ids=body_ids, first_body=first,
                 qpos_start=qpos_start, qvel_start=qvel_start, world_offsets=offsets)
