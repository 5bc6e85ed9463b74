"""Offscreen frames of a swarm with MuJoCo's renderer (EGL or OSMesa, no display needed).

:class:`SwarmRenderer` draws one world of a CPU engine (:class:`quadswarm_mj.envs.cpu_core.CpuSwarm`) as
RGB frames (H, W, 3) uint8: tinted quads, goal markers, trails, deck-sensor rays, overview / chase / room
cameras; :class:`TiledRenderer` puts R x C worlds in one frame. Rendering never changes the simulation (own
model copy and ``MjData``, no random numbers). With ``MUJOCO_GL`` unset the renderer makes its own EGL
context (:func:`start_renderer`), leaving mujoco's choice for your own renderers. Details: docs/api.md
("Rendering").
"""

from __future__ import annotations

import colorsys
import contextlib
import copy
import math
import os
import sys
from collections.abc import Iterator
from typing import Any

import mujoco
import numpy as np

from quadswarm_mj.spatial import yaw_of

#: geoms of each quad that carry its colour (suffixes of the attached geom names).
TINTED_GEOMS = ("plate", "prop_fr", "prop_br", "prop_bl", "prop_fl")
CAMERAS = ("overview", "chase")
#: length (m) of the depth camera's drawn frustum edges
FRUSTUM_LENGTH = 0.5
_FIX_HINT = (
    "Fix: install Mesa's EGL driver (Debian/Ubuntu: `apt-get install libegl1 libgl1-mesa-dri libegl-mesa0`), "
    "or use software OSMesa (`apt-get install libosmesa6` and run with MUJOCO_GL=osmesa). MUJOCO_GL must be "
    "set before mujoco is first imported; with MUJOCO_GL unset, quadswarm_mj's renderers use EGL."
)


def quad_colors(n: int) -> np.ndarray:
    """(n, 4) RGBA colours in [0, 1], one per quad: saturated hues (golden-ratio steps from red),
    full value, so they stand out from the grey floor and the pale sky."""
    hues = (np.arange(n) * 0.6180339887498949) % 1.0
    rgb = np.array([colorsys.hsv_to_rgb(h, 0.9, 1.0) for h in hues]).reshape(n, 3)
    return np.concatenate([rgb, np.ones((n, 1))], axis=1)


def _gl_backend() -> str:
    try:
        from mujoco.rendering.classic import gl_context

        cls = getattr(gl_context, "GLContext", None)
        return "" if cls is None else cls.__module__
    except Exception:  # noqa: BLE001
        return ""


def _headless_class() -> Any:
    """MuJoCo's context class for this package's renderers when mujoco's own choice would not be the
    one wanted (None: keep mujoco's): ``MUJOCO_GL`` egl/osmesa, or EGL when it is unset (mujoco's
    default, GLFW, needs a display); only if no other PyOpenGL platform is in use yet."""
    gl = os.environ.get("MUJOCO_GL", "").lower().strip()
    if gl not in ("", "egl", "osmesa"):
        return None
    want = gl or "egl"
    platform = os.environ.get("PYOPENGL_PLATFORM", "").lower()
    if ("OpenGL" in sys.modules or platform) and platform != want:
        return None
    try:
        from mujoco.rendering.classic import gl_context
    except ImportError:
        return None
    if getattr(getattr(gl_context, "GLContext", None), "__module__", "").startswith(f"mujoco.{want}"):
        return None
    if want == "egl":
        from mujoco.egl import GLContext  # sets PYOPENGL_PLATFORM=egl when unset (mujoco.egl, once)
    else:
        from mujoco.osmesa import GLContext  # sets PYOPENGL_PLATFORM=osmesa when unset
    return GLContext


@contextlib.contextmanager
def _headless_context() -> Iterator[None]:
    """While mujoco's ``Renderer`` is created inside: the context class of :func:`_headless_class`;
    mujoco's own choice is restored on exit (the renderer keeps its context), so the user's own
    ``mujoco.Renderer`` or viewer is unaffected."""
    cls = _headless_class()
    if cls is None:
        yield
        return
    from mujoco.rendering.classic import gl_context

    before = getattr(gl_context, "GLContext", None)
    gl_context.GLContext = cls
    try:
        yield
    finally:
        gl_context.GLContext = before


def start_renderer(model: mujoco.MjModel, width: int, height: int, max_geom: int) -> mujoco.Renderer:
    """``mujoco.Renderer`` or a RuntimeError that names the fix (headless EGL when ``MUJOCO_GL`` is unset)."""
    gl = os.environ.get("MUJOCO_GL")
    try:
        with _headless_context():
            return mujoco.Renderer(model, height=height, width=width, max_geom=max_geom)
    except Exception as e:  # noqa: BLE001 - GL failures come as ImportError, FatalError, AttributeError...
        backend = _gl_backend()
        extra = ""
        if gl in ("egl", "osmesa") and backend and gl not in backend:
            extra = (f" mujoco was imported before MUJOCO_GL={gl!r} was set and uses {backend}; "
                     "set MUJOCO_GL in the shell, before mujoco is imported.")
        elif gl in ("glfw", "glx") and not os.environ.get("DISPLAY"):
            extra = f" MUJOCO_GL={gl!r} needs a display and DISPLAY is unset; use MUJOCO_GL=egl."
        raise RuntimeError(f"MuJoCo's offscreen renderer could not start (MUJOCO_GL={gl!r}, "
                           f"{type(e).__name__}: {e}).{extra} {_FIX_HINT}") from e


class SwarmRenderer:
    """Offscreen RGB frames of one world of a swarm engine (see the module docstring).

    Args:
        core: the engine (``env.core`` of the CPU envs).
        width, height: frame size in pixels.
        camera: default camera of :meth:`render` (``"overview"``, ``"chase"``, a room camera name or
            index, ``"fixed:<name>"``, or a ``mujoco.MjvCamera`` used as given).
        world: which world of a multi-world engine to draw (the others are hidden).
        trail_length: rendered positions kept per quad for trails (0: no trails).
        show_goals: draw the goal markers.
        marker_radius: goal marker radius (m); the marker is a translucent, unlit sphere.
        marker_alpha: goal marker opacity in (0, 1].
        shadows: render shadows (prettier; costs about 2x in software GL).
        antialias: 4x multisampling (costs about 2x more in software GL; barely visible in videos).
        smooth_camera: smooth the overview camera over frames (for videos).
        chase_quad: the quad the chase camera follows.
        sensors: the ``SensorConfig`` of the readings to draw (``render(..., readings=...)``; None:
            no sensor drawing).
    """

    def __init__(self, core: Any, width: int = 640, height: int = 480, camera: Any = "overview",
                 world: int = 0, trail_length: int = 0, show_goals: bool = True, marker_radius: float = 0.05,
                 marker_alpha: float = 0.55, shadows: bool = True, antialias: bool = False,
                 smooth_camera: bool = True, chase_quad: int = 0, sensors: Any = None):
        for name, v in (("width", width), ("height", height)):
            if not isinstance(v, int) or isinstance(v, bool) or not 16 <= v <= 8192:
                raise ValueError(f"{name} must be an int in [16, 8192] pixels, got {v!r}")
        if not isinstance(trail_length, int) or trail_length < 0:
            raise ValueError(f"trail_length must be an int >= 0, got {trail_length!r}")
        # the engine's arena and model, or their visual twin (CpuSwarm.visual_arena: the same bodies and qpos)
        arena, model = core.visual_arena() if hasattr(core, "visual_arena") else (core.arena, core.model)
        self.arena = arena
        if not 0 <= world < arena.num_worlds:
            raise ValueError(f"world must be in [0, {arena.num_worlds}), got {world!r}")
        if not 0 <= chase_quad < arena.num_quads:
            raise ValueError(f"chase_quad must be in [0, {arena.num_quads}), got {chase_quad!r}")
        self.core, self.world, self.width, self.height = core, world, width, height
        self.num_quads = arena.num_quads
        if not 0.0 < marker_alpha <= 1.0:
            raise ValueError(f"marker_alpha must be in (0, 1], got {marker_alpha!r}")
        self.show_goals, self.marker_radius, self.marker_alpha = show_goals, float(marker_radius), float(marker_alpha)
        self.trail_length, self.smooth_camera, self.chase_quad = trail_length, smooth_camera, chase_quad
        self.colors = quad_colors(self.num_quads)
        # private model (tints, framebuffer size) and data: the simulation is never touched
        self.model = copy.deepcopy(model)
        self.model.vis.global_.offwidth = max(width, self.model.vis.global_.offwidth)
        self.model.vis.global_.offheight = max(height, self.model.vis.global_.offheight)
        self.model.vis.quality.offsamples = 4 if antialias else 0
        self.data = mujoco.MjData(self.model)
        self.sensors = sensors if sensors is not None and getattr(sensors, "any", False) else None
        self._rgba0 = self.model.geom_rgba.copy()  # the room's own colours (before any tint)
        self._obst_ids = None if getattr(arena, "obstacle_geom_ids", None) is None else arena.obstacle_geom_ids
        self._states: dict[int, tuple] = {}  # per world: trails and camera smoothing (set_world)
        self._show_world(world)
        self.camera = self._resolve_camera(camera)  # validates the default camera
        max_geom = int(self.model.ngeom + self.num_quads * (2 + trail_length + self._sensor_geoms()) + 100)
        self._renderer = start_renderer(self.model, width, height, max_geom)
        self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = bool(shadows)
        self._option = mujoco.MjvOption()
        self._trail = np.zeros((max(trail_length, 1), self.num_quads, 3))
        self._trail_count = 0
        self._cam_state: tuple[np.ndarray, float] | None = None
        self._chase_yaw: float | None = None
        self._last_time = -1.0

    # ------------------------------------------------------------------ set-up
    def _show_world(self, world: int) -> None:
        """Tint world ``world``'s quads and hide the other worlds' quads and columns."""
        arena = self.arena
        self.world = world
        self.body_ids = np.asarray(arena.body_ids[world])
        self.world_offset = np.asarray(arena.world_offsets[world], dtype=np.float64)
        self.model.geom_rgba[:] = self._rgba0
        self._tint(arena)
        if self._obst_ids is not None:  # other worlds' columns overlap this one's in the "paper" model: hide
            others = np.delete(self._obst_ids, world, axis=0).ravel()
            self.model.geom_rgba[others, 3] = 0.0

    def set_world(self, world: int) -> None:
        """Draw world ``world`` from now on (its trails and camera smoothing are kept separately)."""
        if not 0 <= world < self.arena.num_worlds:
            raise ValueError(f"world must be in [0, {self.arena.num_worlds}), got {world!r}")
        if world == self.world:
            return
        self._states[self.world] = (self._trail, self._trail_count, self._cam_state, self._chase_yaw,
                                    self._last_time)
        self._show_world(world)
        if world in self._states:
            self._trail, self._trail_count, self._cam_state, self._chase_yaw, self._last_time = self._states[world]
        else:
            self._trail = np.zeros((max(self.trail_length, 1), self.num_quads, 3))
            self._trail_count, self._cam_state, self._chase_yaw, self._last_time = 0, None, None, -1.0

    def _sensor_geoms(self) -> int:
        """Scene geoms per quad for the sensor drawing: 2 per range beam, 8 frustum lines, 1 per pixel."""
        s = self.sensors
        if s is None:
            return 0
        h, w = s.depth or (0, 0)
        return 2 * (5 * s.multiranger + s.flow) + (8 + h * w if s.depth is not None else 0)

    def _tint(self, arena: Any) -> None:
        m = self.model
        quad_of_body = {int(b): i for i, b in enumerate(self.body_ids)}
        other = set(int(b) for b in np.asarray(arena.body_ids).ravel()) - set(quad_of_body)
        for gid in range(m.ngeom):
            body = int(m.geom_bodyid[gid])
            if body in other:  # other worlds share the room in the "paper" model: hide them
                m.geom_rgba[gid, 3] = 0.0
            elif body in quad_of_body and m.geom(gid).name.split("/")[-1] in TINTED_GEOMS:
                rgba = self.colors[quad_of_body[body]].copy()
                rgba[3] = m.geom_rgba[gid, 3]
                m.geom_rgba[gid] = rgba

    def _resolve_camera(self, camera: Any) -> Any:
        if isinstance(camera, mujoco.MjvCamera):
            return camera
        if isinstance(camera, (int, np.integer)) and not isinstance(camera, bool):
            if not -1 <= int(camera) < self.model.ncam:
                raise ValueError(f"camera index must be in [-1, {self.model.ncam}), got {camera}")
            return int(camera)
        if not isinstance(camera, str):
            raise ValueError(f"camera must be a name or an index, got {camera!r}")
        if camera in CAMERAS:
            return camera
        name = camera[len("fixed:"):] if camera.startswith("fixed:") else camera
        cid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, name)
        if cid < 0:
            fixed = [self.model.camera(i).name for i in range(self.model.ncam)]
            raise ValueError(f"unknown camera {camera!r}; known: {list(CAMERAS)} and the room cameras {fixed} "
                             f"(prefix 'fixed:' to pick a room camera that shares a name)")
        return int(cid)

    def cameras(self) -> list[str]:
        """Names accepted by :meth:`render`."""
        return list(CAMERAS) + [f"fixed:{self.model.camera(i).name}" for i in range(self.model.ncam)]

    # ------------------------------------------------------------------ state
    def _sync(self, qpos: Any | None) -> np.ndarray:
        """Copy the pose into the private data and update its kinematics; return the quad
        positions (N, 3) in the MuJoCo frame (world offset included)."""
        src = self.core.data.qpos if qpos is None else np.asarray(qpos, dtype=np.float64)
        if src.shape != self.data.qpos.shape:
            raise ValueError(f"qpos must have shape {self.data.qpos.shape}, got {src.shape}")
        self.data.qpos[:] = src
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)
        return self.data.xpos[self.body_ids].copy()

    def _goals(self, goals: Any | None) -> np.ndarray:
        if goals is None:
            goals = np.asarray(self.core.sstate.goals)[self.world]
        goals = np.asarray(goals, dtype=np.float64).reshape(self.num_quads, 3)
        return goals + self.world_offset

    def reset(self) -> None:
        """Forget trails and camera smoothing (called automatically when a new episode starts)."""
        self._trail_count = 0
        self._cam_state = None
        self._chase_yaw = None

    # ------------------------------------------------------------------ cameras
    def _overview_camera(self, points: np.ndarray) -> mujoco.MjvCamera:
        lo, hi = points.min(axis=0), points.max(axis=0)
        center = 0.5 * (lo + hi)
        radius = float(np.max(np.linalg.norm(points - center, axis=1))) + 0.35
        fovy = math.radians(self.model.vis.global_.fovy)
        fovx = 2.0 * math.atan(math.tan(fovy / 2) * self.width / self.height)
        dist = max(1.5, 1.1 * radius / math.sin(min(fovx, fovy) / 2))
        if self.smooth_camera and self._cam_state is not None:
            look, d = self._cam_state
            look = look + 0.15 * (center - look)
            dist = dist if dist > d else d + 0.05 * (dist - d)
            center = look
        self._cam_state = (center, dist)
        cam = mujoco.MjvCamera()
        cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        cam.lookat[:] = center
        cam.distance = dist
        cam.azimuth = 60.0  # oblique (from the -x, -y side): planar formations are never seen edge-on
        cam.elevation = -28.0
        return cam

    def _chase_camera(self) -> mujoco.MjvCamera:
        i = self.chase_quad
        yaw = float(yaw_of(self.data.xmat[self.body_ids[i]].reshape(3, 3)))
        if self._chase_yaw is None or not self.smooth_camera:
            self._chase_yaw = yaw
        else:  # smooth the heading on the circle
            self._chase_yaw += 0.2 * math.atan2(math.sin(yaw - self._chase_yaw), math.cos(yaw - self._chase_yaw))
        cam = mujoco.MjvCamera()
        cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        cam.lookat[:] = self.data.xpos[self.body_ids[i]]
        cam.distance = 0.9
        cam.azimuth = math.degrees(self._chase_yaw)
        cam.elevation = -20.0
        return cam

    # ------------------------------------------------------------------ drawing
    def _add_geom(self, gtype: int, size: Any, pos: Any, rgba: Any, emission: float = 0.0) -> Any:
        scn = self._renderer.scene
        if scn.ngeom >= scn.maxgeom:
            return None
        g = scn.geoms[scn.ngeom]
        mujoco.mjv_initGeom(g, int(gtype), np.asarray(size, dtype=np.float64), np.asarray(pos, dtype=np.float64),
                            np.eye(3).ravel(), np.asarray(rgba, dtype=np.float32))
        g.emission = emission
        g.specular = 0.0
        g.castshadow = False
        scn.ngeom += 1
        return g

    def _draw_goals(self, goals: np.ndarray) -> None:
        r = self.marker_radius
        for i in range(self.num_quads):  # scene decoration, not simulation: a loop is fine
            rgba = np.concatenate([self.colors[i, :3], [self.marker_alpha]])
            self._add_geom(mujoco.mjtGeom.mjGEOM_SPHERE, (r, r, r), goals[i], rgba, emission=0.8)

    def _draw_trails(self) -> None:
        k = min(self._trail_count, self.trail_length)
        if k < 2:
            return
        idx = [(self._trail_count - k + j) % self.trail_length for j in range(k)]
        pts = self._trail[idx]  # (k, N, 3), oldest first
        for i in range(self.num_quads):
            for j in range(k - 1):
                alpha = 0.2 + 0.8 * (j + 1) / (k - 1)
                rgba = np.concatenate([self.colors[i, :3], [alpha]])
                g = self._add_geom(mujoco.mjtGeom.mjGEOM_LINE, (1, 1, 1), pts[j, i], rgba, emission=1.0)
                if g is None:
                    return
                mujoco.mjv_connector(g, mujoco.mjtGeom.mjGEOM_LINE, 3.0, pts[j, i], pts[j + 1, i])

    def _line(self, a: np.ndarray, b: np.ndarray, rgba: Any, width: float) -> None:
        g = self._add_geom(mujoco.mjtGeom.mjGEOM_LINE, (1, 1, 1), a, rgba, emission=1.0)
        if g is not None:
            mujoco.mjv_connector(g, mujoco.mjtGeom.mjGEOM_LINE, width, a, b)

    def _draw_sensors(self, pos: np.ndarray, readings: dict[str, Any]) -> None:
        """Range beams (line to the reading, a sphere at a valid hit) and the depth camera's frustum
        and hit points of every quad of the drawn world; ``readings`` as ``info`` gives them (m)."""
        from quadswarm_mj.sensors import DOWN_DIR, MULTIRANGER_DIRS, depth_directions

        s = self.sensors
        R = self.data.xmat[self.body_ids].reshape(-1, 3, 3)  # body -> world
        beams = []  # (body dirs (K, 3), ranges (N, K), valid (N, K))
        if s.multiranger and "multiranger" in readings:
            r = np.asarray(readings["multiranger"], dtype=np.float64).reshape(self.num_quads, 5)
            ok = np.asarray(readings.get("multiranger_valid", np.ones_like(r, bool))).reshape(self.num_quads, 5)
            beams.append((np.asarray(MULTIRANGER_DIRS), r, ok))
        if s.flow and "flow" in readings:
            r = np.asarray(readings["flow"], dtype=np.float64).reshape(self.num_quads, 3)[:, :1]
            ok = np.asarray(readings.get("flow_valid", np.ones((self.num_quads, 2), bool))).reshape(-1, 2)[:, :1]
            beams.append((np.asarray([DOWN_DIR]), r, ok))
        for dirs, r, ok in beams:
            ends = pos[:, None, :] + r[..., None] * np.einsum("nab,kb->nka", R, dirs)  # (N, K, 3)
            for i in range(self.num_quads):  # scene decoration, not simulation: a loop is fine
                beam = np.concatenate([self.colors[i, :3], [0.9]])
                for k in range(dirs.shape[0]):
                    self._line(pos[i], ends[i, k], beam, 2.5)
                    if ok[i, k]:
                        self._add_geom(mujoco.mjtGeom.mjGEOM_SPHERE, (0.04,) * 3, ends[i, k], beam, emission=0.8)
        if s.depth is not None and "depth" in readings:
            h, w = s.depth
            depth = np.asarray(readings["depth"], dtype=np.float64).reshape(self.num_quads, h, w)
            tu, tv = (math.tan(math.radians(f) / 2.0) for f in s.depth_fov)
            corners = np.array([[1.0, tu, tv], [1.0, -tu, tv], [1.0, -tu, -tv], [1.0, tu, -tv]])  # body, +y left
            corners /= np.linalg.norm(corners, axis=1, keepdims=True)
            pix = np.einsum("nab,kb->nka", R, depth_directions(s.depth, s.depth_fov).reshape(-1, 3))
            hits = pos[:, None, :] + depth.reshape(self.num_quads, -1)[..., None] * pix
            for i in range(self.num_quads):
                rgba = np.concatenate([self.colors[i, :3], [0.9]])
                far = pos[i] + FRUSTUM_LENGTH * (R[i] @ corners.T).T
                for c in range(4):
                    self._line(pos[i], far[c], rgba, 2.0)
                    self._line(far[c], far[(c + 1) % 4], rgba, 2.0)
                for k in range(h * w):
                    self._add_geom(mujoco.mjtGeom.mjGEOM_SPHERE, (0.02,) * 3, hits[i, k], rgba, emission=0.8)

    def _sync_obstacles(self, obstacles: Any | None) -> None:
        """Columns of the drawn world: from the engine (``data.mocap_pos``, radii from its model), or
        the given (M, 2) centres (m, world-local) with the other columns parked."""
        if self._obst_ids is None:
            return
        arena = self.core.arena
        gids, mids = self._obst_ids[self.world], arena.obstacle_mocap_ids[self.world]
        self.model.geom_size[gids] = self.core.model.geom_size[gids]
        if obstacles is None:
            if getattr(self.core, "data", None) is not None:
                self.data.mocap_pos[mids] = self.core.data.mocap_pos[mids]
            return
        c = np.asarray(obstacles, dtype=np.float64).reshape(-1, 2)
        if c.shape[0] > len(mids):
            raise ValueError(f"obstacles: at most {len(mids)} columns, got {c.shape[0]}")
        from quadswarm_mj.arena import obstacle_positions

        full = np.zeros((1, len(mids), 2))
        full[0, :c.shape[0]] = c
        H = 2.0 * float(self.model.geom_size[gids[0], 1])
        valid = (np.arange(len(mids)) < c.shape[0])[None]
        self.data.mocap_pos[mids] = obstacle_positions(arena, full, valid, H, worlds=[self.world])[0]

    def render(self, camera: Any = None, qpos: Any | None = None, goals: Any | None = None,
               obstacles: Any | None = None, readings: dict[str, Any] | None = None) -> np.ndarray:
        """One RGB frame (height, width, 3) uint8 of the current state.

        ``camera`` overrides the default camera for this frame. ``qpos`` (model nq), ``goals``
        (N, 3, world-local m) and ``obstacles`` (M, 2 column centres, world-local m) draw a given
        state instead of the engine's (e.g. an MJX state copied to NumPy). ``readings``: the drawn
        world's deck readings (``info["multiranger"]``, ``"multiranger_valid"``, ``"flow"``,
        ``"flow_valid"``, ``"depth"`` as the env reports them, m), drawn when the renderer was made
        with ``sensors``.
        """
        self._sync_obstacles(obstacles)
        cam_key = self.camera if camera is None else self._resolve_camera(camera)
        t = float(self.core.data.time) if qpos is None else -1.0
        if 0.0 <= t < self._last_time:  # time went back: a new episode
            self.reset()
        self._last_time = t
        pos = self._sync(qpos)
        goal_w = self._goals(goals)
        if self.trail_length:
            self._trail[self._trail_count % self.trail_length] = pos
            self._trail_count += 1
        if cam_key == "overview":
            pts = np.concatenate([pos, goal_w]) if self.show_goals else pos
            cam: Any = self._overview_camera(pts)
        elif cam_key == "chase":
            cam = self._chase_camera()
        else:
            cam = cam_key
        self._renderer.update_scene(self.data, camera=cam, scene_option=self._option)
        if self.show_goals:
            self._draw_goals(goal_w)
        if self.trail_length:
            self._draw_trails()
        if self.sensors is not None and readings:
            self._draw_sensors(pos, readings)
        return self._renderer.render()

    def close(self) -> None:
        """Free the GL resources (idempotent)."""
        r = getattr(self, "_renderer", None)
        if r is not None:
            r.close()
            self._renderer = None

    def __enter__(self) -> SwarmRenderer:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class TiledRenderer:
    """R x C worlds of a multi-world engine side by side in one frame, with ONE offscreen context.

    Tile (r, c) shows world ``r * cols + c`` (row-major, from the top left), each with its own
    camera smoothing and trails; a 2-pixel dark gap separates the tiles. The frame is
    (rows * tile_height, cols * tile_width, 3) uint8, tile sizes ``width / cols`` and ``height / rows``
    rounded down to even numbers (h264 needs even frame sizes). Keyword arguments go to the one
    :class:`SwarmRenderer` used for every tile (``camera``, ``trail_length``, ``sensors``, ...).
    """

    GAP = 2  # pixels between tiles

    def __init__(self, core: Any, rows: int, cols: int, width: int = 640, height: int = 480, **kwargs: Any):
        for name, v in (("rows", rows), ("cols", cols)):
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"{name} must be an int >= 1, got {v!r}")
        if rows * cols > core.arena.num_worlds:
            raise ValueError(f"a {rows}x{cols} tiling needs {rows * cols} worlds; the engine has "
                             f"{core.arena.num_worlds}")
        self.rows, self.cols = rows, cols
        self.tile_width, self.tile_height = 2 * (width // (2 * cols)), 2 * (height // (2 * rows))  # even
        if min(self.tile_width, self.tile_height) < 16:
            raise ValueError(f"tiles of {width}x{height} / {cols}x{rows} are under 16 pixels")
        self.width, self.height = self.tile_width * cols, self.tile_height * rows
        self.renderer = SwarmRenderer(core, width=self.tile_width, height=self.tile_height, **kwargs)

    def render(self, readings: dict[str, Any] | None = None, **kwargs: Any) -> np.ndarray:
        """One frame of all tiles; ``readings``: the deck readings of all worlds ((B, N, ...) arrays
        as the vector env's info gives them) to draw with ``sensors``; other keyword arguments go to
        :meth:`SwarmRenderer.render` of every tile (``camera``)."""
        frame = np.zeros((self.height, self.width, 3), np.uint8)
        th, tw, g = self.tile_height, self.tile_width, self.GAP // 2
        for w in range(self.rows * self.cols):  # one context drawn once per world
            self.renderer.set_world(w)
            rd = None if readings is None else {k: np.asarray(v)[w] for k, v in readings.items()}
            tile = self.renderer.render(readings=rd, **kwargs)
            r, c = divmod(w, self.cols)
            frame[r * th:(r + 1) * th, c * tw:(c + 1) * tw] = tile
        for r in range(1, self.rows):  # dark gaps between the tiles
            frame[r * th - g:r * th + g] = 24
        for c in range(1, self.cols):
            frame[:, c * tw - g:c * tw + g] = 24
        return frame

    def close(self) -> None:
        """Free the GL resources (idempotent)."""
        self.renderer.close()

    def __enter__(self) -> TiledRenderer:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
