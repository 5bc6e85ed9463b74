"""Ship a trained policy: evaluate it, then copy it into a directory of shipped policies (``--out``) and
record its SHA-256, size and metrics in that directory's ``manifest.json`` (NumPy only, no JAX).

A failed release changes nothing: the name (a plain name), the scenarios, the directory and the
policy are checked and the evaluation done before anything is written; the policy file and then the
manifest are each replaced atomically.

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
import re
import shutil
import sys
from pathlib import Path
from typing import Any

import numpy as np

from quadswarm_mj.outfiles import check_writable, replacing
from quadswarm_mj.policies import MANIFEST, load_policy_file, read_manifest, sha256_file
from quadswarm_mj.training.evaluation import evaluate, make_eval_config

#: a release name: letters, digits, "_" and "-", starting with a letter or digit (the file is ``<name>.npz``)
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,63}")


def _finite(x: float) -> float | None:
    return None if not math.isfinite(x) else round(float(x), 5)


def check_name(name: Any) -> str:
    """``name`` if it is a plain release name (it becomes ``<name>.npz`` in the directory), else ``ValueError``."""
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
        raise ValueError(f"--name must be a plain name (letters, digits, '_' and '-', at most 64, starting with a "
                         f"letter or digit; no path, no extension), got {name!r}")
    return name


def release(name: str, policy_path: str | Path, scenarios: list[str], directory: str | Path, episodes: int = 100,
            seed: int = 0, run_dir: str | Path | None = None, description: str = "",
            train_record: dict[str, Any] | None = None) -> dict[str, Any]:
    """Evaluate ``policy_path`` on ``scenarios``, then ship it as ``directory/<name>.npz`` and record it in
    ``directory/manifest.json`` (created if missing). Returns the manifest entry.

    ``train_record`` (a JSON object: for a chain of runs its method, stages with their commands, budget and
    curves) is merged into the entry's ``train``; a PPO policy file's entry gets ``train.method = "ppo"``.

    Nothing in ``directory`` changes unless every check and evaluation succeeds: the name, the
    scenarios, the directory, the existing manifest and the policy file are checked first; the
    evaluation runs on a private copy of the file (so the bytes shipped are the bytes evaluated); then
    the policy and, last, the manifest are each replaced atomically (temporary file + ``os.replace``).
    """
    if directory is None:
        raise ValueError("directory must be given (the installed package may be read-only); "
                         "use quadswarm_mj/pretrained in a source checkout")
    check_name(name)
    if train_record is not None and not isinstance(train_record, dict):
        raise ValueError(f"the training record must be a JSON object, got {type(train_record).__name__}")
    if not isinstance(scenarios, (list, tuple)) or not scenarios:
        raise ValueError(f"scenarios must be a non-empty list of scenario names, got {scenarios!r}")
    if not isinstance(episodes, int) or isinstance(episodes, bool) or episodes < 1:
        raise ValueError(f"episodes must be an int >= 1, got {episodes!r}")
    if not Path(policy_path).is_file():
        raise ValueError(f"policy file {str(policy_path)!r} does not exist")
    d = Path(directory)
    if d.exists() and not d.is_dir():
        raise ValueError(f"--out {str(d)!r} is not a directory")
    mp = d / MANIFEST
    man = read_manifest(d) if mp.exists() else {"format": 1, "policies": {}}  # a malformed one: ValueError
    dst = d / f"{name}.npz"
    check_writable(dst, "the policy file", make_parents=True)
    check_writable(mp, "the manifest")
    run_info = None
    if run_dir is not None and (Path(run_dir) / "run.json").is_file():
        try:
            run_info = json.loads((Path(run_dir) / "run.json").read_text())
        except (ValueError, RecursionError) as e:
            raise ValueError(f"{str(Path(run_dir) / 'run.json')!r} is not valid JSON ({e})") from None
    # exits in reverse order: the policy is replaced first, the manifest last; on an error, neither
    with replacing(mp) as tmp_manifest, replacing(dst) as tmp:
        shutil.copyfile(policy_path, tmp)  # the evaluated bytes are the shipped bytes
        try:
            pol = load_policy_file(tmp, name=f"pretrained:{name}")
        except ValueError as e:  # name the user's file, not the private copy
            raise ValueError(str(e).replace(repr(str(tmp)), repr(str(policy_path)))) from None
        for s in scenarios:  # every scenario name and the policy's fit to it, before any evaluation
            cfg = make_eval_config(pol, s)
            if pol.obs_dim != cfg.obs_dim:
                raise ValueError(f"policy expects obs_dim {pol.obs_dim} but {s} gives {cfg.obs_dim}")
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
                                                                         "mean_distance") if k in e), flush=True)
        train = pol.meta.get("train", {})
        entry: dict[str, Any] = {"file": dst.name, "sha256": sha256_file(tmp), "bytes": tmp.stat().st_size,
                                 "description": description, "obs_dim": pol.obs_dim, "env": pol.env_kwargs,
                                 "eval": ev, "train": dict(train) if isinstance(train, dict) else {}}
        if run_info is not None:
            entry["train"]["run"] = run_info
        if "ppo" in entry["train"]:
            entry["train"].setdefault("method", "ppo")
        entry["train"].update(train_record or {})
        entry["env"] = {k: (list(v) if isinstance(v, tuple) else v) for k, v in entry["env"].items()}
        if mp.exists():  # re-read: keep entries another release added during the evaluation
            man = read_manifest(d)
        man["policies"][name] = entry
        tmp_manifest.write_text(json.dumps(man, indent=1, sort_keys=True) + "\n")
    return entry


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--name", required=True, help="release name: the file is <out>/<name>.npz (a plain name)")
    p.add_argument("--policy", required=True, help="policy .npz to ship")
    p.add_argument("--scenarios", required=True, help="comma list of evaluation scenarios")
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--run", help="training run directory (its run.json is recorded)")
    p.add_argument("--description", default="")
    p.add_argument("--train-record", help="JSON file merged into the entry's train record (method, stages, budget)")
    p.add_argument("--out", required=True, help="directory of shipped policies to write (e.g. quadswarm_mj/pretrained)")
    a = p.parse_args(argv)
    try:
        record = None
        if a.train_record is not None:
            try:
                record = json.loads(Path(a.train_record).read_text())
            except (OSError, ValueError) as e:
                raise ValueError(f"--train-record {a.train_record!r} is not a readable JSON file ({e})") from None
        release(a.name, a.policy, [s.strip() for s in a.scenarios.split(",") if s.strip()], a.out, a.episodes, a.seed,
                a.run, a.description, record)
    except ValueError as e:
        print(f"error: {e}\nnothing was written", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"error: could not write the release ({e})", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
