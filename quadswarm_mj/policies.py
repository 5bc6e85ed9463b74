"""Policies that fly the quads: trained MLP, deep-sets and attention networks (NumPy inference), the baseline
controller, random.

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

Encoder policies (deep sets, attention; SPEC_obstacles C.1) use format ``"quadswarm_mj.policy/2"``:

================== ============ ===============================================================
key                dtype        content
================== ============ ===============================================================
``meta``           unicode 0-d  JSON: ``format``, ``arch`` (see :func:`validate_arch`: ``type``
                                ``"deepsets"`` or ``"attention"``, layer sizes, ``activation``,
                                heads), ``obs_layout`` (``self_dim`` 18/19/24, ``num_neighbors``
                                K, ``neighbor_dim`` 6, ``obstacle_dim`` 9 or 0), ``obs_dim``,
                                ``action_dim``, ``env``, ``train``
``actor/<name>``   float32      the actor's parameters, named as the flax modules of
                                ``quadswarm_mj.training.networks`` (e.g. ``actor/self_0/kernel``,
                                ``actor/attn/w_q/kernel``); shapes in :func:`param_shapes`
``obs_mean``       float32      (obs_dim,) observation normalization: x' = (x - mean) / std
``obs_std``        float32      (obs_dim,)
================== ============ ===============================================================

The observation is ``[self (self_dim) | K x (rel_pos 3, rel_vel 3) | obstacle SDF (obstacle_dim)]``;
MLP files written now also record ``arch`` (``{"type": "mlp", "layers": [...]}``) and, when the
``env`` entry fixes it, ``obs_layout`` in their ``meta`` (older files load unchanged).

Shipped policies live in ``quadswarm_mj/pretrained/`` and are listed in ``manifest.json`` with
their SHA-256 and size; :func:`load_policy` (``"pretrained:<name>"``) refuses a file whose hash
or size differs (tampered, truncated or replaced) with a ``ValueError``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import math
import os
import zipfile
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from quadswarm_mj.outfiles import atomic_write_bytes

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


def _env_kwargs(meta: dict[str, Any]) -> dict[str, Any]:
    """The EnvConfig overrides recorded in a policy file's metadata (JSON lists back to tuples)."""
    env = meta.get("env", {})
    env = dict(env) if isinstance(env, dict) else {}  # a loaded file's env was checked (_check_meta)
    if isinstance(env.get("room_size"), list):
        env["room_size"] = tuple(env["room_size"])
    return env


def _normalized_rows(obs: Any, obs_dim: int, mean: np.ndarray, std: np.ndarray) -> tuple[tuple[int, ...], np.ndarray]:
    """(leading shape, (rows, obs_dim) normalized float64 observations); ValueError on a wrong last axis."""
    x = np.asarray(obs, dtype=np.float64)
    if x.ndim < 1 or x.shape[-1] != obs_dim:
        raise ValueError(f"observations must have shape (..., {obs_dim}), e.g. (N, {obs_dim}); got {x.shape}")
    return x.shape[:-1], (x.reshape(-1, obs_dim) - mean) / std


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


#: Most values (actor parameters and normalization) a policy file may declare: 16.8 M, 10x the largest
#: preset (``attention_large``, ~1.5 M); a file declaring more is refused before anything is inflated.
MAX_POLICY_PARAMS = 1 << 24
#: Most bytes of a policy file's ``meta`` JSON, and most members of the archive.
MAX_META_BYTES = 1 << 22
MAX_MEMBERS = 4096


@dataclass(frozen=True)
class _Member:
    """A ``.npy`` member of a policy archive, from its header: the data is not read."""

    key: str
    info: zipfile.ZipInfo
    shape: tuple[int, ...]
    dtype: np.dtype
    offset: int  # bytes of magic and header before the data

    @property
    def nbytes(self) -> int:
        return math.prod(self.shape) * self.dtype.itemsize


def _short(v: Any, n: int = 80) -> str:
    """repr of a (possibly huge, hostile) value for an error message, at most ``n`` characters."""
    r = repr(v)
    return r if len(r) <= n else r[: n - 3] + "..."


def _member_headers(zf: zipfile.ZipFile, where: str) -> dict[str, _Member]:
    """Every ``.npy`` member's header (a few hundred bytes inflated per member); object dtypes refused.
    Members that are not ``.npy`` arrays are left alone (never read)."""
    infos = zf.infolist()
    if len(infos) > MAX_MEMBERS:
        raise ValueError(f"{where} has {len(infos)} members, more than a policy file holds ({MAX_MEMBERS})")
    out: dict[str, _Member] = {}
    for info in infos:
        if not info.filename.endswith(".npy"):
            continue
        key = info.filename[: -len(".npy")]
        if key in out:
            raise ValueError(f"{where} holds member {key!r} twice")
        try:
            with zf.open(info) as f:
                version = np.lib.format.read_magic(f)
                if version == (1, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
                elif version == (2, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
                else:
                    raise ValueError(f".npy format version {version} is not supported")
                offset = f.tell()
        except Exception as e:  # noqa: BLE001 - zip, zlib and header errors of a corrupt or hostile member
            raise ValueError(f"{where}: member {key!r} is not a readable .npy array ({type(e).__name__}: {e})") from e
        if dtype.hasobject:
            raise ValueError(f"{where}: member {key!r} has dtype object (pickled Python objects); policy files hold "
                             "plain numeric/unicode arrays only")
        out[key] = _Member(key, info, tuple(int(x) for x in shape), dtype, offset)
    return out


def _read_member(zf: zipfile.ZipFile, m: _Member, where: str) -> np.ndarray:
    """The data of a member whose header was checked: its uncompressed size must be what the header declares."""
    if m.info.file_size != m.offset + m.nbytes:
        raise ValueError(f"{where}: member {m.key!r} holds {m.info.file_size} bytes but its header "
                         f"(shape {m.shape}, dtype {m.dtype}) declares {m.offset + m.nbytes}")
    try:
        with zf.open(m.info) as f:
            return np.lib.format.read_array(f, allow_pickle=False)
    except Exception as e:  # noqa: BLE001 - a corrupt stream (CRC, zlib, truncation)
        raise ValueError(f"{where}: member {m.key!r} is not a readable .npy array ({type(e).__name__}: {e})") from e


def _read_meta(zf: zipfile.ZipFile, headers: dict[str, _Member], where: str) -> dict[str, Any]:
    m = headers.get("meta")
    if m is None:
        raise ValueError(f"{where} has no 'meta' entry; not a quadswarm_mj policy")
    if m.dtype.kind not in "US" or m.shape != ():
        raise ValueError(f"{where}: 'meta' must be a 0-d string array, got dtype {m.dtype} and shape {m.shape}")
    if m.nbytes > MAX_META_BYTES:
        raise ValueError(f"{where}: 'meta' declares {m.nbytes} bytes, more than {MAX_META_BYTES}")
    raw = _read_member(zf, m, where).item()
    try:
        text = raw.decode("utf-8") if isinstance(raw, bytes) else str(raw)
        meta = json.loads(text)
    except (ValueError, RecursionError) as e:  # JSONDecodeError, UnicodeDecodeError; nesting too deep
        raise ValueError(f"{where}: 'meta' is not valid JSON ({type(e).__name__}: {str(e)[:200]})") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{where}: 'meta' must be a JSON object")
    return meta


def _is_int(v: Any, lo: int = 0) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= lo


def _check_meta(meta: dict[str, Any], where: str) -> None:
    """The metadata fields the loader and its users read have the types they need (``ValueError`` naming the
    field otherwise); unknown top-level fields are free-form."""
    for key in ("obs_dim", "action_dim"):
        if key in meta and not _is_int(meta[key], 1):
            raise ValueError(f"{where}: meta {key} must be a positive int, got {_short(meta[key])}")
    if "activation" in meta and (not isinstance(meta["activation"], str) or meta["activation"] not in ACTIVATIONS):
        raise ValueError(f"{where}: meta activation must be one of {ACTIVATIONS}, got {_short(meta['activation'])}")
    for key in ("env", "arch", "obs_layout", "train"):
        if key in meta and not isinstance(meta[key], dict):
            raise ValueError(f"{where}: meta {key} must be a JSON object, got {_short(meta[key])}")
    if "obs_layout" in meta:
        try:
            validate_layout(meta["obs_layout"])
        except ValueError as e:
            raise ValueError(f"{where}: meta {e}") from None
    env = meta.get("env", {})
    from quadswarm_mj.config import EnvConfig

    fields = {f.name for f in dataclasses.fields(EnvConfig)}
    unknown = sorted(_short(k) for k in env if k not in fields)
    if unknown:
        raise ValueError(f"{where}: meta env has fields EnvConfig does not know: {', '.join(unknown)}")
    if "num_quads" in env and not _is_int(env["num_quads"], 1):
        raise ValueError(f"{where}: meta env num_quads must be a positive int, got {_short(env['num_quads'])}")
    if env.get("num_neighbors") is not None and not _is_int(env["num_neighbors"]):
        raise ValueError(f"{where}: meta env num_neighbors must be an int >= 0 or null, "
                         f"got {_short(env['num_neighbors'])}")
    if "obs_self" in env and env["obs_self"] not in SELF_DIMS:
        raise ValueError(f"{where}: meta env obs_self must be one of {tuple(SELF_DIMS)}, got {_short(env['obs_self'])}")
    rs = env.get("room_size")
    if "room_size" in env and not (isinstance(rs, list) and len(rs) == 3 and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) for x in rs)):
        raise ValueError(f"{where}: meta env room_size must be a list of 3 numbers (m), got {_short(rs)}")


def _numeric(m: _Member, where: str) -> None:
    if m.dtype.kind not in "fiu":
        raise ValueError(f"{where}: member {m.key!r} must hold real numbers, got dtype {m.dtype}")


def _expect(headers: dict[str, _Member], key: str, shape: tuple[int, ...], where: str) -> None:
    m = headers.get(key)
    if m is None:
        raise ValueError(f"{where} lacks {key!r}")
    _numeric(m, where)
    if m.shape != tuple(shape):
        raise ValueError(f"{where}: member {key!r} has shape {m.shape}, the architecture needs {tuple(shape)}")


def _check_size(shapes: dict[str, tuple[int, ...]], where: str) -> None:
    total = sum(math.prod(s) for s in shapes.values())
    if total > MAX_POLICY_PARAMS:
        raise ValueError(f"{where} declares {total} parameters, more than a policy may hold ({MAX_POLICY_PARAMS})")


def _mlp_member_shapes(meta: dict[str, Any], headers: dict[str, _Member], where: str) -> dict[str, tuple[int, ...]]:
    """The members an MLP policy reads and their shapes, checked from the headers: the layers chain from
    ``obs_dim`` (meta) through ``arch["layers"]`` (if recorded) to 2 * action_dim outputs."""
    if "layer_0/kernel" not in headers:
        raise ValueError(f"{where} lacks layer_0/kernel")
    shapes: dict[str, tuple[int, ...]] = {}
    layers = meta.get("arch", {}).get("layers")
    width = meta.get("obs_dim", headers["layer_0/kernel"].shape[0] if len(headers["layer_0/kernel"].shape) else 0)
    i = 0
    while f"layer_{i}/kernel" in headers:
        k, b = f"layer_{i}/kernel", f"layer_{i}/bias"
        _numeric(headers[k], where)
        kshape = headers[k].shape
        if len(kshape) != 2 or kshape[0] != width:
            raise ValueError(f"{where}: member {k!r} has shape {kshape}, the architecture needs ({width}, n)")
        out = kshape[1]
        if isinstance(layers, list) and (i >= len(layers) or out != layers[i]):
            raise ValueError(f"{where}: member {k!r} has shape {kshape}, but meta arch layers are {_short(layers)}")
        shapes[k], shapes[b] = kshape, (out,)
        _check_size(shapes, where)
        _expect(headers, b, (out,), where)
        width = out
        i += 1
    if isinstance(layers, list) and len(layers) != i:
        raise ValueError(f"{where} has {i} layers but meta arch layers are {_short(layers)}")
    d = headers["layer_0/kernel"].shape[0]
    shapes["obs_mean"] = shapes["obs_std"] = (d,)
    _check_size(shapes, where)
    for key in ("obs_mean", "obs_std"):
        _expect(headers, key, (d,), where)
    return shapes


def _encoder_member_shapes(meta: dict[str, Any], headers: dict[str, _Member],
                           where: str) -> dict[str, tuple[int, ...]]:
    """The members an encoder policy reads and their shapes, from the architecture in ``meta``."""
    if "arch" not in meta or "obs_layout" not in meta:
        raise ValueError(f"{where}: format {ENCODER_FORMAT} needs 'arch' and 'obs_layout' in meta")
    try:
        params = param_shapes(meta["arch"], meta["obs_layout"])
        d = layout_obs_dim(meta["obs_layout"])
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from None
    shapes = {f"actor/{n}": s for n, s in params.items()}
    shapes["obs_mean"] = shapes["obs_std"] = (d,)
    _check_size(shapes, where)
    unknown = sorted(k for k in headers if k.startswith("actor/") and k not in shapes)
    if unknown:
        raise ValueError(f"{where}: {meta['arch']['type']} policy has parameters its architecture does not use: "
                         f"{[k[len('actor/'):] for k in unknown][:20]}")
    missing = sorted(k[len("actor/"):] for k in shapes if k not in headers and k.startswith("actor/"))
    if missing:
        raise ValueError(f"{where}: {meta['arch']['type']} policy lacks parameters {missing[:20]}")
    for k, s in shapes.items():
        _expect(headers, k, s, where)
    return shapes


# ---------------------------------------------------------------------------- encoder policies
ENCODER_FORMAT = "quadswarm_mj.policy/2"
ENCODER_TYPES = ("deepsets", "attention")
NEIGHBOR_DIM = 6
OBSTACLE_DIM = 9
LN_EPS = 1e-6
SELF_DIMS = {"base": 18, "floor": 19, "wall": 24}


#: Named architectures. ``*_large`` are the original's sizes (H = 256); ``attention_sim2real`` is the
#: original's deployable model exactly (one fc-tanh layer per embedding, OneHeadAttention H x H, head
#: fc(3H, H)); ``attention_deployable`` narrows the query/key/value width to 4 so that K = 2 with
#: obstacles fits 2,000 actor parameters (see :func:`count_params`).
ARCH_PRESETS: dict[str, dict[str, Any]] = {
    "deepsets_large": {"type": "deepsets", "self_layers": [256, 256], "neighbor_layers": [256, 256],
                       "obstacle_layers": [256, 256], "head_layers": [512]},
    "deepsets_deployable": {"type": "deepsets", "self_layers": [16], "neighbor_layers": [16],
                            "obstacle_layers": [16], "head_layers": [16]},
    "attention_large": {"type": "attention", "hidden": 256, "embed_layers": 2, "num_heads": 4, "attn_dim": 256,
                        "head_layers": [512]},
    "attention_sim2real": {"type": "attention", "hidden": 16, "embed_layers": 1, "num_heads": 1, "attn_dim": 16,
                           "head_layers": [16]},
    "attention_deployable": {"type": "attention", "hidden": 16, "embed_layers": 1, "num_heads": 1, "attn_dim": 4,
                             "head_layers": [16]},
}


def _pos_int_list(arch: dict[str, Any], key: str, allow_empty: bool = False) -> list[int]:
    v = arch.get(key)
    if not isinstance(v, (list, tuple)) or (not v and not allow_empty) or not all(
            isinstance(x, int) and not isinstance(x, bool) and x >= 1 for x in v):
        raise ValueError(f"arch[{key!r}] must be a {'possibly empty ' if allow_empty else 'non-empty '}list of "
                         f"positive ints, got {v!r}")
    return [int(x) for x in v]


def validate_layout(layout: dict[str, Any]) -> dict[str, int]:
    """Check an observation layout ``{self_dim, num_neighbors, neighbor_dim, obstacle_dim}``; returns it as ints."""
    if not isinstance(layout, dict):
        raise ValueError(f"obs_layout must be a mapping, got {layout!r}")
    out = {k: layout.get(k, d) for k, d in (("self_dim", None), ("num_neighbors", 0), ("neighbor_dim", NEIGHBOR_DIM),
                                              ("obstacle_dim", 0))}
    if out["self_dim"] not in SELF_DIMS.values():
        raise ValueError(f"obs_layout self_dim must be one of {sorted(SELF_DIMS.values())}, got {out['self_dim']!r}")
    if not isinstance(out["num_neighbors"], int) or not 0 <= out["num_neighbors"] <= 64:
        raise ValueError(f"obs_layout num_neighbors must be an int in [0, 64], got {out['num_neighbors']!r}")
    if out["neighbor_dim"] != NEIGHBOR_DIM:
        raise ValueError(f"obs_layout neighbor_dim must be {NEIGHBOR_DIM}, got {out['neighbor_dim']!r}")
    if out["obstacle_dim"] not in (0, OBSTACLE_DIM):
        raise ValueError(f"obs_layout obstacle_dim must be 0 or {OBSTACLE_DIM}, got {out['obstacle_dim']!r}")
    return {k: int(v) for k, v in out.items()}


def layout_obs_dim(layout: dict[str, Any]) -> int:
    """self_dim + neighbor_dim * K + obstacle_dim."""
    lay = validate_layout(layout)
    return lay["self_dim"] + lay["neighbor_dim"] * lay["num_neighbors"] + lay["obstacle_dim"]


def layout_from_env(env: dict[str, Any], obs_dim: int | None = None) -> dict[str, int] | None:
    """The observation layout implied by a policy's ``meta["env"]`` (None if it does not fix it).

    The obstacle block (9) is inferred from ``obs_dim`` when given.
    """
    obs_self = env.get("obs_self", "base")
    if obs_self not in SELF_DIMS or "num_quads" not in env:
        return None
    n = int(env["num_quads"])
    k = env.get("num_neighbors")
    k = min(6, n - 1) if k is None else int(k)
    lay = {"self_dim": SELF_DIMS[obs_self], "num_neighbors": k, "neighbor_dim": NEIGHBOR_DIM, "obstacle_dim": 0}
    if obs_dim is not None:
        rest = int(obs_dim) - lay["self_dim"] - NEIGHBOR_DIM * k
        if rest not in (0, OBSTACLE_DIM):
            return None
        lay["obstacle_dim"] = rest
    return lay


def validate_arch(arch: dict[str, Any], layout: dict[str, Any]) -> dict[str, Any]:
    """Check an encoder architecture against an observation layout; returns a normalized copy.

    ``deepsets``: ``self_layers``, ``neighbor_layers`` (per-neighbour MLP on the 6 features, then the
    mean over the K neighbours), ``obstacle_layers`` (on the 9 SDF features; used iff obstacle_dim 9),
    ``head_layers`` (on the concatenation), all hidden layers followed by ``activation``.
    ``attention``: ``hidden`` H, ``embed_layers`` (fc-act layers of width H for the self, neighbour
    (on the concatenated 6K vector) and obstacle embeddings; 1 = the Sim2Real model), ``num_heads``,
    ``attn_dim`` (per-head query/key/value width, default H as the original), ``head_layers`` (on
    [self | tokens], 3H with obstacles and neighbours). Both end with a linear action layer of
    ``2 * action_dim`` outputs (pre-tanh mean, then the trainer's std parameters).
    """
    if not isinstance(arch, dict):
        raise ValueError(f"arch must be a mapping, got {arch!r}")
    lay = validate_layout(layout)
    t = arch.get("type")
    if t not in ENCODER_TYPES:
        raise ValueError(f"arch type must be one of {ENCODER_TYPES}, got {t!r}")
    act = arch.get("activation", "tanh")
    if act not in ACTIVATIONS:
        raise ValueError(f"arch activation must be one of {ACTIVATIONS}, got {act!r}")
    a_dim = arch.get("action_dim", 4)
    if a_dim != 4:
        raise ValueError(f"arch action_dim must be 4, got {a_dim!r}")
    out: dict[str, Any] = {"type": t, "activation": act, "action_dim": 4}
    if t == "deepsets":
        out["self_layers"] = _pos_int_list(arch, "self_layers")
        out["neighbor_layers"] = _pos_int_list(arch, "neighbor_layers")
        out["obstacle_layers"] = _pos_int_list(arch, "obstacle_layers") if "obstacle_layers" in arch else [
            out["neighbor_layers"][-1]]
        out["head_layers"] = _pos_int_list(arch, "head_layers", allow_empty=True)
    else:
        h = arch.get("hidden")
        if not isinstance(h, int) or isinstance(h, bool) or h < 1:
            raise ValueError(f"arch hidden must be a positive int, got {h!r}")
        el, nh = arch.get("embed_layers", 1), arch.get("num_heads", 1)
        ad = arch.get("attn_dim", h)
        for key, v in (("embed_layers", el), ("num_heads", nh), ("attn_dim", ad)):
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"arch {key} must be a positive int, got {v!r}")
        if lay["num_neighbors"] == 0 and lay["obstacle_dim"] == 0:
            raise ValueError("an attention encoder needs a neighbour or an obstacle token (num_neighbors >= 1 or "
                             "obstacle_dim 9)")
        out.update(hidden=h, embed_layers=el, num_heads=nh, attn_dim=ad,
                   head_layers=_pos_int_list(arch, "head_layers", allow_empty=True))
    return out


def num_tokens(layout: dict[str, Any]) -> int:
    """Attention tokens: one for the neighbours (if K >= 1), one for the obstacles (if obstacle_dim 9)."""
    lay = validate_layout(layout)
    return int(lay["num_neighbors"] > 0) + int(lay["obstacle_dim"] > 0)


def _dense_shapes(prefix: str, n_in: int, sizes: list[int]) -> tuple[dict[str, tuple[int, ...]], int]:
    shapes: dict[str, tuple[int, ...]] = {}
    for i, n in enumerate(sizes):
        shapes[f"{prefix}_{i}/kernel"] = (n_in, n)
        shapes[f"{prefix}_{i}/bias"] = (n,)
        n_in = n
    return shapes, n_in


def param_shapes(arch: dict[str, Any], layout: dict[str, Any]) -> dict[str, tuple[int, ...]]:
    """Actor parameter names (flax paths joined by '/') and shapes, in evaluation order."""
    a = validate_arch(arch, layout)
    lay = validate_layout(layout)
    k, od = lay["num_neighbors"], lay["obstacle_dim"]
    shapes: dict[str, tuple[int, ...]] = {}
    if a["type"] == "deepsets":
        s, width = _dense_shapes("self", lay["self_dim"], a["self_layers"])
        shapes.update(s)
        if k:
            s, w = _dense_shapes("nbr", NEIGHBOR_DIM, a["neighbor_layers"])
            shapes.update(s)
            width += w
        if od:
            s, w = _dense_shapes("obst", od, a["obstacle_layers"])
            shapes.update(s)
            width += w
    else:
        h, el = a["hidden"], a["embed_layers"]
        s, _ = _dense_shapes("self", lay["self_dim"], [h] * el)
        shapes.update(s)
        if k:
            shapes.update(_dense_shapes("nbr", NEIGHBOR_DIM * k, [h] * el)[0])
        if od:
            shapes.update(_dense_shapes("obst", od, [h] * el)[0])
        qk = a["num_heads"] * a["attn_dim"]
        shapes.update({"attn/w_q/kernel": (h, qk), "attn/w_k/kernel": (h, qk), "attn/w_v/kernel": (h, qk),
                       "attn/fc/kernel": (qk, h), "attn/ln/scale": (h,), "attn/ln/bias": (h,)})
        width = h * (1 + num_tokens(lay))
    s, width = _dense_shapes("head", width, a["head_layers"])
    shapes.update(s)
    shapes["action/kernel"] = (width, 2 * a["action_dim"])
    shapes["action/bias"] = (2 * a["action_dim"],)
    return shapes


def count_params(shapes: dict[str, tuple[int, ...]], deployed: bool = True, action_dim: int = 4) -> int:
    """Actor parameter count; ``deployed`` counts only the mean part of the action layer (what runs on board)."""
    total = 0
    for name, shp in shapes.items():
        if deployed and name == "action/kernel":
            total += shp[0] * action_dim
        elif deployed and name == "action/bias":
            total += action_dim
        else:
            total += int(np.prod(shp))
    return total


def _mlp(x: np.ndarray, params: dict[str, np.ndarray], prefix: str, n: int, act: str) -> np.ndarray:
    for i in range(n):
        x = _activation(act, x @ params[f"{prefix}_{i}/kernel"] + params[f"{prefix}_{i}/bias"])
    return x


def _layer_norm(x: np.ndarray, scale: np.ndarray, bias: np.ndarray) -> np.ndarray:
    mu = x.mean(-1, keepdims=True)
    var = ((x - mu) ** 2).mean(-1, keepdims=True)
    return (x - mu) / np.sqrt(var + LN_EPS) * scale + bias


def attention_tokens(tokens: np.ndarray, params: dict[str, np.ndarray], num_heads: int, attn_dim: int) -> np.ndarray:
    """Attention over T tokens (B, T, H) -> (B, T, H): per head softmax(Q K^T / sqrt(d)) V, concat, bias-free fc,
    residual, LayerNorm (eps 1e-6)."""
    b, t, _ = tokens.shape
    q, k, v = (np.matmul(tokens, params[f"attn/w_{c}/kernel"]).reshape(b, t, num_heads, attn_dim)
               for c in "qkv")
    s = np.einsum("bihd,bjhd->bhij", q, k) / np.sqrt(attn_dim)
    s = np.exp(s - s.max(-1, keepdims=True))
    w = s / s.sum(-1, keepdims=True)
    o = np.einsum("bhij,bjhd->bihd", w, v).reshape(b, t, num_heads * attn_dim)
    return _layer_norm(o @ params["attn/fc/kernel"] + tokens, params["attn/ln/scale"], params["attn/ln/bias"])


def encoder_forward(arch: dict[str, Any], layout: dict[str, Any], params: dict[str, np.ndarray],
                    x: np.ndarray) -> np.ndarray:
    """Raw action-layer outputs (B, 2 * action_dim) of an encoder network on normalized observations (B, obs_dim)."""
    a, lay = arch, layout
    act = a["activation"]
    sd, k, od = lay["self_dim"], lay["num_neighbors"], lay["obstacle_dim"]
    xs, xn, xo = x[:, :sd], x[:, sd: sd + NEIGHBOR_DIM * k], x[:, sd + NEIGHBOR_DIM * k:]
    if a["type"] == "deepsets":
        parts = [_mlp(xs, params, "self", len(a["self_layers"]), act)]
        if k:
            e = _mlp(xn.reshape(x.shape[0], k, NEIGHBOR_DIM), params, "nbr", len(a["neighbor_layers"]), act)
            parts.append(e.mean(axis=1))
        if od:
            parts.append(_mlp(xo, params, "obst", len(a["obstacle_layers"]), act))
    else:
        el = a["embed_layers"]
        toks = []
        if k:
            toks.append(_mlp(xn, params, "nbr", el, act))
        if od:
            toks.append(_mlp(xo, params, "obst", el, act))
        att = attention_tokens(np.stack(toks, axis=1), params, a["num_heads"], a["attn_dim"])
        parts = [_mlp(xs, params, "self", el, act), att.reshape(x.shape[0], -1)]
    h = _mlp(np.concatenate(parts, axis=-1), params, "head", len(a["head_layers"]), act)
    return h @ params["action/kernel"] + params["action/bias"]


@dataclass
class EncoderPolicy:
    """A deterministic deep-sets or attention policy: observations (N, obs_dim) -> actions (N, 4) in [-1, 1].

    ``params`` maps the names of :func:`param_shapes` to arrays; the action is
    ``clip(tanh(out[:4]), -1, 1)`` of the linear action layer's output, as for :class:`MLPPolicy`.
    """

    arch: dict[str, Any]
    obs_layout: dict[str, Any]
    params: dict[str, np.ndarray]
    obs_mean: np.ndarray
    obs_std: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)
    name: str = "encoder"

    def __post_init__(self) -> None:
        self.obs_layout = validate_layout(self.obs_layout)
        self.arch = validate_arch(self.arch, self.obs_layout)
        shapes = param_shapes(self.arch, self.obs_layout)
        missing, unknown = sorted(set(shapes) - set(self.params)), sorted(set(self.params) - set(shapes))
        if missing:
            raise ValueError(f"{self.arch['type']} policy lacks parameters {missing}")
        if unknown:
            raise ValueError(f"{self.arch['type']} policy has parameters its architecture does not use: {unknown}")
        self.params = {n: np.asarray(self.params[n], dtype=np.float64) for n in shapes}
        for n, shp in shapes.items():
            if self.params[n].shape != shp:
                raise ValueError(f"parameter {n!r} has shape {self.params[n].shape}, the architecture needs {shp}")
            if not np.all(np.isfinite(self.params[n])):
                raise ValueError("policy weights must be finite")
        d = layout_obs_dim(self.obs_layout)
        self.obs_mean = np.asarray(self.obs_mean, dtype=np.float64)
        self.obs_std = np.asarray(self.obs_std, dtype=np.float64)
        if self.obs_mean.shape != (d,) or self.obs_std.shape != (d,):
            raise ValueError(f"obs_mean/obs_std must have shape ({d},), got {self.obs_mean.shape}, "
                             f"{self.obs_std.shape}")
        if not (np.all(np.isfinite(self.obs_std)) and np.all(self.obs_std > 0) and np.all(np.isfinite(self.obs_mean))):
            raise ValueError("obs_std must be finite and positive, obs_mean finite")

    @property
    def obs_dim(self) -> int:
        return layout_obs_dim(self.obs_layout)

    @property
    def action_dim(self) -> int:
        return int(self.arch["action_dim"])

    @property
    def num_params(self) -> int:
        """Deployed actor parameters (the action layer's mean part only)."""
        return count_params(param_shapes(self.arch, self.obs_layout), deployed=True, action_dim=self.action_dim)

    @property
    def env_kwargs(self) -> dict[str, Any]:
        """EnvConfig overrides that reproduce the observation layout the policy was trained on."""
        return _env_kwargs(self.meta)

    def __call__(self, obs: Any) -> np.ndarray:
        """Deterministic actions: obs (..., obs_dim) -> (..., 4) float32 in [-1, 1]."""
        lead, h = _normalized_rows(obs, self.obs_dim, self.obs_mean, self.obs_std)
        out = encoder_forward(self.arch, self.obs_layout, self.params, h)
        a = np.clip(np.tanh(out[:, : self.action_dim]), -1.0, 1.0).astype(np.float32)
        return a.reshape(lead + (self.action_dim,))

    def act(self, obs: Any, info: dict[str, Any] | None = None) -> np.ndarray:
        """Same as calling the policy (``info`` is ignored)."""
        return self(obs)


def _xavier(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    lim = np.sqrt(6.0 / (shape[0] + shape[-1]))
    return rng.uniform(-lim, lim, shape)


def random_encoder_policy(arch: dict[str, Any], layout: dict[str, Any], seed: int = 0, bias_std: float = 0.1,
                          obs_mean: np.ndarray | None = None, obs_std: np.ndarray | None = None,
                          meta: dict[str, Any] | None = None) -> EncoderPolicy:
    """An :class:`EncoderPolicy` with xavier-uniform kernels and N(0, bias_std) biases (LayerNorm scale 1 +
    N(0, bias_std)); for tests and export checks."""
    rng = np.random.default_rng(seed)
    params: dict[str, np.ndarray] = {}
    for n, shp in param_shapes(arch, layout).items():
        if n.endswith("kernel"):
            params[n] = _xavier(rng, shp)
        else:
            params[n] = rng.normal(0.0, bias_std, shp) + (1.0 if n.endswith("ln/scale") else 0.0)
    d = layout_obs_dim(layout)
    mean = np.zeros(d) if obs_mean is None else obs_mean
    std = np.ones(d) if obs_std is None else obs_std
    return EncoderPolicy(dict(arch), dict(layout), params, mean, std, meta=dict(meta or {}))


def encoder_policy_arrays(arch: dict[str, Any], layout: dict[str, Any], params: dict[str, np.ndarray],
                          obs_mean: np.ndarray, obs_std: np.ndarray, meta: dict[str, Any],
                          extra: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """The arrays of an encoder policy file (format ``quadswarm_mj.policy/2``)."""
    lay = validate_layout(layout)
    a = validate_arch(arch, lay)
    shapes = param_shapes(a, lay)
    meta = {**meta, "format": ENCODER_FORMAT, "arch": a, "obs_layout": lay, "obs_dim": layout_obs_dim(lay),
            "action_dim": a["action_dim"], "activation": a["activation"]}
    out: dict[str, np.ndarray] = {"meta": np.array(json.dumps(meta, sort_keys=True))}
    for n, shp in shapes.items():
        v = np.asarray(params[n], dtype=np.float32)
        if v.shape != shp:
            raise ValueError(f"parameter {n!r} has shape {v.shape}, the architecture needs {shp}")
        out[f"actor/{n}"] = v
    out["obs_mean"] = np.asarray(obs_mean, dtype=np.float32)
    out["obs_std"] = np.asarray(obs_std, dtype=np.float32)
    for k, v in (extra or {}).items():
        out[k] = np.asarray(v)
    return out


def _write_npz(path: str | os.PathLike, arrays: dict[str, np.ndarray]) -> str:
    for k, v in arrays.items():
        if v.dtype == object:
            raise ValueError(f"array {k!r} has dtype object; policy files hold plain numeric/unicode arrays only")
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, buf.getvalue())  # a failed save leaves an earlier file (a checkpoint) whole
    return hashlib.sha256(buf.getvalue()).hexdigest()


def save_encoder_policy(path: str | os.PathLike, policy: EncoderPolicy, meta: dict[str, Any] | None = None,
                        extra: dict[str, np.ndarray] | None = None) -> str:
    """Write an encoder policy ``.npz`` (no pickled objects) and return its SHA-256."""
    m = {k: v for k, v in {**policy.meta, **(meta or {})}.items() if k != "manifest"}
    return _write_npz(path, encoder_policy_arrays(policy.arch, policy.obs_layout, policy.params, policy.obs_mean,
                                                  policy.obs_std, m, extra))


def _encoder_from_arrays(arrays: dict[str, np.ndarray], meta: dict[str, Any], path: Path,
                         name: str | None) -> EncoderPolicy:
    """An :class:`EncoderPolicy` from the arrays :func:`load_policy_file` read and checked."""
    params = {k[len("actor/"):]: v.astype(np.float64) for k, v in arrays.items() if k.startswith("actor/")}
    try:
        pol = EncoderPolicy(meta["arch"], meta["obs_layout"], params, arrays["obs_mean"].astype(np.float64),
                            arrays["obs_std"].astype(np.float64), meta=meta, name=name or path.stem)
    except ValueError as e:
        raise ValueError(f"policy file {str(path)!r}: {e}") from e
    if "obs_dim" in meta and int(meta["obs_dim"]) != pol.obs_dim:
        raise ValueError(f"policy file {str(path)!r}: meta obs_dim {meta['obs_dim']} != layout {pol.obs_dim}")
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
