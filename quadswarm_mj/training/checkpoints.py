"""Files of the PPO trainers: the policy file a run writes (:func:`save_policy_file`: format 1 for the
MLP, format 2 for encoders, both with the critic and the normalizer count), the resumable learner state
(:func:`save_train_state` / :func:`load_train_state`: parameters, optimizer state, normalizer, RNG key,
counters; a pickle-free ``.npz`` written atomically) and the warm start from a policy file
(:func:`load_init`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from brax.training.agents.ppo import losses as ppo_losses

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.policies import load_policy_file, save_policy
from quadswarm_mj.training import networks as enc_networks
from quadswarm_mj.training.learner import (
    TrainState,
    _dense_layers,
    _to_tree,
    _uint64,
    constant_action_std,
    env_meta,
    normalizer_stats,
    obs_layout,
)
from quadswarm_mj.training.ppo_config import PPOConfig


def save_policy_file(path: str | Path, ppo: PPOConfig, arch: dict[str, Any] | None, cfg: EnvConfig,
                     state: TrainState, train_meta: dict[str, Any]) -> str:
    """Write the trained policy as a ``quadswarm_mj.policies`` file: format 1 (MLP) or 2 (encoder, via
    ``networks.export_policy``: architecture and observation layout recorded); both also hold the critic
    (``value/layer_i/...``) and the normalizer count. Returns the SHA-256."""
    layout = obs_layout(cfg)
    d = cfg.obs_dim
    mean, std, count = normalizer_stats(state.normalizer, ppo, d)
    meta = {"activation": ppo.activation, "obs_dim": d, "action_dim": 4, "env": env_meta(cfg), "train": train_meta}
    extra = {"norm_count": np.array(count, np.float64)}
    for i, (k, b) in enumerate(_dense_layers(state.params.value)):
        extra[f"value/layer_{i}/kernel"] = k
        extra[f"value/layer_{i}/bias"] = b
    if arch is None:
        layers = _dense_layers(state.params.policy)
        return save_policy(path, [k for k, _ in layers], [b for _, b in layers], mean, std, meta, extra)
    return enc_networks.export_policy(path, arch, layout, state.params.policy, mean, std, meta, extra)


def _value_layers(arrays: dict[str, np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
    """The critic's (kernel, bias) layers stored in a policy file (``value/layer_i/...``; [] if none)."""
    out, i = [], 0
    while f"value/layer_{i}/kernel" in arrays:
        out.append((arrays[f"value/layer_{i}/kernel"], arrays[f"value/layer_{i}/bias"]))
        i += 1
    return out


TRAIN_STATE_FILE = "train_state.npz"
# train states written before the learning rate was an injected hyper-parameter hold Adam's state at
# ``state.opt_state[1][0]``, now at ``state.opt_state[1].inner_state[0]``; the injection's own leaves
# (its counter and the learning rate, which every update sets from the schedule) start from the template
_INJECTED = ".inner_state"
_INJECT_OWN = ("state.opt_state[1].hyperparams", "state.opt_state[1].count")


def _key_data(key: jax.Array) -> np.ndarray:
    if jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key):
        return np.asarray(jax.random.key_data(key))
    return np.asarray(key)


def save_train_state(path: str | Path, state: TrainState, key: jax.Array, scalars: dict[str, Any],
                     extra: dict[str, Any] | None = None) -> None:
    """The full learner state (parameters, Adam state, normalizer), the trainer's RNG key and JSON
    ``scalars`` (step counters, lr scale, configuration) as a pickle-free ``.npz``, written atomically
    (temporary file, then rename). ``extra``: more named arrays (e.g. the worlds' step counters)."""
    leaves = jax.tree_util.tree_flatten_with_path(state)[0]
    arrays: dict[str, np.ndarray] = {f"state{jax.tree_util.keystr(kp)}": np.asarray(v) for kp, v in leaves}
    arrays["rng"] = _key_data(key)
    arrays["scalars"] = np.array(json.dumps(scalars, default=str))
    for k, v in (extra or {}).items():
        arrays[f"extra/{k}"] = np.asarray(v)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **arrays)
    tmp.replace(path)


def load_train_state(path: str | Path, template: TrainState) -> tuple[TrainState, jax.Array, dict[str, Any],
                                                                       dict[str, np.ndarray]]:
    """Inverse of :func:`save_train_state` for a learner of the same networks and optimizer (``template``
    gives the tree structure): (state, key, scalars, extra arrays). Raises ValueError on a mismatch."""
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
    out = []
    for kp, like in leaves:
        name = f"state{jax.tree_util.keystr(kp)}"
        if name not in arrays and name.replace(_INJECTED, "") in arrays:  # a file of the plain-Adam layout
            name = name.replace(_INJECTED, "")
        elif name not in arrays and name.startswith(_INJECT_OWN):  # its lr and counter: set by the next update
            out.append(jnp.asarray(like))
            continue
        if name not in arrays:
            raise ValueError(f"checkpoint {str(path)!r} lacks {name} (was it written by another --arch or network "
                             f"size?)")
        v = arrays[name]
        if tuple(v.shape) != tuple(np.shape(like)):
            raise ValueError(f"checkpoint {str(path)!r}: {name} has shape {v.shape}, this run needs "
                             f"{tuple(np.shape(like))}")
        out.append(jnp.asarray(v, dtype=jnp.asarray(like).dtype))
    state = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(template), out)
    scalars = json.loads(str(arrays["scalars"]))
    extra = {k[len("extra/"):]: v for k, v in arrays.items() if k.startswith("extra/")}
    return state, jnp.asarray(arrays["rng"]), scalars, extra


def load_init(path: str, params: Any, normalizer: Any, arch: dict[str, Any] | None, layout: dict[str, int],
              obs_dim: int, action_std: float | None = None, min_std: float = 0.001) -> tuple[Any, Any]:
    """Start from a policy checkpoint (transfer, e.g. single -> swarm): layers are copied; a
    larger observation (more neighbours) gets zero input weights for the new components, so
    the starting policy ignores them; the new components' normalizer is mean 0, std 1. Encoder runs
    (``arch`` not None) start from an encoder file of the same architecture and ``layout``. Returns
    (params, normalizer) on the templates ``params``/``normalizer``. ``action_std`` (pre-tanh) replaces the
    file's state-dependent std by this constant (:func:`~quadswarm_mj.training.learner.constant_action_std`)
    above the run's std floor ``min_std``."""
    params, normalizer = _load_init(path, params, normalizer, arch, layout, obs_dim)
    if action_std is not None:
        params = params.replace(policy=constant_action_std(params.policy, action_std, arch, min_std))
    return params, normalizer


def _load_init(path: str, params: Any, normalizer: Any, arch: dict[str, Any] | None, layout: dict[str, int],
               obs_dim: int) -> tuple[Any, Any]:
    pol = load_policy_file(path)
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    if arch is not None or not hasattr(pol, "kernels"):
        return _load_init_encoder(path, pol, arrays, params, normalizer, arch, layout)
    d_old, d = pol.obs_dim, obs_dim
    if d_old > d:
        raise ValueError(f"init_from policy has obs_dim {d_old} > this run's {d}")

    def pad(layers: list[tuple[np.ndarray, np.ndarray]], like: Any) -> list[tuple[np.ndarray, np.ndarray]]:
        want = _dense_layers(like)
        if [k.shape[1] for k, _ in layers] != [k.shape[1] for k, _ in want] or len(layers) != len(want):
            raise ValueError(f"init_from network sizes {[k.shape for k, _ in layers]} do not match this run's "
                             f"{[k.shape for k, _ in want]}")
        k0 = np.zeros((d, layers[0][0].shape[1]), np.float32)
        k0[:d_old] = layers[0][0]
        rest = [(np.asarray(k, np.float32), np.asarray(b, np.float32)) for k, b in layers[1:]]
        return [(k0, np.asarray(layers[0][1], np.float32))] + rest

    pol_layers = pad([(k, b) for k, b in zip(pol.kernels, pol.biases)], params.policy)
    value = params.value
    vl = _value_layers(arrays)
    if vl:
        value = _to_tree(pad(vl, params.value))
    params = ppo_losses.PPONetworkParams(policy=_to_tree(pol_layers), value=value)
    mean = np.zeros(d, np.float32)
    std = np.ones(d, np.float32)
    mean[:d_old], std[:d_old] = pol.obs_mean, pol.obs_std
    count = float(arrays["norm_count"]) if "norm_count" in arrays else 1e6
    normalizer = normalizer.replace(count=_uint64(count), mean=jnp.asarray(mean), std=jnp.asarray(std),
                                    summed_variance=jnp.asarray(std.astype(np.float64) ** 2 * count, jnp.float32))
    return params, normalizer

def _load_init_encoder(path: str, pol: Any, arrays: dict[str, np.ndarray], params: Any, normalizer: Any,
                       arch: dict[str, Any] | None, layout: dict[str, int]) -> tuple[Any, Any]:
    """Start from an encoder policy file of the same architecture and observation layout."""
    from quadswarm_mj.policies import validate_arch

    if arch is None or not hasattr(pol, "arch"):
        raise ValueError(f"init_from {path!r}: an MLP run starts from an MLP file and an encoder run from an "
                         f"encoder file of the same --arch")
    if pol.obs_layout != layout or pol.arch != validate_arch(arch, layout):
        raise ValueError(f"init_from {path!r}: architecture {pol.arch} / layout {pol.obs_layout} differ from this "
                         f"run's {arch} / {layout}")
    policy = enc_networks.unflatten_params(pol.params)
    value = params.value
    vl = _value_layers(arrays)
    if vl:
        if [k.shape for k, _ in vl] == [k.shape for k, _ in _dense_layers(params.value)]:
            value = _to_tree(vl)
    count = float(arrays["norm_count"]) if "norm_count" in arrays else 1e6
    mean, std = np.asarray(pol.obs_mean, np.float32), np.asarray(pol.obs_std, np.float32)
    normalizer = normalizer.replace(count=_uint64(count), mean=jnp.asarray(mean), std=jnp.asarray(std),
                                    summed_variance=jnp.asarray(std.astype(np.float64) ** 2 * count, jnp.float32))
    return ppo_losses.PPONetworkParams(policy=policy, value=value), normalizer
