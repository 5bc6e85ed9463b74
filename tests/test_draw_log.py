"""The order of the CPU engine's random draws: the sequence of ``numpy.random.Generator`` calls of
seeded episodes, logged and compared with ``tests/reference_data/cpu_draw_log.json``.

The engine draws from one generator (``CpuSwarm.rng``) in a fixed order; the seeded record
(``test_cpu_seeded*.py``) fails when any number changes, this test says *which draw* moved: each
call is logged as one line (episode and step, method, arguments, the shape, dtype and a hash of the
values) and the first line that differs is shown with its neighbours. The episodes have quad-quad
collisions, floor, wall and ceiling hits, columns, downwash, randomization, motor, sensor and deck
sensor noise (paper collision model), the "blend" model with a control mode and aerodynamics, and three
worlds in one ``CpuSwarm`` (event draws sized by the worlds where the event happens; a partial reset).

Regenerate (only after an intended change of the draws) with
``PYTHONPATH=$PWD python tests/test_draw_log.py --regenerate``.
"""

from __future__ import annotations

import hashlib
import json
import pathlib
import sys
from typing import Any

import numpy as np

from quadswarm_mj import EnvConfig, ObstacleConfig, QuadSwarmEnv
from quadswarm_mj.config import RewardScales

REF = pathlib.Path(__file__).parent / "reference_data" / "cpu_draw_log.json"
COLS = np.array([[0.0, 0.0], [2.0, -1.0], [-3.0, 2.5]])  # m, column centres of the first episode
CONTEXT = 4  # lines shown on each side of the first difference


def _summary(x: Any) -> str:
    """A short exact description of an argument or a result: scalars by value, arrays by dtype, shape
    and a hash of their bytes."""
    if isinstance(x, (bool, int, float, np.integer, np.floating)) or x is None:
        return repr(x.item() if isinstance(x, np.generic) else x)
    if isinstance(x, tuple):
        return repr(x)
    a = np.asarray(x)
    h = hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:12]
    return f"{a.dtype}{list(a.shape)}#{h}"


class RecordingGenerator:
    """A ``numpy.random.Generator`` stand-in that forwards every call and logs it as one line
    ``"<where> <method>(<args>) -> <result>"`` (``where`` is set by the caller: episode and step)."""

    def __init__(self, gen: np.random.Generator):
        self._gen = gen
        self.log: list[str] = []
        self.where = ""

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._gen, name)
        if not callable(attr):
            self.log.append(f"{self.where} .{name}")
            return attr

        def call(*args: Any, **kwargs: Any) -> Any:
            out = attr(*args, **kwargs)
            a = ", ".join([_summary(x) for x in args] + [f"{k}={_summary(v)}" for k, v in kwargs.items()])
            self.log.append(f"{self.where} {name}({a}) -> {_summary(out)}")
            return out

        return call


def _start() -> dict[str, np.ndarray]:
    """Six quads (motors off): three 0.12 m apart flying at each other 0.7 m above the floor, one at
    the +x wall, one below the ceiling flying up, one at the column at (0, 0)."""
    pos = np.array([[-2.0, -2.0, 0.7], [-1.88, -2.0, 0.7], [-2.0, -1.88, 0.7], [4.8, 0.0, 1.0], [0.0, -3.0, 9.8],
                    [-1.0, 0.0, 2.5]])
    vel = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, -1.5, 0.0], [2.0, 0.0, -1.0], [0.0, 0.0, 3.0],
                    [2.0, 0.0, 0.0]])
    return {"pos": pos, "vel": vel}


def _episodes(cfg: EnvConfig, seed: int, steps: tuple[int, int]) -> tuple[list[str], dict[str, float]]:
    """Two episodes of random actions around the midpoint of the action box: the first from
    ``_start()`` (columns ``COLS`` if obstacles are on), the second drawn (map, spawn, goals).
    Returns the draw log and the event terms' counts of nonzero (step, quad) entries."""
    env = QuadSwarmEnv(cfg)
    env.reset(seed=seed)  # seeds the engine; the logged resets below go on from this generator
    rec = RecordingGenerator(np.random.default_rng(seed))
    env.core.rng = rec
    act_rng = np.random.default_rng(seed + 1)
    lo, hi = env.action_space.low.astype(np.float64), env.action_space.high.astype(np.float64)
    mid = np.full(lo.shape, cfg.quad.hover_action) if cfg.control_mode == "rotor" else 0.5 * (lo + hi)
    if cfg.control_mode in ("ctbr", "attitude"):
        mid[..., 0] = cfg.quad.mass * cfg.quad.gravity
    events: dict[str, float] = {}
    for ep, n in enumerate(steps):
        rec.where = f"ep{ep} reset"
        opts = {"state": _start(), **({"obstacles": COLS} if cfg.obstacles is not None else {})} if ep == 0 else None
        env.reset(options=opts)
        for t in range(n):
            rec.where = f"ep{ep} step{t}"
            a = np.clip(mid + 0.3 * 0.5 * (hi - lo) * act_rng.standard_normal(lo.shape), lo, hi)
            _, _, _, _, info = env.step(a)
            for k in ("quad_collision", "floor_hit", "wall_hit", "ceiling_hit", "obstacle_collision"):
                if k in info["reward_terms"]:
                    events[k] = events.get(k, 0) + int(np.count_nonzero(info["reward_terms"][k]))
    env.close()
    return rec.log, events


def _worlds_episode(cfg: EnvConfig, seed: int, steps: int) -> tuple[list[str], dict[str, float]]:
    """Three worlds in one ``CpuSwarm`` (the vector env's shard): event draws are made for the worlds
    where the event happens only. Worlds 0 and 2 start from ``_start()``, world 1 from it with the
    colliding trio spread apart (no quad-quad pair); world 1 is reset alone half way through."""
    from quadswarm_mj.envs.cpu_core import CpuSwarm

    B = 3
    core = CpuSwarm(cfg, num_worlds=B, visual=False)
    rec = RecordingGenerator(np.random.default_rng(seed))
    core.rng = rec
    st = {k: np.repeat(v[None], B, axis=0) for k, v in _start().items()}
    st["pos"][1, :3] = [[-3.0, -3.0, 0.7], [-1.0, -3.0, 0.7], [-3.0, -1.0, 0.7]]
    rec.where = "reset"
    core.reset(state=st)
    act_rng = np.random.default_rng(seed + 1)
    events: dict[str, float] = {}
    for t in range(steps):
        rec.where = f"step{t}"
        a = np.clip(cfg.quad.hover_action + 0.3 * act_rng.standard_normal((B, cfg.num_quads, 4)), -1, 1)
        out = core.step(a)
        for k in ("quad_collision", "floor_hit", "wall_hit", "ceiling_hit"):
            events[k] = events.get(k, 0) + int(np.count_nonzero(out["terms"][k]))
        if t == steps // 2:
            rec.where = f"step{t} reset world 1"
            core.reset(mask=np.arange(B) == 1)
    return rec.log, events


def _cases() -> dict[str, tuple[EnvConfig, int, tuple[int, int]]]:
    base = {"num_quads": 6, "grace_period_s": 0.0, "rewards": RewardScales(floor_hit=1.0, wall_hit=1.0,
                                                                           ceiling_hit=1.0)}
    return {
        "paper_obstacles_sensors": (EnvConfig(**base, scenario="o_random", obstacles=ObstacleConfig(density=0.2),
                                              downwash=True, randomize=True,
                                              sensors={"multiranger": True, "flow": True}), 3, (60, 5)),
        "blend_ctbr_aero": (EnvConfig(**base, scenario="swap_goals", collision_model="blend", control_mode="ctbr",
                                      aero={"ground_effect": True, "drag": True}, downwash=True, randomize=True),
                            5, (60, 5)),
    }


def logs() -> tuple[dict[str, list[str]], dict[str, dict[str, float]]]:
    out, ev = {}, {}
    for name, (cfg, seed, steps) in _cases().items():
        out[name], ev[name] = _episodes(cfg, seed, steps)
    cfg = _cases()["paper_obstacles_sensors"][0].replace(sensors={}, scenario="static_same_goal", obstacles=None)
    out["three_worlds"], ev["three_worlds"] = _worlds_episode(cfg, 7, 60)
    return out, ev


def _first_difference(name: str, want: list[str], got: list[str]) -> str:
    i = next((i for i, (a, b) in enumerate(zip(want, got)) if a != b), min(len(want), len(got)))
    lo = max(0, i - CONTEXT)
    show = [f"case {name!r}: {len(got)} draws, {len(want)} recorded; first difference at draw {i}:"]
    for title, log in (("recorded", want), ("now", got)):
        show += [f"  {title}:"] + [f"  {'>' if j == i else ' '} {j}: {log[j]}"
                                   for j in range(lo, min(len(log), i + 1 + CONTEXT))]
    return "\n".join(show)


def test_draw_order_unchanged() -> None:
    ref = json.loads(REF.read_text())
    got, events = logs()
    assert sorted(got) == sorted(ref["logs"])
    diffs = [_first_difference(k, ref["logs"][k], got[k]) for k in ref["logs"] if ref["logs"][k] != got[k]]
    assert not diffs, "the engine's random draws changed (order, size or values):\n" + "\n".join(diffs)
    # the episodes exercise the event models whose draws are logged (so the log cannot become trivial)
    for name, ev in events.items():
        for k in ("quad_collision", "floor_hit", "wall_hit", "ceiling_hit"):
            assert ev[k] > 0, (name, ev)
    assert events["paper_obstacles_sensors"]["obstacle_collision"] > 0


if __name__ == "__main__" and "--regenerate" in sys.argv:
    got, events = logs()
    REF.write_text(json.dumps({"regenerate": "PYTHONPATH=$PWD python tests/test_draw_log.py --regenerate",
                               "events": events, "logs": got}, indent=1) + "\n")
    print("wrote", REF, {k: len(v) for k, v in got.items()}, events)
