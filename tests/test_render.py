"""Headless rendering: frames of a clip, goal-marker colours, no effect on the simulation, a fresh
process with MUJOCO_GL unset, the error that names the fix, and scripts/render_rollout.py end to end."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest

from quadswarm_mj import QuadSwarmEnv
from quadswarm_mj.controllers import PositionController
from quadswarm_mj.render import SwarmRenderer, TiledRenderer, quad_colors, start_renderer

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "scripts" / "render_rollout.py"


def hue_sat_val(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """HSV in [0, 1] of uint8 RGB arrays (..., 3)."""
    x = np.asarray(rgb, dtype=np.float64) / 255.0
    mx, mn = x.max(-1), x.min(-1)
    d = np.maximum(mx - mn, 1e-9)
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    h = np.where(mx == r, ((g - b) / d) % 6, np.where(mx == g, (b - r) / d + 2, (r - g) / d + 4)) / 6.0
    s = np.where(mx > 0, (mx - mn) / np.maximum(mx, 1e-9), 0.0)
    return h, s, mx


def palette_pixels(frame: np.ndarray, colors: np.ndarray, hue_tol: float = 0.03) -> np.ndarray:
    """Pixel count per quad colour (saturated, bright pixels of that hue). The room (grey floor,
    pale blue walls and sky) has saturation < 0.35, so only quads and their markers count."""
    h, s, v = hue_sat_val(frame)
    ph, _, _ = hue_sat_val(np.round(colors[:, :3] * 255))
    dh = np.abs(h[..., None] - ph)
    dh = np.minimum(dh, 1.0 - dh)
    m = (dh < hue_tol) & (s[..., None] > 0.5) & (v[..., None] > 0.5)
    return m.reshape(-1, len(colors)).sum(0)


def close_camera(center=(0.0, 0.0, 2.0), distance=5.0) -> mujoco.MjvCamera:
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = center
    cam.distance, cam.azimuth, cam.elevation = distance, 90.0, -30.0
    return cam


def test_one_second_clip_frames():
    env = QuadSwarmEnv(num_quads=8, scenario="static_diff_goal")
    obs, info = env.reset(seed=0)
    ctrl = PositionController(env.cfg)
    fps, hz = 30, env.cfg.control_hz
    shots = set(np.round(np.arange(fps) * hz / fps).astype(int).tolist())
    frames = []
    with SwarmRenderer(env.core, width=320, height=240, camera=close_camera(), shadows=False) as r:
        for k in range(hz):
            if k in shots:
                frames.append(r.render())
            _, _, _, _, info = env.step(ctrl(info["state"], info["goals"], info["goal_vel"], info["params"]))
    frames = np.array(frames)
    assert frames.shape == (30, 240, 320, 3) and frames.dtype == np.uint8
    for f in frames:  # not blank: many distinct colours, real contrast
        assert f.std() > 10
        assert len(np.unique(f.reshape(-1, 3), axis=0)) > 100
    # fixed camera, static goal markers: any change between frames is the quads flying
    changed = (np.abs(np.diff(frames.astype(np.int16), axis=0)).sum(-1) > 30).sum(axis=(1, 2))
    assert (changed > 5).all(), changed
    assert palette_pixels(frames[-1], quad_colors(8)).min() > 0  # every quad's colour is on screen


def test_goal_markers_add_their_colours():
    env = QuadSwarmEnv(num_quads=8, scenario="static_diff_goal")
    env.reset(seed=1)
    colors = quad_colors(8)
    with SwarmRenderer(env.core, width=320, height=240, shadows=False, camera=close_camera(distance=3.0)) as r:
        with_goals = palette_pixels(r.render(), colors)
        r.show_goals = False
        without = palette_pixels(r.render(), colors)
    gain = with_goals - without
    assert (gain > 0).sum() >= 7, (with_goals, without)  # one marker may hide behind a quad
    assert gain.sum() > 8 * 10


def test_colours_are_distinct_and_saturated():
    c = quad_colors(12)
    assert c.shape == (12, 4) and np.all(c[:, 3] == 1)
    h, s, v = hue_sat_val(np.round(c[:, :3] * 255))
    assert (s > 0.8).all() and (v > 0.95).all()
    dh = np.abs(h[:8, None] - h[None, :8])
    dh = np.minimum(dh, 1 - dh) + np.eye(8)
    assert dh.min() > 0.07  # the first 8 hues are told apart by the marker test (tol 0.03)


def test_rendering_does_not_change_the_simulation():
    def run(render: bool) -> dict:
        env = QuadSwarmEnv(num_quads=4, scenario="static_diff_goal")
        obs, info = env.reset(seed=7)
        ctrl = PositionController(env.cfg)
        r = SwarmRenderer(env.core, width=64, height=48, shadows=False, trail_length=3) if render else None
        for _ in range(20):
            if r is not None:
                r.render()
                r.render("chase")
            obs, _, _, _, info = env.step(ctrl(info["state"], info["goals"]))
        if r is not None:
            r.close()
        return {"qpos": env.core.data.qpos.copy(), "qvel": env.core.data.qvel.copy(), "obs": obs,
                "rng": env.core.rng.bit_generator.state}

    a, b = run(False), run(True)
    np.testing.assert_array_equal(a["qpos"], b["qpos"])
    np.testing.assert_array_equal(a["qvel"], b["qvel"])
    np.testing.assert_array_equal(a["obs"], b["obs"])
    assert a["rng"] == b["rng"]


def test_cameras_and_sizes():
    env = QuadSwarmEnv(num_quads=3, scenario="static_diff_goal")
    env.reset(seed=2)
    with SwarmRenderer(env.core, width=96, height=64, shadows=False) as r:
        for cam in ("overview", "chase", "top", "fixed:overview", 0):
            f = r.render(cam)
            assert f.shape == (64, 96, 3) and f.std() > 1
        assert "fixed:top" in r.cameras()
        with pytest.raises(ValueError, match="unknown camera"):
            r.render("nope")
    with pytest.raises(ValueError, match="width"):
        SwarmRenderer(env.core, width=0)


def test_overview_frames_every_quad_and_goal():
    """Project quads and goals with the overview camera: all inside the image."""
    env = QuadSwarmEnv(num_quads=8, scenario="static_diff_goal")
    env.reset(seed=4)
    with SwarmRenderer(env.core, width=320, height=240, shadows=False, smooth_camera=False) as r:
        r.render()
        scn = r._renderer.scene
        cam = scn.camera[0]
        pos = np.asarray(cam.pos, dtype=np.float64)
        fwd = np.asarray(cam.forward, dtype=np.float64)
        up = np.asarray(cam.up, dtype=np.float64)
        right = np.cross(fwd, up)
        pts = np.concatenate([r.data.xpos[r.body_ids], env.core.sstate.goals[0]])
        rel = pts - pos
        z = rel @ fwd
        fovy = np.radians(r.model.vis.global_.fovy)
        y = (rel @ up) / (z * np.tan(fovy / 2))
        x = (rel @ right) / (z * np.tan(fovy / 2) * 320 / 240)
        assert (z > 0).all() and (np.abs(x) < 1).all() and (np.abs(y) < 1).all()


def test_gym_env_render_rgb_array():
    env = QuadSwarmEnv(num_quads=2, render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (480, 640, 3) and frame.dtype == np.uint8 and frame.std() > 1
    env.close()


def test_renderer_failure_names_the_fix(monkeypatch):
    def broken(*args, **kwargs):
        raise mujoco.FatalError("gladLoadGL error")

    monkeypatch.setattr(mujoco, "Renderer", broken)
    env = QuadSwarmEnv(num_quads=1)
    with pytest.raises(RuntimeError) as e:
        start_renderer(env.core.model, 64, 48, 100)
    msg = str(e.value)
    assert "libegl1" in msg and "libgl1-mesa-dri" in msg and "MUJOCO_GL=osmesa" in msg and "libosmesa6" in msg


def clean_env() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "DISPLAY", "PYOPENGL_PLATFORM",
                                                            "WAYLAND_DISPLAY")}
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


@pytest.mark.parametrize("first", ["quadswarm_mj", "mujoco"])
def test_fresh_process_without_mujoco_gl_renders(first):
    """No MUJOCO_GL, no display: the package's renderer picks EGL by itself, also when the user imported
    mujoco first (it then chose GLFW), and leaves MUJOCO_GL unset and mujoco's own choice in place."""
    code = (
        "import os; assert 'MUJOCO_GL' not in os.environ and 'DISPLAY' not in os.environ\n"
        f"import {first}\n"
        "import quadswarm_mj\n"
        "assert 'MUJOCO_GL' not in os.environ\n"
        "from mujoco.rendering.classic import gl_context\n"
        "before = gl_context.GLContext\n"
        "env = quadswarm_mj.QuadSwarmEnv(num_quads=2, render_mode='rgb_array'); env.reset(seed=0)\n"
        "f = env.render(); assert f.shape == (480, 640, 3) and f.std() > 1, f.std()\n"
        "assert gl_context.GLContext is before\n"
        "print('OK', os.environ.get('MUJOCO_GL'), os.environ.get('PYOPENGL_PLATFORM'))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], env=clean_env(), capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "OK None egl" in out.stdout


def read_mp4(path: Path) -> np.ndarray:
    import imageio_ffmpeg

    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    w, h = meta["size"]
    return np.array([np.frombuffer(b, np.uint8).reshape(h, w, 3) for b in gen])


@pytest.mark.slow
def test_render_rollout_script_writes_video_with_markers(tmp_path):
    out = tmp_path / "swarm.mp4"
    cmd = [sys.executable, str(SCRIPT), "--scenario", "swap_goals", "--num-quads", "8", "--seconds", "1",
           "--out", str(out)]
    res = subprocess.run(cmd, env=clean_env(), capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert out.exists() and out.stat().st_size > 10_000
    assert "samples/s" in res.stdout and "mean_distance" in res.stdout and "success" in res.stdout
    frames = read_mp4(out)
    assert frames.shape == (30, 480, 640, 3)
    counts = np.array([palette_pixels(f, quad_colors(8)) for f in frames[::5]])
    assert (counts.max(axis=0) > 20).all(), counts  # every quad's marker/tint colour is in the video
    assert frames[0].std() > 10 and np.abs(frames[-1].astype(int) - frames[0]).mean() > 0.5


def test_render_rollout_script_rejects_bad_input(tmp_path):
    res = subprocess.run([sys.executable, str(SCRIPT), "--scenario", "nope", "--seconds", "0.1",
                          "--out", str(tmp_path / "x.mp4")], env=clean_env(), capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 2 and "unknown scenario" in res.stderr


# ------------------------------------------------------------------------ sensor rays, tiles


def project(r: SwarmRenderer, x: np.ndarray) -> tuple[float, float]:
    """(row, col) pixel of the world point ``x`` in the last rendered frame (MuJoCo's GL camera)."""
    cam = r._renderer.scene.camera[0]
    pos, fwd, up = np.asarray(cam.pos), np.asarray(cam.forward), np.asarray(cam.up)
    right = np.cross(fwd, up)
    v = np.asarray(x) - pos
    z = v @ fwd
    u, w = cam.frustum_near * (v @ right) / z, cam.frustum_near * (v @ up) / z
    # mjr_render: a zero frustum_width means half the height times the aspect ratio
    half = cam.frustum_width or 0.5 * (cam.frustum_top - cam.frustum_bottom) * r.width / r.height
    col = (u - (cam.frustum_center - half)) / (2 * half) * r.width
    row = (cam.frustum_top - w) / (cam.frustum_top - cam.frustum_bottom) * r.height
    return row, col


def test_sensor_rays_are_drawn_where_the_beams_are():
    from quadswarm_mj import SensorConfig

    s = SensorConfig(multiranger=True, flow=True, depth=(4, 4), noise=False)
    env = QuadSwarmEnv(num_quads=2, scenario="static_same_goal", sensors=s)
    state = {"pos": np.array([[0.0, 0.0, 1.5], [0.0, 1.0, 1.5]]), "motors": "hover"}
    _, info = env.reset(seed=0, options={"state": state})
    readings = {k: info[k] for k in ("multiranger", "multiranger_valid", "flow", "flow_valid", "depth")}
    colors = quad_colors(2)
    cam = close_camera(center=(0.0, 0.5, 1.2), distance=4.0)
    with SwarmRenderer(env.core, width=320, height=240, shadows=False, camera=cam, sensors=s,
                       show_goals=False) as r:
        plain = r.render()
        rays = r.render(readings=readings)
        pos = r.data.xpos[r.body_ids]
        R = r.data.xmat[r.body_ids].reshape(-1, 3, 3)
        changed = np.abs(rays.astype(int) - plain).sum(-1) > 30
        assert changed.sum() > 300  # long beams
        gain = palette_pixels(rays, colors) - palette_pixels(plain, colors)
        assert (gain > 50).all(), gain  # both quads' beams in their colours
        # the changed pixels lie on the beams: points 0.4 m along quad 0's front beam (body +x) and along
        # quad 1's flow-deck beam (down) are drawn, a point off every beam is not
        for i, d in ((0, [1.0, 0, 0]), (1, [0, 0, -1.0])):
            row, col = project(r, pos[i] + 0.4 * R[i] @ np.asarray(d))
            assert 0 <= row < 240 and 0 <= col < 320
            y, x = int(round(row)), int(round(col))
            assert changed[max(y - 2, 0):y + 3, max(x - 2, 0):x + 3].any(), (i, row, col)
        row, col = project(r, pos[0] + np.array([0.0, -0.5, 0.7]))  # above-right of quad 0: no beam
        y, x = int(round(row)), int(round(col))
        assert 0 < y < 239 and 0 < x < 319 and not changed[y - 1:y + 2, x - 1:x + 2].any()
        # without a SensorConfig the readings are ignored
    with SwarmRenderer(env.core, width=320, height=240, shadows=False, camera=cam, show_goals=False) as r2:
        assert np.array_equal(r2.render(readings=readings), plain)


def test_tiled_frame_has_every_world():
    from quadswarm_mj.config import EnvConfig
    from quadswarm_mj.envs.cpu_core import CpuSwarm

    core = CpuSwarm(EnvConfig(num_quads=3, scenario="static_diff_goal"), 6)
    core.seed(0)
    core.reset()
    colors = quad_colors(3)
    with TiledRenderer(core, 2, 3, width=605, height=300, shadows=False) as t:
        frame = t.render()
        assert (t.width, t.height) == (600, 300) and frame.shape == (300, 600, 3)  # even tiles of 200 x 150
        assert (t.tile_width, t.tile_height) == (200, 150)
        tiles = [frame[r * 150:(r + 1) * 150, c * 200:(c + 1) * 200] for r in range(2) for c in range(3)]
        for k, tile in enumerate(tiles):  # every tile shows its world: the quads' colours, real contrast
            assert tile.std() > 10, k
            assert palette_pixels(tile, colors).sum() > 10, k
        # the worlds differ (their own spawns and goals), and world 4 alone looks like tile 4
        assert min(np.abs(tiles[0].astype(int) - t_).mean() for t_ in tiles[1:]) > 0.5
        with SwarmRenderer(core, width=200, height=150, shadows=False, world=4) as one:
            alone = one.render()
        assert np.abs(alone[2:-2, 2:-2].astype(int) - tiles[4][2:-2, 2:-2]).mean() < 1.0
    with pytest.raises(ValueError, match="needs 9 worlds"):
        TiledRenderer(core, 3, 3)


def test_render_cli_parses_sensors_and_tiles():
    from quadswarm_mj.cli.render import parse_args

    a = parse_args(["--sensors", "--tile", "2x3"])
    assert a.grid == (2, 3) and a.sensor_config.multiranger and a.sensor_config.flow
    assert a.sensor_config.depth == (8, 8)
    assert parse_args(["--sensors", "multiranger,depth=4x6"]).sensor_config.depth == (4, 6)
    assert parse_args([]).sensor_config is None and parse_args([]).grid is None
    for bad in (["--tile", "2"], ["--tile", "0x2"], ["--sensors", "radar"], ["--sensors", "depth=8"]):
        with pytest.raises(SystemExit):
            parse_args(bad)


@pytest.mark.slow
def test_render_cli_tiles_with_sensor_rays(tmp_path):
    out, still = tmp_path / "t.mp4", tmp_path / "t.png"
    cmd = [sys.executable, str(SCRIPT), "--scenario", "o_random", "--num-quads", "2", "--seconds", "0.2",
           "--fps", "10", "--width", "160", "--height", "120", "--tile", "1x2", "--sensors", "multiranger,flow",
           "--still", str(still), "--out", str(out)]
    res = subprocess.run(cmd, env=clean_env(), capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    frames = read_mp4(out)
    assert frames.shape == (2, 120, 160, 3)
    import mediapy

    img = mediapy.read_image(still)
    assert img.shape == (120, 160, 3)
    for half in (img[:, :80], img[:, 80:]):
        assert palette_pixels(half, quad_colors(2)).sum() > 20  # each world's quads and their beams
