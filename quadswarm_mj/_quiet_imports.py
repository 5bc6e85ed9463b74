"""Keep the console clean when MJX is imported.

``mujoco.mjx`` imports its optional Warp back end (``mujoco.mjx.warp``) eagerly and *prints*
"Failed to import warp: ..." and "Failed to import mujoco_warp: ..." when NVIDIA Warp is not
installed (the normal case on CPU). :func:`install` adds a meta-path finder that runs only that
one module's import with stdout captured: those two lines go to the ``quadswarm_mj`` logger at
DEBUG level, anything else it prints is passed through. mujoco itself is not modified, and no
module is imported early (JAX and MJX stay lazy).
"""

from __future__ import annotations

import contextlib
import importlib.abc
import importlib.machinery
import io
import logging
import sys
from types import ModuleType
from typing import Any

QUIET_MODULES = ("mujoco.mjx.warp",)
_PREFIXES = ("Failed to import warp:", "Failed to import mujoco_warp:")
log = logging.getLogger("quadswarm_mj")


class _QuietLoader(importlib.abc.Loader):
    def __init__(self, loader: importlib.abc.Loader):
        self._loader = loader

    def __getattr__(self, name: str) -> Any:  # everything else (resource readers, get_code, ...) as the original
        return getattr(self._loader, name)

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType | None:
        return self._loader.create_module(spec)

    def exec_module(self, module: ModuleType) -> None:
        buf = io.StringIO()
        try:
            with contextlib.redirect_stdout(buf):
                self._loader.exec_module(module)
        finally:
            for line in buf.getvalue().splitlines():
                if line.startswith(_PREFIXES):
                    log.debug("%s: %s", module.__name__, line)
                else:
                    print(line)


class _QuietFinder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname: str, path: Any, target: Any = None) -> importlib.machinery.ModuleSpec | None:
        if fullname not in QUIET_MODULES:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None:
                if spec.loader is not None and hasattr(spec.loader, "exec_module"):
                    spec.loader = _QuietLoader(spec.loader)
                return spec
        return None


def install() -> None:
    """Put the finder first on ``sys.meta_path`` (once)."""
    if not any(isinstance(f, _QuietFinder) for f in sys.meta_path):
        sys.meta_path.insert(0, _QuietFinder())
