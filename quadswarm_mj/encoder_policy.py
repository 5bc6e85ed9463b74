"""Encoder policies (deep sets, attention; format ``quadswarm_mj.policy/2``, SPEC_obstacles C.1): layout
and architecture checks, parameter shapes, NumPy inference, random and saved policies. NumPy only;
re-exported by :mod:`quadswarm_mj.policies` (the file format is described there)."""

from __future__ import annotations

import hashlib
import io
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from quadswarm_mj.outfiles import atomic_write_bytes
from quadswarm_mj.policy_common import ACTIVATIONS, _activation, _env_kwargs, _normalized_rows

# ---------------------------------------------------------------------------- encoder policies
ENCODER_FORMAT = "quadswarm_mj.policy/2"
ENCODER_TYPES = ("deepsets", "attention")
NEIGHBOR_DIM = 6
OBSTACLE_DIM = 9
#: the widest observation tail after the neighbours (9 column features + every deck sensor, 32 x 32 depth)
MAX_TAIL_DIM = 2048
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
    """Check an observation layout ``{self_dim, num_neighbors, neighbor_dim, obstacle_dim}``; returns it as ints.

    ``obstacle_dim`` is the width of the observation's tail after the neighbours, which the obstacle
    branch reads: the 9 column features (obstacles on, ``observe_features``), then the deck readings
    (``EnvConfig.sensors``); 0 without either."""
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
    od = out["obstacle_dim"]
    if not isinstance(od, int) or isinstance(od, bool) or not 0 <= od <= MAX_TAIL_DIM:
        raise ValueError(f"obs_layout obstacle_dim (the tail after the neighbours: {OBSTACLE_DIM} column features "
                         f"and/or the deck readings) must be an int in [0, {MAX_TAIL_DIM}], got {od!r}")
    return {k: int(v) for k, v in out.items()}


def layout_obs_dim(layout: dict[str, Any]) -> int:
    """self_dim + neighbor_dim * K + obstacle_dim."""
    lay = validate_layout(layout)
    return lay["self_dim"] + lay["neighbor_dim"] * lay["num_neighbors"] + lay["obstacle_dim"]


def layout_from_env(env: dict[str, Any], obs_dim: int | None = None) -> dict[str, int] | None:
    """The observation layout implied by a policy's ``meta["env"]`` (None if it does not fix it).

    The tail after the neighbours (9 column features and/or deck readings) is inferred from ``obs_dim``
    when given.
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
        if not 0 <= rest <= MAX_TAIL_DIM:
            return None
        lay["obstacle_dim"] = rest
    return lay


def validate_arch(arch: dict[str, Any], layout: dict[str, Any]) -> dict[str, Any]:
    """Check an encoder architecture against an observation layout; returns a normalized copy.

    ``deepsets``: ``self_layers``, ``neighbor_layers`` (per-neighbour MLP on the 6 features, then the
    mean over the K neighbours), ``obstacle_layers`` (on the tail: the 9 SDF features and/or deck readings; used iff
    obstacle_dim > 0),
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
                             "obstacle_dim >= 1)")
        out.update(hidden=h, embed_layers=el, num_heads=nh, attn_dim=ad,
                   head_layers=_pos_int_list(arch, "head_layers", allow_empty=True))
    return out


def num_tokens(layout: dict[str, Any]) -> int:
    """Attention tokens: one for the neighbours (if K >= 1), one for the tail (if obstacle_dim >= 1)."""
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

