"""Policy files, the pretrained manifest and its integrity checks, NumPy inference, baselines,
and the shipped policies' recorded performance (SPEC §8 metrics)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.policies import (
    ARCH_PRESETS,
    ENCODER_FORMAT,
    FORMAT,
    EncoderPolicy,
    MLPPolicy,
    count_params,
    encoder_policy_arrays,
    layout_obs_dim,
    load_policy,
    load_policy_file,
    load_pretrained,
    param_shapes,
    pretrained_dir,
    random_encoder_policy,
    read_manifest,
    save_encoder_policy,
    save_policy,
    sha256_file,
    validate_arch,
    validate_layout,
)
from quadswarm_mj.training.evaluation import evaluate


def _random_policy_file(path, obs_dim=18, hidden=(16, 16), seed=0, activation="tanh"):
    rng = np.random.default_rng(seed)
    sizes = [obs_dim, *hidden, 8]
    kernels = [rng.normal(0, 0.5, (a, b)) for a, b in zip(sizes[:-1], sizes[1:])]
    biases = [rng.normal(0, 0.1, (b,)) for b in sizes[1:]]
    mean, std = rng.normal(0, 1, obs_dim), rng.uniform(0.5, 2.0, obs_dim)
    meta = {"activation": activation, "obs_dim": obs_dim, "action_dim": 4, "env": {"num_quads": 1}}
    sha = save_policy(path, kernels, biases, mean, std, meta)
    return kernels, biases, mean, std, sha


def _reference_forward(kernels, biases, mean, std, obs):
    h = (obs - mean) / std
    for i, (k, b) in enumerate(zip(kernels, biases)):
        h = h @ k.astype(np.float32).astype(np.float64) + b.astype(np.float32).astype(np.float64)
        if i < len(kernels) - 1:
            h = np.tanh(h)
    return np.tanh(h[:, :4])


def _manifest_dir(tmp_path, name="toy"):
    d = tmp_path / "pretrained"
    d.mkdir()
    _, _, _, _, sha = _random_policy_file(d / f"{name}.npz")
    man = {"format": 1, "policies": {name: {"file": f"{name}.npz", "sha256": sha,
                                            "bytes": (d / f"{name}.npz").stat().st_size}}}
    (d / "manifest.json").write_text(json.dumps(man))
    return d


# ---------------------------------------------------------------------------- format and inference
def test_roundtrip_and_numpy_forward(tmp_path):
    p = tmp_path / "pol.npz"
    kernels, biases, mean, std, sha = _random_policy_file(p)
    assert sha == sha256_file(p)
    pol = load_policy_file(p)
    assert pol.obs_dim == 18 and pol.action_dim == 4 and pol.meta["format"] == FORMAT
    obs = np.random.default_rng(1).normal(0, 3, (7, 18))
    a = pol(obs)
    assert a.shape == (7, 4) and a.dtype == np.float32
    assert np.all(np.abs(a) <= 1.0)
    np.testing.assert_allclose(a, _reference_forward(kernels, biases, mean.astype(np.float32),
                                                     std.astype(np.float32), obs), atol=1e-5)
    assert pol(obs[0]).shape == (4,)  # a single quad's flat observation
    np.testing.assert_allclose(pol(obs[0]), a[0], atol=1e-6)
    assert pol(obs.reshape(7, 1, 18)).shape == (7, 1, 4)  # any leading dims (worlds, quads)
    with pytest.raises(ValueError, match="shape"):
        pol(np.zeros((3, 17)))


def test_policy_file_holds_no_pickled_objects(tmp_path):
    p = tmp_path / "pol.npz"
    _random_policy_file(p)
    with np.load(p, allow_pickle=False) as z:  # would raise on any object array
        assert all(z[k].dtype != object for k in z.files)
    # a file with a pickled object array is refused by the loader, not unpickled
    evil = tmp_path / "evil.npz"
    np.savez(evil, meta=np.array(json.dumps({"format": FORMAT})), obj=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError):
        load_policy_file(evil)
    with pytest.raises(ValueError, match="object"):
        save_policy(tmp_path / "x.npz", [np.zeros((2, 8))], [np.zeros(8)], np.zeros(2), np.ones(2), {},
                    extra={"bad": np.array([None], dtype=object)})


def test_malformed_files_raise_value_error(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip file at all")
    with pytest.raises(ValueError, match="not a readable"):
        load_policy_file(bad)
    with pytest.raises(ValueError, match="does not exist"):
        load_policy_file(tmp_path / "missing.npz")
    nometa = tmp_path / "nometa.npz"
    np.savez(nometa, x=np.zeros(3))
    with pytest.raises(ValueError, match="meta"):
        load_policy_file(nometa)
    with pytest.raises(ValueError, match="chain"):
        MLPPolicy([np.zeros((4, 5)), np.zeros((6, 8))], [np.zeros(5), np.zeros(8)], np.zeros(4), np.ones(4))


def test_numpy_inference_matches_brax_mode(tmp_path):
    """The exported MLP reproduces the deterministic action of the Brax network it came from."""
    pytest.importorskip("brax")
    import jax
    import jax.numpy as jnp
    from brax.training.acme import running_statistics
    from brax.training.agents.ppo import networks as ppo_networks
    from flax import linen

    from quadswarm_mj.training.ppo import _dense_layers

    d = 54
    nets = ppo_networks.make_ppo_networks(d, 4, preprocess_observations_fn=running_statistics.normalize,
                                          policy_hidden_layer_sizes=(32, 32), activation=linen.tanh)
    params = nets.policy_network.init(jax.random.PRNGKey(3))
    rng = np.random.default_rng(0)
    batch = jnp.asarray(rng.normal(1.0, 2.0, (256, d)), jnp.float32)
    norm = running_statistics.update(running_statistics.init_state(jax.ShapeDtypeStruct((d,), jnp.float32)), batch)
    obs = rng.normal(1.0, 2.0, (9, d)).astype(np.float32)
    logits = nets.policy_network.apply(norm, params, jnp.asarray(obs))
    expected = np.asarray(nets.parametric_action_distribution.mode(logits))
    layers = _dense_layers(params)
    save_policy(tmp_path / "b.npz", [k for k, _ in layers], [b for _, b in layers], np.asarray(norm.mean),
                np.asarray(norm.std), {"activation": "tanh", "obs_dim": d})
    np.testing.assert_allclose(load_policy_file(tmp_path / "b.npz")(obs), expected, atol=2e-5)


def test_policies_module_needs_no_jax():
    code = ("import sys, numpy as np\n"
            "from quadswarm_mj.policies import load_policy\n"
            "pol = load_policy('pretrained:single')\n"
            "a = pol(np.zeros((3, pol.obs_dim), np.float32))\n"
            "assert a.shape == (3, 4)\n"
            "from quadswarm_mj.training.evaluation import evaluate\n"
            "assert 'jax' not in sys.modules, sorted(m for m in sys.modules if m.startswith('jax'))\n")
    subprocess.run([sys.executable, "-c", code], check=True)


# ---------------------------------------------------------------------------- manifest and integrity
def test_manifest_lists_shipped_policies_with_hashes():
    man = read_manifest()
    assert {"single", "swarm8"} <= set(man["policies"])
    for name, entry in man["policies"].items():
        path = pretrained_dir() / entry["file"]
        assert sha256_file(path) == entry["sha256"], name
        assert path.stat().st_size == entry["bytes"], name
        pol = load_policy(f"pretrained:{name}")
        assert pol.obs_dim == EnvConfig(**pol.env_kwargs).obs_dim


def test_tampered_file_is_rejected(tmp_path):
    d = _manifest_dir(tmp_path)
    assert load_pretrained("toy", d).obs_dim == 18
    data = bytearray((d / "toy.npz").read_bytes())
    data[len(data) // 2] ^= 0x01  # flip one bit, same size
    (d / "toy.npz").write_bytes(bytes(data))
    with pytest.raises(ValueError, match="SHA-256"):
        load_pretrained("toy", d)


def test_truncated_or_missing_file_is_rejected(tmp_path):
    d = _manifest_dir(tmp_path)
    data = (d / "toy.npz").read_bytes()
    (d / "toy.npz").write_bytes(data[:-100])
    with pytest.raises(ValueError, match="truncated"):
        load_pretrained("toy", d)
    (d / "toy.npz").unlink()
    with pytest.raises(ValueError, match="missing"):
        load_pretrained("toy", d)


def test_replaced_file_and_bad_manifest_are_rejected(tmp_path):
    d = _manifest_dir(tmp_path)
    man = json.loads((d / "manifest.json").read_text())
    _random_policy_file(d / "toy.npz", seed=5)  # another valid policy under the same name
    man["policies"]["toy"]["bytes"] = (d / "toy.npz").stat().st_size
    (d / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(ValueError, match="SHA-256"):
        load_pretrained("toy", d)
    with pytest.raises(ValueError, match="unknown pretrained policy"):
        load_pretrained("nope", d)
    man["policies"]["toy"]["file"] = "../toy.npz"
    (d / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(ValueError, match="plain file name"):
        load_pretrained("toy", d)
    (d / "manifest.json").write_text("{not json")
    with pytest.raises(ValueError, match="JSON"):
        load_pretrained("toy", d)


def test_shipped_file_tamper_detected_through_load_policy(tmp_path, monkeypatch):
    d = tmp_path / "pretrained"
    shutil.copytree(pretrained_dir(), d)
    import quadswarm_mj.policies as policies

    monkeypatch.setattr(policies, "pretrained_dir", lambda: d)
    entry = read_manifest(d)["policies"]["swarm8"]
    raw = bytearray((d / entry["file"]).read_bytes())
    raw[-30] ^= 0xFF
    (d / entry["file"]).write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="tampered"):
        load_policy("pretrained:swarm8")
    assert load_policy("pretrained:single").obs_dim > 0


def test_load_policy_specs(tmp_path):
    with pytest.raises(ValueError, match="unknown policy"):
        load_policy("nonsense")
    with pytest.raises(ValueError, match="unknown pretrained policy"):
        load_policy("pretrained:nope")
    p = tmp_path / "ck.npz"
    _random_policy_file(p)
    assert isinstance(load_policy(str(p)), MLPPolicy)
    obs = np.zeros((2, 18), np.float32)
    a = load_policy("random", seed=0).act(obs)
    assert a.shape == (2, 4) and np.all(np.abs(a) <= 1)


# ---------------------------------------------------------------------------- baselines and evaluation
def test_controller_policy_hovers_at_goal_in_gym_env():
    from quadswarm_mj.envs.gym_env import QuadSwarmEnv

    pol = load_policy("controller")
    for n, scenario in ((1, "static_same_goal"), (3, "static_diff_goal")):
        env = QuadSwarmEnv(num_quads=n, scenario=scenario, episode_seconds=4.0)
        obs, info = env.reset(seed=0)
        for _ in range(400):
            obs, _, _, trunc, info = env.step(pol.act(obs, info))
        assert trunc
        assert np.all(np.linalg.norm(info["state"]["pos"] - info["goals"], axis=-1) < 0.3)


def test_evaluate_gym_and_batched_agree_for_the_controller():
    """The two evaluation paths measure the same thing: the controller reaches a static goal."""
    pol = load_policy("controller")
    env = {"episode_seconds": 4.0}
    g = evaluate(pol, "static_same_goal", episodes=2, num_quads=1, env=env, mode="gym")
    b = evaluate(pol, "static_same_goal", episodes=4, num_quads=1, env=env, mode="batched", max_worlds=3)
    for r in (g, b):
        assert r.per_episode["success"].shape == (r.episodes,)
        assert r.mean("success") == 1.0 and r.mean("goal_reach_rate") == 1.0
        assert r.mean("mean_distance") < 1.5
    rnd = evaluate(load_policy("random", seed=0), "static_same_goal", episodes=2, num_quads=1, env=env)
    assert rnd.mean("success") == 0.0 and rnd.mean("floor_hits") >= 1.0


# ---------------------------------------------------------------------------- shipped policies reproduce
def _tolerance(rec, key, episodes, z=3.0):
    """z sigma of the difference between a fresh mean over ``episodes`` and the recorded mean, from the
    recorded per-episode spread (floored at one 'failure' among the recorded episodes, so a
    recorded 100 % still allows the rare miss of a Bernoulli-like metric)."""
    n_rec = rec["episodes"]
    p_floor = 1.0 / n_rec
    var = max((rec.get(key + "_std") or 0.0) ** 2, p_floor * (1 - p_floor))
    return z * np.sqrt(var / episodes + var / n_rec)


def _check_recorded(name, scenarios, episodes=20):
    pol = load_policy(f"pretrained:{name}")
    for scenario in scenarios:
        rec = pol.meta["manifest"]["eval"][scenario]
        res = evaluate(pol, scenario, episodes=episodes, seed=12345)  # other seeds than the recorded run
        assert res.num_quads == rec["num_quads"]
        for key in ("success", "goal_reach_rate", "collisions", "mean_distance"):
            if rec[key] is None:
                continue
            tol = _tolerance(rec, key, episodes)
            got = res.mean(key)
            assert abs(got - rec[key]) <= tol, (name, scenario, key, got, rec[key], tol)


def test_pretrained_single_reproduces_recorded_metrics():
    _check_recorded("single", ["static_same_goal", "dynamic_same_goal"])


def test_pretrained_swarm8_reproduces_recorded_metrics():
    _check_recorded("swarm8", ["static_diff_goal", "swap_goals"])


def test_pretrained_swarm8_rl_is_ppo_alone_and_reproduces_recorded_metrics():
    """issue 35: the swarm policy trained by PPO alone (no teacher, no imitation loss), its stages' commands
    and budget recorded; a fresh evaluation on other seeds agrees with the recorded figures."""
    train = load_policy("pretrained:swarm8_rl").meta["manifest"]["train"]
    assert train["method"] == "ppo" and train["teacher"] is None and train["imitation_loss"] is False
    assert all(s["command"].startswith("quadswarm-train --preset swarm8_rl") for s in train["stages"])
    assert train["budget"]["agent_steps"] == sum(s["checkpoint_env_steps"] for s in train["stages"])
    _check_recorded("swarm8_rl", ["static_diff_goal", "swap_goals"])


def test_pretrained_swarm8_obstacles_rl_is_ppo_alone_and_reproduces_recorded_metrics():
    """issue 35: among columns by PPO alone from pretrained:single (success below the issue's target, recorded as
    measured); shipped with the issue's columns (density 0.2, 0.6 m) and the near feature form."""
    pol = load_policy("pretrained:swarm8_obstacles_rl")
    train = pol.meta["manifest"]["train"]
    assert train["method"] == "ppo" and train["teacher"] is None and train["imitation_loss"] is False
    assert train["stages"][0]["command"].startswith("quadswarm-train --preset swarm8_obstacles_rl")
    assert train["budget"]["agent_steps"] == sum(s["checkpoint_env_steps"] for s in train["stages"])
    o = EnvConfig(**pol.env_kwargs).obstacles
    assert (o.density, o.size, o.density_random, o.size_random, o.feature_form) == (0.2, 0.6, False, False, "near")
    assert train["stages"][0]["init_from"] == "pretrained:single"
    _check_recorded("swarm8_obstacles_rl", ["o_random"])


def test_pretrained_swarm8_deployable_reproduces_recorded_metrics():
    _check_recorded("swarm8_deployable", ["static_diff_goal"])


def test_pretrained_obstacle_policies_reproduce_recorded_metrics():
    _check_recorded("swarm8_obstacles", ["o_random"])
    _check_recorded("swarm8_obstacles_deployable", ["o_random"])
    _check_recorded("swarm8_sensors", ["o_random"])


def test_shipped_swarm_policies_are_what_the_manifest_says():
    """The current swarm policies: encoders over K = 6 neighbours (+ the 9 column features among
    obstacles), deployable ones within 2,000 actor parameters, env_kwargs that rebuild the training env."""
    from quadswarm_mj.policies import EncoderPolicy

    for name in ("swarm8", "swarm8_deployable", "swarm8_obstacles", "swarm8_obstacles_deployable"):
        pol = load_policy(f"pretrained:{name}")
        assert isinstance(pol, EncoderPolicy) and pol.env_kwargs["num_quads"] == 8
        cfg = EnvConfig(**pol.env_kwargs)
        assert cfg.obs_dim == pol.obs_dim and cfg.neighbors == 6
        if "obstacles" in name:
            assert cfg.obstacles.density == 0.2 and cfg.obstacles.size == 0.6 and cfg.downwash
            assert pol.obs_layout["obstacle_dim"] == 9
        else:
            assert cfg.obstacles is None
        assert (pol.num_params <= 2000) == name.endswith("deployable")
    # the multi-ranger student: the columns in the world, their 9 features not observed, the 10 deck readings instead
    pol = load_policy("pretrained:swarm8_sensors")
    cfg = EnvConfig(**pol.env_kwargs)
    assert cfg.obs_dim == pol.obs_dim == 18 + 36 + 10 and pol.obs_layout["obstacle_dim"] == 10
    assert not cfg.obstacles.observe_features and cfg.sensors.multiranger and not cfg.sensors.flow
    assert cfg.obstacles.density == 0.2 and cfg.obstacles.size == 0.6 and cfg.downwash


# ---------------------------------------------------------------------------- encoder policies (deep sets, attention)
LAYOUT_OBST = {"self_dim": 19, "num_neighbors": 2, "neighbor_dim": 6, "obstacle_dim": 9}
LAYOUT_SWARM = {"self_dim": 18, "num_neighbors": 3, "neighbor_dim": 6, "obstacle_dim": 0}
SMALL_ARCHS = {
    "deepsets": {"type": "deepsets", "self_layers": [24, 20], "neighbor_layers": [12, 10], "obstacle_layers": [8],
                 "head_layers": [16]},
    "attention_sim2real": ARCH_PRESETS["attention_sim2real"],
    "attention_multihead": {"type": "attention", "hidden": 12, "embed_layers": 2, "num_heads": 3, "attn_dim": 5,
                            "head_layers": [20, 10]},
}


def _obs(layout, n=64, seed=0):
    return np.random.default_rng(seed).normal(0.3, 2.0, (n, layout_obs_dim(layout))).astype(np.float32)


def _random_stats(layout, seed=0):
    rng = np.random.default_rng(seed)
    d = layout_obs_dim(layout)
    return rng.normal(0, 1, d), rng.uniform(0.5, 2.0, d)


def _reference_attention_policy(pol, obs):
    """An independent, per-sample loop implementation of the C.1 attention model (one observation at a time)."""
    p, a, lay = pol.params, pol.arch, pol.obs_layout
    sd, k = lay["self_dim"], lay["num_neighbors"]
    out = []
    for o in (obs.astype(np.float64) - pol.obs_mean) / pol.obs_std:
        def emb(x, pre):
            for i in range(a["embed_layers"]):
                x = np.tanh(x @ p[f"{pre}_{i}/kernel"] + p[f"{pre}_{i}/bias"])
            return x
        toks = ([emb(o[sd:sd + 6 * k], "nbr")] if k else []) + ([emb(o[sd + 6 * k:], "obst")]
                                                                if lay["obstacle_dim"] else [])
        t = np.stack(toks)
        heads = []
        for h in range(a["num_heads"]):
            sl = slice(h * a["attn_dim"], (h + 1) * a["attn_dim"])
            q, kk, v = (t @ p[f"attn/w_{c}/kernel"][:, sl] for c in "qkv")
            s = q @ kk.T / np.sqrt(a["attn_dim"])
            w = np.exp(s) / np.exp(s).sum(1, keepdims=True)  # no max shift: a different computation path
            heads.append(w @ v)
        y = np.concatenate(heads, 1) @ p["attn/fc/kernel"] + t
        y = (y - y.mean(1, keepdims=True)) / np.sqrt(y.var(1, keepdims=True) + 1e-6) * p["attn/ln/scale"] \
            + p["attn/ln/bias"]
        x = np.concatenate([emb(o[:sd], "self"), y.ravel()])
        for i in range(len(a["head_layers"])):
            x = np.tanh(x @ p[f"head_{i}/kernel"] + p[f"head_{i}/bias"])
        out.append(np.tanh((x @ p["action/kernel"] + p["action/bias"])[:4]))
    return np.array(out)


@pytest.mark.parametrize("layout", [LAYOUT_OBST, LAYOUT_SWARM, {**LAYOUT_OBST, "num_neighbors": 0}])
def test_attention_policy_matches_loop_reference(layout):
    for name in ("attention_sim2real", "attention_multihead"):
        mean, std = _random_stats(layout)
        pol = random_encoder_policy(SMALL_ARCHS[name], layout, seed=2, obs_mean=mean, obs_std=std)
        obs = _obs(layout)
        np.testing.assert_allclose(pol(obs), _reference_attention_policy(pol, obs), atol=1e-6)


def test_deepsets_policy_is_neighbour_order_invariant_and_uses_every_block():
    pol = random_encoder_policy(SMALL_ARCHS["deepsets"], LAYOUT_SWARM, seed=1)
    obs = _obs(LAYOUT_SWARM)
    sd = LAYOUT_SWARM["self_dim"]
    perm = obs.copy()
    perm[:, sd:] = obs[:, sd:].reshape(-1, 3, 6)[:, [2, 0, 1]].reshape(-1, 18)
    np.testing.assert_allclose(pol(perm), pol(obs), atol=1e-6)
    # a deep-sets policy is invariant to the order, not to the content: every block changes the action
    for sl in (slice(0, sd), slice(sd, sd + 6)):
        moved = obs.copy()
        moved[:, sl] += 1.0
        assert np.abs(pol(moved) - pol(obs)).max() > 1e-3
    obst = random_encoder_policy(SMALL_ARCHS["deepsets"], LAYOUT_OBST, seed=1)
    o = _obs(LAYOUT_OBST)
    moved = o.copy()
    moved[:, -9:] += 1.0
    assert np.abs(obst(moved) - obst(o)).max() > 1e-3


def test_encoder_file_roundtrip_records_architecture_and_layout(tmp_path):
    for name, arch in SMALL_ARCHS.items():
        mean, std = _random_stats(LAYOUT_OBST)
        pol = random_encoder_policy(arch, LAYOUT_OBST, seed=3, obs_mean=mean, obs_std=std,
                                    meta={"env": {"num_quads": 3, "num_neighbors": 2, "obs_self": "floor"}})
        p = tmp_path / f"{name}.npz"
        sha = save_encoder_policy(p, pol)
        assert sha == sha256_file(p)
        with np.load(p, allow_pickle=False) as z:
            assert all(z[k].dtype != object for k in z.files)
            meta = json.loads(str(z["meta"]))
            assert {k for k in z.files if k.startswith("actor/")} == {f"actor/{n}" for n in param_shapes(arch,
                                                                                                          LAYOUT_OBST)}
            assert all(z[k].dtype == np.float32 for k in z.files if k.startswith("actor/"))
        assert meta["format"] == ENCODER_FORMAT and meta["arch"]["type"] == arch["type"]
        assert meta["obs_layout"] == LAYOUT_OBST and meta["obs_dim"] == 40
        back = load_policy(str(p))
        assert isinstance(back, EncoderPolicy) and back.obs_dim == 40
        assert back.env_kwargs == {"num_quads": 3, "num_neighbors": 2, "obs_self": "floor"}
        obs = _obs(LAYOUT_OBST)
        np.testing.assert_allclose(back(obs), pol(obs), atol=1e-5)  # float32 storage
        assert back(obs[0]).shape == (4,)


def test_encoder_pretrained_is_hash_checked(tmp_path):
    d = tmp_path / "pretrained"
    pol = random_encoder_policy(SMALL_ARCHS["attention_sim2real"], LAYOUT_OBST, seed=0)
    sha = save_encoder_policy(d / "att.npz", pol)
    (d / "manifest.json").write_text(json.dumps({"format": 1, "policies": {"att": {
        "file": "att.npz", "sha256": sha, "bytes": (d / "att.npz").stat().st_size}}}))
    assert isinstance(load_pretrained("att", d), EncoderPolicy)
    raw = bytearray((d / "att.npz").read_bytes())
    raw[len(raw) // 2] ^= 0x01
    (d / "att.npz").write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="SHA-256"):
        load_pretrained("att", d)


def test_encoder_validation_errors(tmp_path):
    with pytest.raises(ValueError, match="arch type"):
        validate_arch({"type": "rnn"}, LAYOUT_OBST)
    with pytest.raises(ValueError, match="neighbour or an obstacle token"):
        validate_arch(SMALL_ARCHS["attention_sim2real"], {**LAYOUT_SWARM, "num_neighbors": 0})
    with pytest.raises(ValueError, match="self_dim"):
        validate_layout({**LAYOUT_OBST, "self_dim": 20})
    for bad in (-1, 4.0, 5000):  # any tail width 0..MAX_TAIL_DIM (column features and/or deck readings)
        with pytest.raises(ValueError, match="obstacle_dim"):
            validate_layout({**LAYOUT_OBST, "obstacle_dim": bad})
    assert validate_layout({**LAYOUT_OBST, "obstacle_dim": 10})["obstacle_dim"] == 10
    with pytest.raises(ValueError, match="head_layers"):
        validate_arch({**SMALL_ARCHS["deepsets"], "head_layers": [0]}, LAYOUT_OBST)
    pol = random_encoder_policy(SMALL_ARCHS["deepsets"], LAYOUT_OBST)
    bad = dict(pol.params)
    bad["head_0/kernel"] = bad["head_0/kernel"][:-1]
    with pytest.raises(ValueError, match="head_0/kernel"):
        EncoderPolicy(pol.arch, pol.obs_layout, bad, pol.obs_mean, pol.obs_std)
    with pytest.raises(ValueError, match="does not use"):
        EncoderPolicy(pol.arch, pol.obs_layout, {**pol.params, "head_9/bias": np.zeros(3)}, pol.obs_mean, pol.obs_std)
    del bad["head_0/kernel"]
    with pytest.raises(ValueError, match="lacks parameters"):
        EncoderPolicy(pol.arch, pol.obs_layout, bad, pol.obs_mean, pol.obs_std)
    with pytest.raises(ValueError, match="shape"):
        pol(np.zeros((2, 39)))
    # a file whose meta lacks the layout is refused
    arrays = encoder_policy_arrays(pol.arch, pol.obs_layout, pol.params, pol.obs_mean, pol.obs_std, {})
    meta = json.loads(str(arrays["meta"]))
    del meta["obs_layout"]
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "nolayout.npz", **arrays)
    with pytest.raises(ValueError, match="obs_layout"):
        load_policy_file(tmp_path / "nolayout.npz")


def test_deployable_attention_parameter_count():
    """Actor parameters (the action layer's mean part) of the C.1 attention model, by the formula
    H (S + 1) + H (6K + 1) + H (9 + 1) [embeddings] + 3 H n d + n d H + 2 H [Q, K, V, fc, LayerNorm]
    + (3H + 1) F [head] + (F + 1) 4 [action means]."""
    def formula(s, k, h, nh, d, f):
        return h * (s + 1) + h * (6 * k + 1) + h * 10 + 4 * h * nh * d + 2 * h + (3 * h + 1) * f + (f + 1) * 4

    for name in ("attention_sim2real", "attention_deployable"):
        a = ARCH_PRESETS[name]
        pol = random_encoder_policy(a, LAYOUT_OBST)
        assert pol.num_params == formula(19, 2, a["hidden"], a["num_heads"], a["attn_dim"], a["head_layers"][0])
        # the trainer's action layer has 2 x 4 outputs (means, std parameters): (F + 1) 4 more
        assert count_params(param_shapes(a, LAYOUT_OBST), deployed=False) == pol.num_params + 17 * 4
    assert random_encoder_policy(ARCH_PRESETS["attention_deployable"], LAYOUT_OBST).num_params <= 2000
    assert random_encoder_policy(ARCH_PRESETS["deepsets_deployable"], LAYOUT_OBST).num_params <= 2000
    mlp = load_policy("pretrained:swarm8_v1")
    assert mlp.num_params == sum(k.size + b.size for k, b in zip(mlp.kernels, mlp.biases)) - 4 * 65


def test_shipped_policies_act_as_their_arrays_say():
    """The shipped MLP files still load as MLPs and act as a forward pass over their raw arrays."""
    for name in ("single", "swarm8_v1"):
        pol = load_policy(f"pretrained:{name}")
        assert isinstance(pol, MLPPolicy) and pol.meta["format"] == FORMAT
        entry = read_manifest()["policies"][name]
        with np.load(pretrained_dir() / entry["file"], allow_pickle=False) as z:
            n = sum(1 for k in z.files if k.startswith("layer_") and k.endswith("/kernel"))
            ks = [z[f"layer_{i}/kernel"].astype(np.float64) for i in range(n)]
            bs = [z[f"layer_{i}/bias"].astype(np.float64) for i in range(n)]
            mean, std = z["obs_mean"].astype(np.float64), z["obs_std"].astype(np.float64)
        obs = np.random.default_rng(0).normal(0, 2, (32, pol.obs_dim))
        np.testing.assert_allclose(pol(obs), _reference_forward(ks, bs, mean, std, obs), atol=1e-6)
        assert pol.obs_layout == {"self_dim": 18, "num_neighbors": EnvConfig(**pol.env_kwargs).neighbors,
                                  "neighbor_dim": 6, "obstacle_dim": 0}


def test_new_mlp_files_record_architecture(tmp_path):
    p = tmp_path / "m.npz"
    _random_policy_file(p)
    meta = load_policy_file(p).meta
    assert meta["arch"] == {"type": "mlp", "activation": "tanh", "layers": [16, 16, 8]}
    assert meta["obs_layout"] == {"self_dim": 18, "num_neighbors": 0, "neighbor_dim": 6, "obstacle_dim": 0}


@pytest.mark.parametrize("name", sorted(SMALL_ARCHS))
def test_flax_networks_match_numpy_policy(tmp_path, name):
    """Flax params exported to the policy file act as Brax's deterministic (mode) action of the same network."""
    pytest.importorskip("flax")
    import jax
    import jax.numpy as jnp
    from brax.training.acme import running_statistics

    from quadswarm_mj.training.networks import (
        export_policy,
        flatten_params,
        make_ppo_networks,
        set_action_std,
        to_numpy_policy,
        unflatten_params,
    )

    arch, lay = SMALL_ARCHS[name], LAYOUT_OBST
    d = layout_obs_dim(lay)
    nets = make_ppo_networks(arch, lay, running_statistics.normalize, value_hidden_layer_sizes=(8,))
    # the flax module's parameter tree (traced, not compiled) is the NumPy format's layout
    shapes = jax.eval_shape(nets.policy_network.init, jax.random.PRNGKey(4))
    from flax.traverse_util import flatten_dict

    assert {n: tuple(v.shape) for n, v in flatten_dict(shapes["params"], sep="/").items()} == param_shapes(arch, lay)
    # weights drawn in NumPy (saves compiling the init on a busy machine), normalizer from data
    mean, std = _random_stats(lay, seed=5)
    params = unflatten_params(random_encoder_policy(arch, lay, seed=6).params)
    norm = running_statistics.init_state(jax.ShapeDtypeStruct((d,), jnp.float32)).replace(
        mean=jnp.asarray(mean, jnp.float32), std=jnp.asarray(std, jnp.float32))
    obs = np.random.default_rng(0).normal(1.0, 2.0, (33, d)).astype(np.float32)

    @jax.jit
    def mode(p, o):
        logits = nets.policy_network.apply(norm, p, o)
        return logits, nets.parametric_action_distribution.mode(logits)

    logits, expected = mode(params, jnp.asarray(obs))
    assert logits.shape == (33, 8)
    export_policy(tmp_path / "p.npz", arch, lay, params, norm.mean, norm.std, meta={"env": {"num_quads": 3}})
    pol = load_policy_file(tmp_path / "p.npz")
    assert isinstance(pol, EncoderPolicy)
    assert np.abs(np.asarray(expected)).max() > 0.1
    np.testing.assert_allclose(pol(obs), np.asarray(expected), atol=1e-5)
    # the trainer's std initialization leaves the deterministic action alone
    p2 = set_action_std(params, 0.3)
    assert np.allclose(flatten_params(p2)["action/bias"][4:], np.log(np.expm1(0.299)))
    np.testing.assert_allclose(to_numpy_policy(arch, lay, p2, norm.mean, norm.std)(obs), pol(obs), atol=1e-6)
    value = jax.eval_shape(lambda: nets.value_network.apply(norm, nets.value_network.init(jax.random.PRNGKey(0)),
                                                            jnp.asarray(obs)))
    assert value.shape == (33,)
