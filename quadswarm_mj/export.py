"""Export a policy as plain C99 for the Crazyflie firmware (SPEC_obstacles B, with its Decisions).

:func:`export_c` writes ``<name>.c`` and ``<name>.h`` (``name`` default ``qs_policy``) with one entry point::

    void qs_policy_evaluate(const float *obs, float *action);

``obs`` is one quad's observation exactly as the env returns it (``QS_POLICY_OBS_DIM`` floats:
``[self | K x 6 neighbours | 9 SDF]``), normalized inside with the policy's mean/std; ``action``
receives the four deterministic actions ``clip(tanh(mean), -1, 1)``, as :class:`MLPPolicy` and
:class:`EncoderPolicy` compute them. Every architecture of :mod:`quadswarm_mj.policies` is
supported (MLP, deep sets, attention with any number of heads), with any widths, K and obstacle
block from the policy's metadata. Only actor parameters are written (no critic, no std
parameters), as ``static const float`` arrays; activations live in ``static float`` buffers
sized to what is written (so the function is not reentrant). The code needs ``math.h`` only.

CLI: ``python -m quadswarm_mj.export pretrained:<name> --out DIR`` (or a policy ``.npz`` path).
"""

from __future__ import annotations

import argparse
import math
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.policies import (
    LN_EPS,
    NEIGHBOR_DIM,
    EncoderPolicy,
    MLPPolicy,
    load_policy,
    num_tokens,
)

ENTRY = "qs_policy_evaluate"

_C_ACT = {
    "tanh": "return tanhf(x);",
    "relu": "return x > 0.0f ? x : 0.0f;",
    "swish": "return x / (1.0f + expf(-x));",
    "elu": "return x > 0.0f ? x : expm1f(x);",
}

_HELPERS = """\
static float qs_act(float x)
{
    {act}
}

/* y[j] = b[j] + sum_i x[i] w[i][j] (w row-major (n_in, n_out); b may be 0), then the activation if act. */
static void qs_dense(const float *w, const float *b, const float *x, float *y, int n_in, int n_out, int act)
{
    int i, j;
    for (j = 0; j < n_out; ++j) {
        float acc = b ? b[j] : 0.0f;
        for (i = 0; i < n_in; ++i) {
            acc += x[i] * w[i * n_out + j];
        }
        y[j] = act ? qs_act(acc) : acc;
    }
}
"""

_ATTN_HELPER = """\
/* Attention over QS_NUM_TOKENS tokens of width QS_HIDDEN: per head softmax(q k^T / sqrt(d)) v, concat,
   bias-free fc, residual, LayerNorm (eps 1e-6); token t goes to out + t * QS_HIDDEN. */
static void qs_attention(const float *tok, float *out)
{
    int t, i, j, h, d;
    for (t = 0; t < QS_NUM_TOKENS; ++t) {
        qs_dense(&qs_attn_w_q_kernel[0][0], 0, tok + t * QS_HIDDEN, qs_q + t * QS_QK, QS_HIDDEN, QS_QK, 0);
        qs_dense(&qs_attn_w_k_kernel[0][0], 0, tok + t * QS_HIDDEN, qs_k + t * QS_QK, QS_HIDDEN, QS_QK, 0);
        qs_dense(&qs_attn_w_v_kernel[0][0], 0, tok + t * QS_HIDDEN, qs_v + t * QS_QK, QS_HIDDEN, QS_QK, 0);
    }
    for (h = 0; h < QS_NUM_HEADS; ++h) {
        for (i = 0; i < QS_NUM_TOKENS; ++i) {
            float s[QS_NUM_TOKENS];
            float smax, ssum = 0.0f;
            for (j = 0; j < QS_NUM_TOKENS; ++j) {
                float acc = 0.0f;
                for (d = 0; d < QS_ATTN_DIM; ++d) {
                    acc += qs_q[i * QS_QK + h * QS_ATTN_DIM + d] * qs_k[j * QS_QK + h * QS_ATTN_DIM + d];
                }
                s[j] = acc / QS_ATTN_SQRT_DIM;
            }
            smax = s[0];
            for (j = 1; j < QS_NUM_TOKENS; ++j) {
                smax = s[j] > smax ? s[j] : smax;
            }
            for (j = 0; j < QS_NUM_TOKENS; ++j) {
                s[j] = expf(s[j] - smax);
                ssum += s[j];
            }
            for (d = 0; d < QS_ATTN_DIM; ++d) {
                float acc = 0.0f;
                for (j = 0; j < QS_NUM_TOKENS; ++j) {
                    acc += s[j] * qs_v[j * QS_QK + h * QS_ATTN_DIM + d];
                }
                qs_o[i * QS_QK + h * QS_ATTN_DIM + d] = acc / ssum;
            }
        }
    }
    for (t = 0; t < QS_NUM_TOKENS; ++t) {
        float *y = out + t * QS_HIDDEN;
        float mu = 0.0f, var = 0.0f, inv;
        qs_dense(&qs_attn_fc_kernel[0][0], 0, qs_o + t * QS_QK, y, QS_QK, QS_HIDDEN, 0);
        for (d = 0; d < QS_HIDDEN; ++d) {
            y[d] += tok[t * QS_HIDDEN + d];
            mu += y[d];
        }
        mu /= (float)QS_HIDDEN;
        for (d = 0; d < QS_HIDDEN; ++d) {
            var += (y[d] - mu) * (y[d] - mu);
        }
        var /= (float)QS_HIDDEN;
        inv = sqrtf(var + QS_LN_EPS);
        for (d = 0; d < QS_HIDDEN; ++d) {
            y[d] = (y[d] - mu) / inv * qs_attn_ln_scale[d] + qs_attn_ln_bias[d];
        }
    }
}
"""


def _lit(v: float) -> str:
    """A C float literal that round-trips the float32 value."""
    s = f"{float(np.float32(v)):.9g}"
    if not any(c in s for c in ".en"):
        s += ".0"
    return s + "f"


def _initializer(a: np.ndarray) -> str:
    """Brace initializer of a 1-D or 2-D float32 array (one brace group per row, 8 values a line)."""
    def row(v: np.ndarray, indent: str) -> str:
        lits = [_lit(x) for x in v]
        lines = [", ".join(lits[i: i + 8]) for i in range(0, len(lits), 8)]
        return "{\n" + indent + "    " + (",\n" + indent + "    ").join(lines) + "\n" + indent + "}"

    if a.ndim == 1:
        return row(a, "")
    return "{\n    " + ",\n    ".join(row(r, "    ") for r in a) + "\n}"


def _c_name(name: str) -> str:
    return "qs_" + re.sub(r"[^0-9A-Za-z_]", "_", name)


class _Writer:
    """Collects the constants, buffers and statements of the generated C."""

    def __init__(self) -> None:
        self.consts: list[str] = []
        self.bufs: list[str] = []
        self.body: list[str] = []
        self.num_params = 0

    def const(self, name: str, arr: np.ndarray, count: bool = True) -> str:
        a = np.asarray(arr, dtype=np.float32)
        cname = _c_name(name)
        dims = "".join(f"[{n}]" for n in a.shape)
        self.consts.append(f"static const float {cname}{dims} = " + _initializer(a) + ";")
        if count:
            self.num_params += a.size
        return f"&{cname}" + "[0]" * a.ndim

    def buf(self, name: str, size: int) -> str:
        cname = _c_name(name)
        self.bufs.append(f"static float {cname}[{size}];")
        return cname

    def dense(self, params: dict[str, np.ndarray], layer: str, x: str, y: str, act: bool,
              cols: int | None = None) -> int:
        """Emit one dense layer ``layer`` (params ``<layer>/kernel``, ``<layer>/bias``); returns n_out."""
        k, b = params[f"{layer}/kernel"], params.get(f"{layer}/bias")
        if cols is not None:
            k, b = k[:, :cols], None if b is None else b[:cols]
        w = self.const(f"{layer}/kernel", k)
        bp = "0" if b is None else self.const(f"{layer}/bias", b)
        self.body.append(f"qs_dense({w}, {bp}, {x}, {y}, {k.shape[0]}, {k.shape[1]}, {int(act)});")
        return int(k.shape[1])

    def mlp(self, params: dict[str, np.ndarray], prefix: str, n: int, x: str, out: str | None) -> tuple[str, int]:
        """Emit ``n`` activated layers ``<prefix>_<i>``, the last into ``out`` if given; returns (buffer, width)."""
        width = 0
        for i in range(n):
            width = params[f"{prefix}_{i}/kernel"].shape[1]
            y = out if (out is not None and i == n - 1) else self.buf(f"{prefix}_{i}_out", width)
            self.dense(params, f"{prefix}_{i}", x, y, act=True)
            x = y
        return x, width


def _mlp_params(policy: MLPPolicy) -> dict[str, np.ndarray]:
    p: dict[str, np.ndarray] = {}
    for i, (k, b) in enumerate(zip(policy.kernels, policy.biases)):
        p[f"layer_{i}/kernel"], p[f"layer_{i}/bias"] = k, b
    return p


def _emit(policy: MLPPolicy | EncoderPolicy, w: _Writer) -> list[str]:
    """Fill ``w`` with the network; returns extra #defines for the .c file."""
    d, a_dim = policy.obs_dim, policy.action_dim
    defines: list[str] = []
    w.const("obs_mean", policy.obs_mean, count=False)
    w.const("obs_std", policy.obs_std, count=False)
    x = w.buf("x", d)
    w.body.append(f"for (i = 0; i < {d}; ++i) {{\n        {x}[i] = (obs[i] - qs_obs_mean[i]) / qs_obs_std[i];\n    }}")
    if isinstance(policy, MLPPolicy):
        params = _mlp_params(policy)
        n = len(policy.kernels)
        h, _ = w.mlp(params, "layer", n - 1, x, None) if n > 1 else (x, d)
        last = f"layer_{n - 1}"
    else:
        params, arch, lay = policy.params, policy.arch, policy.obs_layout
        sd, k, od = lay["self_dim"], lay["num_neighbors"], lay["obstacle_dim"]
        if arch["type"] == "deepsets":
            widths = [arch["self_layers"][-1]] + ([arch["neighbor_layers"][-1]] if k else []) + (
                [arch["obstacle_layers"][-1]] if od else [])
            cat = w.buf("cat", sum(widths))
            w.mlp(params, "self", len(arch["self_layers"]), x, cat)
            off = widths[0]
            if k:
                nl, hn = len(arch["neighbor_layers"]), arch["neighbor_layers"][-1]
                inner = _Writer()
                last_buf, _ = inner.mlp(params, "nbr", nl, f"{x} + {sd} + {NEIGHBOR_DIM} * k", None)
                w.consts += inner.consts
                w.bufs += inner.bufs
                w.num_params += inner.num_params
                w.body.append(f"for (j = 0; j < {hn}; ++j) {{\n        {cat}[{off} + j] = 0.0f;\n    }}")
                loop = "\n        ".join(inner.body)
                w.body.append(f"for (k = 0; k < {k}; ++k) {{\n        {loop}\n"
                              f"        for (j = 0; j < {hn}; ++j) {{\n            {cat}[{off} + j] += {last_buf}[j];\n"
                              "        }\n    }")
                w.body.append(f"for (j = 0; j < {hn}; ++j) {{\n        {cat}[{off} + j] /= {_lit(k)};\n    }}")
                off += hn
            if od:
                w.mlp(params, "obst", len(arch["obstacle_layers"]), f"{x} + {sd + NEIGHBOR_DIM * k}", f"{cat} + {off}")
        else:
            hd, el, nt = arch["hidden"], arch["embed_layers"], num_tokens(lay)
            qk = arch["num_heads"] * arch["attn_dim"]
            defines += [f"#define QS_HIDDEN {hd}", f"#define QS_NUM_TOKENS {nt}",
                        f"#define QS_NUM_HEADS {arch['num_heads']}", f"#define QS_ATTN_DIM {arch['attn_dim']}",
                        f"#define QS_QK {qk}", f"#define QS_ATTN_SQRT_DIM {_lit(math.sqrt(arch['attn_dim']))}",
                        f"#define QS_LN_EPS {_lit(LN_EPS)}"]
            cat = w.buf("cat", hd * (1 + nt))
            tok = w.buf("tok", hd * nt)
            for name, n in (("q", nt * qk), ("k", nt * qk), ("v", nt * qk), ("o", nt * qk)):
                w.buf(name, n)
            w.mlp(params, "self", el, x, cat)
            t = 0
            if k:
                w.mlp(params, "nbr", el, f"{x} + {sd}", tok)
                t += 1
            if od:
                w.mlp(params, "obst", el, f"{x} + {sd + NEIGHBOR_DIM * k}", f"{tok} + {t * hd}")
            for name in ("attn/w_q/kernel", "attn/w_k/kernel", "attn/w_v/kernel", "attn/fc/kernel",
                         "attn/ln/scale", "attn/ln/bias"):
                w.const(name, params[name])
            w.body.append(f"qs_attention({tok}, {cat} + {hd});")
        h, _ = w.mlp(params, "head", len(arch["head_layers"]), cat, None)
        last = "action"
    out = w.buf("out", a_dim)
    w.dense(params, last, h, out, act=False, cols=a_dim)
    w.body.append(f"for (i = 0; i < {a_dim}; ++i) {{\n        float a = tanhf({out}[i]);\n"
                  "        action[i] = a > 1.0f ? 1.0f : (a < -1.0f ? -1.0f : a);\n    }")
    return defines


def _layout(policy: MLPPolicy | EncoderPolicy) -> dict[str, int]:
    lay = policy.obs_layout
    if lay is None:
        return {"self_dim": policy.obs_dim, "num_neighbors": 0, "neighbor_dim": NEIGHBOR_DIM, "obstacle_dim": 0}
    return dict(lay)


#: ObstacleConfig.feature_form -> the header's QS_POLICY_OBSTACLE_FORM
OBSTACLE_FORMS = {"grid": 0, "slopes": 1, "near": 2}


def _obstacle_form_lines(policy: MLPPolicy | EncoderPolicy) -> list[str]:
    """The header's statement of how the 9 column inputs are formed (none when the policy observes no columns)."""
    obst = policy.env_kwargs.get("obstacles") or {}
    if _layout(policy)["obstacle_dim"] != 9 or not obst.get("observe_features", True):
        return []
    form = obst.get("feature_form", "grid")
    lines = [f"#define QS_POLICY_OBSTACLE_FORM {OBSTACLE_FORMS[form]}  /* the 9 column inputs: 0 grid (distances at"
             f" 3 x 3 points), 1 slopes, 2 near: {form} (docs/model.md, Obstacles) */"]
    if form == "near":
        lines.append(f"#define QS_POLICY_OBSTACLE_NEAR_RANGE {float(obst.get('near_range', 1.0))!r}f  /* m */")
        if obst.get("near_speed_reach", 0.0):  # the reach grows with the closing speed (docs/model.md)
            lines.append(f"#define QS_POLICY_OBSTACLE_NEAR_SPEED_REACH {float(obst['near_speed_reach'])!r}f  /* s */")
    return lines


def _neighbor_form_lines(policy: MLPPolicy | EncoderPolicy) -> list[str]:
    """The header's statement of the neighbour inputs' form when it is not the raw (rel pos, rel vel)."""
    env = policy.env_kwargs
    if _layout(policy)["num_neighbors"] == 0 or env.get("neighbor_form", "raw") == "raw":
        return []
    return ["#define QS_POLICY_NEIGHBOR_FORM 1  /* the neighbour inputs: 0 raw (rel pos, rel vel), 1 near:"
            " (w r / |r|, w v), w = max(1 - |r| / NEAR_RANGE, 0) (docs/model.md, Observations) */",
            f"#define QS_POLICY_NEIGHBOR_NEAR_RANGE {float(env.get('neighbor_near_range', 1.0))!r}f  /* m */"]


def _control_hz(policy: MLPPolicy | EncoderPolicy) -> int:
    """The control rate (Hz) the policy was trained at: its file's ``env``, else the EnvConfig default."""
    return int(policy.env_kwargs.get("control_hz", EnvConfig.control_hz))


def generate_c(policy: MLPPolicy | EncoderPolicy, name: str = "qs_policy") -> tuple[str, str]:
    """The C source and header text of a policy (see the module docstring)."""
    if not isinstance(policy, (MLPPolicy, EncoderPolicy)):
        raise ValueError(f"only trained network policies can be exported, got {type(policy).__name__}")
    if not re.fullmatch(r"[A-Za-z_][0-9A-Za-z_]*", name):
        raise ValueError(f"name must be a C identifier (used for the file names and include guard), got {name!r}")
    w = _Writer()
    defines = _emit(policy, w)
    lay = _layout(policy)
    arch = policy.arch if isinstance(policy, EncoderPolicy) else {"type": "mlp", "activation": policy.activation}
    guard = name.upper() + "_H"
    desc = f"{arch['type']} policy {policy.name!r}, activation {arch['activation']}".replace("*/", "* /")
    h_text = "\n".join([
        f"/* {name}.h: generated by quadswarm_mj.export from the {desc}. */",
        f"#ifndef {guard}", f"#define {guard}", "",
        "/* Observation layout: [self | NUM_NEIGHBORS x NEIGHBOR_DIM (rel pos, rel vel) | OBSTACLE_DIM (SDF)]. */",
        f"#define QS_POLICY_OBS_DIM {policy.obs_dim}",
        f"#define QS_POLICY_ACTION_DIM {policy.action_dim}",
        f"#define QS_POLICY_SELF_DIM {lay['self_dim']}",
        f"#define QS_POLICY_NUM_NEIGHBORS {lay['num_neighbors']}",
        f"#define QS_POLICY_NEIGHBOR_DIM {lay['neighbor_dim']}",
        f"#define QS_POLICY_OBSTACLE_DIM {lay['obstacle_dim']}",
        f"#define QS_POLICY_NUM_PARAMS {w.num_params}",
        f"#define QS_POLICY_CONTROL_HZ {_control_hz(policy)}  /* call it at this rate: one action per period */",
        *_obstacle_form_lines(policy), *_neighbor_form_lines(policy), "",
        "#ifdef __cplusplus", 'extern "C" {', "#endif", "",
        "/* One quad's observation as the simulator returns it (normalized inside) -> QS_POLICY_ACTION_DIM actions",
        "   in [-1, 1]; motor command k = 0.5 (action[k] + 1) x full scale. Not reentrant (static buffers). */",
        f"void {ENTRY}(const float *obs, float *action);", "",
        "#ifdef __cplusplus", "}", "#endif", "", f"#endif /* {guard} */", ""])
    helpers = _HELPERS.replace("{act}", _C_ACT[arch["activation"]])
    parts = [f"/* {name}.c: generated by quadswarm_mj.export from the {desc}; C99, needs math.h only. */",
             "#include <math.h>", f'#include "{name}.h"', "", *defines, "", *w.bufs, "", *w.consts, "", helpers]
    if isinstance(policy, EncoderPolicy) and policy.arch["type"] == "attention":
        parts.append(_ATTN_HELPER)
    body = "\n    ".join(w.body)
    parts.append(f"void {ENTRY}(const float *obs, float *action)\n{{\n    int i, j, k;\n    (void)j;\n    (void)k;\n"
                 f"    {body}\n}}\n")
    return "\n".join(parts), h_text


def export_c(policy: MLPPolicy | EncoderPolicy | str | os.PathLike, out_dir: str | os.PathLike,
             name: str = "qs_policy") -> tuple[Path, Path]:
    """Write ``<out_dir>/<name>.c`` and ``<name>.h`` for a policy (object, ``"pretrained:<name>"`` or ``.npz`` path)."""
    pol = load_policy(policy) if isinstance(policy, (str, os.PathLike)) else policy
    c_text, h_text = generate_c(pol, name)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    c_path, h_path = out / f"{name}.c", out / f"{name}.h"
    c_path.write_text(c_text)
    h_path.write_text(h_text)
    return c_path, h_path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m quadswarm_mj.export",
                                 description="Export a policy as C99 for the Crazyflie firmware.")
    ap.add_argument("policy", help="pretrained:<name> or a policy .npz path")
    ap.add_argument("--out", required=True, help="output directory")
    ap.add_argument("--name", default="qs_policy", help="base name of the .c/.h files (default qs_policy)")
    args = ap.parse_args(argv)
    try:
        pol: Any = load_policy(args.policy)
        c_path, h_path = export_c(pol, args.out, args.name)
    except ValueError as e:
        ap.error(str(e))
    print(f"{c_path}\n{h_path}\n{type(pol).__name__} {pol.name}: obs_dim {pol.obs_dim}, "
          f"{pol.num_params} actor parameters")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
