"""The docs stay manuals: within their sizes, without dated work logs, with links and spec citations that
resolve, and with BENCHMARKS.md's generated part in the shape ``scripts/benchmark.py`` rewrites."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from quadswarm_mj.bench.report import NOTES_MARKER

ROOT = Path(__file__).parent.parent
PKG = ROOT / "quadswarm_mj"
MAX_LINES = {"README.md": 400, "BENCHMARKS.md": 250, "TRAINING.md": 400}
#: what a dated work log looks like: calendar dates, "session" narratives, re-measurement notes, and the
#: "target ... escape clause" tables
WORK_LOG = re.compile(r"\b20\d\d-\d\d-\d\d\b|\bsessions?\b|\bre-?measured\b|\bescape clause\b", re.IGNORECASE)
#: modules whose docstrings are manuals of at most 20 lines (the long explanations live in docs/): all of
#: the package but the files another change is editing (this allow-list only shrinks)
LONG_DOCSTRING_ALLOW = {"sensors.py"}
SHORT_DOCSTRINGS = sorted(p for p in PKG.rglob("*.py") if p.relative_to(PKG).as_posix() not in LONG_DOCSTRING_ALLOW)


def _docs() -> list[Path]:
    return [ROOT / "README.md", ROOT / "BENCHMARKS.md", ROOT / "TRAINING.md", *sorted((ROOT / "docs").glob("*.md"))]


def _manual_text(path: Path) -> str:
    """The hand-written text of a doc: for BENCHMARKS.md the notes below the marker (the generated part
    above it records the run's date by design)."""
    text = path.read_text(encoding="utf-8")
    if path.name == "BENCHMARKS.md":
        return text.split(NOTES_MARKER, 1)[1]
    return text


@pytest.mark.parametrize("name", sorted(MAX_LINES))
def test_top_level_docs_within_their_size(name: str) -> None:
    lines = (ROOT / name).read_text(encoding="utf-8").count("\n")
    assert lines <= MAX_LINES[name], f"{name} has {lines} lines, more than {MAX_LINES[name]}: move detail to docs/"


@pytest.mark.parametrize("path", _docs(), ids=lambda p: p.name)
def test_no_dated_work_log(path: Path) -> None:
    hits = [line.strip() for line in _manual_text(path).splitlines() if WORK_LOG.search(line)]
    assert not hits, f"{path.name} reads as a work log (git history keeps those): {hits[:3]}"


@pytest.mark.parametrize("path", SHORT_DOCSTRINGS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_module_docstrings_are_short_manuals(path: Path) -> None:
    doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
    assert len(doc.splitlines()) <= 20, f"{path} docstring has {len(doc.splitlines())} lines (at most 20)"
    assert not WORK_LOG.search(doc), f"{path} docstring reads as a work log"


def test_docs_pages_cited_by_the_code_exist() -> None:
    """Every ``docs/<page>.md`` the package, scripts or tests point a reader to is in the repository."""
    missing = set()
    for path in [*PKG.rglob("*.py"), *(ROOT / "scripts").glob("*.py"), *(ROOT / "tests").glob("*.py")]:
        for page in re.findall(r"\bdocs/([A-Za-z0-9_]+\.md)\b", path.read_text(encoding="utf-8")):
            if not (ROOT / "docs" / page).is_file():
                missing.add(f"{path.relative_to(ROOT)}: docs/{page}")
    assert not missing, sorted(missing)


def test_benchmarks_generated_part_is_what_the_script_rewrites() -> None:
    text = (ROOT / "BENCHMARKS.md").read_text(encoding="utf-8")
    assert text.count(NOTES_MARKER) == 1
    generated = text.split(NOTES_MARKER, 1)[0]
    assert generated.startswith("# Benchmarks\n")
    assert re.search(r"^- command: `[^`]*scripts/benchmark\.py[^`]*`$", generated, flags=re.M)
    assert "| configuration |" in generated  # at least one measured table


@pytest.mark.parametrize("path", _docs(), ids=lambda p: p.name)
def test_relative_links_resolve(path: Path) -> None:
    text = path.read_text(encoding="utf-8")
    targets = re.findall(r"\]\(([^)\s]+)\)", text)
    missing = [t for t in targets if not re.match(r"[a-z]+:", t)
               and not (path.parent / t.split("#", 1)[0]).exists()]
    assert not missing, f"{path.name} links to missing files: {missing}"


def test_spec_citations_resolve() -> None:
    """Every "SPEC §N" and "SPEC_obstacles X" in the package names a section of docs/spec.md or
    docs/spec_obstacles.md, and docs/model.md points to both."""
    spec = (ROOT / "docs" / "spec.md").read_text(encoding="utf-8")
    spec_o = (ROOT / "docs" / "spec_obstacles.md").read_text(encoding="utf-8")
    sections = set(re.findall(r"^## (\d+)\. ", spec, flags=re.M))
    sections_o = set(re.findall(r"^#{2,3} ([A-D](?:\.\d+)?)[. ]", spec_o, flags=re.M))
    code = "\n".join(p.read_text(encoding="utf-8") for p in PKG.rglob("*.py"))
    cited = set(re.findall(r"SPEC §(\d+)", code)) | {n for a, b in re.findall(r"SPEC §(\d+)-(\d+)", code)
                                                     for n in map(str, range(int(a), int(b) + 1))}
    cited_o = set(re.findall(r"SPEC_obstacles ([A-D](?:\.\d+)?)\b", code))
    assert cited and cited <= sections, f"SPEC sections cited but not in docs/spec.md: {cited - sections}"
    assert cited_o and cited_o <= sections_o, f"not in docs/spec_obstacles.md: {cited_o - sections_o}"
    model = (ROOT / "docs" / "model.md").read_text(encoding="utf-8")
    assert "(spec.md)" in model and "(spec_obstacles.md)" in model
