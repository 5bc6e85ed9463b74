"""A ``quadswarm-train`` process for tests/test_distributed.py: runs the console command's ``main`` with the
given options and records, for this process, the policy parameters after every update and how often it
wrote files, in ``$QS_DIST_RECORD_<process index>.npz`` (test output, outside the run directory)."""

from __future__ import annotations

import json
import os
import sys

import numpy as np


def main() -> int:
    from quadswarm_mj.cli import train as cli
    from quadswarm_mj.training import jax_ppo

    writes = {"save_policy_file": 0, "save_train_state": 0, "write_logs": 0, "plot_curves": 0}
    for name in writes:
        fn = getattr(jax_ppo, name)

        def counted(*a, _fn=fn, _name=name, **kw):
            writes[_name] += 1
            return _fn(*a, **kw)

        setattr(jax_ppo, name, counted)
    params: list[np.ndarray] = []
    lr: list[float] = []
    train = jax_ppo.JaxPPOTrainer.train

    def recording_train(self, *a, callback=None, **kw):
        import jax.flatten_util

        def cb(row):
            params.append(np.asarray(jax.flatten_util.ravel_pytree(self.state.params)[0]))
            lr.append(row["learning_rate"])
            if callback is not None:
                callback(row)

        return train(self, *a, callback=cb, **kw)

    jax_ppo.JaxPPOTrainer.train = recording_train
    code = cli.main(sys.argv[1:])
    import jax

    np.savez(f"{os.environ['QS_DIST_RECORD']}_{jax.process_index()}.npz", params=np.stack(params),
             learning_rate=np.array(lr), writes=np.array(json.dumps(writes)),
             devices=np.array([jax.process_count(), jax.device_count()]))
    return code


if __name__ == "__main__":
    raise SystemExit(main())
