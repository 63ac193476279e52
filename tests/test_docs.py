"""The README is a user guide that fits on a few screens, and every link in it and in docs/
leads somewhere: a moved section that a link still names is a broken promise to a reader."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README_MAX_LINES = 400
LINK = re.compile(r"\]\(([^)\s]+)\)")


def slug(heading: str) -> str:
    """GitHub's anchor for a Markdown heading: lower case, punctuation dropped, spaces to '-'."""
    text = re.sub(r"[`*]", "", heading.strip().lower())
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    out, seen, fenced = set(), {}, False
    for line in path.read_text().splitlines():
        if line.startswith("```"):
            fenced = not fenced
        if fenced or not line.startswith("#"):
            continue
        base = slug(line.lstrip("#"))
        n = seen.get(base, 0)
        out.add(base if n == 0 else f"{base}-{n}")
        seen[base] = n + 1
    return out


def doc_files() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def test_readme_fits_its_budget():
    lines = (ROOT / "README.md").read_text().count("\n")
    assert lines <= README_MAX_LINES, f"README.md has {lines} lines; move detail to docs/"


def test_no_readme_line_is_over_200_characters():
    long = [n for n, line in enumerate((ROOT / "README.md").read_text().splitlines(), 1) if len(line) > 200]
    assert not long, f"README.md lines over 200 characters: {long}; shorten or move the detail to docs/"


@pytest.mark.parametrize("doc", doc_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_reaches_a_file_and_its_heading(doc):
    broken = []
    for target in LINK.findall(doc.read_text()):
        if re.match(r"[a-z]+:", target):  # http(s):, mailto:
            continue
        file, _, anchor = target.partition("#")
        dest = (doc.parent / file).resolve() if file else doc
        if not dest.exists():
            broken.append(f"{target} (no such file)")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{target} (no heading #{anchor} in {dest.relative_to(ROOT)})")
    assert not broken, f"{doc.relative_to(ROOT)}: " + "; ".join(broken)


def test_slug_matches_githubs_anchors():
    assert slug("Disk per run and per preset") == "disk-per-run-and-per-preset"
    assert slug("The pilot runs: `python studies/pilot_task.py`") == "the-pilot-runs-python-studiespilot_taskpy"
    assert slug("Scale-out: a cluster of several machines") == "scale-out-a-cluster-of-several-machines"
    assert slug("Testing trained cars (the protocol)") == "testing-trained-cars-the-protocol"


def test_every_row_of_the_studies_tables_has_its_headers_cells():
    """docs/studies.md's tables (scripts, studies): a row pasted into another row (it happened
    twice, when an insert matched a link inside a cell) leaves one row with too many cells."""
    def cells(line: str) -> int:
        return len(re.sub(r"`[^`]*`", "code", line).strip().strip("|").split("|"))

    width = None
    for number, line in enumerate((ROOT / "docs" / "studies.md").read_text().splitlines(), 1):
        if not line.startswith("|"):
            width = None
        elif width is None:
            width = cells(line)  # the header
        else:
            assert cells(line) == width, f"docs/studies.md:{number} has {cells(line)} cells, its header {width}"
