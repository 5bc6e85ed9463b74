"""Reading policy files safely: zip member headers checked before anything is inflated (sizes, dtypes,
shapes), metadata validated, and the members each format must hold. Re-exported by
:mod:`quadswarm_mj.policies`."""

from __future__ import annotations

import dataclasses
import json
import math
import zipfile
from dataclasses import dataclass
from typing import Any

import numpy as np

from quadswarm_mj.config_checks import NEIGHBOR_FORMS
from quadswarm_mj.encoder_policy import ENCODER_FORMAT, SELF_DIMS, layout_obs_dim, param_shapes, validate_layout
from quadswarm_mj.policy_common import ACTIVATIONS

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
    for k in ("control_hz", "sim_hz"):  # the rates a policy was trained at (Hz; the C export writes control_hz)
        if k in env and not _is_int(env[k], 1):
            raise ValueError(f"{where}: meta env {k} must be a positive int (Hz), got {_short(env[k])}")
    if "neighbor_form" in env and env["neighbor_form"] not in NEIGHBOR_FORMS:
        raise ValueError(f"{where}: meta env neighbor_form must be one of {NEIGHBOR_FORMS}, "
                         f"got {_short(env['neighbor_form'])}")
    nr = env.get("neighbor_near_range", 1.0)
    if not (isinstance(nr, (int, float)) and not isinstance(nr, bool) and 0 < nr <= 10):
        raise ValueError(f"{where}: meta env neighbor_near_range must be a number in (0, 10] (m), got {_short(nr)}")
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

