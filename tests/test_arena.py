"""The compiled world: with MuJoCo contacts, each quad of a multi-world model touches exactly one
floor (at z = 0), its own world's walls and ceiling, and nothing of the other worlds."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from quadswarm_mj import EnvConfig
from quadswarm_mj.arena import build_arena


def contacts_per_quad(arena, data) -> np.ndarray:
    """(B, N) number of contacts between each quad and a world (room) geom."""
    m = arena.model
    out = np.zeros(arena.body_ids.shape, int)
    where = {int(b): idx for idx, b in np.ndenumerate(arena.body_ids)}
    for c in data.contact[:data.ncon]:
        bodies = m.geom_bodyid[[c.geom1, c.geom2]]
        if 0 in bodies:  # one side is a room geom
            other = int(bodies[1] if bodies[0] == 0 else bodies[0])
            if other in where:
                out[where[other]] += 1
    return out


@pytest.mark.parametrize("num_worlds", [1, 3])
def test_each_quad_touches_one_floor_and_its_own_walls(num_worlds):
    cfg = EnvConfig(num_quads=2, room_size=(3.0, 2.0, 2.5), collision_model="mujoco")
    arena = build_arena(cfg, num_worlds, visual=False)
    m = arena.model
    planes = [m.geom(g).name for g in range(m.ngeom) if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE]
    assert planes == ["floor"]  # one infinite floor, shared by every world
    data = mujoco.MjData(m)
    qpos = data.qpos[arena.qpos_start:].reshape(num_worlds, cfg.num_quads, 7)
    r = cfg.quad.arm
    L, W, H = cfg.room_size
    # quad 0 rests on the floor (1 mm into it); quad 1 sits in a floor/wall/ceiling-free spot
    qpos[:, 0, :3] = arena.world_offsets + [0.0, 0.0, r - 1e-3]
    qpos[:, 1, :3] = arena.world_offsets + [0.5, 0.0, 1.0]
    qpos[..., 3] = 1.0
    mujoco.mj_forward(m, data)
    np.testing.assert_array_equal(contacts_per_quad(arena, data), [[1, 0]] * num_worlds)
    floor = [c for c in data.contact[:data.ncon] if m.geom(c.geom1).name == "floor" or m.geom(c.geom2).name == "floor"]
    np.testing.assert_allclose([c.pos[2] for c in floor], -5e-4, atol=1e-9)  # the floor surface is z = 0
    # quad 1 in the corner of its room: floor, two walls (x+ and y+), within 1 mm of each
    qpos[:, 1, :3] = arena.world_offsets + [L / 2 - r + 1e-3, W / 2 - r + 1e-3, r - 1e-3]
    mujoco.mj_forward(m, data)
    np.testing.assert_array_equal(contacts_per_quad(arena, data), [[1, 3]] * num_worlds)
    # and under its ceiling
    qpos[:, 1, :3] = arena.world_offsets + [0.0, 0.0, H - r + 1e-3]
    mujoco.mj_forward(m, data)
    np.testing.assert_array_equal(contacts_per_quad(arena, data), [[1, 1]] * num_worlds)
