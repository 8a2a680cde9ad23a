"""The user docs and the lab's index hold together: every module named, the README short and
starting with the two commands, no lab notes in user text, no dead links, every report indexed."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ROOMS = ("common", "capture", "reconstruct", "appearance", "export", "cli", "synth", "paper", "damcap")
LAB_NOTE = re.compile(r"issue [0-9]+|throwaway|session [0-9]+|20[0-9]{2}-[0-9]{2}-[0-9]{2}", re.I)
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
USER_DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def library_modules() -> list[str]:
    """Every module of the library as docs/architecture.md names it: `room/x.py`, a package as `room/pkg/`."""
    out = []
    for room in ROOMS:
        for f in sorted((REPO / room).rglob("*.py")):
            rel = f.relative_to(REPO)
            out.append(f"{rel.parent.as_posix()}/" if f.name == "__init__.py" else rel.as_posix())
    return out


def test_every_library_module_is_in_architecture():
    text = (REPO / "docs" / "architecture.md").read_text()
    modules = library_modules()
    assert len(modules) > 100, modules  # the walk found the library
    missing = [m for m in modules if f"`{m}`" not in text]
    assert not missing, f"docs/architecture.md does not name: {missing}"


def test_readme_is_short_and_starts_with_the_two_commands():
    lines = (REPO / "README.md").read_text().splitlines()
    assert len(lines) <= 150, f"README.md has {len(lines)} lines, at most 150"
    first_block = lines[lines.index("```") + 1:]
    first_block = first_block[:first_block.index("```")]
    assert [line.split()[:2] for line in first_block] == [["make", "demo"], ["make", "test"]], first_block
    before = [line for line in lines[:lines.index("```")] if line.strip()]
    assert len(before) == 1 and before[0].startswith("# "), before  # only the title comes first


@pytest.mark.parametrize("path", USER_DOCS, ids=lambda p: p.relative_to(REPO).as_posix())
def test_user_docs_carry_no_lab_notes(path):
    hits = [f"{i}: {line}" for i, line in enumerate(path.read_text().splitlines(), 1) if LAB_NOTE.search(line)]
    assert not hits, f"{path.name}: dates, issue numbers or side-run notes belong in bench/: {hits}"


def test_lab_note_pattern_catches_what_it_should():
    assert LAB_NOTE.search("measured 2026-11-27") and LAB_NOTE.search("Issue 29 asks")
    assert LAB_NOTE.search("a Throwaway script") and LAB_NOTE.search("in session 24")
    assert not LAB_NOTE.search("v10 + 300 steps, 0.306 novel view")


@pytest.mark.parametrize("path", [*USER_DOCS, REPO / "bench" / "README.md"], ids=lambda p: p.relative_to(REPO).as_posix())
def test_relative_links_point_to_files(path):
    dead = []
    for target in LINK.findall(path.read_text()):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue  # a URL or an anchor in the same page
        file = target.split("#", 1)[0]
        if not (path.parent / file).exists():
            dead.append(target)
    assert not dead, f"{path.relative_to(REPO)}: links to missing files: {dead}"


def test_every_bench_report_is_indexed():
    index = (REPO / "bench" / "README.md").read_text()
    linked = {(REPO / "bench" / t.split("#", 1)[0]).resolve() for t in LINK.findall(index)}
    reports = [p for p in sorted((REPO / "bench").glob("*.md")) if p.name != "README.md"]
    assert len(reports) >= 10, reports
    missing = [p.name for p in reports if p.resolve() not in linked]
    assert not missing, f"bench/README.md does not link these reports: {missing}"


def test_bench_readme_names_every_study_module():
    index = (REPO / "bench" / "README.md").read_text()
    helpers = {"__init__", "common", "view_grid"}
    studies = [p.stem for p in sorted((REPO / "bench").glob("*.py")) if p.stem not in helpers]
    missing = [s for s in studies if f"`{s}`" not in index]
    assert not missing, f"bench/README.md does not list these studies: {missing}"
