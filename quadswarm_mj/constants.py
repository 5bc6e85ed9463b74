"""Model constants shared by several model modules (a leaf: imports nothing of the package, so the
modules that share a constant do not import each other for it)."""

from __future__ import annotations

#: z tolerance (m) above the floor height within which a grounded quad stays grounded.
FLOOR_TOL = 1e-6
