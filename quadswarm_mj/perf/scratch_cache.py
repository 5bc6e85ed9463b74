"""Work arrays ("scratch") of the NumPy speed forms, made once per (config, batch shape, thread).

The deck forms (:mod:`quadswarm_mj.perf.numpy_deck`, :mod:`quadswarm_mj.perf.numpy_depth`) write into
preallocated arrays; each thread gets its own (envs stepped in several threads must not share them), the
table keeps the last 32 and is guarded by one lock; ``local.last`` is the calling thread's last
``(cfg, scratch)``, which a form checks first (``last[0] is cfg``) to skip the table.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

LOCK = threading.Lock()  # guards every table of the speed forms' caches


class ScratchCache:
    """``get(cfg, shape)``: ``make(cfg, shape)`` made once per (cfg, shape, thread), the last 32 kept."""

    def __init__(self, make: Callable[[Any, tuple[int, ...]], Any]):
        self._make = make
        self.table: dict[tuple[int, tuple[int, ...], int], tuple[Any, Any]] = {}  # (id(cfg), shape, thread) ->
        self.local = threading.local()  # .last: this thread's last (cfg, scratch)

    def get(self, cfg: Any, shape: tuple[int, ...]) -> Any:
        key = (id(cfg), shape, threading.get_ident())
        hit = self.table.get(key)
        if hit is None or hit[0] is not cfg:
            hit = (cfg, self._make(cfg, shape))
            with LOCK:
                self.table[key] = hit
                while len(self.table) > 32:
                    self.table.pop(next(iter(self.table)))
        self.local.last = hit
        return hit[1]
