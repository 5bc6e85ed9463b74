#!/usr/bin/env python
"""Thin wrapper of ``quadswarm_mj.cli.profile_jax`` (console command ``quadswarm-profile-jax``); see ``--help``."""

import sys
from pathlib import Path

# From a source checkout the checkout's package is used, installed or not.
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from quadswarm_mj.cli.profile_jax import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
