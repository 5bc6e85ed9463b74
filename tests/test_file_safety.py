"""No file is destroyed by a failed command, and hostile policy files stay cheap (issue 32, items 6, 7 and 8).

* ``python -m quadswarm_mj.training.release`` validates and evaluates before it writes, writes the
  policy and the manifest atomically (manifest last) and takes a plain ``--name`` only;
* ``quadswarm-benchmark --out`` refuses to overwrite a file that is not a benchmark report;
* ``--out``, ``quadswarm-evaluate --json`` and ``quadswarm-render --still``/``--out`` check that
  they can write before the work, and print the results (exit 1, no traceback) when the write fails;
* a policy ``.npz`` whose member inflates far beyond its architecture is refused from the member
  headers, before any data is read; malformed metadata and manifests raise ``ValueError``.
"""

from __future__ import annotations

import io
import json
import shutil
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest

from quadswarm_mj.policies import (
    FORMAT,
    load_policy_file,
    load_pretrained,
    pretrained_dir,
    random_encoder_policy,
    save_encoder_policy,
    save_policy,
    sha256_file,
)
from quadswarm_mj.training.evaluation import EvalResult

META_1Q = {"activation": "tanh", "obs_dim": 18, "action_dim": 4, "env": {"num_quads": 1}}


def _policy_file(path: Path, seed: int = 0, meta: dict | None = None) -> str:
    """A random 1-quad MLP policy (18 -> 16 -> 8) at ``path``; returns its SHA-256."""
    rng = np.random.default_rng(seed)
    sizes = [18, 16, 8]
    kernels = [rng.normal(0, 0.5, (a, b)) for a, b in zip(sizes[:-1], sizes[1:])]
    biases = [rng.normal(0, 0.1, (b,)) for b in sizes[1:]]
    return save_policy(path, kernels, biases, np.zeros(18), np.ones(18), dict(meta or META_1Q))


def _shipped_dir(tmp_path: Path, name: str = "toy") -> Path:
    """A directory of shipped policies holding ``name`` and its manifest entry."""
    d = tmp_path / "shipped"
    d.mkdir()
    sha = _policy_file(d / f"{name}.npz")
    man = {"format": 1, "policies": {name: {"file": f"{name}.npz", "sha256": sha,
                                            "bytes": (d / f"{name}.npz").stat().st_size, "eval": {}}}}
    (d / "manifest.json").write_text(json.dumps(man))
    return d


def _snapshot(d: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(d.iterdir())}


def _fake_result(scenario: str = "static_same_goal") -> EvalResult:
    per = {"success": np.array([1.0, 0.0]), "mean_distance": np.array([0.25, 0.75])}
    return EvalResult(scenario, 1, 2, per, 0.1)


def _a_file(tmp_path: Path) -> Path:
    """A regular file: a path below it can never be written (whatever the user's privileges)."""
    f = tmp_path / "a_file"
    f.write_text("x")
    return f


# ---------------------------------------------------------------------------- release
def test_release_of_a_bad_file_keeps_the_shipped_policy(tmp_path, capsys):
    from quadswarm_mj.training import release

    d = _shipped_dir(tmp_path)
    before = _snapshot(d)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"PK\x03\x04 this is not a policy")
    rc = release.main(["--name", "toy", "--policy", str(bad), "--scenarios", "static_same_goal", "--episodes", "1",
                       "--out", str(d)])
    assert rc == 2
    err = capsys.readouterr().err
    assert "error" in err and repr(str(bad)) in err and ".tmp" not in err  # names the user's file, not a copy
    assert _snapshot(d) == before
    for missing in (tmp_path / "missing.npz", tmp_path):  # no such file; a directory
        rc = release.main(["--name", "toy", "--policy", str(missing), "--scenarios", "static_same_goal",
                           "--episodes", "1", "--out", str(d)])
        assert rc == 2 and "does not exist" in capsys.readouterr().err
    assert _snapshot(d) == before


def test_release_with_a_typo_in_the_scenarios_keeps_the_shipped_policy(tmp_path, capsys, monkeypatch):
    from quadswarm_mj.training import release

    d = _shipped_dir(tmp_path)
    before = _snapshot(d)
    new = tmp_path / "new.npz"
    _policy_file(new, seed=1)

    def no_evaluation(*a, **k):
        raise AssertionError("evaluated although a scenario name is unknown")

    monkeypatch.setattr(release, "evaluate", no_evaluation)
    rc = release.main(["--name", "toy", "--policy", str(new), "--scenarios", "static_same_goal,static_same_gaol",
                       "--episodes", "1", "--out", str(d)])
    assert rc == 2
    assert "static_same_gaol" in capsys.readouterr().err
    assert _snapshot(d) == before


def test_release_evaluates_before_it_writes(tmp_path, monkeypatch):
    from quadswarm_mj.training import release

    d = _shipped_dir(tmp_path)
    before = _snapshot(d)
    new = tmp_path / "new.npz"
    _policy_file(new, seed=1)

    def failing_evaluation(*a, **k):
        raise RuntimeError("evaluation interrupted")

    monkeypatch.setattr(release, "evaluate", failing_evaluation)
    with pytest.raises(RuntimeError, match="interrupted"):
        release.release("toy", new, ["static_same_goal"], d, episodes=1)
    assert _snapshot(d) == before  # neither the policy, nor the manifest, nor a temporary file


@pytest.mark.parametrize("name", ["../../x", "../x", "a/b", "/tmp/x", "", ".hidden", "x.npz", "x\\y", "a b"])
def test_release_name_must_be_a_plain_name(tmp_path, capsys, name):
    from quadswarm_mj.training import release

    (tmp_path / "deep" / "er").mkdir(parents=True)
    d = _shipped_dir(tmp_path / "deep" / "er")  # ../../x would land in tmp_path/deep
    before = _snapshot(d)
    rc = release.main(["--name", name, "--policy", str(pretrained_dir() / "single.npz"), "--scenarios",
                       "static_same_goal", "--episodes", "1", "--out", str(d)])
    assert rc == 2
    assert "--name" in capsys.readouterr().err
    assert _snapshot(d) == before
    assert sorted(p.name for p in (tmp_path / "deep").iterdir()) == ["er"]


def test_release_writes_policy_then_manifest_atomically(tmp_path, monkeypatch):
    import os

    from quadswarm_mj.training import release

    d = _shipped_dir(tmp_path)
    new = tmp_path / "new.npz"
    sha = _policy_file(new, seed=1)
    replaced: list[str] = []
    real_replace = os.replace

    def recording_replace(src, dst):
        replaced.append(Path(dst).name)
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", recording_replace)
    monkeypatch.setattr(release, "evaluate", lambda pol, s, **k: _fake_result(s))
    entry = release.release("toy", new, ["static_same_goal"], d, episodes=2)
    assert replaced == ["toy.npz", "manifest.json"]  # the manifest last
    assert sorted(p.name for p in d.iterdir()) == ["manifest.json", "toy.npz"]  # no temporary file left
    assert sha256_file(d / "toy.npz") == sha == entry["sha256"]
    man = json.loads((d / "manifest.json").read_text())
    assert man["policies"]["toy"]["eval"]["static_same_goal"]["success"] == 0.5
    assert load_pretrained("toy", d).obs_dim == 18


def test_release_with_a_malformed_manifest_writes_nothing(tmp_path, capsys, monkeypatch):
    from quadswarm_mj.training import release

    d = _shipped_dir(tmp_path)
    (d / "manifest.json").write_text('{"format": 1, "policies": [')
    before = _snapshot(d)
    monkeypatch.setattr(release, "evaluate", lambda pol, s, **k: _fake_result(s))
    rc = release.main(["--name", "toy", "--policy", str(pretrained_dir() / "single.npz"), "--scenarios",
                       "static_same_goal", "--episodes", "1", "--out", str(d)])
    assert rc == 2 and "manifest" in capsys.readouterr().err
    assert _snapshot(d) == before


# ---------------------------------------------------------------------------- benchmark
@pytest.fixture
def stub_benchmark(monkeypatch):
    """The benchmark with instant measurements (one row, no JAX)."""
    from quadswarm_mj.cli import benchmark

    monkeypatch.setattr(benchmark, "bench_single", lambda n, w, s, r: 1234.0)
    monkeypatch.setattr(benchmark, "ceiling", lambda b, s, r: {"one_core": 2000.0, "rollout": 3000.0,
                                                                "ceiling": 3000.0})
    monkeypatch.setattr(benchmark, "_jax_rows", lambda *a: "")
    return benchmark


BENCH_ARGS = ["--rows", "single", "--single-n", "1", "--quick", "--skip-mjx"]


def test_benchmark_refuses_to_overwrite_a_file_that_is_not_a_report(tmp_path, stub_benchmark, monkeypatch, capsys):
    def no_work(*a):
        raise AssertionError("measured although the report cannot be written")

    monkeypatch.setattr(stub_benchmark, "bench_single", no_work)
    notes = tmp_path / "notes.md"
    notes.write_text("# My notes\n\nweeks of work\n")
    with pytest.raises(SystemExit) as e:
        stub_benchmark.main(["--out", str(notes), *BENCH_ARGS])
    assert e.value.code == 2
    assert "not a benchmark report" in capsys.readouterr().err
    assert notes.read_text() == "# My notes\n\nweeks of work\n"
    binary = tmp_path / "data.bin"
    binary.write_bytes(bytes(range(256)))
    with pytest.raises(SystemExit):
        stub_benchmark.main(["--out", str(binary), *BENCH_ARGS])
    assert binary.read_bytes() == bytes(range(256))


def test_benchmark_rewrites_its_report_and_keeps_the_notes(tmp_path, stub_benchmark):
    out = tmp_path / "BENCH.md"
    out.write_text(f"# Benchmarks\n\nold table\n\n{stub_benchmark.NOTES_MARKER}\nmy notes\n")
    assert stub_benchmark.main(["--out", str(out), *BENCH_ARGS]) == 0
    text = out.read_text()
    assert "old table" not in text and "QuadSwarmEnv, 1 world x 1" in text and text.endswith("my notes\n")
    fresh = tmp_path / "new.md"  # a new file is fine too
    assert stub_benchmark.main(["--out", str(fresh), *BENCH_ARGS]) == 0
    assert stub_benchmark.NOTES_MARKER in fresh.read_text()


def test_benchmark_checks_the_out_path_before_measuring(tmp_path, stub_benchmark, monkeypatch, capsys):
    def no_work(*a):
        raise AssertionError("measured although the report cannot be written")

    monkeypatch.setattr(stub_benchmark, "bench_single", no_work)
    with pytest.raises(SystemExit) as e:
        stub_benchmark.main(["--out", str(_a_file(tmp_path) / "BENCH.md"), *BENCH_ARGS])
    assert e.value.code == 2 and "cannot write" in capsys.readouterr().err


def test_benchmark_prints_the_report_when_the_write_fails(tmp_path, stub_benchmark, monkeypatch, capsys):
    sub = tmp_path / "sub"
    sub.mkdir()

    def measure_then_lose_the_directory(n, w, s, r):
        shutil.rmtree(sub)  # the directory goes away during the run
        return 1234.0

    monkeypatch.setattr(stub_benchmark, "bench_single", measure_then_lose_the_directory)
    rc = stub_benchmark.main(["--out", str(sub / "BENCH.md"), *BENCH_ARGS])
    out, err = capsys.readouterr()
    assert rc == 1
    assert "could not write" in err and "Traceback" not in err
    assert "# Benchmarks" in out and "QuadSwarmEnv, 1 world x 1" in out  # the whole report, kept on stdout


# ---------------------------------------------------------------------------- evaluate
def test_evaluate_checks_the_json_path_before_evaluating(tmp_path, monkeypatch):
    from quadswarm_mj.cli import evaluate as cli
    from quadswarm_mj.training import evaluation

    def no_work(*a, **k):
        raise AssertionError("evaluated although the results cannot be written")

    monkeypatch.setattr(evaluation, "evaluate", no_work)
    for bad in (_a_file(tmp_path) / "r.json", tmp_path):  # below a file; a directory
        with pytest.raises(SystemExit) as e:
            cli.main(["--policy", "controller", "--num-quads", "1", "--scenarios", "static_same_goal", "--episodes",
                      "1", "--json", str(bad)])
        assert "cannot write" in str(e.value.code)


def test_evaluate_refuses_to_overwrite_a_file_that_is_not_json(tmp_path, monkeypatch):
    from quadswarm_mj.cli import evaluate as cli
    from quadswarm_mj.training import evaluation

    monkeypatch.setattr(evaluation, "evaluate", lambda policy, scenario, **k: _fake_result(scenario))
    policy = tmp_path / "mine.npz"
    _policy_file(policy)
    before = policy.read_bytes()
    with pytest.raises(SystemExit) as e:  # a typo: --json names the policy
        cli.main(["--policy", str(policy), "--scenarios", "static_same_goal", "--episodes", "1", "--json", str(policy)])
    assert "not a JSON file" in str(e.value.code)
    assert policy.read_bytes() == before
    old = tmp_path / "old.json"  # earlier results are replaced
    old.write_text('{"results": []}')
    assert cli.main(["--policy", str(policy), "--scenarios", "static_same_goal", "--episodes", "2", "--json",
                     str(old)]) == 0
    assert json.loads(old.read_text())["results"][0]["success"] == 0.5


def test_evaluate_prints_the_results_when_the_json_write_fails(tmp_path, monkeypatch, capsys):
    from quadswarm_mj.cli import evaluate as cli
    from quadswarm_mj.training import evaluation

    sub = tmp_path / "sub"
    sub.mkdir()

    def evaluate_then_lose_the_directory(policy, scenario, **k):
        shutil.rmtree(sub, ignore_errors=True)
        return _fake_result(scenario)

    monkeypatch.setattr(evaluation, "evaluate", evaluate_then_lose_the_directory)
    rc = cli.main(["--policy", "controller", "--num-quads", "1", "--scenarios", "static_same_goal", "--episodes", "2",
                   "--json", str(sub / "r.json")])
    out, err = capsys.readouterr()
    assert rc == 1
    assert "could not write" in err and "Traceback" not in err
    printed = json.loads(out[out.index("{"):])  # the JSON that could not be written, on stdout
    assert printed["results"][0]["success"] == 0.5


def test_evaluate_json_is_written_after_a_real_evaluation(tmp_path):
    from quadswarm_mj.cli import evaluate as cli

    target = tmp_path / "r.json"
    target.write_text('{"old": true}')
    assert cli.main(["--policy", "controller", "--num-quads", "1", "--scenarios", "static_same_goal",
                     "--episodes", "1", "--env", "episode_seconds=0.5", "--json", str(target)]) == 0
    res = json.loads(target.read_text())
    assert res["results"][0]["scenario"] == "static_same_goal" and res["results"][0]["episodes"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json"]


# ---------------------------------------------------------------------------- render
RENDER_ARGS = ["--num-quads", "1", "--policy", "hover", "--seconds", "0.1", "--fps", "10", "--width", "64",
               "--height", "48", "--trail", "0", "--no-shadows"]


@pytest.mark.parametrize("flag", ["--still", "--out"])
def test_render_checks_its_outputs_before_flying(tmp_path, monkeypatch, capsys, flag):
    from quadswarm_mj.cli import render as cli

    def no_work(*a, **k):
        raise AssertionError("flew although an output cannot be written")

    monkeypatch.setattr(cli, "QuadSwarmEnv", no_work)
    paths = {"--still": tmp_path / "s.png", "--out": tmp_path / "v.gif"}
    paths[flag] = _a_file(tmp_path) / ("s.png" if flag == "--still" else "v.gif")
    rc = cli.main([*RENDER_ARGS, "--out", str(paths["--out"]), "--still", str(paths["--still"])])
    assert rc == 2
    assert "cannot write" in capsys.readouterr().err
    assert not (tmp_path / "v.gif").exists() and not (tmp_path / "s.png").exists()


def test_render_prints_the_results_when_the_still_write_fails(tmp_path, monkeypatch, capsys):
    import mediapy

    from quadswarm_mj.cli import render as cli

    still = tmp_path / "s.png"
    still.write_bytes(b"old still")

    def disk_full(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(mediapy, "write_image", disk_full)
    rc = cli.main([*RENDER_ARGS, "--out", str(tmp_path / "v.gif"), "--still", str(still)])
    out, err = capsys.readouterr()
    assert rc == 1
    assert "could not write" in err and "No space left" in err and "Traceback" not in err
    assert "mean_distance" in out and "samples/s" in out  # the results, printed
    assert still.read_bytes() == b"old still"  # not truncated by the failed write
    assert (tmp_path / "v.gif").stat().st_size > 0  # the video was written
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.png", "v.gif"]


# ---------------------------------------------------------------------------- hostile policy files
def _npy_header(arr_shape: tuple[int, ...], descr: str = "<f4") -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": arr_shape})
    return buf.getvalue()


def _inflating_npz(path: Path, member: str, nbytes: int, meta: dict | None = None) -> None:
    """A valid 1-quad MLP policy file, plus (or with, in place of the real one) ``member`` holding
    ``nbytes`` of zeros (float32), compressed (~1/200 of its size)."""
    rng = np.random.default_rng(0)
    arrays = {"meta": np.array(json.dumps({"format": FORMAT, **(meta or META_1Q)})),
              "layer_0/kernel": rng.normal(size=(18, 16)).astype(np.float32),
              "layer_0/bias": np.zeros(16, np.float32), "layer_1/kernel": rng.normal(size=(16, 8)).astype(np.float32),
              "layer_1/bias": np.zeros(8, np.float32), "obs_mean": np.zeros(18, np.float32),
              "obs_std": np.ones(18, np.float32)}
    arrays.pop(member, None)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for k, v in arrays.items():
            with zf.open(k + ".npy", "w") as f:
                np.lib.format.write_array(f, v, allow_pickle=False)
        with zf.open(member + ".npy", "w", force_zip64=True) as f:
            f.write(_npy_header((nbytes // 4,)))
            chunk = bytes(1 << 22)
            for _ in range(nbytes // len(chunk)):
                f.write(chunk)


def _peak_bytes(fn) -> tuple[int, object]:
    tracemalloc.start()
    try:
        try:
            out = fn()
        except ValueError as e:
            out = e
        return tracemalloc.get_traced_memory()[1], out
    finally:
        tracemalloc.stop()


BOMB = 64 << 20  # 64 MiB of zeros in ~0.3 MB of file: enough to tell reading it from not reading it


@pytest.mark.parametrize("member", ["obs_mean", "layer_0/kernel", "layer_1/bias"])
def test_inflating_member_is_refused_from_its_header(tmp_path, member):
    p = tmp_path / "bomb.npz"
    _inflating_npz(p, member, BOMB)
    assert p.stat().st_size < BOMB / 50
    peak, err = _peak_bytes(lambda: load_policy_file(p))
    assert isinstance(err, ValueError), err
    assert member in str(err) and str(BOMB // 4) in str(err)  # names the member and its declared shape
    assert peak < BOMB / 8, f"peak {peak / 2**20:.0f} MiB: the member was inflated"


def test_inflating_member_the_policy_does_not_use_is_never_read(tmp_path):
    p = tmp_path / "critic.npz"
    _inflating_npz(p, "value/layer_0/kernel", BOMB)
    peak, pol = _peak_bytes(lambda: load_policy_file(p))
    assert not isinstance(pol, Exception), pol
    assert pol.obs_dim == 18
    assert peak < BOMB / 8, f"peak {peak / 2**20:.0f} MiB: the unused member was inflated"


def test_oversized_architecture_is_refused_before_reading(tmp_path):
    """A chain of layers consistent with itself but of absurd width (declared in the headers only; the
    file holds no data for it): refused for its size, not by running out of memory."""
    p = tmp_path / "wide.npz"
    wide = 1 << 26
    members = {"meta": np.array(json.dumps({"format": FORMAT, **META_1Q}))}
    with zipfile.ZipFile(p, "w", zipfile.ZIP_DEFLATED) as zf:
        for k, v in members.items():
            with zf.open(k + ".npy", "w") as f:
                np.lib.format.write_array(f, v)
        for k, shape in (("layer_0/kernel", (18, wide)), ("layer_0/bias", (wide,)), ("layer_1/kernel", (wide, 8)),
                         ("layer_1/bias", (8,)), ("obs_mean", (18,)), ("obs_std", (18,))):
            with zf.open(k + ".npy", "w") as f:
                f.write(_npy_header(shape))
    with pytest.raises(ValueError, match="parameters"):
        load_policy_file(p)


def test_object_member_is_refused_even_when_unused(tmp_path):
    p = tmp_path / "evil.npz"
    _policy_file(p)
    with zipfile.ZipFile(p, "a") as zf:
        with zf.open("value/x.npy", "w") as f:
            f.write(_npy_header((1,), descr="|O"))
            f.write(b"\x80\x04N.")
    with pytest.raises(ValueError, match="object"):
        load_policy_file(p)


def test_encoder_member_shapes_are_checked_against_the_architecture(tmp_path):
    from quadswarm_mj.policies import ARCH_PRESETS

    pol = random_encoder_policy(ARCH_PRESETS["deepsets_deployable"], {"self_dim": 18, "num_neighbors": 2})
    p = tmp_path / "enc.npz"
    save_encoder_policy(p, pol, meta={"env": {"num_quads": 3}})
    assert load_policy_file(p).obs_dim == 30
    bomb = tmp_path / "enc_bomb.npz"
    with zipfile.ZipFile(p) as src, zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as dst:
        for info in src.infolist():
            if info.filename != "actor/head_0/kernel.npy":
                dst.writestr(info.filename, src.read(info))
        with dst.open("actor/head_0/kernel.npy", "w", force_zip64=True) as f:
            f.write(_npy_header((BOMB // 64, 16)))
            chunk = bytes(1 << 22)
            for _ in range(BOMB // len(chunk)):
                f.write(chunk)
    peak, err = _peak_bytes(lambda: load_policy_file(bomb))
    assert isinstance(err, ValueError) and "actor/head_0/kernel" in str(err), err
    assert peak < BOMB / 8


# ---------------------------------------------------------------------------- malformed metadata and manifests
def _with_meta(path: Path, meta_json: str) -> Path:
    """The 1-quad policy with its meta replaced by this JSON text."""
    src = path.with_suffix(".src.npz")
    _policy_file(src)
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["meta"] = np.array(meta_json)
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize("meta", [
    {**META_1Q, "obs_dim": [18]},
    {**META_1Q, "obs_dim": None},
    {**META_1Q, "obs_dim": "x"},
    {**META_1Q, "env": [1, 2]},
    {**META_1Q, "env": "num_quads"},
    {**META_1Q, "env": {"num_quads": 1, "room_size": 5}},
    {**META_1Q, "env": {"num_quads": "one"}},
    {**META_1Q, "env": {"num_quads": 1, "no_such_field": 3}},
    {**META_1Q, "env": {"num_quads": 1, "num_neighbors": [2]}},
    {**META_1Q, "train": "yesterday"},
    {**META_1Q, "activation": ["tanh"]},
    {**META_1Q, "obs_layout": [18, 0]},
    {**META_1Q, "arch": "mlp"},
])
def test_malformed_metadata_raises_value_error(tmp_path, meta):
    p = _with_meta(tmp_path / "m.npz", json.dumps({"format": FORMAT, **meta}))
    with pytest.raises(ValueError, match="m.npz"):
        pol = load_policy_file(p)
        _ = pol.env_kwargs, pol.obs_layout  # what evaluation and rendering read


def test_deeply_nested_metadata_raises_value_error(tmp_path):
    p = _with_meta(tmp_path / "deep.npz", "[" * 100_000 + "]" * 100_000)
    with pytest.raises(ValueError, match="meta"):
        load_policy_file(p)


def test_missing_bias_raises_value_error(tmp_path):
    p = tmp_path / "nobias.npz"
    _policy_file(p)
    with np.load(p) as z:
        arrays = {k: z[k] for k in z.files if k != "layer_1/bias"}
    np.savez(p, **arrays)
    with pytest.raises(ValueError, match="layer_1/bias"):
        load_policy_file(p)


@pytest.mark.parametrize("entry", [
    {"file": 123, "sha256": "0"},
    {"file": ["toy.npz"], "sha256": "0"},
    {"file": "toy.npz", "sha256": 5},
    {"file": "toy.npz", "sha256": None},
    {"file": "toy.npz", "sha256": "SHA", "bytes": [1]},
    {"file": "toy.npz", "sha256": "SHA", "bytes": "many"},
    {"file": "toy.npz", "sha256": "SHA", "bytes": 1e400},
    "toy.npz",
    None,
])
def test_malformed_manifest_entry_raises_value_error(tmp_path, entry):
    d = _shipped_dir(tmp_path)
    if isinstance(entry, dict) and entry.get("sha256") == "SHA":
        entry = {**entry, "sha256": sha256_file(d / "toy.npz")}
    text = json.dumps({"format": 1, "policies": {"toy": entry}}).replace("Infinity", "1e400")
    (d / "manifest.json").write_text(text)
    with pytest.raises(ValueError, match="manifest"):
        load_pretrained("toy", d)


@pytest.mark.parametrize("text", ["[" * 100_000 + "]" * 100_000, '{"policies": {"toy": ' * 5000, "\udcff"])
def test_malformed_manifest_file_raises_value_error(tmp_path, text):
    d = _shipped_dir(tmp_path)
    (d / "manifest.json").write_bytes(text.encode("utf-8", "surrogateescape"))
    with pytest.raises(ValueError, match="manifest"):
        load_pretrained("toy", d)


def test_shipped_policies_still_load():
    from quadswarm_mj.policies import list_pretrained

    for name in list_pretrained():
        assert load_pretrained(name).obs_dim > 0


def test_evaluate_unknown_env_field_is_a_clear_error():
    from quadswarm_mj.cli import evaluate as cli

    with pytest.raises(SystemExit) as e:
        cli.main(["--policy", "controller", "--num-quads", "1", "--scenarios", "static_same_goal", "--episodes", "1",
                  "--env", "no_such_field=3"])
    assert "no_such_field" in str(e.value.code) and str(e.value.code).startswith("error:")


# ---------------------------------------------------------------------------- atomic writes
def test_failed_save_keeps_the_earlier_checkpoint(tmp_path, monkeypatch):
    import os

    ck = tmp_path / "final.npz"
    sha = _policy_file(ck, seed=0)

    def disk_full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", disk_full)
    with pytest.raises(OSError, match="No space"):
        _policy_file(ck, seed=1)
    monkeypatch.undo()
    assert sha256_file(ck) == sha and load_policy_file(ck).obs_dim == 18
    assert sorted(p.name for p in tmp_path.iterdir()) == ["final.npz"]


def test_atomic_write_keeps_links_and_permissions(tmp_path):
    import os
    import stat

    from quadswarm_mj.outfiles import atomic_write_text, replacing

    real = tmp_path / "results.json"
    real.write_text("{}")
    os.chmod(real, 0o640)
    link = tmp_path / "latest.json"
    link.symlink_to(real.name)
    atomic_write_text(link, '{"new": 1}')
    assert link.is_symlink() and json.loads(real.read_text()) == {"new": 1}
    assert stat.S_IMODE(real.stat().st_mode) == 0o640
    with pytest.raises(RuntimeError), replacing(real) as tmp:  # an error while writing: the target is untouched
        tmp.write_text("half")
        raise RuntimeError("interrupted")
    assert json.loads(real.read_text()) == {"new": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["latest.json", "results.json"]
