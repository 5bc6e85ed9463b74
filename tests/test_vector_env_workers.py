"""QuadSwarmVectorEnv's worker processes: failures surface with the worker's own error, the env
refuses work until reset, reset rebuilds the workers, and workers live exactly as long as the env's
process (not the thread that created the env)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, QuadSwarmVectorEnv
from quadswarm_mj.envs.vector_env import WorkerError

CFG = EnvConfig(num_quads=2, episode_seconds=0.1)
HOVER = CFG.quad.hover_action
REPO = Path(__file__).resolve().parent.parent


def actions(t: int) -> np.ndarray:
    return HOVER + 0.2 * np.random.default_rng(t).standard_normal((4, 2, 4))


def rollout(env: QuadSwarmVectorEnv, steps: int = 12) -> list[np.ndarray]:
    """Observations and rewards of ``steps`` steps (crossing one auto-reset) after ``reset(seed=3)``."""
    obs, _ = env.reset(seed=3)
    out = [obs]
    for t in range(steps):
        obs, rew, _, trunc, _ = env.step(actions(t))
        out += [obs, rew, trunc]
    return out


@pytest.fixture(scope="module")
def reference() -> list[np.ndarray]:
    env = QuadSwarmVectorEnv(CFG, num_envs=4, num_shards=2)
    try:
        return rollout(env)
    finally:
        env.close()


def assert_same(a: list[np.ndarray], b: list[np.ndarray]) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def assert_needs_reset(env: QuadSwarmVectorEnv) -> None:
    for call in (lambda: env.step(actions(0)), env.episode_metrics):
        with pytest.raises(RuntimeError, match=r"failed .* must be reset: call reset\(\)"):
            call()
    with pytest.raises(ValueError, match="first after a failure"):  # a partial reset cannot repair it
        env.reset(options={"reset_mask": np.array([True, False, True, False])})


def _break_step(shard, message: str) -> None:
    """Test hook run in every shard's process: worker shards raise ``message`` in their next step."""
    if shard.lo == 0:
        return

    def exploding_step(actions):
        raise ValueError(message)

    shard.core.step = exploding_step


def _raise_here(shard, message: str) -> None:
    if shard.lo > 0:
        raise KeyError(message)


def test_killed_worker_gives_clear_error_and_reset_rebuilds(reference):
    env = QuadSwarmVectorEnv(CFG, num_envs=4, num_shards=2)
    try:
        block = env._res.shm.name
        assert not os.path.exists(f"/dev/shm/{block}")  # unlinked once the workers mapped it
        env.reset(seed=3)
        env.step(actions(0))
        (worker,) = env._res.workers
        old_pid = worker.proc.pid
        os.kill(old_pid, signal.SIGKILL)
        worker.proc.join(5)
        with pytest.raises(WorkerError, match=rf"worker 1 \(worlds \[2, 4\), pid {old_pid}\) was killed by signal "
                                              r"SIGKILL during step") as e:
            env.step(actions(1))
        assert e.value.worker == 1 and isinstance(e.value, RuntimeError)
        assert_needs_reset(env)
        assert_same(rollout(env), reference)  # reset rebuilt the workers: same results as a fresh env
        (new,) = env._res.workers
        assert new.proc.pid != old_pid and new.proc.is_alive()
    finally:
        env.close()


def test_worker_exception_carries_its_traceback_and_reset_recovers(reference):
    env = QuadSwarmVectorEnv(CFG, num_envs=4, num_shards=2)
    try:
        env.reset(seed=3)
        env._call_shards(_break_step, "injected failure 4711")
        with pytest.raises(WorkerError) as e:
            env.step(actions(0))
        msg = str(e.value)
        assert msg.startswith("vector env worker 1 (worlds [2, 4), pid ")
        assert "raised ValueError during step: injected failure 4711" in msg
        assert "Worker traceback:" in msg and "in exploding_step" in msg  # the worker's own frames
        assert "in exploding_step" in e.value.traceback and "ValueError: injected failure 4711" in e.value.traceback
        assert_needs_reset(env)
        assert_same(rollout(env), reference)
        # a failing command (not a step) does the same
        with pytest.raises(WorkerError, match=r"worker 1 .* raised KeyError during call: 'no such key'"):
            env._call_shards(_raise_here, "no such key")
        assert_needs_reset(env)
        assert_same(rollout(env), reference)
    finally:
        env.close()


@pytest.mark.parametrize("shards", [1, 2])
def test_exception_in_calling_process_mid_step_needs_reset(reference, shards, monkeypatch):
    env = QuadSwarmVectorEnv(CFG, num_envs=4, num_shards=shards)
    try:
        env.reset(seed=3)

        def interrupted(actions):
            raise KeyboardInterrupt

        monkeypatch.setattr(env._shard.core, "step", interrupted)
        with pytest.raises(KeyboardInterrupt):
            env.step(actions(0))
        assert_needs_reset(env)
        out = rollout(env)  # shard 0 is rebuilt too (the patched engine is gone)
        if shards == 2:
            assert_same(out, reference)
        else:
            fresh = QuadSwarmVectorEnv(CFG, num_envs=4, num_shards=1)
            try:
                assert_same(out, rollout(fresh))
            finally:
                fresh.close()
    finally:
        env.close()


def test_workers_follow_the_process_not_the_creating_thread():
    box = {}
    t = threading.Thread(target=lambda: box.setdefault("env", QuadSwarmVectorEnv(CFG, num_envs=4, num_shards=2)))
    t.start()
    t.join()
    env = box["env"]
    try:
        time.sleep(0.5)  # a worker tied to the thread (PR_SET_PDEATHSIG) would be gone by now
        assert all(w.proc.is_alive() for w in env._res.workers)
        env.reset(seed=0)
        env.step(actions(0))
    finally:
        env.close()


def script_env() -> dict[str, str]:
    """The environment of a child Python that imports this checkout's package."""
    return dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))


def gone(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")  # exited, not yet reaped
    except FileNotFoundError:
        return True


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")
def test_workers_exit_when_the_parent_process_dies(tmp_path):
    """The parent is SIGKILLed while a forked child keeps the pipes open: the workers' parent
    watchdog still ends them."""
    code = textwrap.dedent("""
        import os, signal, sys, time
        from quadswarm_mj import EnvConfig, QuadSwarmVectorEnv
        env = QuadSwarmVectorEnv(EnvConfig(num_quads=2), num_envs=3, num_shards=3)
        env.reset(seed=0)
        holder = os.fork()
        if holder == 0:  # holds copies of the parent's pipe ends (not the test's stdout)
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, 1)
            os.dup2(null, 2)
            time.sleep(60)
            os._exit(0)
        print(holder, *[w.proc.pid for w in env._res.workers], flush=True)
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    err = tmp_path / "stderr.txt"
    with open(err, "w") as f:  # read one line, not to EOF: the holder and its heirs keep stdout open
        proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=f, text=True,
                                env=script_env(), cwd=REPO)
        line = proc.stdout.readline()
        assert proc.wait(timeout=120) == -signal.SIGKILL, err.read_text()
    proc.stdout.close()
    holder, *workers = map(int, line.split())
    try:
        assert len(workers) == 2
        deadline = time.monotonic() + 20
        while not all(gone(p) for p in workers) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert all(gone(p) for p in workers)
    finally:
        os.kill(holder, signal.SIGKILL)


def test_script_without_main_guard_works(tmp_path):
    """Workers never import the user's script, so top-level env creation in a script works."""
    script = tmp_path / "unguarded.py"
    script.write_text("import numpy as np\n"
                      "from quadswarm_mj import EnvConfig, QuadSwarmVectorEnv\n"
                      "print('script body ran')\n"
                      "env = QuadSwarmVectorEnv(EnvConfig(num_quads=1), num_envs=2, num_shards=2)\n"
                      "obs, _ = env.reset(seed=0)\n"
                      "obs, *_ = env.step(np.zeros((2, 1, 4)))\n"
                      "print('stepped', obs.shape)\n"
                      "env.close()\n")
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, env=script_env())
    assert out.returncode == 0, out.stderr
    assert out.stdout.count("script body ran") == 1  # not re-run in the worker
    assert "stepped (2, 1, " in out.stdout


def test_send_order_puts_the_worker_on_this_cpu_last(monkeypatch):
    """A message wakes its worker on that worker's core; the one sharing the caller's core goes last,
    so it cannot preempt the caller before the other messages are out."""
    from types import SimpleNamespace

    from quadswarm_mj.envs import workers

    cpu = workers.current_cpu()  # this thread's CPU now (Linux), else None
    assert cpu is None or cpu in os.sched_getaffinity(0)
    ws = [SimpleNamespace(index=k, cpu=k) for k in range(3)]
    monkeypatch.setattr(workers, "current_cpu", lambda: 0)
    assert [w.index for w in workers.send_order(ws)] == [1, 2, 0]
    monkeypatch.setattr(workers, "current_cpu", lambda: 2)
    assert [w.index for w in workers.send_order(ws)] == [0, 1, 2]
    monkeypatch.setattr(workers, "current_cpu", lambda: None)  # unknown CPU, or unpinned workers: as given
    assert workers.send_order(ws) == ws
    monkeypatch.setattr(workers, "current_cpu", lambda: 1)
    unpinned = [SimpleNamespace(index=k, cpu=None) for k in range(2)]
    assert workers.send_order(unpinned) == unpinned
