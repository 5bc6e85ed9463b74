"""Worker processes for the vector envs: spawned interpreters that each run one shard of worlds,
commanded through a ``Pipe`` and sharing their arrays through one ``multiprocessing.shared_memory``
block (see :mod:`quadswarm_mj.envs.vector_env` for the protocol and the lifetime rules).

A worker builds its shard with ``init["factory"](init, arrays)`` (a module-level function, pickled by
reference): :func:`quadswarm_mj.envs.vector_env.mujoco_shard` for the MuJoCo engine,
:func:`quadswarm_mj.envs.jax_workers.jax_shard` for the JAX engine. A shard has ``step()`` (the
one-byte ``STEP`` message), ``handle(command_tuple)`` (the rare commands) and, if it writes into one
of several output blocks (:class:`OutputBlocks`, mapped in the worker by :func:`map_block_rows`),
``step_into(block_index)`` (the ``STEP_INTO`` message).

No hangs: every wait for a reply is bounded by the worker's ``timeout`` (the envs' ``worker_timeout``;
a worker that does not answer, e.g. stopped by SIGSTOP, raises :class:`WorkerError` naming it); the
envs' public calls are :func:`exclusive` (a second thread's call during one raises instead of
interleaving on the pipes); a forked child forgets the parent's workers (its exit never terminates
them) and only the creating process ends them (:meth:`Resources.release`); a process forked from one
running JAX refuses the JAX engine (:func:`check_not_forked_from_jax`) instead of deadlocking."""

from __future__ import annotations

import ctypes
import functools
import importlib
import multiprocessing
import os
import pickle
import select
import signal
import sys
import threading
import time
import traceback
import weakref
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from multiprocessing import shared_memory
from typing import Any, TypeVar

import numpy as np

STEP, DONE = b"s", b"k"  # the step message and its reply (a pickled message never equals them)
STEP_INTO = b"i"  # + a block index (little-endian): step, writing the outputs into that output block
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}  # defaults for workers (one core each)
PARENT_CHECK_S = 1.0  # how often a worker checks that its parent process still exists (s)
JOIN_TIMEOUT_S = 5.0  # how long close() waits for a worker to exit before terminating it (s)
#: default of the vector envs' ``worker_timeout``: how long the env waits for one reply of a worker before
#: raising WorkerError (s); generous, as a worker's first reply may include a JAX compile on a loaded machine
DEFAULT_WORKER_TIMEOUT_S = 600.0
_POLL_S = 1.0  # the slice of a reply wait between checks that the worker still runs (s)


def map_arrays(buf: Any, layout: list) -> dict[str, np.ndarray]:
    """NumPy views of ``buf`` for a layout of (name, shape, dtype), each 64-byte aligned."""
    arrays, off = {}, 0
    for name, shape, dtype in layout:
        n = int(np.prod(shape)) * np.dtype(dtype).itemsize
        arrays[name] = np.ndarray(shape, dtype=dtype, buffer=buf, offset=off)
        off += -(-n // 64) * 64  # 64-byte aligned
    return arrays


def layout_bytes(layout: list) -> int:
    """Bytes of a buffer holding ``layout`` (:func:`map_arrays`)."""
    return sum(-(-int(np.prod(s)) * np.dtype(d).itemsize // 64) * 64 for _, s, d in layout)


class WorkerError(RuntimeError):
    """A vector-env worker failed: raised an exception (``traceback`` holds its text) or died."""

    def __init__(self, message: str, worker: int, traceback_text: str | None = None):
        super().__init__(message)
        self.worker, self.traceback = worker, traceback_text


class SharedBlock(shared_memory.SharedMemory):
    """A ``SharedMemory`` block that NumPy views may outlive: ``close()`` cannot unmap while views
    exist (BufferError); the mapping then goes with the last view and only the descriptor is closed."""

    def close(self) -> None:
        try:
            super().close()
        except BufferError:
            fd = getattr(self, "_fd", -1)
            if fd >= 0:
                os.close(fd)
                self._fd = -1


# ------------------------------------------------------------------ fork and thread safety
_LIVE_RESOURCES: weakref.WeakSet = weakref.WeakSet()  # every Resources of this process with workers
#: True in a process forked (``os.fork``, multiprocessing's "fork") from one where JAX had started its
#: runtime: JAX is not fork-safe, so the JAX engine refuses to run here (instead of hanging)
FORKED_FROM_JAX = False


def _after_fork_in_child() -> None:
    """``os.register_at_fork`` hook (child side): note whether the parent had started JAX, and forget the
    parent's worker processes, so that this process's exit (multiprocessing's atexit handler terminates
    every daemonic child it knows of) never kills them."""
    global FORKED_FROM_JAX
    jax = sys.modules.get("jax")
    if jax is not None and not FORKED_FROM_JAX:
        try:
            from jax._src import xla_bridge

            FORKED_FROM_JAX = bool(xla_bridge.backends_are_initialized())
        except Exception:  # noqa: BLE001 - a JAX without this function: assume it started
            FORKED_FROM_JAX = True
    children = getattr(multiprocessing.process, "_children", None)
    for res in list(_LIVE_RESOURCES):
        for w in res.workers:
            if children is not None:
                children.discard(w.proc)


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


def check_not_forked_from_jax() -> None:
    """Raise RuntimeError in a process forked from one where JAX runs (a JAX call here would hang)."""
    if FORKED_FROM_JAX:
        raise RuntimeError(
            "this process was forked (os.fork(), or multiprocessing's 'fork' start method: gymnasium's "
            "AsyncVectorEnv default context on Linux, SB3's SubprocVecEnv(start_method='fork')) from a process "
            "in which JAX was already running; JAX is not fork-safe and the JAX engine would hang here. Start "
            "the subprocesses with context='spawn' or 'forkserver' (AsyncVectorEnv(fns, context='spawn'), "
            "SubprocVecEnv(fns, start_method='spawn')), or run no JAX (no engine='jax' env's reset or step) in "
            "the parent before it forks")


_F = TypeVar("_F", bound=Callable[..., Any])


def exclusive(method: _F) -> _F:
    """Decorate an env method: refuse a call from another thread while one is running in this env
    (the worker protocol and the shared arrays serve one call at a time: interleaved calls would
    deadlock or mix the worlds), and refuse any call in a process forked from the env's owner when
    the env has worker processes or runs JAX (``env._forked_use_error()``), raising RuntimeError."""

    @functools.wraps(method)
    def guarded(self: Any, *args: Any, **kwargs: Any) -> Any:
        owner = self.__dict__.get("_owner_pid")
        if owner is not None and owner != os.getpid():
            why = self._forked_use_error()
            if why is not None:
                raise RuntimeError(f"this {type(self).__name__} was created in process {owner}; this is a "
                                   f"forked copy in process {os.getpid()}: {why}. Create a new env in this "
                                   f"process instead")
        lock = self.__dict__.get("_call_lock") or self.__dict__.setdefault("_call_lock", threading.Lock())
        if not lock.acquire(blocking=False):
            raise RuntimeError(f"{type(self).__name__}.{method.__name__}() was called while another thread is "
                               f"inside a call of the same env; an env serves one call at a time: use one env "
                               f"per thread, or serialize the calls with a lock")
        try:
            return method(self, *args, **kwargs)
        finally:
            lock.release()

    return guarded  # type: ignore[return-value]


def _proc_state(pid: int | None) -> str | None:
    """The Linux scheduler state letter of process ``pid`` ("T": stopped), or None if unknown."""
    if pid is None:
        return None
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rsplit(b")", 1)[1].split()[0].decode()
    except (OSError, IndexError, UnicodeDecodeError):
        return None


def _exit_with_parent(parent_pid: int) -> None:
    """Watchdog thread of a worker: end the process once its parent is gone."""
    while os.getppid() == parent_pid:
        time.sleep(PARENT_CHECK_S)
    os._exit(1)


def _error_reply(e: BaseException) -> tuple:
    return ("error", type(e).__name__, str(e), traceback.format_exc())


def worker_main(conn: Any, init: dict[str, Any], parent_pid: int) -> None:
    """A worker process: pin it to CPU ``init["cpu"]`` (if given), map the shared arrays (``init["shm"]``,
    ``init["layout"]``), build the shard (``init["factory"](init, arrays)``; the factory a function or
    a ``"module:function"`` string), serve messages until the pipe closes.

    ``STEP`` steps the shard and answers ``DONE``; a pickled command tuple is answered with
    ``("ok", value)``; any exception is answered with ``("error", type, message, traceback)``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is for the parent, which then ends us
    threading.Thread(target=_exit_with_parent, args=(parent_pid,), name="parent-watchdog", daemon=True).start()
    try:
        if init.get("cpu") is not None and hasattr(os, "sched_setaffinity"):
            os.sched_setaffinity(0, {init["cpu"]})  # before the factory's imports start thread pools
        shm = SharedBlock(name=init["shm"])
        arrays = map_arrays(shm.buf, init["layout"])
        factory = init["factory"]
        if isinstance(factory, str):  # "module:function", imported only now (after the pinning)
            module, _, name = factory.partition(":")
            factory = getattr(importlib.import_module(module), name)
        shard = factory(init, arrays)
        reply: tuple = ("ok", None)
    except Exception as e:  # noqa: BLE001 - reported to the parent, which raises it
        reply = _error_reply(e)
    try:
        conn.send(reply)
        if reply[0] != "ok":
            return
        while True:
            msg = conn.recv_bytes()
            try:
                if msg == STEP:
                    shard.step()
                    reply = None
                elif msg[:1] == STEP_INTO:
                    shard.step_into(int.from_bytes(msg[1:], "little"))
                    reply = None
                else:
                    reply = ("ok", shard.handle(pickle.loads(msg)))
            except Exception as e:  # noqa: BLE001 - reported to the parent, which raises it
                reply = _error_reply(e)
            if reply is None:
                conn.send_bytes(DONE)
                continue
            try:
                conn.send(reply)
            except (EOFError, OSError):
                raise
            except Exception as e:  # noqa: BLE001 - e.g. a result that does not pickle (nothing was sent)
                conn.send(_error_reply(e))
    except (EOFError, OSError):  # the env closed its end (close(), garbage collection, its process died)
        return


@contextmanager
def _worker_environ(overrides: Mapping[str, str | None]) -> Iterator[None]:
    """``WORKER_ENV`` defaults and ``overrides`` (None: removed) in ``os.environ`` while a worker is
    spawned (it inherits them); the parent's environment is restored afterwards."""
    saved = {k: os.environ.get(k) for k in (*WORKER_ENV, *overrides)}
    for k, v in WORKER_ENV.items():
        os.environ.setdefault(k, v)
    for k, v in overrides.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextmanager
def _main_module_hidden() -> Iterator[None]:
    """Hide ``__main__``'s file and spec while a worker is spawned, so the worker does not import the
    user's script (the "spawn" start method re-imports it by default, which would run a script's
    top-level code, env creation included, in every worker). The worker's target and arguments live
    in quadswarm_mj, so it never needs the main module; scripts need no ``__main__`` guard."""
    main = sys.modules.get("__main__")
    saved = {k: main.__dict__[k] for k in ("__file__", "__spec__") if main is not None and k in main.__dict__}
    try:
        if main is not None:
            main.__dict__.pop("__file__", None)
            main.__dict__["__spec__"] = None
        yield
    finally:
        if main is not None:
            main.__dict__.pop("__spec__", None)
            main.__dict__.update(saved)


class Worker:
    """Parent-side handle of the worker process running shard ``index`` (worlds [lo, hi))."""

    def __init__(self, index: int, lo: int, hi: int, init: dict[str, Any],
                 environ: Mapping[str, str | None] | None = None):
        ctx = multiprocessing.get_context("spawn")
        self.index, self.lo, self.hi = index, lo, hi
        self.cpu: int | None = init.get("cpu")  # the core it is pinned to (None: not pinned)
        #: longest wait for one reply (s; None: no limit), then WorkerError
        self.timeout: float | None = init.get("timeout", DEFAULT_WORKER_TIMEOUT_S)
        self._poller: Any = None  # select.poll of the pipe, made at the first wait
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=worker_main, args=(child, init, os.getpid()), daemon=True,
                                name=f"quadswarm-vector-worker-{index}")
        try:
            with _worker_environ(environ or {}), _main_module_hidden():
                self.proc.start()
        finally:
            child.close()  # only the worker holds its end now: its death closes the pipe

    def describe(self) -> str:
        return f"vector env worker {self.index} (worlds [{self.lo}, {self.hi}), pid {self.proc.pid})"

    def send(self, msg: Any, what: str) -> None:
        """Send ``STEP``, a ``STEP_INTO`` message (bytes) or a command tuple; a dead worker raises WorkerError."""
        try:
            if isinstance(msg, bytes):
                self.conn.send_bytes(msg)
            else:
                self.conn.send(msg)
        except OSError:
            raise self._died(what) from None

    def result(self, what: str) -> Any:
        """Wait for the reply to the last message; a failure (also no reply within ``timeout``) raises WorkerError."""
        self._wait(what, self.timeout if what != "start" or self.timeout is None else
                   max(self.timeout, DEFAULT_WORKER_TIMEOUT_S))  # a start imports and builds: slow under load
        try:
            buf = self.conn.recv_bytes()
        except (EOFError, OSError):
            raise self._died(what) from None
        if buf == DONE:
            return None
        status, *rest = pickle.loads(buf)
        if status == "ok":
            return rest[0]
        name, text, tb = rest
        raise WorkerError(f"{self.describe()} raised {name} during {what}: {text}\n\nWorker traceback:\n{tb}",
                          self.index, tb)

    def _wait(self, what: str, timeout: float | None) -> None:
        """Wait until a reply (or the pipe's end) is readable; after ``timeout`` s raise WorkerError."""
        if timeout is None:
            return
        try:
            if self._poller is None:  # one poll(2) per wait (Connection.poll builds a selector per call)
                self._poller = select.poll()
                self._poller.register(self.conn.fileno(), select.POLLIN)
            deadline = time.monotonic() + timeout
            while not self._poller.poll(1000.0 * max(0.0, min(_POLL_S, deadline - time.monotonic()))):
                if time.monotonic() >= deadline:
                    state = " (it is stopped, e.g. by SIGSTOP)" if _proc_state(self.proc.pid) == "T" else ""
                    raise WorkerError(f"{self.describe()} did not reply within worker_timeout = {timeout:g} s "
                                      f"during {what}{state}", self.index)
        except (EOFError, OSError, ValueError):
            return  # the pipe closed (poll reports the hang-up as an event): recv_bytes reports how

    def _died(self, what: str) -> WorkerError:
        self.proc.join(timeout=2.0)
        code = self.proc.exitcode
        if code is None:
            how = "closed its pipe"
        elif code < 0:
            try:
                how = f"was killed by signal {signal.Signals(-code).name}"
            except ValueError:
                how = f"was killed by signal {-code}"
        else:
            how = f"exited with code {code}"
        msg = f"{self.describe()} {how} during {what}"
        if what == "start":
            msg += " (its output above tells why)"
        return WorkerError(msg, self.index)

    def stop(self) -> None:
        """Close the pipe (the worker exits); ``join`` then waits for it."""
        self.conn.close()

    def join(self) -> None:
        self.proc.join(timeout=JOIN_TIMEOUT_S)
        if self.proc.exitcode is None:
            self.proc.terminate()
            self.proc.join(timeout=1.0)
        if self.proc.exitcode is None:
            self.proc.kill()
            self.proc.join()


class Resources:
    """The env's worker processes and shared-memory block (released by ``release``, also at GC)."""

    def __init__(self) -> None:
        self.workers: list[Worker] = []
        self.shm: SharedBlock | None = None
        self.linked = False  # the block still has its name in /dev/shm
        self.pid = os.getpid()  # the owner: only it ends the workers (a forked copy only lets go)
        _LIVE_RESOURCES.add(self)

    def create_block(self, size: int) -> SharedBlock:
        self.shm, self.linked = SharedBlock(create=True, size=size), True
        return self.shm

    def unlink(self) -> None:
        """Remove the block's name (the mappings stay); done once every worker has mapped it."""
        if self.shm is not None and self.linked:
            self.linked = False
            self.shm.unlink()

    def release(self) -> None:
        if os.getpid() != self.pid:  # a forked copy: the workers and the block are the owner's
            for w in self.workers:
                w.conn.close()
            self.workers.clear()
            self.shm, self.linked = None, False
            return
        for w in self.workers:
            w.stop()
        for w in self.workers:
            w.join()
        self.workers.clear()
        if self.shm is not None:
            self.unlink()
            self.shm.close()
            self.shm = None


class OutputBlocks:
    """Output blocks of shared memory, all of one layout, that every worker maps (the ``("map", index,
    name)`` command) and writes its rows into when a step names the block (``STEP_INTO``). The env
    hands a step's outputs out as NumPy views of a block that nothing views any more, so no copy is
    made in its process; a block is free again when every array viewing it is gone
    (``weakref.finalize`` on the step's carrier array). At most ``max_blocks`` exist; when the caller
    keeps all of them alive a step goes through block 0, the scratch block, and is copied out.

    ``run(what, msg_for)`` sends ``msg_for(k)`` to every worker and waits for the replies
    (:func:`run_on_workers`)."""

    def __init__(self, layout: list, max_blocks: int, run: Callable[[str, Callable[[int], Any]], Any]):
        self.layout, self.max_blocks, self._run = layout, int(max_blocks), run
        self.size = layout_bytes(layout)
        self.blocks: list[SharedBlock] = []  # 0 is the scratch block (copied out, never handed out)
        self.free: list[bool] = []
        self.new()

    def new(self) -> int:
        """Create a block, have every worker map it, unlink its name; returns its index."""
        block = SharedBlock(create=True, size=self.size)
        try:
            k = len(self.blocks)
            self._run("map", lambda _: ("map", k, block.name))
        finally:
            block.unlink()  # mapped by every worker (or failed): the name can go
        self.blocks.append(block)
        self.free.append(k != 0)
        return k

    def acquire(self) -> int:
        """A free block (a new one while fewer than ``max_blocks`` exist), else 0 (the scratch block)."""
        for k in range(1, len(self.blocks)):
            if self.free[k]:
                return k
        if len(self.blocks) <= self.max_blocks:
            return self.new()
        return 0

    def arrays(self, k: int) -> dict[str, np.ndarray]:
        """Block k's arrays: new copies (scratch block) or views that free the block when all are gone."""
        carrier = np.frombuffer(self.blocks[k].buf, np.uint8, count=self.size)
        out = map_arrays(carrier, self.layout)
        if k == 0:
            return {name: x.copy() for name, x in out.items()}
        self.free[k] = False
        weakref.finalize(carrier, self.free.__setitem__, k, True)
        return out

    def close(self) -> None:
        for block in self.blocks:
            block.close()
        self.blocks, self.free = [], []


def map_block_rows(name: str, layout: list, lo: int, hi: int) -> tuple[SharedBlock, dict[str, np.ndarray]]:
    """A worker's side of an output block: the block ``name`` and views of rows [lo, hi) of its arrays."""
    shm = SharedBlock(name=name)
    arrays = map_arrays(shm.buf, layout)
    return shm, {k: v[lo:hi] for k, v in arrays.items()}


def wait_started(workers: list[Worker]) -> None:
    """Read every worker's start reply, then raise the first failure (WorkerError)."""
    error = None
    for w in workers:
        try:
            w.result("start")
        except WorkerError as e:
            error = error or e
    if error is not None:
        raise error


def _libc_sched_getcpu() -> Any:
    try:
        return ctypes.CDLL(None, use_errno=True).sched_getcpu
    except (OSError, AttributeError, TypeError):  # not glibc/Linux: no ordering
        return None


_SCHED_GETCPU = _libc_sched_getcpu()


def current_cpu() -> int | None:
    """The CPU the calling thread runs on now (Linux), else None."""
    if _SCHED_GETCPU is None:
        return None
    cpu = int(_SCHED_GETCPU())
    return cpu if cpu >= 0 else None


def send_order(workers: list[Worker]) -> list[Worker]:
    """``workers`` with the one pinned to the caller's current CPU last: the message wakes it on this
    CPU, where it preempts the caller before the other messages are out (measured on 2 cores, 1024 x 8
    on the JAX engine: median 1.17x the env's steps/s of sending in index order, 8 alternating rounds)."""
    cpu = current_cpu()
    if cpu is None or not any(w.cpu == cpu for w in workers):
        return workers
    return sorted(workers, key=lambda w: w.cpu == cpu)


def run_on_workers(workers: list[Worker], what: str, msg_for: Any, size: int,
                   local: Any = None) -> list[Any]:
    """Send ``msg_for(w.index)`` to every worker (:func:`send_order`), run ``local()`` meanwhile (shard 0
    in the calling process; its result is entry 0), then read every reply (so the pipes stay in step)
    and raise the first failure. Returns the ``size`` results by shard index."""
    sent, error = [], None
    for w in send_order(workers):
        try:
            w.send(msg_for(w.index), what)
            sent.append(w)
        except WorkerError as e:
            error = error or e
    out: list[Any] = [None] * size
    try:
        if local is not None:
            out[0] = local()
    finally:  # read every reply, so the pipes stay in step
        for w in sent:
            try:
                out[w.index] = w.result(what)
            except WorkerError as e:
                error = error or e
    if error is not None:
        raise error
    return out
