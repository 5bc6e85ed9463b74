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
    argv = ["--out", str(out), "--timesteps", "96", "--scenario", "static_same_goal,dynamic_same_goal",
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


def test_ppo_config_validation():
    with pytest.raises(ValueError, match="num_worlds"):
        PPOConfig(num_worlds=0)
    with pytest.raises(ValueError, match="activation"):
        PPOConfig(activation="sigmoid")
    with pytest.raises(ValueError, match="divisible"):
        PPOTrainer([EnvConfig(num_quads=1)], PPOConfig(num_worlds=3, num_minibatches=2, unroll_length=2))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))


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
