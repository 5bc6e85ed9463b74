"""Ship a trained policy: copy it into a directory of shipped policies (``--out``), evaluate it and
record its SHA-256, size and metrics in that directory's ``manifest.json`` (NumPy only, no JAX).

The directory is always given: an installed package (site-packages) may be read-only. To update
the policies that ship with the package, run from the source checkout::

    python -m quadswarm_mj.training.release --name single --policy runs/single/final.npz \\
        --scenarios static_same_goal,dynamic_same_goal --episodes 100 --run runs/single --out quadswarm_mj/pretrained

The recorded metrics (mean, standard deviation over episodes, standard error, episodes, seed) are
what ``tests/test_policies.py`` checks a fresh 20-episode evaluation against.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from quadswarm_mj.policies import MANIFEST, load_policy_file, sha256_file
from quadswarm_mj.training.evaluation import evaluate


def _finite(x: float) -> float | None:
    return None if not math.isfinite(x) else round(float(x), 5)


def release(name: str, policy_path: str | Path, scenarios: list[str], directory: str | Path, episodes: int = 100,
            seed: int = 0, run_dir: str | Path | None = None, description: str = "") -> dict[str, Any]:
    """Copy ``policy_path`` to ``directory/<name>.npz``, evaluate it on ``scenarios`` and record it in
    ``directory/manifest.json`` (created if missing). Returns the manifest entry."""
    if directory is None:
        raise ValueError("directory must be given (the installed package may be read-only); "
                         "use quadswarm_mj/pretrained in a source checkout")
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    dst = d / f"{name}.npz"
    if Path(policy_path).resolve() != dst.resolve():
        shutil.copyfile(policy_path, dst)
    pol = load_policy_file(dst, name=f"pretrained:{name}")
    ev: dict[str, Any] = {}
    for s in scenarios:
        r = evaluate(pol, s, episodes=episodes, seed=seed)
        e: dict[str, Any] = {"episodes": episodes, "seed": seed, "num_quads": r.num_quads}
        for k in r.per_episode:
            v = r.per_episode[k]
            v = v[np.isfinite(v)]
            e[k] = _finite(r.mean(k))
            e[k + "_std"] = _finite(float(v.std(ddof=1))) if v.size > 1 else None
            e[k + "_stderr"] = _finite(r.stderr(k))
        ev[s] = e
        print(f"{name} on {s}: " + ", ".join(f"{k} {e[k]}" for k in ("success", "goal_reach_rate", "collisions",
                                                                     "mean_distance")), flush=True)
    entry: dict[str, Any] = {"file": dst.name, "sha256": sha256_file(dst), "bytes": dst.stat().st_size,
                             "description": description, "obs_dim": pol.obs_dim, "env": pol.env_kwargs,
                             "eval": ev, "train": pol.meta.get("train", {})}
    if run_dir is not None and (Path(run_dir) / "run.json").is_file():
        entry["train"]["run"] = json.loads((Path(run_dir) / "run.json").read_text())
    entry["env"] = {k: (list(v) if isinstance(v, tuple) else v) for k, v in entry["env"].items()}
    mp = d / MANIFEST
    man = json.loads(mp.read_text()) if mp.is_file() else {"format": 1, "policies": {}}
    man["policies"][name] = entry
    mp.write_text(json.dumps(man, indent=1, sort_keys=True) + "\n")
    return entry


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--name", required=True)
    p.add_argument("--policy", required=True, help="policy .npz to ship")
    p.add_argument("--scenarios", required=True, help="comma list of evaluation scenarios")
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--run", help="training run directory (its run.json is recorded)")
    p.add_argument("--description", default="")
    p.add_argument("--out", required=True, help="directory of shipped policies to write (e.g. quadswarm_mj/pretrained)")
    a = p.parse_args(argv)
    release(a.name, a.policy, [s.strip() for s in a.scenarios.split(",") if s.strip()], a.out, a.episodes, a.seed,
            a.run, a.description)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
