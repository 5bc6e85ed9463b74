"""scripts/train_chain.py: a shipped policy's PPO chain as stages with agent-step budgets, resumable."""

from __future__ import annotations

import json

from script_module import load_script


def _module():
    return load_script("train_chain")


def _parse(cmd):
    from quadswarm_mj.cli.train import build_parser

    return build_parser().parse_args(cmd)


def test_fresh_chain_runs_every_stage_from_the_one_before(tmp_path):
    mod = _module()
    todo = mod.stage_commands("swarm8_rl", tmp_path, "1", 8.0)
    assert [n for n, _ in todo] == [s[0] for s in mod.CHAINS["swarm8_rl"]]
    budgets = [s[1] for s in mod.CHAINS["swarm8_rl"]]
    for i, (name, cmd) in enumerate(todo):
        a = _parse(cmd)  # every command is one the train CLI accepts
        assert a.preset == "swarm8_rl" and a.timesteps == budgets[i] and a.out == str(tmp_path / name)
        assert a.init_from == (None if i == 0 else str(tmp_path / todo[i - 1][0] / "final.npz"))
    assert sum(budgets) == 424_345_600  # the shipped chain's agent-steps (the manifest's train.budget)


def test_each_stage_decays_its_learning_rate_as_the_shipped_wall_clock_stage_did(tmp_path):
    """The shipped stages ran on --minutes and kept a checkpoint before the end: the horizon is the stage's
    agent-steps over the fraction of its minutes it had run (the manifest's train.stages)."""
    import re

    from quadswarm_mj.policies import read_manifest

    mod = _module()
    stages = read_manifest()["policies"]["swarm8_rl"]["train"]["stages"]
    todo = mod.stage_commands("swarm8_rl", tmp_path, "1", 8.0)
    assert len(stages) == len(todo)
    for shipped, (_, cmd) in zip(stages, todo):
        minutes = float(re.search(r"--minutes (\S+)", shipped["command"]).group(1))
        horizon = shipped["checkpoint_env_steps"] / (shipped["wall_s"] / (60.0 * minutes))
        a = _parse(cmd)
        assert a.timesteps == shipped["checkpoint_env_steps"]
        assert abs(a.lr_decay_steps - horizon) / horizon < 1e-3, (cmd, horizon)


def test_finished_stages_are_skipped_and_a_stopped_stage_resumes_with_the_rest_of_its_budget(tmp_path):
    mod = _module()
    (tmp_path / "s1").mkdir()
    (tmp_path / "s1" / "final.npz").write_bytes(b"")
    ck = tmp_path / "s3" / "checkpoints"
    ck.mkdir(parents=True)
    for steps in (32768, 65536):
        (ck / f"step_{steps:012d}.npz").write_bytes(b"")
    (ck / "train_state.npz").write_bytes(b"")
    todo = mod.stage_commands("swarm8_rl", tmp_path, "2", 4.0)
    assert todo[0][0] == "s3"
    a = _parse(todo[0][1])
    assert a.resume == str(tmp_path / "s3") and a.timesteps == 49_741_824 - 65536 and a.cpu_devices == "2"
    assert _parse(todo[1][1]).init_from == str(tmp_path / "s3" / "final.npz")


def test_dry_run_prints_the_commands_and_writes_nothing(tmp_path, capsys):
    mod = _module()
    out = tmp_path / "chain"
    assert mod.main(["swarm8_rl", "--out", str(out), "--dry-run"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 6 and all(ln.startswith("quadswarm-train --preset swarm8_rl") for ln in lines)
    assert not out.exists()


def test_a_failed_stage_stops_the_chain_and_is_recorded(tmp_path, monkeypatch):
    mod = _module()
    monkeypatch.setattr(mod.subprocess, "call", lambda *a, **k: 3)
    assert mod.main(["swarm8_rl", "--out", str(tmp_path)]) == 3
    rec = json.loads((tmp_path / "chain.json").read_text())
    assert [s["stage"] for s in rec["stages"]] == ["s1"] and rec["stages"][0]["rc"] == 3
