"""Fly a swarm headless and write a video, then print the episode metrics and the speed reached.

    quadswarm-render --scenario swap_goals --num-quads 8 --seconds 3 --out swarm.mp4
    quadswarm-render --scenario o_random --sensors multiranger,flow --seconds 2 --out s.mp4   # deck rays
    quadswarm-render --scenario swap_goals --tile 2x2 --seconds 3 --out tiles.mp4            # 4 worlds

Runs one world of the CPU env (``QuadSwarmEnv``, 100 Hz control) and renders every k-th control step
offscreen (EGL by default) so the video plays in real time at ``--fps``. Policies: ``controller``
(default), ``hover``, ``random``, ``pretrained:<name>`` or a policy ``.npz``. ``--obstacles`` turns the
columns on for any scenario. ``--sensors`` draws the deck sensors' readings (range beams ending in a dot
at the hit, the depth camera's frustum and pixel hits); ``--tile RxC`` flies R x C worlds of the
multi-world CPU engine side by side in one frame with one offscreen context. ``--out`` and ``--still``
are checked to be writable before the flight and each replaces its target only once complete; if
writing the still fails anyway, the metrics are printed and the exit status is 1.
"""
from __future__ import annotations

# Headless: with MUJOCO_GL unset, quadswarm_mj.render picks EGL when it first renders (MUJOCO_GL stays unset).
import argparse
import copy
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

import quadswarm_mj
from quadswarm_mj import QuadSwarmEnv
from quadswarm_mj.config import ObstacleConfig
from quadswarm_mj.controllers import PositionController
from quadswarm_mj.outfiles import check_writable, replacing
from quadswarm_mj.policies import baseline_gains
from quadswarm_mj.render import SwarmRenderer, TiledRenderer
from quadswarm_mj.sensor_config import SensorConfig

#: A policy maps (observation, info) of ``QuadSwarmEnv`` to an action of its action space.
Policy = Callable[[np.ndarray, dict[str, Any]], np.ndarray]
BUILTIN_POLICIES = ("controller", "hover", "random")


def load_external_policy(spec: str) -> Any:
    """A trained policy (``pretrained:<name>`` or a policy ``.npz`` path) through
    ``quadswarm_mj.policies.load_policy``: an object with ``act(obs, info)`` and ``env_kwargs``
    (the EnvConfig overrides its observations need)."""
    try:
        from quadswarm_mj.policies import load_policy
    except ImportError as e:
        raise ValueError(f"policy {spec!r} needs quadswarm_mj.policies (trained-policy loading), "
                         f"which is not available: {e}") from e
    return load_policy(spec)


def make_policy(name: str, env: QuadSwarmEnv, seed: int | None, external: Any = None) -> Policy:
    """The policy called ``name`` for ``env`` (see the module docstring); ``external`` is a loaded
    trained policy (from :func:`load_external_policy`)."""
    shape = env.action_space.shape
    if external is not None:
        return lambda obs, info: np.asarray(external.act(obs, info), dtype=np.float64).reshape(shape)
    if name == "controller":
        ctrl = PositionController(env.cfg, baseline_gains(env.cfg))

        def controller(obs: np.ndarray, info: dict[str, Any]) -> np.ndarray:
            return ctrl(info["state"], info["goals"], info["goal_vel"], info["params"],
                        obstacles=info.get("obstacles")).reshape(shape)

        return controller
    if name == "hover":
        hover = np.full(shape, env.cfg.quad.hover_action)
        return lambda obs, info: hover
    if name == "random":
        env.action_space.seed(seed)
        return lambda obs, info: env.action_space.sample()
    raise ValueError(f"unknown policy {name!r}; use {', '.join(BUILTIN_POLICIES)}, pretrained:<name> or a "
                     "policy .npz path")


def parse_sensors(text: str) -> SensorConfig:
    """``SensorConfig`` from a comma-separated list of ``multiranger``, ``flow``, ``depth`` (8 x 8) or
    ``depth=HxW``."""
    on: dict[str, Any] = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        name, _, size = item.partition("=")
        if name in ("multiranger", "flow") and not size:
            on[name] = True
        elif name == "depth":
            try:
                on["depth"] = parse_grid(size) if size else (8, 8)
            except ValueError as e:
                raise ValueError(f"--sensors depth={size}: {e}") from None
        else:
            raise ValueError(f"--sensors: unknown item {item!r}; use multiranger, flow, depth or depth=HxW")
    if not on:
        raise ValueError("--sensors: name at least one of multiranger, flow, depth")
    return SensorConfig(**on)


def parse_grid(text: str) -> tuple[int, int]:
    """(R, C) from ``"RxC"`` (two ints >= 1)."""
    parts = text.lower().replace(" ", "").split("x")
    if len(parts) != 2 or not all(p.isdigit() and int(p) >= 1 for p in parts):
        raise ValueError(f"expected RxC with two ints >= 1 (e.g. 2x2), got {text!r}")
    return int(parts[0]), int(parts[1])


READING_KEYS = ("multiranger", "multiranger_valid", "flow", "flow_valid", "depth")


class TiledWorlds:
    """B worlds of the multi-world CPU engine (:class:`~quadswarm_mj.envs.cpu_core.CpuSwarm`, the vector
    env's) stepped together, with per-world observations and infos as ``QuadSwarmEnv`` gives them
    (``state``, ``goals``, ``goal_vel``, ``params``, ``obstacles``, the deck readings)."""

    def __init__(self, cfg: Any, num_worlds: int):
        from quadswarm_mj.envs.cpu_core import CpuSwarm

        self.cfg, self.num_worlds = cfg, num_worlds
        self.core = CpuSwarm(cfg, num_worlds)

    def reset(self, seed: int) -> tuple[np.ndarray, list[dict[str, Any]]]:
        self.core.seed(seed)
        self.core.reset()
        return self._out(self.core.observe())

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, list[dict[str, Any]], bool]:
        n = self.cfg.num_quads
        out = self.core.step(np.asarray(actions, dtype=np.float64).reshape(self.num_worlds, n, 4))
        obs, infos = self._out(out["obs"])
        return obs, infos, bool(np.all(out["truncated"]))

    def _out(self, obs: np.ndarray) -> tuple[np.ndarray, list[dict[str, Any]]]:
        from quadswarm_mj.observations import obs_scale
        from quadswarm_mj.sensors import deck_info

        c, cfg = self.core, self.cfg
        st, par = c.state_dict(), c.params_dict()
        scale = obs_scale(cfg) if cfg.normalize_obs else None
        deck = deck_info(cfg, obs, scale)
        infos = []
        for w in range(self.num_worlds):  # per-world views for the per-world policies (not a quad loop)
            info = {"state": {k: v[w] for k, v in st.items()}, "goals": c.sstate.goals[w].copy(),
                    "goal_vel": c.sstate.goal_vel[w].copy(), "params": {k: v[w] for k, v in par.items()},
                    **{k: v[w] for k, v in deck.items()}}
            if c.omap is not None:
                info["obstacles"] = c.obstacle_centres(w)
            infos.append(info)
        o = obs.astype(np.float32)
        return (o[:, 0] if cfg.num_quads == 1 else o), infos


class _WorldView:
    """What :func:`make_policy` needs of an env (``cfg``, ``action_space``) for one tiled world."""

    def __init__(self, cfg: Any, action_space: Any):
        self.cfg, self.action_space = cfg, action_space


def frame_steps(seconds: float, fps: float, control_hz: int) -> np.ndarray:
    """Control-step indices at which frames are taken: frame j shows the state at time j / fps
    (rounded to the control step), for ``round(seconds * fps)`` frames."""
    n = int(round(seconds * fps))
    return np.round(np.arange(n) * control_hz / fps).astype(np.int64)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--scenario", default="swap_goals", help=f"one of {quadswarm_mj.list_scenarios()}")
    p.add_argument("--num-quads", type=int, default=8)
    p.add_argument("--seconds", type=float, default=3.0, help="simulated time (the episode length)")
    p.add_argument("--policy", default="controller",
                   help="controller, hover, random, pretrained:<name> or a policy .npz path")
    p.add_argument("--camera", default="overview",
                   help="overview (frames the swarm and its goals), chase (follows quad 0), or a room camera: "
                        "top, fixed:overview")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--obstacles", action="store_true",
                   help="columns in the room (ObstacleConfig() defaults; the o_* scenarios turn them on anyway)")
    p.add_argument("--trail", type=int, default=20, help="trail length in rendered frames (0: none)")
    p.add_argument("--shadows", action=argparse.BooleanOptionalAction, default=True)
    p.add_argument("--antialias", action=argparse.BooleanOptionalAction, default=False)
    p.add_argument("--still", type=Path, default=None, help="also save one frame as a PNG here")
    p.add_argument("--still-at", type=float, default=None, help="time (s) of the --still frame (default: last)")
    p.add_argument("--out", type=Path, default=Path("video.mp4"), help="video file (.mp4 or .gif)")
    p.add_argument("--sensors", nargs="?", const="multiranger,flow,depth", default=None,
                   help="turn on deck sensors and draw their rays: a comma list of multiranger, flow, depth, "
                        "depth=HxW (alone: multiranger,flow,depth)")
    p.add_argument("--tile", default=None, help="RxC: fly R*C worlds and draw them side by side (e.g. 2x2)")
    args = p.parse_args(argv)
    try:
        args.sensor_config = None if args.sensors is None else parse_sensors(args.sensors)
        args.grid = None if args.tile is None else parse_grid(args.tile)
    except ValueError as e:
        p.error(str(e))
    if args.seconds <= 0 or args.fps <= 0:
        p.error("--seconds and --fps must be > 0")
    if args.fps > 100:
        p.error("--fps must be <= the 100 Hz control rate")
    if args.out.suffix.lower() != ".gif" and (args.width % 2 or args.height % 2):
        p.error("--width and --height must be even for h264 video")
    return args


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Fly, render and write the video; return the metrics and timings."""
    import imageio_ffmpeg
    import mediapy
    from tqdm import tqdm

    # before the work: outputs that cannot be written are known now, not after the flight
    check_writable(args.out, "--out", make_parents=True)
    if args.still is not None:
        check_writable(args.still, "--still", make_parents=True)
    mediapy.set_ffmpeg(imageio_ffmpeg.get_ffmpeg_exe())
    external = None if args.policy in BUILTIN_POLICIES else load_external_policy(args.policy)
    env_kwargs: dict[str, Any] = {"num_quads": args.num_quads}
    if args.obstacles or args.scenario.startswith("o_"):
        env_kwargs["obstacles"] = ObstacleConfig()
    if external is not None:  # the observation layout the policy was trained on
        env_kwargs.update(getattr(external, "env_kwargs", {}) or {})
        if env_kwargs["num_quads"] != args.num_quads:
            print(f"note: {args.policy} was trained with {env_kwargs['num_quads']} quads; using that",
                  file=sys.stderr)
            args.num_quads = env_kwargs["num_quads"]
    sensor_config = getattr(args, "sensor_config", None)
    if sensor_config is not None and "sensors" not in env_kwargs:  # a policy's own sensors stay
        env_kwargs["sensors"] = sensor_config
    env = QuadSwarmEnv(scenario=args.scenario, episode_seconds=args.seconds, **env_kwargs)
    cfg = env.cfg
    sensors = cfg.sensors if sensor_config is not None and cfg.sensors.any else None
    draw = {"camera": args.camera, "trail_length": args.trail, "shadows": args.shadows,
            "antialias": args.antialias, "sensors": sensors}
    grid = getattr(args, "grid", None)
    num_worlds = 1 if grid is None else grid[0] * grid[1]
    if grid is None:
        policy = make_policy(args.policy, env, args.seed, external)
        renderer: Any = SwarmRenderer(env.core, width=args.width, height=args.height, **draw)

        def act(obs: np.ndarray, info: Any) -> np.ndarray:
            return policy(obs, info)

        def advance(action: np.ndarray) -> tuple[np.ndarray, Any, bool, Any]:
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
            return obs, info, done, info.get("episode_metrics") if done else None

        def draw_frame(info: Any) -> np.ndarray:
            return renderer.render(readings={k: info[k] for k in READING_KEYS if k in info} if sensors else None)

        def reset() -> tuple[np.ndarray, Any]:
            return env.reset(seed=args.seed)
    else:
        worlds = TiledWorlds(cfg, num_worlds)
        policies = [make_policy(args.policy, _WorldView(cfg, copy.deepcopy(env.action_space)), args.seed + w, external)
                    for w in range(num_worlds)]
        renderer = TiledRenderer(worlds.core, grid[0], grid[1], width=args.width, height=args.height, **draw)

        def act(obs: np.ndarray, infos: Any) -> np.ndarray:
            return np.stack([pol(obs[w], infos[w]) for w, pol in enumerate(policies)])  # per world, not per quad

        def advance(action: np.ndarray) -> tuple[np.ndarray, Any, bool, Any]:
            obs, infos, done = worlds.step(action)
            return obs, infos, done, None

        def draw_frame(infos: Any) -> np.ndarray:
            readings = None
            if sensors:
                readings = {k: np.stack([i[k] for i in infos]) for k in READING_KEYS if k in infos[0]}
            return renderer.render(readings=readings)

        def reset() -> tuple[np.ndarray, Any]:
            return worlds.reset(args.seed)
    n_steps = cfg.episode_steps
    shots = frame_steps(args.seconds, args.fps, cfg.control_hz)
    still_step = None
    if args.still is not None:
        t = args.seconds if args.still_at is None else args.still_at
        still_step = int(shots[np.argmin(np.abs(shots - t * cfg.control_hz))])
    codec = "gif" if args.out.suffix.lower() == ".gif" else "h264"
    t_sim = t_policy = t_render = 0.0
    metrics: dict[str, float] | None = None
    wall0 = time.perf_counter()
    obs, info = reset()
    shot_iter = iter(shots.tolist())
    next_shot = next(shot_iter, None)
    frames = 0
    still_frame = None
    # the video goes to a temporary file that replaces --out only once it is complete
    shape = (renderer.height, renderer.width)
    with replacing(args.out) as video_tmp, \
            mediapy.VideoWriter(video_tmp, shape=shape, fps=args.fps, codec=codec) as video, \
            tqdm(total=n_steps, unit="step", desc=f"{args.scenario} x{args.num_quads}", file=sys.stderr) as bar:
        for k in range(n_steps):
            if k == next_shot:  # the state at time k / control_hz
                t0 = time.perf_counter()
                frame = draw_frame(info)
                t_render += time.perf_counter() - t0
                video.add_image(frame)
                frames += 1
                if k == still_step:
                    still_frame = frame
                next_shot = next(shot_iter, None)
            t0 = time.perf_counter()
            action = act(obs, info)
            t1 = time.perf_counter()
            obs, info, done, last_metrics = advance(action)
            t2 = time.perf_counter()
            t_policy += t1 - t0
            t_sim += t2 - t1
            bar.update(1)
            if done:
                metrics = last_metrics
                break
    wall = time.perf_counter() - wall0
    if metrics is None:  # (tiled: the mean over the worlds)
        core = env.core if grid is None else worlds.core
        metrics = {k: float(np.mean(v)) for k, v in core.episode_metrics().items()}
    renderer.close()
    env.close()
    write_error = None
    if still_frame is not None:
        try:
            with replacing(args.still) as still_tmp:
                mediapy.write_image(still_tmp, still_frame)
        except OSError as e:  # e.g. the disk filled up: the results are still reported
            write_error = f"could not write --still {str(args.still)!r} ({e.strerror or e})"
    steps = k + 1
    samples = steps * args.num_quads * num_worlds
    return {"metrics": metrics, "steps": steps, "sim_seconds": steps * cfg.control_dt, "frames": frames,
            "samples": samples, "t_sim": t_sim,
            "t_policy": t_policy, "t_render": t_render, "wall": wall, "write_error": write_error}


def report(args: argparse.Namespace, r: dict[str, Any]) -> str:
    m = r["metrics"]
    lines = [f"episode metrics ({args.scenario}, {args.num_quads} quads, {r['sim_seconds']:.2f} s simulated, "
             f"policy {args.policy}, seed {args.seed}):"]
    lines += [f"  {k:<16} {v:.4g}" for k, v in m.items()]
    sim_rate = r["samples"] / max(r["t_sim"], 1e-9)
    no_render = r["samples"] / max(r["t_sim"] + r["t_policy"], 1e-9)
    lines.append(f"simulation speed: {sim_rate:,.0f} samples/s (quad-steps/s, env.step only; "
                 f"{r['steps'] / max(r['t_sim'], 1e-9):,.0f} control steps/s)")
    lines.append(f"  with the policy: {no_render:,.0f} samples/s (excluding rendering; policy {r['t_policy']:.2f} s)")
    lines.append(f"  total: {r['samples'] / max(r['wall'], 1e-9):,.0f} samples/s over {r['wall']:.1f} s wall "
                 f"(rendering {r['frames']} frames took {r['t_render']:.1f} s, "
                 f"{r['frames'] / max(r['t_render'], 1e-9):.1f} frames/s at {args.width}x{args.height})")
    lines.append(f"wrote {args.out} ({r['frames']} frames, {args.fps:g} fps)"
                 + (f" and {args.still}" if args.still is not None and not r.get("write_error") else ""))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # run as a command: the opt-in XLA:CPU tuning (quadswarm_mj.tune_jax_cpu), before JAX starts
        from quadswarm_mj.devices import tune_jax_cpu

        tune_jax_cpu()
    args = parse_args(argv)
    try:
        result = run(args)
    except ValueError as e:  # bad scenario, policy, camera or size: a clean message
        print(f"error: {e}", file=sys.stderr)
        return 2
    except RuntimeError as e:  # the renderer could not start: the message names the fix
        print(f"error: {e}", file=sys.stderr)
        return 1
    except OSError as e:  # writing the video failed during the run (e.g. the disk filled up)
        print(f"error: could not write --out {str(args.out)!r} ({e.strerror or e}); it was left as it was",
              file=sys.stderr)
        return 1
    print(report(args, result))
    if result.get("write_error"):
        print(f"error: {result['write_error']}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
