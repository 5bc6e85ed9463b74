"""Smoke tests of the PPO trainer and scripts/train.py: a tiny run writes logs, curves and
policy checkpoints that the NumPy loader reads; transfer from a single-quad policy to a swarm
keeps the policy's actions; the rollout batch keeps per-quad rewards and episode metrics."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("brax")

from quadswarm_mj.config import EnvConfig  # noqa: E402
from quadswarm_mj.policies import load_policy  # noqa: E402
from quadswarm_mj.training.ppo import AgentBatch, PPOConfig, PPOTrainer  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TINY = {"num_worlds": 4, "unroll_length": 8, "num_minibatches": 2, "num_epochs": 1, "policy_hidden": (8, 8),
        "value_hidden": (8,)}


def _train_script():
    spec = importlib.util.spec_from_file_location("train_script", ROOT / "scripts" / "train.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_train_script_writes_logs_curves_and_policies(tmp_path):
    out = tmp_path / "run"
    argv = ["--preset", "single_v1", "--out", str(out), "--timesteps", "96",
            "--scenario", "static_same_goal,dynamic_same_goal",
            "--num-worlds", "4", "--unroll-length", "8", "--num-minibatches", "2", "--num-epochs", "1",
            "--policy-hidden", "8,8", "--value-hidden", "8", "--reward", "vel=0.05", "--env", "episode_seconds=0.2",
            "--no-progress", "--seed", "3"]
    assert _train_script().main(argv) == 0
    rows = json.loads((out / "progress.json").read_text())
    assert len(rows) == 3 and rows[-1]["env_steps"] == 96  # 4 worlds x 1 quad x 8 steps per iteration
    assert {"reward_per_step", "static_same_goal/success", "dynamic_same_goal/goal_reach_rate"} <= set(rows[-1])
    # 20-step episodes, 24 steps per world: every world finished an episode after the first (desynced) one
    assert sum(r["static_same_goal/episodes"] for r in rows) >= 1
    header = (out / "progress.csv").read_text().splitlines()[0].split(",")
    assert "env_steps" in header and "static_same_goal/mean_distance" in header
    assert (out / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    run = json.loads((out / "run.json").read_text())
    assert run["rewards"] == {"vel": 0.05} and run["num_quads"] == 1
    pol = load_policy(str(out / "final.npz"))
    assert pol.obs_dim == 18 and pol.meta["train"]["env_steps"] == 96
    a = pol(np.zeros((5, 18), np.float32))
    assert a.shape == (5, 4) and np.all(np.abs(a) <= 1)


def test_train_script_rejects_bad_config(tmp_path, capsys):
    mod = _train_script()
    with pytest.raises(SystemExit, match="unknown scenario"):
        mod.main(["--out", str(tmp_path), "--scenario", "nope", "--timesteps", "1"])
    with pytest.raises(SystemExit, match="rewards"):
        mod.main(["--out", str(tmp_path), "--reward", "pos=-1", "--timesteps", "1"])


def test_agent_batch_per_quad_rewards_and_resets():
    cfg = EnvConfig(num_quads=3, scenario="static_diff_goal", episode_seconds=0.05)  # 5 steps
    b = AgentBatch([cfg], [2], seed=0, desync=False)
    obs = b.reset()
    assert obs.shape == (6, cfg.obs_dim) and obs.dtype == np.float32
    hover = np.full((6, 4), cfg.quad.hover_action)
    finished = []
    for i in range(5):
        nobs, r, trunc, cont, fin = b.step(hover)
        assert r.shape == (6,) and np.all(r < 0.05)
        finished += fin
        if i < 4:
            assert not trunc.any() and np.array_equal(nobs, nobs)
    assert trunc.all()  # time limit of every world, flagged per agent
    # first episodes are not logged (their start may be desynchronized); the second ones are
    assert finished == []
    for _ in range(5):
        *_, fin = b.step(hover)
        finished += fin
    (scn, metrics, returns), = finished
    assert scn == "static_diff_goal" and metrics["success"].shape == (2,) and returns.shape == (2,)


def test_init_from_single_policy_transfers_to_swarm(tmp_path):
    """A single-quad checkpoint starts a swarm run whose policy acts exactly like it on the own-state
    part of the observation (zero weights on the new neighbour inputs)."""
    single = PPOTrainer([EnvConfig(num_quads=1)], PPOConfig(**TINY), seed=1)
    single.save(tmp_path / "single.npz")
    swarm = PPOTrainer([EnvConfig(num_quads=4)], PPOConfig(**TINY), seed=2, init_from=str(tmp_path / "single.npz"))
    swarm.save(tmp_path / "swarm.npz")
    p1, p4 = load_policy(str(tmp_path / "single.npz")), load_policy(str(tmp_path / "swarm.npz"))
    assert p1.obs_dim == 18 and p4.obs_dim == 18 + 6 * 3
    obs = np.random.default_rng(0).normal(0, 1, (10, p4.obs_dim)).astype(np.float32)
    np.testing.assert_allclose(p4(obs), p1(obs[:, :18]), atol=1e-5)
    with pytest.raises(ValueError, match="obs_dim"):
        PPOTrainer([EnvConfig(num_quads=1)], PPOConfig(**TINY), init_from=str(tmp_path / "swarm.npz"))


def test_warm_start_std_sets_a_constant_std_and_keeps_the_means(tmp_path):
    """--warm-start-std: the warm-started policy's std is the given value in every state (pre-tanh,
    Brax's softplus + 0.001), its greedy actions are the file's."""
    from quadswarm_mj.training.learner import _dense_layers

    src = PPOTrainer([EnvConfig(num_quads=1)], PPOConfig(**TINY), seed=1)
    src.save(tmp_path / "src.npz")
    warm = PPOTrainer([EnvConfig(num_quads=1)], PPOConfig(**TINY, warm_start_std=0.2), seed=2,
                      init_from=str(tmp_path / "src.npz"))
    obs = np.random.default_rng(0).normal(0, 1, (10, 18)).astype(np.float32)
    h = obs
    layers = _dense_layers(warm.state.params.policy)
    for k, b in layers[:-1]:
        h = np.tanh(h @ k + b)
    out = h @ layers[-1][0] + layers[-1][1]
    np.testing.assert_allclose(np.logaddexp(0.0, out[:, 4:]) + 0.001, 0.2, rtol=1e-5)
    warm.save(tmp_path / "warm.npz")
    greedy_warm, greedy_src = load_policy(str(tmp_path / "warm.npz")), load_policy(str(tmp_path / "src.npz"))
    np.testing.assert_allclose(greedy_warm(obs), greedy_src(obs), atol=1e-6)
    with pytest.raises(ValueError, match="warm_start_std"):
        PPOConfig(warm_start_std=0.0)


def test_train_inputs_from_trains_only_the_new_inputs_and_the_critic(tmp_path):
    """--train-inputs-from N: after updates, the warm start's policy is unchanged except the first-layer
    rows of the inputs >= N (the new neighbours here), so the greedy actions on the old inputs with the new
    ones at 0 are still the file's; the critic trains; the observation statistics are not updated."""
    import jax

    from quadswarm_mj.training.learner import _dense_layers

    single = PPOTrainer([EnvConfig(num_quads=1)], PPOConfig(**TINY), seed=1)
    single.save(tmp_path / "single.npz")
    ppo = PPOConfig(**TINY, learning_rate=1e-2, train_inputs_from=18)
    tr = PPOTrainer([EnvConfig(num_quads=4)], ppo, seed=2, init_from=str(tmp_path / "single.npz"))
    before = jax.tree.map(np.asarray, (tr.state.params, tr.state.normalizer))
    tr.train(total_steps=TINY["num_worlds"] * 4 * TINY["unroll_length"] * 2, progress=False)
    (pol0, val0), (pol1, val1) = [(_dense_layers(p.policy), _dense_layers(p.value))
                                  for p in (before[0], tr.state.params)]
    assert np.array_equal(pol1[0][0][:18], pol0[0][0][:18]) and not np.array_equal(pol1[0][0][18:], pol0[0][0][18:])
    assert all(np.array_equal(a, b) for (ka, ba), (kb, bb) in zip(pol0[1:], pol1[1:]) for a, b in ((ka, kb), (ba, bb)))
    assert np.array_equal(pol1[0][1], pol0[0][1]) and not np.array_equal(val1[0][0], val0[0][0])
    for a, b in zip(jax.tree.leaves(before[1]), jax.tree.leaves(tr.state.normalizer)):
        assert np.array_equal(a, np.asarray(b))
    tr.save(tmp_path / "swarm.npz")
    obs = np.random.default_rng(0).normal(0, 1, (10, tr.obs_dim)).astype(np.float32)
    obs[:, 18:] = 0.0
    np.testing.assert_allclose(load_policy(str(tmp_path / "swarm.npz"))(obs),
                               load_policy(str(tmp_path / "single.npz"))(obs[:, :18]), atol=1e-6)
    with pytest.raises(ValueError, match="train_inputs_from > 0 keeps a warm start's policy: it needs init_from"):
        PPOTrainer([EnvConfig(num_quads=4)], ppo)
    with pytest.raises(ValueError, match="train_inputs_from must be below the observation size 36"):
        PPOTrainer([EnvConfig(num_quads=4)], PPOConfig(**TINY, train_inputs_from=36),
                   init_from=str(tmp_path / "single.npz"))
    with pytest.raises(ValueError, match="train_inputs_from must be an int >= 0"):
        PPOConfig(train_inputs_from=-1)
    with pytest.raises(ValueError, match="train_inputs_from needs arch 'mlp'"):
        PPOConfig(train_inputs_from=18, arch="deepsets_large")


def test_min_action_std_floors_the_std_and_the_warm_start_lands_on_it(tmp_path):
    """--min-action-std: the tanh-normal std is softplus(output) + the floor, so no output takes it below;
    a warm start's --warm-start-std is met exactly above the floor; a floor at or above it is refused."""
    import jax.numpy as jnp

    from quadswarm_mj.training.learner import _dense_layers

    src = PPOTrainer([EnvConfig(num_quads=1)], PPOConfig(**TINY), seed=1)
    src.save(tmp_path / "src.npz")
    warm = PPOTrainer([EnvConfig(num_quads=1)], PPOConfig(**TINY, warm_start_std=0.12, min_action_std=0.1), seed=2,
                      init_from=str(tmp_path / "src.npz"))
    dist = warm.networks.parametric_action_distribution
    scale = dist.create_dist(jnp.concatenate([jnp.zeros((3, 4)), jnp.full((3, 4), -50.0)], axis=-1)).scale
    np.testing.assert_allclose(np.asarray(scale), 0.1, rtol=1e-6)
    layers = _dense_layers(warm.state.params.policy)
    out = np.zeros((1, 8), np.float32) @ layers[-1][0] + layers[-1][1]
    np.testing.assert_allclose(np.asarray(dist.create_dist(jnp.asarray(out)).scale), 0.12, rtol=1e-5)
    fresh = PPOTrainer([EnvConfig(num_quads=1)], PPOConfig(**TINY, init_std=0.5, min_action_std=0.2), seed=3)
    b = _dense_layers(fresh.state.params.policy)[-1][1]
    np.testing.assert_allclose(np.logaddexp(0.0, b[4:]) + 0.2, 0.5, rtol=1e-5)
    with pytest.raises(ValueError, match="warm_start_std must be above ppo.min_action_std"):
        PPOConfig(warm_start_std=0.1, min_action_std=0.1)
    with pytest.raises(ValueError, match="min_action_std must be a number"):
        PPOConfig(min_action_std=0.0)


def test_correlated_exploration_noise_is_standard_normal_and_trains_on_the_jax_engine():
    """noise_correlation: AR(1) draws stay N(0, 1) with lag-1 correlation rho; the policy step takes the
    pre-tanh action mean + std * eps with its log-prob; a JAX-engine run trains; the CPU trainer refuses it."""
    import jax
    import jax.numpy as jnp

    from quadswarm_mj.training.jax_ppo import JaxPPOTrainer
    from quadswarm_mj.training.learner import correlated_noise, make_noise_policy_step

    rho, eps, keys = 0.9, [jax.random.normal(jax.random.key(0), (4000, 4))], jax.random.split(jax.random.key(1), 60)
    for k in keys:
        eps.append(correlated_noise(eps[-1], k, rho))
    e = np.asarray(jnp.stack(eps))  # (61, 4000, 4)
    assert abs(e.mean()) < 0.02 and abs(e.std() - 1.0) < 0.02
    lag1 = np.mean(e[1:] * e[:-1]) / np.mean(e * e)
    assert abs(lag1 - rho) < 0.01
    ppo = PPOConfig(**TINY, noise_correlation=rho)
    tr = JaxPPOTrainer([EnvConfig(num_quads=2, episode_seconds=0.3)], ppo, seed=0)
    obs = jnp.asarray(np.random.default_rng(0).normal(0, 1, (5, tr.obs_dim)), jnp.float32)
    z = jnp.asarray(np.random.default_rng(1).normal(0, 1, (5, 4)), jnp.float32)
    act, extras = make_noise_policy_step(tr.networks)(tr.state.normalizer, tr.state.params.policy, obs, z)
    dist = tr.networks.parametric_action_distribution
    logits = tr.networks.policy_network.apply(tr.state.normalizer, tr.state.params.policy, obs)
    normal = dist.create_dist(logits)
    np.testing.assert_allclose(np.asarray(extras["raw_action"]), np.asarray(normal.loc + normal.scale * z), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(act), np.tanh(np.asarray(extras["raw_action"])), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(extras["log_prob"]), np.asarray(dist.log_prob(logits, extras["raw_action"])),
                               rtol=1e-6)
    rows = tr.train(total_steps=TINY["num_worlds"] * 2 * TINY["unroll_length"] * 2, progress=False)
    assert len(rows) == 2 and all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(tr.state.params))
    with pytest.raises(ValueError, match="needs the JAX engine"):
        PPOTrainer([EnvConfig(num_quads=1)], ppo)
    with pytest.raises(ValueError, match="noise_correlation must be a number in"):
        PPOConfig(noise_correlation=1.0)


def test_ppo_config_validation():
    with pytest.raises(ValueError, match="num_worlds"):
        PPOConfig(num_worlds=0)
    with pytest.raises(ValueError, match="activation"):
        PPOConfig(activation="sigmoid")
    with pytest.raises(ValueError, match="divisible"):
        PPOTrainer([EnvConfig(num_quads=1)], PPOConfig(num_worlds=3, num_minibatches=2, unroll_length=2))


def test_desync_truncates_first_episodes_without_moving_scenario_clocks():
    """The first episode of each world ends after its own random length; every world starts at
    t = 0, so dynamic_same_goal's first goal jump (U(4, 6) s) never fires before t = 4 s."""
    cfg = EnvConfig(num_quads=1, scenario="dynamic_same_goal", episode_seconds=6.0).without_noise()
    batch = AgentBatch([cfg], [8], seed=3, desync=True)
    batch.reset()
    e = batch.engines[0]
    assert (e.steps == 0).all()
    first_len = batch.first_len[0].copy()
    assert first_len.min() >= 1 and first_len.max() <= cfg.episode_steps and len(np.unique(first_len)) > 1
    goals = e.sstate.goals.copy()
    ended = np.zeros(8, bool)
    for step in range(1, cfg.episode_steps + 1):
        t_before = e.steps * cfg.control_dt + cfg.control_dt  # time of the state this step reaches
        _, _, trunc, _, _ = batch.step(np.full((8, 4), cfg.quad.hover_action))
        done = trunc.astype(bool)
        np.testing.assert_array_equal(done & ~ended, ~ended & (first_len == step))
        changed = np.abs(e.sstate.goals - goals).max(axis=(1, 2)) > 0
        first = ~ended & ~done
        assert not (changed & first & (t_before < 4.0 - 1e-4)).any(), f"goal jump before 4 s at step {step}"
        ended |= done
        goals = e.sstate.goals.copy()
    assert ended.all()


# ---------------------------------------------------------------------------- encoders, presets, resume
def _tiny_argv(out, *extra):
    return ["--preset", "single_v1", "--out", str(out), "--num-worlds", "2", "--unroll-length", "4",
            "--num-minibatches", "2", "--num-epochs", "1", "--value-hidden", "8", "--no-progress", "--seed", "1",
            *extra]


@pytest.mark.slow
def test_arch_attention_deployable_run_writes_encoder_policy(tmp_path):
    """A 1-iteration run with --arch attention_deployable writes a format-2 policy file recording its
    architecture and observation layout, which loads with load_policy and acts."""
    out = tmp_path / "enc"
    assert _train_script().main(_tiny_argv(out, "--timesteps", "24", "--scenario", "static_diff_goal",
                                           "--num-quads", "3", "--arch", "attention_deployable")) == 0
    pol = load_policy(str(out / "final.npz"))
    assert pol.meta["format"] == "quadswarm_mj.policy/2" and pol.arch["type"] == "attention"
    assert pol.obs_layout == {"self_dim": 18, "num_neighbors": 2, "neighbor_dim": 6, "obstacle_dim": 0}
    assert pol.meta["train"]["ppo"]["arch"] == "attention_deployable" and pol.num_params <= 2000
    obs = np.random.default_rng(0).normal(0, 1, (3, pol.obs_dim))
    a = pol(obs)
    assert a.shape == (3, 4) and np.all(np.abs(a) <= 1) and np.ptp(a) > 0
    env = pol.env_kwargs
    assert env["num_quads"] == 3


def test_swarm8_presets_sizes_and_configs():
    from quadswarm_mj.cli.train import PRESETS
    from quadswarm_mj.policies import count_params, param_shapes
    from quadswarm_mj.training.ppo import PPOConfig, encoder_arch, obs_layout

    for name in ("swarm8", "swarm8_deployable", "swarm8_obstacles", "swarm8_obstacles_deployable"):
        pr = PRESETS[name]
        assert pr["engine"] == "jax" and pr["num_quads"] == 8 and pr["replay_prob"] == 0.75
        ppo = PPOConfig(**pr["ppo"])
        cfg = EnvConfig(num_quads=8, scenario=pr["scenarios"][0], **pr["env"])
        n_act = count_params(param_shapes(encoder_arch(ppo.arch, ppo.arch_width), obs_layout(cfg)))
        if name.endswith("deployable"):
            assert n_act <= 2000, (name, n_act)
        else:
            assert n_act > 2000
        if "obstacles" in name:
            assert cfg.obstacles.density == 0.2 and cfg.obstacles.size == 0.6 and cfg.downwash
            assert cfg.neighbors == 2 and cfg.obs_self == "floor" and cfg.obs_dim == 19 + 12 + 9
        else:
            assert pr["scenarios"] == ["mix", "run_away"] and pr["weights"] == [9, 1]


def test_finetune_presets_start_from_the_shipped_warm_start():
    """The recipes of the shipped swarm policies: their warm start resolves to the shipped file (SHA-256
    checked) and its observation layout is the first part of the run's (obstacle features appended)."""
    from quadswarm_mj.cli.train import PRESETS, resolve_policy_path
    from quadswarm_mj.training.ppo import PPOConfig

    for name in ("swarm8_finetune", "swarm8_obstacles_finetune", "swarm8_rl", "swarm8_obstacles_rl"):
        pr = PRESETS[name]
        path = resolve_policy_path(pr["init_from"])
        start = load_policy(path)
        cfg = EnvConfig(num_quads=8, scenario=pr["scenarios"][0], **pr["env"])
        assert Path(path).is_file() and start.obs_dim == 54
        assert cfg.obs_dim == 54 + (9 if cfg.obstacles is not None else 0)
        PPOConfig(**pr["ppo"])
    assert EnvConfig(**PRESETS["swarm8_obstacles_rl"]["env"]).obstacles.feature_form == "slopes"
    assert PRESETS["swarm8_obstacles_rl"]["scenarios"] == ["o_random"]  # the evaluated scenario only (TRAINING.md)
    assert resolve_policy_path("runs/x.npz") == "runs/x.npz"
    with pytest.raises(ValueError, match="unknown pretrained policy"):
        resolve_policy_path("pretrained:nope")


def test_obstacle_preset_trains_on_the_cpu_engine(tmp_path):
    """The obstacle preset's config (K = 2, obstacle features last) trains and writes a policy file
    whose observation layout records the 9 obstacle features."""
    from quadswarm_mj.policies import load_policy

    out = tmp_path / "o"
    rc = _train_script().main(_tiny_argv(out, "--preset", "swarm8_obstacles_deployable", "--engine", "mujoco",
                                         "--num-quads", "3", "--replay-prob", "0", "--timesteps", "8"))
    assert rc in (0, None)
    pol = load_policy(str(out / "final.npz"))
    assert pol.obs_layout["obstacle_dim"] == 9 and pol.obs_layout["num_neighbors"] == 2


def test_replay_needs_the_jax_engine(tmp_path):
    with pytest.raises(SystemExit, match="--engine jax"):
        _train_script().main(_tiny_argv(tmp_path / "r", "--replay-prob", "0.5", "--timesteps", "8"))


@pytest.mark.slow
def test_resume_continues_step_count_optimizer_and_normalizer(tmp_path):
    out = tmp_path / "run"
    base = _tiny_argv(out, "--scenario", "static_same_goal", "--policy-hidden", "8", "--env", "episode_seconds=0.1")
    mod = _train_script()
    assert mod.main(base + ["--timesteps", "16"]) == 0  # 2 iterations of 2 worlds x 4 steps
    from quadswarm_mj.training.ppo import TRAIN_STATE_FILE

    with np.load(out / "checkpoints" / TRAIN_STATE_FILE, allow_pickle=False) as z:
        sc1 = json.loads(str(z["scalars"]))
        norm1 = {k: z[k] for k in z.files if "normalizer" in k and "mean" in k}
    assert sc1["env_steps"] == 16 and sc1["iteration"] == 2
    assert mod.main(["--resume", str(out), "--timesteps", "8", "--no-progress"]) == 0
    rows = json.loads((out / "progress.json").read_text())
    assert [r["env_steps"] for r in rows] == [8, 16, 24] and [r["iteration"] for r in rows] == [1, 2, 3]
    assert all(np.isfinite(r["total_loss"]) for r in rows)
    with np.load(out / "checkpoints" / TRAIN_STATE_FILE, allow_pickle=False) as z:
        sc2 = json.loads(str(z["scalars"]))
        counts = [z[k] for k in z.files if k.startswith("state.opt_state") and "count" in k]
    assert sc2["env_steps"] == 24 and sc2["iteration"] == 3
    assert any(int(np.asarray(c).max()) == 3 * 2 for c in counts)  # Adam count: 3 iterations x 2 minibatches
    assert load_policy(str(out / "final.npz")).meta["train"]["env_steps"] == 24
    assert norm1  # the normalizer is part of the checkpoint
    with pytest.raises(SystemExit, match="needs"):
        mod.main(["--resume", str(tmp_path / "nothing"), "--timesteps", "8"])


@pytest.mark.slow
def test_resume_without_a_budget_finishes_the_runs_own_timesteps(tmp_path):
    """A run stopped before its --timesteps (here by a --minutes cap) resumed with no new budget trains the rest of
    its steps, so its learning-rate schedule ends where the uninterrupted run's does; once reached, it says so."""
    out = tmp_path / "run"
    base = _tiny_argv(out, "--scenario", "static_same_goal", "--policy-hidden", "8", "--env", "episode_seconds=0.1")
    mod = _train_script()
    # stopped by the clock (0.06 s) after its first iteration, which compiles for seconds
    assert mod.main(base + ["--timesteps", "32", "--minutes", "0.001"]) == 0
    assert json.loads((out / "run.json").read_text())["total_timesteps"] == 32
    assert [r["env_steps"] for r in json.loads((out / "progress.json").read_text())] == [8]
    assert mod.main(["--resume", str(out), "--no-progress"]) == 0
    assert [r["env_steps"] for r in json.loads((out / "progress.json").read_text())] == [8, 16, 24, 32]
    with pytest.raises(SystemExit, match="already reached its budget of 32 agent-steps"):
        mod.main(["--resume", str(out), "--no-progress"])


@pytest.mark.slow
def test_jax_engine_training_with_encoder_replay_anneal_and_resume(tmp_path):
    """The JAX engine trainer: one jitted iteration per call; an attention policy file that loads and acts;
    the replay columns in the log; the annealing clock (info["total_steps"]) carried over desync cuts,
    auto-resets and the resume; a resumed run continues the step count with a finite loss."""
    out = tmp_path / "jax"
    argv = _tiny_argv(out, "--engine", "jax", "--scenario", "static_diff_goal", "--num-quads", "2",
                      "--arch", "attention_deployable", "--replay-prob", "0.75", "--anneal-agent-steps", "400",
                      "--env", "episode_seconds=0.05")
    mod = _train_script()
    assert mod.main(argv + ["--timesteps", "32"]) == 0  # 2 iterations of 2 worlds x 2 quads x 4 steps
    run = json.loads((out / "run.json").read_text())
    assert run["engine"] == "jax" and run["rewards"]["anneal_steps"] == 100  # 400 agent-steps / 4 agents
    rows = json.loads((out / "progress.json").read_text())
    assert [r["env_steps"] for r in rows] == [16, 32]
    assert {"static_diff_goal/replay_rate", "static_diff_goal/replay_buffer_size"} <= set(rows[-1])
    assert rows[-1]["static_diff_goal/episodes"] >= 1  # 5-step episodes, 8 steps per world
    pol = load_policy(str(out / "final.npz"))
    assert pol.arch["type"] == "attention" and pol.meta["train"]["engine"] == "jax"
    a = pol(np.zeros((2, pol.obs_dim)))
    assert a.shape == (2, 4) and np.all(np.abs(a) <= 1)
    from quadswarm_mj.training.ppo import TRAIN_STATE_FILE

    with np.load(out / "checkpoints" / TRAIN_STATE_FILE, allow_pickle=False) as z:
        np.testing.assert_array_equal(z["extra/total_steps_0"], [8, 8])
    assert mod.main(["--resume", str(out), "--timesteps", "16", "--no-progress"]) == 0
    rows = json.loads((out / "progress.json").read_text())
    assert [r["env_steps"] for r in rows] == [16, 32, 48] and np.isfinite(rows[-1]["total_loss"])
    with np.load(out / "checkpoints" / TRAIN_STATE_FILE, allow_pickle=False) as z:
        np.testing.assert_array_equal(z["extra/total_steps_0"], [12, 12])
        assert json.loads(str(z["scalars"]))["iteration"] == 3


def test_progress_bar_lines_and_terminal_line():
    """Off a terminal: full lines (agent-steps, agent-steps/s, elapsed and remaining time, the recent
    episodes' metrics); on a terminal: one line redrawn with \\r, ended by close()."""
    import io

    from quadswarm_mj.training.progress import ProgressBar, fmt_time

    rows = [{"env_steps": 1000 * (i + 1), "reward_per_step": 0.001 * i, "a/episodes": n, "a/success": s,
             "a/mean_distance": d, "a/floor_hits": 0.0} for i, (n, s, d) in enumerate([(0, float("nan"), float("nan")),
                                                                                       (1, 0.0, 2.0), (3, 1.0, 0.4)])]
    buf = io.StringIO()
    bar = ProgressBar(total_steps=6000, stream=buf, every_s=0.0)
    assert not bar.tty
    for r in rows:
        bar.update(r)
    bar.close()
    lines = buf.getvalue().splitlines()
    assert len(lines) == 3 and "\r" not in buf.getvalue()
    assert "3.00 k agent-steps" in lines[-1] and "/s" in lines[-1] and "elapsed" in lines[-1] and "left" in lines[-1]
    assert " 50%" in lines[-1]
    # episode-weighted over the recent rows: success (0 * 1 + 1 * 3) / 4, distance (2 * 1 + 0.4 * 3) / 4
    assert "a: succ 0.75" in lines[-1] and "dist 0.80 m" in lines[-1]
    assert "a:" not in lines[0]  # no episode ended yet
    tty = io.StringIO()
    bar = ProgressBar(seconds=60.0, stream=tty, tty=True)
    for r in rows:
        bar.update(r)
    bar.close()
    text = tty.getvalue()
    assert text.count("\r") == 3 and text.count("\n") == 1 and text.endswith("\n")
    assert fmt_time(75) == "1:15" and fmt_time(3725) == "1:02:05" and fmt_time(float("inf")) == "?"


def test_training_run_prints_progress_and_writes_curves(tmp_path, capsys):
    """A few seconds of training with the progress bar on (stdout is not a terminal here: periodic lines,
    and always the final one) and the curves as PNG in the run directory."""
    out = tmp_path / "run"
    argv = ["--preset", "single_v1", "--out", str(out), "--timesteps", "256", "--scenario", "static_same_goal",
            "--num-worlds", "8", "--unroll-length", "16", "--num-minibatches", "2", "--num-epochs", "1",
            "--policy-hidden", "8,8", "--value-hidden", "8", "--env", "episode_seconds=0.1"]
    assert _train_script().main(argv) == 0
    text = capsys.readouterr().out
    bar = [ln for ln in text.splitlines() if "agent-steps |" in ln]
    assert bar and "[####################] 100%" in bar[-1] and "256 agent-steps" in bar[-1]
    assert "static_same_goal: succ" in bar[-1] and "elapsed" in bar[-1]
    assert (out / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_single_preset_is_the_one_minute_recipe():
    """The default preset trains one quad on the JAX engine with a fixed agent-step budget (the schedule
    follows it: reproducible from the seed); the recipe of pretrained:single stays as single_v1."""
    from quadswarm_mj.cli.train import PRESETS, build_parser

    pr = PRESETS["single"]
    assert build_parser().parse_args([]).preset == "single"
    assert pr["engine"] == "jax" and pr["num_quads"] == 1 and pr["scenarios"] == ["static_same_goal"]
    assert pr["timesteps"] > 0 and PRESETS["single_v1"]["scenarios"] == ["static_same_goal", "dynamic_same_goal"]
    assert "engine" not in PRESETS["single_v1"]


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))


def test_learning_rate_is_injected_and_plain_adam_train_states_still_load(tmp_path):
    """The schedule's learning rate is the optimizer's injected hyper-parameter (set by each update, kept in
    the train state); a train state of the earlier plain-Adam layout (Adam at ``opt_state[1][0]``, no injected
    leaves) resumes with its Adam moments."""
    import jax
    import jax.numpy as jnp

    from quadswarm_mj.training.checkpoints import load_train_state, save_train_state
    from quadswarm_mj.training.learner import learning_rate_of

    ppo = PPOConfig(**{**TINY, "learning_rate": 1e-3})
    tr = PPOTrainer([EnvConfig(num_quads=1, scenario="static_same_goal")], ppo, seed=1)
    assert float(learning_rate_of(tr.state.opt_state)) == pytest.approx(1e-3)
    data, _, _ = tr.collect(tr.batch.reset())
    state, m = tr._update(tr.state, data, jax.random.PRNGKey(0), jnp.float32(0.25))
    assert float(learning_rate_of(state.opt_state)) == pytest.approx(2.5e-4) == float(m["learning_rate"])
    path = tmp_path / "train_state.npz"
    save_train_state(path, state, jax.random.PRNGKey(5), {"iteration": 1})
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    legacy = {k.replace(".inner_state", ""): v for k, v in arrays.items()
              if not k.startswith(("state.opt_state[1].hyperparams", "state.opt_state[1].count"))}
    assert any(k.startswith("state.opt_state[1][0].mu") for k in legacy)
    np.savez(tmp_path / "legacy.npz", **legacy)
    back, _, sc, _ = load_train_state(tmp_path / "legacy.npz", tr.state)
    assert sc == {"iteration": 1}
    for a, b in zip(jax.tree.leaves(back.opt_state[1].inner_state), jax.tree.leaves(state.opt_state[1].inner_state)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for a, b in zip(jax.tree.leaves(back.params), jax.tree.leaves(state.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_lr_decay_timesteps_sets_the_schedule_horizon_apart_from_the_budget(tmp_path):
    """--lr-decay-timesteps N: the linear schedule decays over N agent-steps from the run's first step, whatever
    the budget, and a resumed run continues it (the schedule of a wall-clock run kept at a checkpoint)."""
    from quadswarm_mj.training.ppo_config import run_lr_scale

    with pytest.raises(ValueError, match="lr_decay_steps must be None or an int >= 1"):
        PPOConfig(lr_decay_steps=0)
    p = PPOConfig(lr_decay_steps=100)
    assert run_lr_scale(p, 50, budget_frac=0.9, start=1.0) == pytest.approx(0.55)  # the budget plays no part
    assert run_lr_scale(p, 500, budget_frac=0.1, start=1.0) == pytest.approx(0.1)
    assert run_lr_scale(PPOConfig(), 50, budget_frac=0.5, start=1.0) == pytest.approx(0.55)

    out = tmp_path / "run"
    lr = 1e-3
    base = _tiny_argv(out, "--scenario", "static_same_goal", "--policy-hidden", "8", "--env", "episode_seconds=0.1",
                      "--lr", str(lr), "--lr-decay-timesteps", "64")
    mod = _train_script()
    assert mod.main(base + ["--timesteps", "16"]) == 0
    assert mod.main(["--resume", str(out), "--timesteps", "16", "--no-progress"]) == 0
    rows = json.loads((out / "progress.json").read_text())
    assert [r["env_steps"] for r in rows] == [8, 16, 24, 32]
    # each update's rate is the schedule's at the agent-steps before it: 0, 8, 16, 24 of 64
    np.testing.assert_allclose([r["learning_rate"] for r in rows], [lr * (1 - 0.9 * e / 64) for e in (0, 8, 16, 24)],
                               rtol=1e-5)
