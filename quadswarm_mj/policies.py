"""Policies that fly the quads: trained MLP, deep-sets and attention networks (NumPy inference), the baseline
controller, random.

NumPy only: JAX is never imported here, so the CPU env, ``scripts/evaluate.py`` and
``scripts/render_rollout.py --policy pretrained:<name>`` run without JAX. A policy file is one ``.npz``
read with ``allow_pickle=False`` (formats ``quadswarm_mj.mlp_policy/1`` and, for encoders,
``quadswarm_mj.policy/2``); the deterministic action is ``clip(tanh(mean), -1, 1)``. :func:`load_policy`
(``"pretrained:<name>"``) checks a shipped file's SHA-256 and size against ``pretrained/manifest.json``.
The file formats, key by key: docs/training.md ("Policy files").
"""

from __future__ import annotations

import hashlib
import json
import os
import zipfile
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from quadswarm_mj.encoder_policy import (  # noqa: F401  (re-exported)
    ARCH_PRESETS,
    ENCODER_FORMAT,
    ENCODER_TYPES,
    LN_EPS,
    NEIGHBOR_DIM,
    OBSTACLE_DIM,
    SELF_DIMS,
    EncoderPolicy,
    _encoder_from_arrays,
    _write_npz,
    attention_tokens,
    count_params,
    encoder_forward,
    encoder_policy_arrays,
    layout_from_env,
    layout_obs_dim,
    num_tokens,
    param_shapes,
    random_encoder_policy,
    save_encoder_policy,
    validate_arch,
    validate_layout,
)
from quadswarm_mj.policy_common import (  # noqa: F401  (re-exported)
    ACTIVATIONS,
    OBS_ENV_FIELDS,
    _activation,
    _env_kwargs,
    _normalized_rows,
)
from quadswarm_mj.policy_files import (  # noqa: F401  (re-exported)
    MAX_MEMBERS,
    MAX_META_BYTES,
    MAX_POLICY_PARAMS,
    _check_meta,
    _encoder_member_shapes,
    _is_int,
    _member_headers,
    _mlp_member_shapes,
    _read_member,
    _read_meta,
    _short,
)

FORMAT = "quadswarm_mj.mlp_policy/1"
PRETRAINED_PREFIX = "pretrained:"
MANIFEST = "manifest.json"

def sha256_file(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


# ---------------------------------------------------------------------------- MLP policy
@dataclass
class MLPPolicy:
    """A deterministic MLP policy: observations (N, obs_dim) -> actions (N, 4) in [-1, 1].

    ``kernels[i]`` is (in_i, out_i), ``biases[i]`` (out_i,); the last layer outputs
    2 * action_dim values of which the first action_dim are the pre-tanh mean.
    """

    kernels: list[np.ndarray]
    biases: list[np.ndarray]
    obs_mean: np.ndarray
    obs_std: np.ndarray
    activation: str = "tanh"
    meta: dict[str, Any] = field(default_factory=dict)
    name: str = "mlp"

    def __post_init__(self) -> None:
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {ACTIVATIONS}, got {self.activation!r}")
        if not self.kernels or len(self.kernels) != len(self.biases):
            raise ValueError("an MLP policy needs at least one layer and one bias per kernel")
        prev = self.kernels[0].shape[0]
        for i, (k, b) in enumerate(zip(self.kernels, self.biases)):
            if k.ndim != 2 or b.shape != (k.shape[1],) or k.shape[0] != prev:
                raise ValueError(f"layer {i}: kernel {k.shape} and bias {b.shape} do not chain (expected input {prev})")
            prev = k.shape[1]
        if prev % 2:
            raise ValueError(f"the last layer must output 2 * action_dim values, got {prev}")
        d = self.kernels[0].shape[0]
        if self.obs_mean.shape != (d,) or self.obs_std.shape != (d,):
            raise ValueError(f"obs_mean/obs_std must have shape ({d},), got {self.obs_mean.shape}, "
                             f"{self.obs_std.shape}")
        if not (np.all(np.isfinite(self.obs_std)) and np.all(self.obs_std > 0)):
            raise ValueError("obs_std must be finite and positive")
        for a in [*self.kernels, *self.biases, self.obs_mean]:
            if not np.all(np.isfinite(a)):
                raise ValueError("policy weights must be finite")

    @property
    def obs_dim(self) -> int:
        return int(self.kernels[0].shape[0])

    @property
    def action_dim(self) -> int:
        return int(self.kernels[-1].shape[1] // 2)

    @property
    def num_params(self) -> int:
        """Deployed actor parameters (the last layer's mean part only)."""
        n = sum(k.size + b.size for k, b in zip(self.kernels[:-1], self.biases[:-1]))
        return int(n + (self.kernels[-1].shape[0] + 1) * self.action_dim)

    @property
    def obs_layout(self) -> dict[str, int] | None:
        """The observation layout (self, K neighbours, obstacles) if the file records or implies it."""
        lay = self.meta.get("obs_layout")
        return dict(lay) if lay else layout_from_env(self.meta.get("env", {}), self.obs_dim)

    @property
    def env_kwargs(self) -> dict[str, Any]:
        """EnvConfig overrides that reproduce the observation layout the policy was trained on."""
        return _env_kwargs(self.meta)

    def __call__(self, obs: Any) -> np.ndarray:
        """Deterministic actions: obs (..., obs_dim) -> (..., 4) float32 in [-1, 1] (e.g. (N, obs_dim) -> (N, 4))."""
        lead, h = _normalized_rows(obs, self.obs_dim, self.obs_mean, self.obs_std)
        last = len(self.kernels) - 1
        for i, (k, b) in enumerate(zip(self.kernels, self.biases)):
            h = h @ k + b
            if i < last:
                h = _activation(self.activation, h)
        a = np.clip(np.tanh(h[:, : self.action_dim]), -1.0, 1.0).astype(np.float32)
        return a.reshape(lead + (self.action_dim,))

    def act(self, obs: Any, info: dict[str, Any] | None = None) -> np.ndarray:
        """Same as calling the policy (``info`` is ignored); the common interface of all policies."""
        return self(obs)


def policy_arrays(kernels: list[np.ndarray], biases: list[np.ndarray], obs_mean: np.ndarray, obs_std: np.ndarray,
                  meta: dict[str, Any], extra: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """The arrays of a policy file (see the module docstring)."""
    meta = {"format": FORMAT, **meta}
    meta.setdefault("arch", {"type": "mlp", "activation": meta.get("activation", "tanh"),
                             "layers": [int(np.shape(k)[1]) for k in kernels]})
    if "obs_layout" not in meta:
        lay = layout_from_env(meta.get("env", {}), int(np.shape(kernels[0])[0]))
        if lay is not None:
            meta["obs_layout"] = lay
    out: dict[str, np.ndarray] = {"meta": np.array(json.dumps(meta, sort_keys=True))}
    for i, (k, b) in enumerate(zip(kernels, biases)):
        out[f"layer_{i}/kernel"] = np.asarray(k, dtype=np.float32)
        out[f"layer_{i}/bias"] = np.asarray(b, dtype=np.float32)
    out["obs_mean"] = np.asarray(obs_mean, dtype=np.float32)
    out["obs_std"] = np.asarray(obs_std, dtype=np.float32)
    for k, v in (extra or {}).items():
        out[k] = np.asarray(v)
    return out


def save_policy(path: str | os.PathLike, kernels: list[np.ndarray], biases: list[np.ndarray], obs_mean: np.ndarray,
                obs_std: np.ndarray, meta: dict[str, Any], extra: dict[str, np.ndarray] | None = None) -> str:
    """Write a policy ``.npz`` (no pickled objects) and return its SHA-256."""
    return _write_npz(path, policy_arrays(kernels, biases, obs_mean, obs_std, meta, extra))


def load_policy_file(path: str | os.PathLike, name: str | None = None) -> MLPPolicy | EncoderPolicy:
    """Read a policy ``.npz`` (MLP or encoder format); malformed or hostile files raise ``ValueError``.

    Nothing in the file can run code (no pickles) or cost more than its architecture: every member's
    ``.npy`` header (dtype, shape) is read first, and the members the policy uses are checked against
    the architecture ``meta`` declares (shapes, at most :data:`MAX_POLICY_PARAMS` values, uncompressed
    sizes) before any of their data is inflated; members the policy does not use are never read.
    """
    path = Path(path)
    where = f"policy file {str(path)!r}"
    if not path.is_file():
        raise ValueError(f"{where} does not exist")
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != b"PK\x03\x04":
        raise ValueError(f"{where} is not a readable .npz (not a zip archive)")
    try:
        zf = zipfile.ZipFile(path)
    except Exception as e:  # noqa: BLE001 - BadZipFile, OSError, ... of a corrupt file
        raise ValueError(f"{where} is not a readable .npz ({type(e).__name__}: {e})") from e
    with zf:
        headers = _member_headers(zf, where)
        meta = _read_meta(zf, headers, where)
        fmt = meta.get("format")
        if fmt not in (FORMAT, ENCODER_FORMAT):
            raise ValueError(f"{where} has format {_short(fmt)}, expected {FORMAT!r} or {ENCODER_FORMAT!r}")
        _check_meta(meta, where)
        shapes = _encoder_member_shapes(meta, headers, where) if fmt == ENCODER_FORMAT else \
            _mlp_member_shapes(meta, headers, where)
        arrays = {k: _read_member(zf, headers[k], where) for k in shapes}
    if fmt == ENCODER_FORMAT:
        return _encoder_from_arrays(arrays, meta, path, name)
    n_layers = sum(k.endswith("/kernel") for k in shapes)
    kernels = [arrays[f"layer_{i}/kernel"].astype(np.float64) for i in range(n_layers)]
    biases = [arrays[f"layer_{i}/bias"].astype(np.float64) for i in range(n_layers)]
    try:
        pol = MLPPolicy(kernels, biases, arrays["obs_mean"].astype(np.float64), arrays["obs_std"].astype(np.float64),
                        activation=meta.get("activation", "tanh"), meta=meta, name=name or path.stem)
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from e
    return pol


# ---------------------------------------------------------------------------- pretrained
def pretrained_dir() -> Path:
    """Directory of the shipped policies (package data)."""
    return Path(str(resources.files("quadswarm_mj") / "pretrained"))


def read_manifest(directory: str | os.PathLike | None = None) -> dict[str, Any]:
    """The manifest of the shipped policies: ``{"policies": {name: {"file", "sha256", "bytes", ...}}}``;
    ``ValueError`` if it is missing or malformed."""
    d = Path(directory) if directory is not None else pretrained_dir()
    p = d / MANIFEST
    if not p.is_file():
        raise ValueError(f"no pretrained-policy manifest at {str(p)!r}")
    try:
        man = json.loads(p.read_bytes().decode("utf-8"))
    except OSError as e:
        raise ValueError(f"manifest {str(p)!r} cannot be read ({e.strerror or e})") from None
    except (ValueError, RecursionError) as e:  # JSONDecodeError, UnicodeDecodeError; nesting too deep
        raise ValueError(f"manifest {str(p)!r} is not valid JSON ({type(e).__name__}: {str(e)[:200]})") from None
    if not isinstance(man, dict) or not isinstance(man.get("policies"), dict):
        raise ValueError(f"manifest {str(p)!r} must hold a 'policies' mapping")
    return man


def list_pretrained(directory: str | os.PathLike | None = None) -> list[str]:
    """Names accepted by ``load_policy("pretrained:<name>")``."""
    return sorted(read_manifest(directory)["policies"])


def verify_file(path: str | os.PathLike, sha256: str, size: int | None = None) -> None:
    """Raise ``ValueError`` unless the file exists with this size (bytes) and SHA-256."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"policy file {str(p)!r} listed in the manifest is missing")
    actual_size = p.stat().st_size
    if size is not None and actual_size != int(size):
        raise ValueError(f"policy file {str(p)!r} has {actual_size} bytes but the manifest lists {size}: the file is "
                         "truncated or was replaced; reinstall quadswarm_mj")
    digest = sha256_file(p)
    if digest != sha256:
        raise ValueError(f"policy file {str(p)!r} fails its SHA-256 check (manifest {sha256}, file {digest}): the file "
                         "was tampered with or corrupted; reinstall quadswarm_mj")


def load_pretrained(name: str, directory: str | os.PathLike | None = None) -> MLPPolicy | EncoderPolicy:
    """Load a shipped policy by name after checking its size and SHA-256 against the manifest."""
    d = Path(directory) if directory is not None else pretrained_dir()
    man = read_manifest(d)
    entry = man["policies"].get(name)
    if name not in man["policies"]:
        raise ValueError(f"unknown pretrained policy {name!r}; known: {', '.join(sorted(man['policies']))}")
    where = f"manifest entry {name!r} in {str(d / MANIFEST)!r}"
    if not isinstance(entry, dict):
        raise ValueError(f"{where} must be a mapping with 'file' and 'sha256', got {_short(entry)}")
    fname, sha, size = entry.get("file"), entry.get("sha256"), entry.get("bytes")
    if not isinstance(fname, str) or not fname or Path(fname).name != fname:
        raise ValueError(f"{where}: file must be a plain file name in {str(d)!r}, got {_short(fname)}")
    if not isinstance(sha, str) or len(sha) != 64 or any(c not in "0123456789abcdef" for c in sha.lower()):
        raise ValueError(f"{where}: sha256 must be 64 hex digits, got {_short(sha)}")
    if size is not None and not _is_int(size):
        raise ValueError(f"{where}: bytes must be an int >= 0, got {_short(size)}")
    path = d / fname
    verify_file(path, sha.lower(), size)
    pol = load_policy_file(path, name=f"{PRETRAINED_PREFIX}{name}")
    pol.meta = {**pol.meta, "manifest": {k: v for k, v in entry.items() if k not in ("file", "sha256", "bytes")}}
    return pol


# ---------------------------------------------------------------------------- baselines
#: m from a column's surface within which the baseline controller steers away (with obstacles on)
OBSTACLE_STEER_RADIUS = 0.6


def baseline_gains(cfg: Any = None, avoid_radius: float = 0.0) -> Any:
    """The baseline controller's ``ControllerGains`` for ``cfg``: neighbours within ``avoid_radius`` m
    repel (0: off); with obstacles on it steers around the columns (``OBSTACLE_STEER_RADIUS`` m from the
    surface, the configured column radius)."""
    from quadswarm_mj.controllers import ControllerGains

    o = getattr(cfg, "obstacles", None)
    if o is None:
        return ControllerGains(avoid_radius=avoid_radius)
    return ControllerGains(avoid_radius=avoid_radius, obstacle_radius=OBSTACLE_STEER_RADIUS, column_radius=0.5 * o.size)

class ControllerPolicy:
    """The baseline position controller (``quadswarm_mj.controllers.PositionController``) as a policy.

    It needs the true state and goals, not the observation: ``act(obs, info)`` reads
    ``info["state"]`` (pos, vel, rot, omega; (N, ...)), ``info["goals"]``, ``info["goal_vel"]``
    and ``info["params"]`` (the drawn airframe parameters), as returned by ``QuadSwarmEnv``.
    """

    name = "controller"
    env_kwargs: dict[str, Any] = {}

    def __init__(self, cfg: Any = None):
        from quadswarm_mj.controllers import PositionController

        # with obstacles: steer around the columns of ``info["obstacles"]`` (as scripts/render_rollout.py)
        self.ctrl = PositionController(cfg, baseline_gains(cfg))

    def act(self, obs: Any, info: dict[str, Any] | None = None) -> np.ndarray:
        if info is None or "state" not in info or "goals" not in info:
            raise ValueError("the controller policy needs info with 'state' and 'goals' (as QuadSwarmEnv returns)")
        st = info["state"]
        state = {k: np.asarray(st[k]) for k in ("pos", "vel", "rot", "omega")}
        single = state["pos"].ndim == 1
        if single:
            state = {k: v[None] for k, v in state.items()}
        goals = np.asarray(info["goals"]).reshape(state["pos"].shape)
        gv = info.get("goal_vel")
        gv = None if gv is None else np.asarray(gv).reshape(state["pos"].shape)
        params = info.get("params")
        a = np.asarray(self.ctrl(state, goals, gv, params=params, obstacles=info.get("obstacles")), dtype=np.float32)
        a = np.clip(a, -1.0, 1.0)
        return a.reshape(np.shape(obs)[:-1] + (4,))  # (4,) for a single quad's flat observation


class RandomPolicy:
    """Uniform random actions in [-1, 1] (a lower baseline)."""

    name = "random"
    env_kwargs: dict[str, Any] = {}

    def __init__(self, seed: int | None = None):
        self.rng = np.random.default_rng(seed)

    def act(self, obs: Any, info: dict[str, Any] | None = None) -> np.ndarray:
        shape = np.shape(obs)[:-1] + (4,)
        return self.rng.uniform(-1.0, 1.0, size=shape).astype(np.float32)


def load_policy(spec: str | os.PathLike, cfg: Any = None, seed: int | None = None) -> Any:
    """A policy from a spec: ``"pretrained:<name>"`` (shipped, hash-checked), a path to a policy
    ``.npz`` (a training checkpoint), ``"controller"`` or ``"random"``.

    Every returned policy has ``act(obs, info) -> actions`` ((N, 4) float32 in [-1, 1]) and
    ``env_kwargs`` (EnvConfig overrides its observations need); MLP policies are also callable
    on observations alone. ``cfg`` (EnvConfig) is used by the controller; ``seed`` by ``random``.
    """
    s = os.fspath(spec)
    if not isinstance(s, str) or not s:
        raise ValueError(f"policy spec must be a non-empty string, got {spec!r}")
    if s.startswith(PRETRAINED_PREFIX):
        return load_pretrained(s[len(PRETRAINED_PREFIX):])
    if s == "controller":
        return ControllerPolicy(cfg)
    if s == "random":
        return RandomPolicy(seed)
    if s.endswith(".npz") or Path(s).is_file():
        return load_policy_file(s)
    raise ValueError(f"unknown policy {s!r}: use 'pretrained:<name>' (one of {', '.join(_safe_names())}), a path "
                     "to a policy .npz, 'controller' or 'random'")


def _safe_names() -> list[str]:
    try:
        return list_pretrained()
    except ValueError:
        return []
