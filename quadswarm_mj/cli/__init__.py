"""Console commands (``[project.scripts]`` in pyproject.toml); each module has ``main(argv=None) -> int``.

* ``quadswarm-render``    :mod:`quadswarm_mj.cli.render`    (``scripts/render_rollout.py``)
* ``quadswarm-train``     :mod:`quadswarm_mj.cli.train`     (``scripts/train.py``; needs the ``train`` extra)
* ``quadswarm-evaluate``  :mod:`quadswarm_mj.cli.evaluate`  (``scripts/evaluate.py``)
* ``quadswarm-benchmark`` :mod:`quadswarm_mj.cli.benchmark` (``scripts/benchmark.py``)
* ``quadswarm-profile-jax`` :mod:`quadswarm_mj.cli.profile_jax` (``scripts/profile_jax_step.py``)
"""
