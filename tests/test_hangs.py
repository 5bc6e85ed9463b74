"""No hangs (issue 32 item 5): two threads on one vector env, a stopped worker, ``os.fork()`` after
creating a vector env, fork-started subprocesses over the JAX engine, and the model build of large
swarms. Each scenario that could hang runs in a subprocess with a timeout, so a regression fails the
test instead of hanging the suite."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from quadswarm_mj import EnvConfig, QuadSwarmVectorEnv

ROOT = Path(__file__).resolve().parents[1]


def run_script(code: str, timeout: float) -> str:
    """Run ``code`` in a fresh interpreter (this checkout first on the path); returns its stdout.
    A run that does not finish within ``timeout`` s fails the test (a hang)."""
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    try:
        r = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                           timeout=timeout, env=env, cwd=ROOT)
    except subprocess.TimeoutExpired as e:
        pytest.fail(f"the scenario hung (no end within {timeout} s); output so far:\n{e.stdout}\n{e.stderr}")
    assert r.returncode == 0, f"exit code {r.returncode}\nstdout:\n{r.stdout}\nstderr:\n{r.stderr}"
    return r.stdout


# ------------------------------------------------------------------ (a) two threads, one env
def test_call_from_a_second_thread_during_a_call_raises():
    env = QuadSwarmVectorEnv(EnvConfig(num_quads=1), num_envs=2, num_shards=1)
    try:
        env.reset(seed=0)
        inside = threading.Event()

        def slow(shard):
            inside.set()
            time.sleep(1.0)

        t = threading.Thread(target=env._call_shards, args=(slow,))
        t.start()
        assert inside.wait(30)
        with pytest.raises(RuntimeError, match="another thread"):
            env.step(np.zeros((2, 1, 4)))
        t.join()
        env.step(np.zeros((2, 1, 4)))  # the refused call changed nothing: the env still works
    finally:
        env.close()


def test_two_threads_stepping_one_vector_env_never_hang():
    out = run_script("""
        import threading
        import numpy as np
        from quadswarm_mj import EnvConfig, QuadSwarmVectorEnv

        env = QuadSwarmVectorEnv(EnvConfig(num_quads=1), num_envs=2, num_shards=2)
        env.reset(seed=0)
        refused, other = [], []

        def run():
            for _ in range(300):
                try:
                    env.step(np.zeros((2, 1, 4)))
                except RuntimeError as e:
                    (refused if "another thread" in str(e) else other).append(str(e))

        threads = [threading.Thread(target=run) for _ in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert not other, other[:1]
        env.step(np.zeros((2, 1, 4)))  # still in step: no call was interleaved
        env.close()
        print("OK", len(refused))
    """, timeout=240)
    assert "OK" in out


# ------------------------------------------------------------------ (b) a stopped worker
def test_worker_timeout_is_validated():
    for bad in (0, -1.0, float("inf"), float("nan"), "5", True):
        with pytest.raises(ValueError, match="worker_timeout"):
            QuadSwarmVectorEnv(EnvConfig(num_quads=1), num_envs=2, num_shards=1, worker_timeout=bad)


def test_stopped_worker_raises_worker_error_naming_it():
    out = run_script("""
        import os, signal
        import numpy as np
        from quadswarm_mj import EnvConfig, QuadSwarmVectorEnv
        from quadswarm_mj.envs.vector_env import WorkerError

        env = QuadSwarmVectorEnv(EnvConfig(num_quads=1), num_envs=2, num_shards=2, worker_timeout=2.0)
        env.reset(seed=0)
        pid = env._res.workers[0].proc.pid
        os.kill(pid, signal.SIGSTOP)
        try:
            env.step(np.zeros((2, 1, 4)))
        except WorkerError as e:
            assert e.worker == 1 and "worker 1" in str(e) and "worker_timeout" in str(e), str(e)
            assert "stopped" in str(e), str(e)
            print("RAISED", str(e).splitlines()[0])
        else:
            raise SystemExit("no WorkerError")
        env.reset(seed=0)  # rebuilds the workers (the stopped one is ended)
        env.step(np.zeros((2, 1, 4)))
        env.close()
        print("OK")
    """, timeout=240)
    assert "RAISED" in out and "OK" in out


# ------------------------------------------------------------------ (c) os.fork() after creating an env
def test_fork_child_refuses_to_step_and_its_exit_spares_the_parents_workers():
    out = run_script("""
        import os, sys, time
        import numpy as np
        from quadswarm_mj import EnvConfig, QuadSwarmVectorEnv

        env = QuadSwarmVectorEnv(EnvConfig(num_quads=1), num_envs=2, num_shards=2)
        env.reset(seed=0)
        before = env.step(np.zeros((2, 1, 4)))[4]["state"]["pos"].copy()
        pid = os.fork()
        if pid == 0:  # the child: its copy must refuse, and its normal exit (atexit) must not end the workers
            try:
                env.step(np.zeros((2, 1, 4)))
                code = 3
            except RuntimeError as e:
                code = 0 if "fork" in str(e) else 4
            sys.stdout.flush()
            sys.exit(code)
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0, os.waitstatus_to_exitcode(status)
        time.sleep(0.5)
        assert all(w.proc.is_alive() for w in env._res.workers)
        obs, _, _, _, info = env.step(np.zeros((2, 1, 4)))  # the parent's workers still serve it
        env.close()
        print("OK")
    """, timeout=240)
    assert "OK" in out


def test_fork_child_of_a_workerless_env_is_an_independent_copy():
    out = run_script("""
        import os, sys
        import numpy as np
        from quadswarm_mj import EnvConfig, QuadSwarmVectorEnv

        env = QuadSwarmVectorEnv(EnvConfig(num_quads=1), num_envs=2, num_shards=1)
        env.reset(seed=0)
        pid = os.fork()
        if pid == 0:
            for _ in range(5):
                env.step(np.ones((2, 1, 4)))
            sys.exit(0)
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0
        env.step(np.zeros((2, 1, 4)))
        env.close()
        print("OK")
    """, timeout=240)
    assert "OK" in out


# ------------------------------------------------------------------ (d) fork-started subprocesses over JAX
def test_async_vector_env_fork_over_jax_works_when_the_parent_runs_no_jax():
    out = run_script("""
        import gymnasium as gym
        import numpy as np
        from quadswarm_mj import QuadSwarmEnv

        fns = [lambda: QuadSwarmEnv(num_quads=1, engine="jax")]  # one sub-env: one JAX compile
        venv = gym.vector.AsyncVectorEnv(fns)  # the default context: fork on Linux
        from jax._src import xla_bridge
        assert not xla_bridge.backends_are_initialized()  # building the env's spaces started no JAX here
        obs, _ = venv.reset(seed=0)
        obs, *_ = venv.step(np.zeros((1, 4), np.float32))
        assert np.isfinite(obs).all()
        venv.close()
        print("OK")
    """, timeout=600)
    assert "OK" in out


def test_fork_from_a_process_running_jax_raises_a_clear_error():
    out = run_script("""
        import multiprocessing as mp
        import gymnasium as gym
        import jax.numpy as jnp
        import numpy as np
        from quadswarm_mj import QuadSwarmEnv

        jnp.zeros(1).block_until_ready()  # JAX runs in the parent

        # gymnasium's AsyncVectorEnv, default (fork) context
        venv = gym.vector.AsyncVectorEnv([lambda: QuadSwarmEnv(num_quads=1, engine="jax")] * 2)
        try:
            venv.reset(seed=0)
        except Exception as e:
            assert "spawn" in str(e) and "forkserver" in str(e), str(e)
            print("ASYNC RAISED")
        venv.close(terminate=True)

        # SB3-style: the env built and stepped in a fork-started worker
        def worker(conn):
            try:
                env = QuadSwarmEnv(num_quads=1, engine="jax")
                env.reset(seed=0)
                conn.send("no error")
            except RuntimeError as e:
                conn.send(str(e))

        ctx = mp.get_context("fork")
        parent, child = ctx.Pipe()
        p = ctx.Process(target=worker, args=(child,))
        p.start()
        msg = parent.recv()
        p.join()
        assert "spawn" in msg, msg
        print("FORK RAISED")
    """, timeout=300)
    assert "ASYNC RAISED" in out and "FORK RAISED" in out


# ------------------------------------------------------------------ (e) large swarms
def test_num_quads_above_the_supported_maximum_is_refused():
    from quadswarm_mj.config import MAX_QUADS

    with pytest.raises(ValueError, match="MAX_QUADS"):
        EnvConfig(num_quads=10_000)
    with pytest.raises(ValueError, match="num_quads"):
        EnvConfig(num_quads=MAX_QUADS + 1)
    assert EnvConfig(num_quads=MAX_QUADS).num_quads == MAX_QUADS


def _one_by_one(spec, cf_body, offsets, n):
    """The old build: every quad attached straight into the model (O(T^2) in MuJoCo's MjSpec)."""
    for b in range(offsets.shape[0]):
        for i in range(n):
            frame = spec.worldbody.add_frame(pos=offsets[b] + np.array([0.0, 0.0, 1.0 + 0.2 * i]))
            name = f"q{i}" if offsets.shape[0] == 1 else f"w{b}q{i}"
            body = frame.attach_body(cf_body, f"{name}/", "")
            body.name = name


def _model_fields(model) -> dict:
    out = {}
    for name in dir(model):
        if name.startswith("_"):
            continue
        try:
            v = getattr(model, name)
        except Exception:  # noqa: BLE001
            continue
        if isinstance(v, (np.ndarray, int, float)):
            out[name] = v
    return out


@pytest.mark.parametrize("cfg,worlds,visual", [
    (EnvConfig(num_quads=8), 1, True),
    (EnvConfig(num_quads=5, collision_model="mujoco"), 3, False),
    (EnvConfig(num_quads=3, collision_model="blend"), 4, True),
    (EnvConfig(num_quads=1), 1, True),
])
def test_chunked_arena_build_gives_the_same_model(monkeypatch, cfg, worlds, visual):
    import quadswarm_mj.arena as arena

    new = arena.build_arena(cfg, worlds, visual)
    monkeypatch.setattr(arena, "_attach_quads", _one_by_one)
    old = arena.build_arena(cfg, worlds, visual)
    a, b = _model_fields(new.model), _model_fields(old.model)
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    np.testing.assert_array_equal(new.body_ids, old.body_ids)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_arena_of_the_supported_maximum_builds():
    from quadswarm_mj.arena import build_arena
    from quadswarm_mj.config import MAX_QUADS

    arena = build_arena(EnvConfig(num_quads=MAX_QUADS), 1)
    assert arena.body_ids.shape == (1, MAX_QUADS)
