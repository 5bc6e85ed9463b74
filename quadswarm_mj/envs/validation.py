"""Input checks shared by the front ends: they run before any work, so a rejected call leaves
the environment exactly as it was."""

from __future__ import annotations

import math
import numbers
from typing import Any

import numpy as np

from quadswarm_mj.config import OMEGA_LIMIT, SPEED_LIMIT

#: dtype kinds of real numbers: float, signed and unsigned int (not bool, complex, str, bytes,
#: datetime, timedelta or object)
REAL_KINDS = "fiu"
_F32_MAX = float(np.finfo(np.float32).max)


def as_real_array(value: Any, name: str) -> np.ndarray:
    """``value`` as a float64 array if it holds real numbers only (float or int dtypes; a list of
    Python ints and floats), else ValueError naming ``name``: strings, bytes, bools, complex,
    datetimes and object arrays are refused rather than coerced; a Python int beyond the float64
    range is refused too."""
    try:
        a = np.asarray(value)
    except (TypeError, ValueError, OverflowError) as e:  # ragged nesting, ...
        raise ValueError(f"{name} must be a numeric array of real numbers (float or int), "
                         f"got {type(value).__name__}") from e
    if a.dtype.kind == "O" and not isinstance(value, np.ndarray):
        # a nested list with Python ints too large for int64 lands here: numbers only, float64-sized
        if a.size and all(isinstance(x, numbers.Real) and not isinstance(x, (bool, np.bool_)) for x in a.flat):
            try:
                return a.astype(np.float64)
            except OverflowError as e:
                raise ValueError(f"{name} holds a number beyond the float64 range (|x| > 1.8e308)") from e
    if a.dtype.kind not in REAL_KINDS:
        raise ValueError(f"{name} must be a numeric array of real numbers (float or int), got dtype {a.dtype} "
                         f"({type(value).__name__})")
    return a.astype(np.float64, copy=False)


def check_action(action: Any, expected_shape: tuple[int, ...], dtype: Any = np.float64) -> np.ndarray:
    """Return ``action`` as float64 of ``expected_shape``; raise ValueError on a wrong shape, a
    non-real dtype (:func:`as_real_array`), NaN or inf. Out-of-range values are clipped later, as in
    the paper. ``dtype`` is the engine's: with float32, values beyond its range come back clipped to
    the largest float32 (which the engine clips again to the action bounds), so the cast stays finite."""
    if type(action) is np.ndarray and action.shape == tuple(expected_shape) and action.dtype.kind == "f":
        a = action.astype(np.float64, copy=False)
        total = np.add.reduce(a, axis=None)
        if math.isfinite(total):  # fast path: a NaN or inf makes the sum non-finite
            if dtype == np.float64 or action.dtype.itemsize <= 4 or abs(a).max() <= _F32_MAX:
                return a
            return np.clip(a, -_F32_MAX, _F32_MAX)
    a = as_real_array(action, "action")
    if a.shape != tuple(expected_shape):
        raise ValueError(f"action has the wrong shape: expected shape {tuple(expected_shape)}, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        if np.isnan(a).any():
            raise ValueError(f"action contains NaN at indices {np.argwhere(np.isnan(a)).tolist()[:8]}")
        raise ValueError(f"action contains inf at indices {np.argwhere(np.isinf(a)).tolist()[:8]}")
    if dtype != np.float64 and not abs(a).max() <= _F32_MAX:
        a = np.clip(a, -_F32_MAX, _F32_MAX)
    return a


def _is_tracer(v: Any) -> bool:
    """True for a JAX tracer (a value only known at run time under ``jit``/``vmap``)."""
    try:
        import jax
    except ImportError:  # pragma: no cover - NumPy-only install
        return False
    return isinstance(v, jax.core.Tracer)


def check_state(state: Any, num_quads: int, lead: tuple[int, ...] = (), name: str = "options['state']",
                room: tuple[Any, Any] | None = None) -> dict[str, Any]:
    """Validate a ``reset(options={"state": ...})`` dict; arrays are (*lead, N, ...).

    Values must be real numbers (:func:`as_real_array`) within the physical bounds: speeds
    |vel| <= SPEED_LIMIT m/s, body rates |omega| <= OMEGA_LIMIT rad/s per axis, ``motors`` in
    [0, 1], ``rot`` proper rotations; with these bounds every value is finite in float32 too (the
    JAX engine's dtype). ``name`` is how errors call the dict (e.g. ``"init_state"``). ``room`` =
    (low, high) corners (m, world) also requires ``pos`` and ``goals`` inside the room. Values
    that are JAX tracers (under ``jit``) get only the shape checks and are returned as they are."""
    if not isinstance(state, dict):
        raise ValueError(f"{name} must be a dict, got {type(state).__name__}")
    allowed = {"pos": (3,), "vel": (3,), "rot": (3, 3), "omega": (3,), "goals": (3,), "motors": (4,)}
    unknown = set(state) - set(allowed)
    if unknown:
        raise ValueError(f"{name} has unknown keys {sorted(unknown)}; allowed: {sorted(allowed)}")
    out: dict[str, Any] = {}
    for key, tail in allowed.items():
        if key not in state or state[key] is None:
            continue
        v = state[key]
        if key == "motors" and isinstance(v, str):
            if v not in ("zero", "hover"):
                raise ValueError(f"{name}['motors'] must be 'zero', 'hover' or an array, got {v!r}")
            out[key] = v
            continue
        shape = tuple(lead) + (num_quads,) + tail
        if _is_tracer(v):
            if tuple(np.shape(v)) != shape:
                raise ValueError(f"{name}['{key}'] has the wrong shape: expected shape {shape}, "
                                 f"got shape {tuple(np.shape(v))}")
            out[key] = v
            continue
        a = as_real_array(v, f"{name}['{key}']")
        if a.shape != shape:
            raise ValueError(f"{name}['{key}'] has the wrong shape: expected shape {shape}, "
                             f"got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name}['{key}'] contains NaN or inf")
        _check_bounds(a, key, f"{name}['{key}']")
        out[key] = a.copy()
    if isinstance(out.get("rot"), np.ndarray):
        R = out["rot"]
        err = np.abs(np.einsum("...ij,...kj->...ik", R, R) - np.eye(3)).max()
        if err > 1e-4 or (np.linalg.det(R) < 0).any():
            raise ValueError(f"{name}['rot'] must hold proper rotation matrices (orthonormal, det +1)")
    if room is not None:
        low, high = np.asarray(room[0], np.float64), np.asarray(room[1], np.float64)
        box = " x ".join(f"[{a:g}, {b:g}]" for a, b in zip(low, high))
        for key in ("pos", "goals"):
            a = out.get(key)
            if isinstance(a, np.ndarray):
                outside = ((a < low) | (a > high)).any(axis=-1)
                if outside.any():
                    idx = tuple(int(i) for i in np.argwhere(outside)[0])
                    raise ValueError(f"{name}['{key}'] must be inside the room {box} m; index {idx} is "
                                     f"{a[idx].tolist()}")
    return out


def _check_bounds(a: np.ndarray, key: str, label: str) -> None:
    """ValueError naming the first index beyond the physical bound of state ``key`` (see
    :func:`check_state`)."""
    if key == "vel":
        # |v|^2 against the limit^2 with a relative slack of 1e-12: a speed of exactly SPEED_LIMIT
        # split over the axes may round a hair above it
        bad = np.einsum("...i,...i->...", a, a) > SPEED_LIMIT**2 * (1.0 + 1e-12)
        what = f"speeds |v| <= SPEED_LIMIT = {SPEED_LIMIT:g} m/s"
        show = lambda idx: f"|v| = {float(np.linalg.norm(a[idx])):.4g} m/s"  # noqa: E731
    elif key == "omega":
        bad = np.abs(a) > OMEGA_LIMIT
        what = f"body rates |omega| <= OMEGA_LIMIT = {OMEGA_LIMIT:g} rad/s per axis"
        show = lambda idx: f"{float(a[idx]):.4g} rad/s"  # noqa: E731
    elif key == "motors":
        bad = (a < 0.0) | (a > 1.0)
        what = "normalized rotor thrusts in [0, 1]"
        show = lambda idx: f"{float(a[idx])!r}"  # noqa: E731
    else:
        return
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"{label} must hold {what}; index {idx} is {show(idx)}")


def check_obstacles(obstacles: Any, cfg: Any, lead: tuple[int, ...] = (), name: str = "options['obstacles']") -> Any:
    """Validate given column centres (SPEC_obstacles; ``reset(options={"obstacles": ...})``): an
    (M, 2) array (x, y m, world-local; or ``lead + (M, 2)``: one map per world), M <= the column
    slots, finite, inside the room. Needs ``cfg.obstacles``. Tracers get the shape checks only."""
    o = cfg.obstacles
    if o is None:
        raise ValueError(f"{name} given but obstacles are off; turn them on with EnvConfig(obstacles=ObstacleConfig())")
    shape = tuple(np.shape(obstacles))
    if len(shape) not in (2, 2 + len(lead)) or shape[-1] != 2 or (len(shape) > 2 and shape[:-2] != tuple(lead)):
        want = "(M, 2)" + (f" or {tuple(lead) + ('M', 2)}" if lead else "")
        raise ValueError(f"{name} must be an array of column centres (x, y) in m of shape {want}, got shape {shape}")
    if shape[-2] > o.slots:
        raise ValueError(f"{name}: {shape[-2]} columns given, more than the {o.slots} column slots per world "
                         f"(raise ObstacleConfig.max_columns, at most {o.num_cells})")
    if _is_tracer(obstacles):
        return obstacles
    a = as_real_array(obstacles, name)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or inf")
    lo, hi = np.asarray(cfg.room_low[:2], np.float64), np.asarray(cfg.room_high[:2], np.float64)
    if ((a < lo) | (a > hi)).any():
        raise ValueError(f"{name} must hold centres inside the room [{lo[0]:g}, {hi[0]:g}] x [{lo[1]:g}, {hi[1]:g}] m")
    return a.copy()


ENGINES = ("mujoco", "jax")


def check_engine(engine: Any) -> str:
    """``engine`` if it is one of :data:`ENGINES` ("mujoco": CPU MuJoCo, the reference; "jax": MJX), else
    ValueError."""
    if not isinstance(engine, str) or engine not in ENGINES:
        raise ValueError(f"engine must be one of {list(ENGINES)}, got {engine!r}")
    return engine
