"""``render_fps`` is the control rate: Gymnasium's RecordVideo writes one frame per step, so a
recorded episode plays exactly as long as it lasted in simulated time."""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest
from gymnasium.wrappers import RecordVideo

from quadswarm_mj import EnvConfig, QuadSwarmEnv, QuadSwarmParallelEnv


class _Clip:
    """Stands in for moviepy's ImageSequenceClip (RecordVideo's encoder): records frames and fps."""

    written: list[tuple[int, float, tuple]] = []

    def __init__(self, frames, fps):
        self.frames, self.fps = list(frames), fps

    def write_videofile(self, path, logger=None):
        _Clip.written.append((len(self.frames), self.fps, self.frames[0].shape))


@pytest.fixture
def fake_moviepy(monkeypatch):
    mods = {name: types.ModuleType(name) for name in ("moviepy", "moviepy.video", "moviepy.video.io",
                                                       "moviepy.video.io.ImageSequenceClip")}
    mods["moviepy.video.io.ImageSequenceClip"].ImageSequenceClip = _Clip
    for name, m in mods.items():
        monkeypatch.setitem(sys.modules, name, m)
    _Clip.written.clear()
    return _Clip.written


@pytest.mark.parametrize("control_hz", [100, 50])
def test_render_fps_is_the_control_rate(control_hz):
    cfg = EnvConfig(num_quads=2, control_hz=control_hz)
    env = QuadSwarmEnv(cfg, render_mode="rgb_array")
    assert env.metadata["render_fps"] == control_hz
    assert QuadSwarmEnv.metadata["render_modes"] == ["rgb_array"]  # the class attribute is not mutated
    assert QuadSwarmParallelEnv(cfg).metadata["render_fps"] == control_hz


def test_record_video_lasts_as_long_as_the_episode(tmp_path, fake_moviepy):
    cfg = EnvConfig(num_quads=2, episode_seconds=0.2, control_hz=50, sim_hz=200)
    env = RecordVideo(QuadSwarmEnv(cfg, render_mode="rgb_array"), str(tmp_path / "videos"),
                      episode_trigger=lambda e: True)
    env.reset(seed=0)
    steps, truncated = 0, False
    while not truncated:
        _, _, _, truncated, _ = env.step(np.zeros((2, 4)))
        steps += 1
    env.close()
    assert steps == cfg.episode_steps == 10
    (frames, fps, shape), = fake_moviepy
    assert fps == cfg.control_hz and shape[2] == 3
    # one frame at reset plus one per step: the video's length is the episode's to one frame
    assert frames == steps + 1
    assert abs(frames / fps - steps * cfg.control_dt) <= 1.0 / fps + 1e-12
