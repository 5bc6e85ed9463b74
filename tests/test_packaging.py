"""Packaging: the MJCF assets and policies are package data found with importlib.resources,
pyproject ships them, declares the console commands and every import of the training code;
the CLI modules answer --help; importing MJX keeps the console clean; release writes where told."""

from __future__ import annotations

import ast
import fnmatch
import importlib
import json
import os
import subprocess
import sys
import tomllib
from importlib import resources
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
COMMANDS = {"quadswarm-render": "quadswarm_mj.cli.render", "quadswarm-train": "quadswarm_mj.cli.train",
            "quadswarm-evaluate": "quadswarm_mj.cli.evaluate", "quadswarm-benchmark": "quadswarm_mj.cli.benchmark",
            "quadswarm-profile-jax": "quadswarm_mj.cli.profile_jax"}


def _data_files() -> list[str]:
    pkg = ROOT / "quadswarm_mj"
    return sorted(str(p.relative_to(pkg)) for sub in ("assets", "pretrained") for p in (pkg / sub).rglob("*")
                  if p.is_file() and "__pycache__" not in p.parts)


def test_package_data_globs_ship_every_asset_and_policy():
    globs = PYPROJECT["tool"]["setuptools"]["package-data"]["quadswarm_mj"]
    files = _data_files()
    assert {"assets/crazyflie2.xml", "assets/arenas/room.xml", "pretrained/manifest.json",
            "pretrained/swarm8.npz", "pretrained/single.npz"} <= set(files)
    missing = [f for f in files if not any(fnmatch.fnmatchcase(f, g) and f.count("/") == g.count("/") for g in globs)]
    assert not missing, f"package data not covered by pyproject's package-data globs: {missing}"


def test_assets_are_package_resources_with_one_copy():
    from quadswarm_mj import arena

    pkg_assets = resources.files("quadswarm_mj") / "assets"
    assert arena.CRAZYFLIE_XML == pkg_assets / "crazyflie2.xml" and arena.CRAZYFLIE_XML.is_file()
    assert arena.ROOM_XML == pkg_assets / "arenas" / "room.xml" and arena.ROOM_XML.is_file()
    top = ROOT / "assets"
    if top.exists():  # source checkout: the top-level assets/ is a link to the package's, not a copy
        assert top.is_symlink() and top.resolve() == (ROOT / "quadswarm_mj" / "assets").resolve()


def test_missing_asset_names_the_file(tmp_path):
    from quadswarm_mj.arena import load_spec

    with pytest.raises(FileNotFoundError, match="nope.xml.*missing from the installation"):
        load_spec(resources.files("quadswarm_mj") / "assets" / "nope.xml")


def test_console_commands_declared():
    scripts = PYPROJECT["project"]["scripts"]
    assert scripts == {k: v + ":main" for k, v in COMMANDS.items()}


@pytest.mark.parametrize("command,module", sorted(COMMANDS.items()))
def test_cli_main_answers_help(command, module, capsys):
    mod = importlib.import_module(module)
    with pytest.raises(SystemExit) as e:
        mod.main(["--help"])
    assert e.value.code == 0
    assert "usage:" in capsys.readouterr().out


@pytest.mark.parametrize("script", ["render_rollout", "train", "evaluate", "benchmark", "profile_jax_step"])
def test_scripts_are_thin_wrappers(script):
    text = (ROOT / "scripts" / f"{script}.py").read_text()
    assert len(text.splitlines()) < 20 and "from quadswarm_mj.cli." in text


def _third_party_imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return {n for n in names if n not in sys.stdlib_module_names and n != "quadswarm_mj"}


def _requirement_names(reqs: list[str]) -> set[str]:
    out = set()
    for r in reqs:
        name = r.split(";")[0]
        for sep in "<>=!~[ ":
            name = name.split(sep)[0]
        out.add(name.strip().lower().replace("-", "_"))
    return out


def test_training_imports_are_declared_in_the_train_extra():
    core = _requirement_names(PYPROJECT["project"]["dependencies"])
    extras = PYPROJECT["project"]["optional-dependencies"]
    train, dev = _requirement_names(extras["train"]), _requirement_names(extras["dev"])
    assert {"flax", "optax", "brax", "matplotlib"} <= train <= dev | core
    alias = {"mujoco": "mujoco", "jax": "jax"}
    files = list((ROOT / "quadswarm_mj" / "training").glob("*.py")) + [ROOT / "quadswarm_mj" / "cli" / "train.py"]
    for f in files:
        for name in _third_party_imports(f):
            assert alias.get(name, name) in core | train, f"{f.name} imports {name}, not declared for 'train'"


def test_importing_mjx_prints_nothing():
    pytest.importorskip("mujoco.mjx")
    code = "import quadswarm_mj\nfrom quadswarm_mj.envs import mjx_env\nimport mujoco.mjx\nprint('done')\n"
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout == "done\n"
    assert "Failed to import" not in out.stderr


def test_release_writes_to_the_given_directory(tmp_path):
    from quadswarm_mj.policies import pretrained_dir
    from quadswarm_mj.training.release import release

    manifest = (pretrained_dir() / "manifest.json").read_bytes()
    entry = release("mine", pretrained_dir() / "single.npz", ["static_same_goal"], tmp_path / "shipped", episodes=2)
    man = json.loads((tmp_path / "shipped" / "manifest.json").read_text())
    assert (tmp_path / "shipped" / "mine.npz").is_file() and man["policies"]["mine"] == entry
    assert entry["eval"]["static_same_goal"]["episodes"] == 2
    assert (pretrained_dir() / "manifest.json").read_bytes() == manifest
    assert not (pretrained_dir() / "mine.npz").exists()
    with pytest.raises(ValueError, match="directory must be given"):
        release("mine", pretrained_dir() / "single.npz", ["static_same_goal"], None)


def test_release_records_the_training_method_and_a_chain_of_stages(tmp_path, capsys):
    from quadswarm_mj.policies import pretrained_dir
    from quadswarm_mj.training.release import main

    out = tmp_path / "shipped"
    bad = tmp_path / "bad.json"
    bad.write_text("[1, 2]")
    args = ["--name", "mine", "--policy", str(pretrained_dir() / "single.npz"), "--scenarios", "static_same_goal",
            "--episodes", "1", "--out", str(out)]
    assert main(args + ["--train-record", str(bad)]) == 2  # not an object: nothing written
    assert "must be a JSON object" in capsys.readouterr().err and not out.exists()
    assert main(args + ["--train-record", str(tmp_path / "missing.json")]) == 2
    assert not out.exists()
    record = tmp_path / "chain.json"
    record.write_text(json.dumps({"stages": [{"command": "quadswarm-train --preset single"}], "wall_clock_min": 1}))
    assert main(args + ["--train-record", str(record)]) == 0
    train = json.loads((out / "manifest.json").read_text())["policies"]["mine"]["train"]
    assert train["method"] == "ppo" and train["wall_clock_min"] == 1  # a PPO file: method recorded
    assert train["stages"][0]["command"] == "quadswarm-train --preset single" and "ppo" in train


@pytest.mark.slow
def test_profile_jax_lists_the_step_kernels(capsys):
    from quadswarm_mj.cli import profile_jax

    assert profile_jax.main(["--worlds", "2", "--quads", "2", "--steps", "3", "--top", "5"]) == 0
    out = capsys.readouterr().out
    assert "per control step under the profiler" in out and "us/step" in out
    rows = [ln for ln in out.splitlines() if "%" in ln and ln.split()[0].replace(".", "").isdigit()]
    assert 1 <= len(rows) <= 5


def test_profile_jax_sensors_option_refuses_an_unknown_deck(capsys):
    from quadswarm_mj.cli import profile_jax

    with pytest.raises(SystemExit):
        profile_jax.main(["--sensors", "multiranger,lidar"])
    assert "unknown item 'lidar'" in capsys.readouterr().err


@pytest.mark.slow
def test_profile_jax_with_the_decks_on(capsys):
    from quadswarm_mj.cli import profile_jax

    assert profile_jax.main(["--worlds", "2", "--quads", "2", "--steps", "2", "--top", "3",
                             "--sensors", "multiranger,flow,depth=2x3"]) == 0
    assert "per control step under the profiler" in capsys.readouterr().out
