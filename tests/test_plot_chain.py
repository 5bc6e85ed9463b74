"""scripts/plot_chain.py: a chain of training stages joined into one set of curves."""

from __future__ import annotations

import json

import pytest
from script_module import load_script


def _module():
    return load_script("plot_chain")


def _run(tmp_path, name, steps, wall):
    run = tmp_path / name
    run.mkdir()
    rows = [{"env_steps": s, "wall_s": w, "reward_per_step": -0.01, "mix/episodes": 1, "mix/success": 0.5}
            for s, w in zip(steps, wall)]
    (run / "progress.json").write_text(json.dumps(rows))
    return run


def test_stages_are_cut_at_their_checkpoint_and_added_up(tmp_path):
    mod = _module()
    a = _run(tmp_path, "a", [10, 20, 30], [1.0, 2.0, 3.0])
    b = _run(tmp_path, "b", [5, 10], [0.5, 1.0])
    rows, marks = mod.chain_rows([(a, 20), (b, 10)])
    assert [r["env_steps"] for r in rows] == [10, 20, 25, 30]  # a's row at 30 is after the checkpoint
    assert [r["wall_s"] for r in rows] == [1.0, 2.0, 2.5, 3.0]
    assert marks == [(20.0, "stage 2: b")]


def test_a_checkpoint_without_its_row_is_refused(tmp_path):
    mod = _module()
    a = _run(tmp_path, "a", [10, 20], [1.0, 2.0])
    with pytest.raises(SystemExit, match="no row at 15 agent-steps"):
        mod.chain_rows([(a, 15)])
    with pytest.raises(SystemExit, match="is not RUN_DIR:AGENT_STEPS"):
        mod.main([str(a), "--out", str(tmp_path / "x.png")])


def test_main_writes_the_png(tmp_path):
    pytest.importorskip("matplotlib")
    mod = _module()
    a = _run(tmp_path, "a", [10, 20], [1.0, 2.0])
    b = _run(tmp_path, "b", [5, 10], [0.5, 1.0])
    out = tmp_path / "chain.png"
    assert mod.main([f"{a}:20", f"{b}:10", "--out", str(out)]) == 0
    assert out.stat().st_size > 1000
