"""The JAX-engine trainer over several processes (``jax.distributed``, CPU collectives through gloo), on one
machine: 2 processes with 1 CPU device each, started by ``quadswarm_mj.training.distributed.launch_local``
with the console command's options.

Default suite (cheap): after every update both processes hold the same parameters, and they are the
parameters of a 1-process run on 2 devices with the same options (the streams are per device, so where the
devices live does not change the run); only process 0 writes files. Slow: a 2-process run learns as a
1-process run on 1 device with the same total worlds (curves within the spread of two seeds), and a
2-process run resumes from its checkpoint.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("brax")

from quadswarm_mj.training.distributed import launch_local, wait_all  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
WORKER = [sys.executable, str(ROOT / "tests" / "_dist_worker.py")]
TINY = ["--engine", "jax", "--scenario", "static_same_goal", "--num-quads", "1", "--num-worlds", "4",
        "--unroll-length", "4", "--num-minibatches", "2", "--num-epochs", "1", "--policy-hidden", "8,8",
        "--value-hidden", "8", "--env", "episode_seconds=0.1", "--no-progress"]
TIMEOUT = 600


def _env(record: Path) -> dict[str, str]:
    return {"QS_DIST_RECORD": str(record), "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
            "QUADSWARM_MJ_TUNE_JAX": "0"}


def _single(argv: list[str], record: Path, cpu_devices: int, log: Path) -> subprocess.Popen:
    return subprocess.Popen([*WORKER, *argv, "--cpu-devices", str(cpu_devices)], env={**os.environ, **_env(record)},
                            cwd=ROOT, stdout=log.open("w"), stderr=subprocess.STDOUT)


def _multi(argv: list[str], record: Path, log: Path, n: int = 2) -> list[subprocess.Popen]:
    return launch_local(n, argv, cpu_devices=1, env=_env(record), command=WORKER, cwd=ROOT,
                        stdout=log.open("w"), stderr=subprocess.STDOUT)


def _wait(procs: list[subprocess.Popen], logs: list[Path]) -> None:
    try:
        codes = wait_all(procs, timeout=TIMEOUT)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    text = "\n".join(f"--- {log}\n{log.read_text()[-3000:]}" for log in logs)
    assert codes == [0] * len(procs), text


def _record(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        return {"params": z["params"], "learning_rate": z["learning_rate"], "writes": json.loads(str(z["writes"])),
                "devices": tuple(z["devices"])}


@pytest.fixture(scope="module")
def two_and_one(tmp_path_factory):
    """2 iterations of the same options: 2 processes x 1 device, and 1 process x 2 devices (concurrently)."""
    tmp = tmp_path_factory.mktemp("dist")
    argv = [*TINY, "--timesteps", "32", "--seed", "3"]
    multi = _multi([*argv, "--out", str(tmp / "two")], tmp / "rec_two", tmp / "two.log")
    one = _single([*argv, "--out", str(tmp / "one")], tmp / "rec_one", 2, tmp / "one.log")
    _wait([*multi, one], [tmp / "two.log", tmp / "one.log"])
    return tmp


def test_two_processes_hold_the_same_parameters_after_every_update(two_and_one):
    r0, r1 = _record(two_and_one / "rec_two_0.npz"), _record(two_and_one / "rec_two_1.npz")
    assert r0["devices"] == r1["devices"] == (2, 2)
    assert r0["params"].shape[0] == 2  # one record per update
    np.testing.assert_array_equal(r0["params"], r1["params"])
    assert not np.array_equal(r0["params"][0], r0["params"][1])  # the second update moved them
    np.testing.assert_array_equal(r0["learning_rate"], r1["learning_rate"])  # process 0's schedule


def test_two_processes_run_as_one_process_on_two_devices(two_and_one):
    """The worlds, their streams and the update are per device: the 2-process run is the 1-process run on
    2 devices (same options and seed), to float32 rounding of the collectives."""
    r0, one = _record(two_and_one / "rec_two_0.npz"), _record(two_and_one / "rec_one_0.npz")
    assert one["devices"] == (1, 2)
    np.testing.assert_allclose(r0["params"], one["params"], rtol=1e-5, atol=1e-6)
    rows2 = json.loads((two_and_one / "two" / "progress.json").read_text())
    rows1 = json.loads((two_and_one / "one" / "progress.json").read_text())
    assert [r["env_steps"] for r in rows2] == [r["env_steps"] for r in rows1] == [16, 32]
    np.testing.assert_allclose([r["reward_per_step"] for r in rows2], [r["reward_per_step"] for r in rows1],
                               rtol=1e-5)
    run = json.loads((two_and_one / "two" / "run.json").read_text())
    assert run["processes"] == 2 and run["agents"] == 4


def test_only_process_zero_writes(two_and_one):
    w0, w1 = _record(two_and_one / "rec_two_0.npz")["writes"], _record(two_and_one / "rec_two_1.npz")["writes"]
    assert w0["save_policy_file"] >= 1 and w0["save_train_state"] >= 1 and w0["write_logs"] >= 1
    assert all(v == 0 for v in w1.values()), w1
    assert (two_and_one / "two" / "final.npz").is_file()
    assert (two_and_one / "two" / "checkpoints" / "train_state.npz").is_file()


def test_cli_options_are_checked(tmp_path):
    from quadswarm_mj.cli import train

    with pytest.raises(SystemExit, match="--num-processes needs --engine jax"):
        train.main(["--engine", "mujoco", "--num-processes", "2", "--timesteps", "1", "--out", str(tmp_path)])


@pytest.mark.slow
def test_two_processes_learn_as_one_and_resume(tmp_path):
    """A short single-quad run: the reward curve of 2 processes x 32 worlds is as close to the 1-process
    x 64 worlds curve of the same seed as two seeds of the 1-process run are to each other (mean absolute
    difference over 5-iteration windows); the 2-process run then resumes from its checkpoint with the same
    parameters on both processes."""
    argv = ["--engine", "jax", "--preset", "single", "--num-worlds", "64", "--unroll-length", "16",
            "--num-minibatches", "4", "--env", "episode_seconds=2", "--timesteps", str(64 * 16 * 40),
            "--no-progress", "--checkpoint-minutes", "100"]
    multi = _multi([*argv, "--out", str(tmp_path / "two")], tmp_path / "rec_two", tmp_path / "two.log")
    _wait(multi, [tmp_path / "two.log"])
    ones = [_single([*argv, "--seed", str(s), "--out", str(tmp_path / f"one{s}")], tmp_path / f"rec_one{s}", 1,
                    tmp_path / f"one{s}.log") for s in (0, 1)]
    _wait(ones, [tmp_path / "one0.log", tmp_path / "one1.log"])

    def curve(d: str) -> np.ndarray:
        r = np.array([r["reward_per_step"] for r in json.loads((tmp_path / d / "progress.json").read_text())])
        return r.reshape(-1, 5).mean(1)

    two, one0, one1 = curve("two"), curve("one0"), curve("one1")
    assert len(two) == len(one0) == 8 and np.all(np.isfinite(two))
    d_two, d_seeds = float(np.abs(two - one0).mean()), float(np.abs(one1 - one0).mean())
    assert d_two <= 2 * d_seeds + 1e-3, (d_two, d_seeds, two, one0, one1)

    _wait(_multi(["--resume", str(tmp_path / "two"), "--timesteps", str(64 * 16 * 2), "--no-progress"],
                 tmp_path / "rec_res", tmp_path / "res.log"), [tmp_path / "res.log"])
    rows = json.loads((tmp_path / "two" / "progress.json").read_text())
    assert [r["iteration"] for r in rows][-3:] == [40, 41, 42]
    r0, r1 = _record(tmp_path / "rec_res_0.npz"), _record(tmp_path / "rec_res_1.npz")
    np.testing.assert_array_equal(r0["params"], r1["params"])
    with np.load(tmp_path / "two" / "checkpoints" / "train_state.npz", allow_pickle=False) as z:
        assert json.loads(str(z["scalars"]))["iteration"] == 42
