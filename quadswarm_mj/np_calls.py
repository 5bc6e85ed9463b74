"""NumPy functions without their Python-level wrappers, for the hot paths on small arrays.

``np.clip``, ``np.copyto``, ``np.count_nonzero`` and ``np.concatenate`` are Python functions around C ones
(the clip ufunc, ``_multiarray_umath``'s functions); on arrays of a few dozen elements the wrapper costs
as much as the work. These are the C functions (the same results) where this NumPy has them
(``numpy._core`` in NumPy 2, ``numpy.core`` in 1.x), else the public functions.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def _core() -> Any:
    """``numpy._core`` (NumPy 2) or ``numpy.core`` (NumPy 1.x), None if neither."""
    core = getattr(np, "_core", None)
    if core is None:  # pragma: no cover (NumPy 1.x)
        try:
            from numpy import core
        except ImportError:
            return None
    return core


_umath = getattr(_core(), "umath", None)
_multiarray = getattr(_core(), "_multiarray_umath", None)

#: the clip ufunc: min(max(x, lo), hi) elementwise in one call (with array bounds a -0.0 input stays -0.0
#: only where a bound is -0.0; see the callers' notes on signs of zero)
clip = getattr(_umath, "clip", np.clip)
copyto = getattr(_multiarray, "copyto", np.copyto)
count_nonzero = getattr(_multiarray, "count_nonzero", np.count_nonzero)
concatenate = getattr(_multiarray, "concatenate", np.concatenate)
