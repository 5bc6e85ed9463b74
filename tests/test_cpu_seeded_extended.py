"""The CPU engine's seeded runs beyond the paper model: obstacles, control modes, aerodynamics, the
MuJoCo-contact collision models ("blend", "mujoco"), randomization and the vector env (both back
ends) with auto-resets inside the run.

``tests/reference_data/cpu_seeded_extended.npz`` holds obs, rewards, reward terms, state, goals and
episode metrics of these runs; the CPU engine must reproduce them bit for bit. The runs are built so
that the event models act (quads hit each other, the floor, the walls, the ceiling and columns): the
test checks that in the record too, so it cannot silently become trivial. Regenerate (only after an
intended change of the CPU model) with
``OPENBLAS_CORETYPE=Prescott PYTHONPATH=$PWD python tests/test_cpu_seeded_extended.py --regenerate``
(the older record, ``cpu_seeded_before_pipeline.npz``, is ``tests/test_cpu_seeded.py``'s).
"""

from __future__ import annotations

import pathlib
import sys

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, ObstacleConfig, QuadSwarmEnv, QuadSwarmVectorEnv
from quadswarm_mj.config import RewardScales
from quadswarm_mj.metrics import metric_keys

REF = pathlib.Path(__file__).parent / "reference_data" / "cpu_seeded_extended.npz"
STEPS = 100  # control steps per gym run (1 s at 100 Hz)
VEC_STEPS = 90  # vector env steps (episodes of 0.4 s: two auto-resets per world, one partial reset)
#: event terms on (scale 1) so that the reward terms show every floor, wall and ceiling hit
EVENTS = RewardScales(floor_hit=1.0, wall_hit=1.0, ceiling_hit=1.0)
EVENT_TERMS = ("quad_collision", "floor_hit", "wall_hit", "ceiling_hit", "obstacle_collision")
#: columns (centres x, y m; diameter 0.6 m) of the obstacle runs' first episode
COLS = np.array([[0.0, 0.0], [2.0, -1.0], [-3.0, 2.5]])


def _start() -> dict:
    """Six quads (motors off at the start, so they also sink to the floor): three 0.12 m apart, 0.7 m
    above the floor, flying at each other (quad-quad, floor), one 0.2 m from the +x wall flying at it,
    one 0.2 m below the ceiling flying up, one flying at the column at (0, 0) of ``COLS`` (none starts
    inside a column)."""
    pos = np.array([[-2.0, -2.0, 0.7], [-1.88, -2.0, 0.7], [-2.0, -1.88, 0.7], [4.8, 0.0, 1.0], [0.0, -3.0, 9.8],
                    [-1.0, 0.0, 2.5]])
    vel = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, -1.5, 0.0], [2.0, 0.0, -1.0], [0.0, 0.0, 3.0],
                    [2.0, 0.0, 0.0]])
    return {"pos": pos, "vel": vel}


def _actions(env_space, cfg: EnvConfig, rng: np.random.Generator, scale: float) -> np.ndarray:
    """Random actions of ``cfg.control_mode`` around hover (rotor: the hover action; thrust modes: the
    weight as collective thrust; velocity: 0), ``scale`` x the half range, clipped into the bounds."""
    lo, hi = env_space.low.astype(np.float64), env_space.high.astype(np.float64)
    if cfg.control_mode == "rotor":
        mid = np.full(lo.shape, cfg.quad.hover_action)
    else:
        mid = 0.5 * (lo + hi)
        if cfg.control_mode in ("ctbr", "attitude"):
            mid[..., 0] = cfg.quad.mass * cfg.quad.gravity
    return np.clip(mid + scale * 0.5 * (hi - lo) * rng.standard_normal(lo.shape), lo, hi)


def _gym_run(cfg: EnvConfig, seed: int, options: dict | None, act_scale: float = 0.3) -> dict[str, np.ndarray]:
    env = QuadSwarmEnv(cfg)
    obs, info = env.reset(seed=seed, options=options)
    rng = np.random.default_rng(seed + 1)
    out: dict[str, list] = {"obs": [obs], "goals": [info["goals"]]}
    for t in range(STEPS):
        obs, r, _, trunc, info = env.step(_actions(env.action_space, cfg, rng, act_scale))
        assert trunc == (t == STEPS - 1)  # episode_seconds = STEPS control steps: metrics at the end
        rec = {"obs": obs, "reward": r, "rewards": info["rewards"], "goals": info["goals"],
               "on_floor": info["on_floor"], "new_collisions": info["new_collisions"],
               **{f"state/{k}": v for k, v in info["state"].items()},
               **{f"terms/{k}": v for k, v in info["reward_terms"].items()}}
        for k, v in rec.items():
            out.setdefault(k, []).append(v)
    env.close()
    d = {k: np.asarray(v) for k, v in out.items()}
    d.update({f"metrics/{k}": np.asarray(v) for k, v in info["episode_metrics"].items()})
    return d


def _vec_run(cfg: EnvConfig, seed: int, backend: str, state: dict, obstacles: np.ndarray | None,
             act_scale: float = 0.4) -> dict[str, np.ndarray]:
    """B = 3 worlds (one shard, in this process); the first episode starts from ``state`` (every world)
    and the columns ``obstacles``, later ones are drawn; world 1 is also reset alone at step 25, so
    the worlds' auto-resets fall on different steps."""
    B = 3
    env = QuadSwarmVectorEnv(cfg, num_envs=B, backend=backend)
    opts = {"state": {k: np.broadcast_to(v, (B,) + v.shape).copy() for k, v in state.items()}}
    if obstacles is not None:
        opts["obstacles"] = obstacles
    obs, info = env.reset(seed=seed, options=opts)
    rng = np.random.default_rng(seed + 1)
    out: dict[str, list] = {"obs": [obs], "goals": [info["goals"]]}
    for t in range(VEC_STEPS):
        obs, r, _, trunc, info = env.step(_actions(env.action_space, cfg, rng, act_scale))
        done = info.get("_episode_metrics", np.zeros(B, bool))
        rec = {"obs": obs, "reward": r, "truncated": trunc, "rewards": info["rewards"], "goals": info["goals"],
               "on_floor": info["on_floor"], "new_collisions": info["new_collisions"],
               **{f"state/{k}": v for k, v in info["state"].items()},
               **{f"terms/{k}": v for k, v in info["reward_terms"].items()},
               "final_obs": np.where(done[:, None, None], info["final_obs"], 0.0) if done.any() else 0.0 * obs,
               "done": done}
        metrics = info.get("episode_metrics", {})
        for k in metric_keys(cfg):  # NaN where no episode ended
            rec[f"metrics/{k}"] = np.where(done, metrics[k], np.nan) if done.any() else np.full(B, np.nan)
        for k, v in rec.items():
            out.setdefault(k, []).append(v)
        if t == 25:
            obs, info = env.reset(options={"reset_mask": np.arange(B) == 1})
            out.setdefault("partial_reset_obs", []).append(obs)
    env.close()
    return {k: np.asarray(v) for k, v in out.items()}


def _configs() -> dict[str, tuple]:
    dt = 0.01
    base = {"grace_period_s": 0.0, "episode_seconds": STEPS * dt, "rewards": EVENTS}
    obst = ObstacleConfig(density=0.2, size=0.6)
    six = {"num_quads": 6, **base}
    return {
        # paper model with columns: quad-quad, floor, walls, obstacles, downwash, randomization
        "obst6": (EnvConfig(**six, scenario="o_random", obstacles=obst, downwash=True, randomize=True), 3,
                  {"state": _start(), "obstacles": COLS}),
        # collision models with MuJoCo contacts (the paper's quad-quad response kept in "blend")
        "blend6": (EnvConfig(**six, scenario="swap_goals", collision_model="blend", downwash=True, randomize=True),
                   5, {"state": _start()}),
        "mujoco6": (EnvConfig(**six, collision_model="mujoco", downwash=True, randomize=True), 5,
                    {"state": _start()}),
        # control modes through the mode cascade; aerodynamics (ground effect, rotor drag, randomized)
        "ctbr_aero6": (EnvConfig(**six, control_mode="ctbr", aero={"ground_effect": True, "drag": True},
                                 randomize=True, downwash=True), 7, {"state": _start()}),
        "velocity6": (EnvConfig(**six, control_mode="velocity", quad="crazyflie21_identified",
                                aero={"ground_effect": True}), 9, {"state": _start()}),
    }


def _vec_configs() -> dict[str, tuple]:
    base = {"num_quads": 6, "grace_period_s": 0.0, "episode_seconds": 0.4, "rewards": EVENTS, "randomize": True,
            "downwash": True}
    cfg = EnvConfig(**base, scenario="o_random", obstacles=ObstacleConfig(density=0.2, size=0.6))
    return {f"vec3_obst_{b}": (cfg, 11, b, _start(), COLS) for b in ("mjdata", "batch")}


def runs() -> dict[str, np.ndarray]:
    cases = {name: _gym_run(cfg, seed, opts) for name, (cfg, seed, opts) in _configs().items()}
    cases.update({name: _vec_run(cfg, seed, b, st, cols) for name, (cfg, seed, b, st, cols) in _vec_configs().items()})
    return {f"{c}/{k}": v for c, d in cases.items() for k, v in d.items()}


@pytest.fixture(scope="module")
def recorded() -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    ref = np.load(REF)
    return {k: ref[k] for k in ref.files}, runs()


def test_cpu_seeded_extended_unchanged(recorded) -> None:
    ref, got = recorded
    assert sorted(got) == sorted(ref)
    bad = [k for k in ref if not (got[k].shape == ref[k].shape and np.array_equal(got[k], ref[k], equal_nan=True))]
    if bad:
        k = bad[0]
        g, r = got[k], ref[k]
        if g.shape != r.shape:
            where = f"shape {g.shape}, recorded {r.shape}"
        else:
            same = (g == r) | ((g != g) & (r != r))  # NaN == NaN
            where = f"first difference at (step, ...) {tuple(int(i) for i in np.argwhere(~same)[0])}"
        raise AssertionError(f"{len(bad)} arrays differ from {REF.name}: {bad[:8]}; {k}: {where}")


def _events(ref: dict[str, np.ndarray], case: str) -> dict[str, int]:
    """Steps x quads with each event term nonzero in a recorded case."""
    return {t: int(np.count_nonzero(ref[f"{case}/terms/{t}"])) for t in EVENT_TERMS if f"{case}/terms/{t}" in ref}


def test_the_record_exercises_the_event_models(recorded) -> None:
    ref, _ = recorded
    cases = sorted({k.split("/")[0] for k in ref})
    assert set(cases) == set(_configs()) | set(_vec_configs())
    for c in cases:
        ev = _events(ref, c)
        for t in ("quad_collision", "floor_hit", "wall_hit"):
            assert ev[t] > 0, (c, ev)
    for c in ("obst6", "vec3_obst_mjdata", "vec3_obst_batch"):
        assert _events(ref, c)["obstacle_collision"] > 0, c
    assert _events(ref, "obst6")["ceiling_hit"] > 0
    # the vector runs end episodes inside the run (auto-resets), in different steps for different worlds
    for b in ("mjdata", "batch"):
        done = ref[f"vec3_obst_{b}/done"]
        assert done.any(0).all() and not (done == done[:, :1]).all(), done.nonzero()
    # the two back ends give the same numbers (bit for bit with the paper's collision model)
    for k in ref:
        if k.startswith("vec3_obst_mjdata/"):
            assert np.array_equal(ref[k], ref[k.replace("mjdata", "batch", 1)], equal_nan=True), k
    # the records are not constant: the quads moved
    for c in cases:
        assert np.ptp(ref[f"{c}/state/pos"], axis=0).max() > 0.5, c


if __name__ == "__main__" and "--regenerate" in sys.argv:
    np.savez_compressed(REF, **runs())
    print("wrote", REF)
