"""The benchmark's alternating peer measurement (fresh processes stubbed) and its option checks."""

from __future__ import annotations

from pathlib import Path

import pytest

from quadswarm_mj.bench import peers
from quadswarm_mj.cli import benchmark


def test_alternating_ratio_takes_median_and_better_peer_setup(monkeypatch: pytest.MonkeyPatch) -> None:
    # per round: the JAX engine's figure, then crazyflow tuned and crazyflow with JAX's defaults
    answers = iter([100.0, 200.0, 250.0,   # round 1: ratio 100 / 250
                    300.0, 400.0, 100.0,   # round 2: ratio 300 / 400
                    90.0, None, 100.0])    # round 3: one peer set-up failed, the other counts: 90 / 100
    calls: list[dict[str, str]] = []

    def fake(code: str, env: dict[str, str]) -> float | None:
        calls.append(env)
        return next(answers)

    monkeypatch.setattr(peers, "_fresh_process", fake)
    res = benchmark.alternating_peer_ratio(512, 2, rounds=3, steps=10, repeat=1)
    assert res is not None
    assert res["ratios"] == pytest.approx([0.4, 0.75, 0.9])
    assert res["median"] == pytest.approx(0.75)
    assert (res["min"], res["max"]) == (pytest.approx(0.4), pytest.approx(0.9))
    assert res["peer"] == [250.0, 400.0, 100.0]
    # the second peer process of each round runs with JAX's defaults
    assert [c.get("QUADSWARM_MJ_TUNE_JAX") for c in calls[:3]] == [None, None, "0"]


def test_alternating_ratio_none_when_a_side_is_missing(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(peers, "_fresh_process", lambda code, env: None)
    assert benchmark.alternating_peer_ratio(512, 1, rounds=2, steps=10, repeat=1) is None


def test_negative_alternate_is_rejected(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        benchmark.main(["--alternate", "-1", "--no-write"])
    assert "--alternate must be >= 0" in capsys.readouterr().err


def test_alternating_floor_ratio_warms_up_past_an_episode_and_closes(monkeypatch: pytest.MonkeyPatch) -> None:
    """The vector-env-vs-floor rounds: warm-up past the first episode end, one floor per round, the
    median of the per-round ratios, and the env closed afterwards (env and floor stubbed)."""
    import statistics
    from types import SimpleNamespace

    calls = {"steps": 0, "closed": False, "floors": 0}

    class FakeEnv:
        def __init__(self, cfg, num_envs, engine):
            assert engine == "jax" and num_envs == 4
            self.action_space = SimpleNamespace(shape=(num_envs, cfg.num_quads, 4))

        def reset(self, seed):
            calls["steps"] = 0

        def step(self, actions):
            calls["steps"] += 1

        def close(self):
            calls["closed"] = True

    def fake_floor(bodies, seconds, repeat):
        assert bodies == 32
        calls["floors"] += 1
        return 1e6 * calls["floors"]

    monkeypatch.setattr(peers, "QuadSwarmVectorEnv", FakeEnv)
    monkeypatch.setattr(peers, "ceiling_rollout", fake_floor)
    res = benchmark.alternating_floor_ratio(4, rounds=3, seconds=0.01)
    assert calls["closed"] and calls["floors"] == 3
    assert calls["steps"] > benchmark.EnvConfig().episode_steps  # the warm-up alone passes an episode end
    assert res["floor"] == [1e6, 2e6, 3e6]
    assert res["ratios"] == [e / f for e, f in zip(res["env"], res["floor"])]
    assert res["median"] == statistics.median(res["ratios"])
    assert res["min"] <= res["median"] <= res["max"]


def test_gym_rates_ratio_to_the_first_row_and_a_failed_row_reported() -> None:
    from quadswarm_mj.bench.gym_rows import gym_rates
    from quadswarm_mj.bench.report import gym_table

    rows = (("ref", {"num_quads": 1, "engine": "mujoco"}), ("eight", {"num_quads": 8, "engine": "mujoco"}),
            ("bad", {"num_quads": 0}))
    out = gym_rates(0.05, 1, rows)
    assert [r["label"] for r in out] == ["ref", "eight", "bad"]
    assert out[0]["rate"] > 0 and out[0]["ratio"] == 1.0
    assert out[1]["ratio"] == out[1]["rate"] / out[0]["rate"]
    assert out[0]["cpu_ratio"] == 1.0 and out[1]["cpu_ratio"] == out[1]["cpu_rate"] / out[0]["cpu_rate"]
    assert out[2]["rate"] is None and out[2]["ratio"] is None and "num_quads" in out[2]["error"]
    table = gym_table(out, [("fresh", {"import_s": 0.5, "first_step_s": 1.25}), ("failed", None)])
    assert "| ref | " in table and "1.00x" in table and "| fresh | 0.50 | 1.25 |" in table and "(failed)" in table


def test_first_step_code_runs_in_a_fresh_process() -> None:
    from quadswarm_mj.bench.gym_rows import first_step_code
    from quadswarm_mj.bench.peers import _fresh_process

    res = _fresh_process(first_step_code({"num_quads": 1, "engine": "mujoco"}), {})
    assert res is not None and res["import_s"] > 0 and res["first_step_s"] > 0


@pytest.mark.slow
def test_worker_probe_runs_and_leaves_the_callers_jax_untouched(monkeypatch: pytest.MonkeyPatch) -> None:
    """scripts/worker_probe.py: the JAX engine stepped in a spawned worker that tunes itself; the caller gets
    steps and figures, and its own process has no XLA_FLAGS entry or JAX config change from it."""
    import os
    import sys

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "scripts"))  # spawned worker too
    from worker_probe import probe

    flags = os.environ.get("XLA_FLAGS")
    out = probe(num_quads=1, steps=30, rounds=1)
    assert out["rate"] > 0 and out["hopper_rate"] > 0 and out["first_step_s"] > 0
    assert out["worker_step_us"] > 0 and out["pipe_round_trip_us"] > 0
    assert os.environ.get("XLA_FLAGS") == flags
    assert "jax" not in sys.modules or sys.modules["jax"].config.jax_cpu_enable_async_dispatch
