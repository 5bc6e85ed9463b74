"""Policies that fly the quads: trained MLPs (NumPy inference), the baseline controller, random.

Everything here needs NumPy only; JAX is never imported (the trainer in
``quadswarm_mj.training`` is the only JAX user), so the CPU env, ``scripts/evaluate.py`` and
``scripts/render_rollout.py --policy pretrained:<name>`` run without JAX.

Policy file format (``.npz``, read with ``allow_pickle=False``, so loading cannot run code):

================== ============ ===============================================================
key                dtype        content
================== ============ ===============================================================
``meta``           unicode 0-d  JSON: ``format`` (``"quadswarm_mj.mlp_policy/1"``), ``activation``
                                (``"tanh"``, ``"relu"``, ``"swish"`` or ``"elu"``), ``obs_dim``,
                                ``action_dim`` (4), ``env`` (the EnvConfig fields the observation
                                layout depends on, e.g. ``num_quads``, ``num_neighbors``), and
                                free-form ``train`` information
``layer_i/kernel`` float32      (in_i, out_i), i = 0 .. L-1; hidden layers use the activation,
``layer_i/bias``   float32      (out_i,); the last layer is linear with 2 * action_dim outputs:
                                [mean (pre-tanh), std parameters]
``obs_mean``       float32      (obs_dim,) observation normalization: x' = (x - mean) / std
``obs_std``        float32      (obs_dim,)
================== ============ ===============================================================

Other keys (``value/...``: the trainer's critic, used to resume training) are ignored here.
The deterministic action is ``clip(tanh(mean), -1, 1)``: the mode of Brax's tanh-normal policy.

Shipped policies live in ``quadswarm_mj/pretrained/`` and are listed in ``manifest.json`` with
their SHA-256 and size; :func:`load_policy` (``"pretrained:<name>"``) refuses a file whose hash
or size differs (tampered, truncated or replaced) with a ``ValueError``.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

FORMAT = "quadswarm_mj.mlp_policy/1"
PRETRAINED_PREFIX = "pretrained:"
MANIFEST = "manifest.json"
ACTIVATIONS = ("tanh", "relu", "swish", "elu")
#: EnvConfig fields that fix the observation layout; stored in a policy's ``meta["env"]``.
OBS_ENV_FIELDS = ("num_quads", "num_neighbors", "obs_self", "neighbor_sort", "neighbor_vel_clip", "normalize_obs",
                  "room_size")


def _activation(name: str, x: np.ndarray) -> np.ndarray:
    if name == "tanh":
        return np.tanh(x)
    if name == "relu":
        return np.maximum(x, 0.0)
    if name == "swish":
        return x / (1.0 + np.exp(-x))
    if name == "elu":
        return np.where(x > 0, x, np.expm1(np.minimum(x, 0.0)))
    raise ValueError(f"activation must be one of {ACTIVATIONS}, got {name!r}")


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
    def env_kwargs(self) -> dict[str, Any]:
        """EnvConfig overrides that reproduce the observation layout the policy was trained on."""
        env = dict(self.meta.get("env", {}))
        if "room_size" in env:
            env["room_size"] = tuple(env["room_size"])
        return env

    def __call__(self, obs: Any) -> np.ndarray:
        """Deterministic actions: obs (..., obs_dim) -> (..., 4) float32 in [-1, 1] (e.g. (N, obs_dim) -> (N, 4))."""
        x = np.asarray(obs, dtype=np.float64)
        if x.ndim < 1 or x.shape[-1] != self.obs_dim:
            raise ValueError(f"observations must have shape (..., {self.obs_dim}), e.g. (N, {self.obs_dim}); "
                             f"got {x.shape}")
        lead = x.shape[:-1]
        h = (x.reshape(-1, self.obs_dim) - self.obs_mean) / self.obs_std
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
    arrays = policy_arrays(kernels, biases, obs_mean, obs_std, meta, extra)
    for k, v in arrays.items():
        if v.dtype == object:
            raise ValueError(f"array {k!r} has dtype object; policy files hold plain numeric/unicode arrays only")
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(buf.getvalue())
    return sha256_file(path)


def load_policy_file(path: str | os.PathLike, name: str | None = None) -> MLPPolicy:
    """Read a policy ``.npz`` (``allow_pickle=False``); malformed files raise ``ValueError``."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"policy file {str(path)!r} does not exist")
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != b"PK\x03\x04":
        raise ValueError(f"policy file {str(path)!r} is not a readable .npz (not a zip archive)")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as e:  # noqa: BLE001 - zip/format errors of a corrupt file, or pickled objects
        raise ValueError(f"policy file {str(path)!r} is not a readable .npz of plain arrays "
                         f"({type(e).__name__}: {e})") from e
    if "meta" not in arrays:
        raise ValueError(f"policy file {str(path)!r} has no 'meta' entry; not a quadswarm_mj policy")
    try:
        meta = json.loads(str(arrays["meta"]))
    except json.JSONDecodeError as e:
        raise ValueError(f"policy file {str(path)!r}: 'meta' is not valid JSON ({e})") from e
    if meta.get("format") != FORMAT:
        raise ValueError(f"policy file {str(path)!r} has format {meta.get('format')!r}, expected {FORMAT!r}")
    kernels, biases = [], []
    i = 0
    while f"layer_{i}/kernel" in arrays:
        kernels.append(arrays[f"layer_{i}/kernel"].astype(np.float64))
        biases.append(arrays[f"layer_{i}/bias"].astype(np.float64))
        i += 1
    if not kernels or "obs_mean" not in arrays or "obs_std" not in arrays:
        raise ValueError(f"policy file {str(path)!r} lacks layer_0/kernel, obs_mean or obs_std")
    pol = MLPPolicy(kernels, biases, arrays["obs_mean"].astype(np.float64), arrays["obs_std"].astype(np.float64),
                    activation=meta.get("activation", "tanh"), meta=meta, name=name or path.stem)
    if "obs_dim" in meta and int(meta["obs_dim"]) != pol.obs_dim:
        raise ValueError(f"policy file {str(path)!r}: meta obs_dim {meta['obs_dim']} != weights {pol.obs_dim}")
    return pol


# ---------------------------------------------------------------------------- pretrained
def pretrained_dir() -> Path:
    """Directory of the shipped policies (package data)."""
    return Path(str(resources.files("quadswarm_mj") / "pretrained"))


def read_manifest(directory: str | os.PathLike | None = None) -> dict[str, Any]:
    """The manifest of the shipped policies: ``{"policies": {name: {"file", "sha256", "bytes", ...}}}``."""
    d = Path(directory) if directory is not None else pretrained_dir()
    p = d / MANIFEST
    if not p.is_file():
        raise ValueError(f"no pretrained-policy manifest at {str(p)!r}")
    try:
        man = json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"manifest {str(p)!r} is not valid JSON ({e})") from e
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


def load_pretrained(name: str, directory: str | os.PathLike | None = None) -> MLPPolicy:
    """Load a shipped policy by name after checking its size and SHA-256 against the manifest."""
    d = Path(directory) if directory is not None else pretrained_dir()
    man = read_manifest(d)
    entry = man["policies"].get(name)
    if entry is None:
        raise ValueError(f"unknown pretrained policy {name!r}; known: {', '.join(sorted(man['policies']))}")
    try:
        fname, sha = entry["file"], entry["sha256"]
    except (KeyError, TypeError):
        raise ValueError(f"manifest entry {name!r} needs 'file' and 'sha256'") from None
    if Path(fname).name != fname:
        raise ValueError(f"manifest entry {name!r}: file {fname!r} must be a plain file name in {str(d)!r}")
    path = d / fname
    verify_file(path, sha, entry.get("bytes"))
    pol = load_policy_file(path, name=f"{PRETRAINED_PREFIX}{name}")
    pol.meta = {**pol.meta, "manifest": {k: v for k, v in entry.items() if k not in ("file", "sha256", "bytes")}}
    return pol


# ---------------------------------------------------------------------------- baselines
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

        self.ctrl = PositionController(cfg)

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
        a = np.asarray(self.ctrl(state, goals, gv, params=params), dtype=np.float32)
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
