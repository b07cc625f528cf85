"""The docs in docs/ stand alone: every pointer from the code resolves, nothing points outside.

A source comment (or docstring) that names ``docs/<file>.md`` needs the file; one that names a
section needs its heading: ``docs/model.md sec. 2`` a heading ``## 2. ...``,
``docs/model.md 'traps'`` and ``docs/real-box.md, safety`` a heading holding that word. The
parameter table of docs/model.md lists every field of ``Parameters`` with its value and source.
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import fields
from pathlib import Path

import pytest

from hvac_mpc.models.parameters import Parameters

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
POINTER = re.compile(r"docs/([\w-]+\.md)(?: sec\. (\d+)|,? '([^']+)'|, ([a-z][a-z-]*))?")
HEADING = re.compile(r"^(#+)\s+(.*?)\s*$", re.M)
OUTSIDE = re.compile(r"\.\./shared|shared[/]|design\.md|thesis\.md|research[/]|/work[/]")
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _source_files() -> list[Path]:
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    folders = ["hvac_mpc", "tests", *cfg["tool"]["setuptools"]["package-dir"].values()]
    files = [p for folder in folders for p in (ROOT / folder).rglob("*.py")]
    files += [p for folder in folders for p in (ROOT / folder).rglob("README.md")]
    return sorted(p for p in files if p.name != "test_docs.py")


def _pointers() -> list[tuple[str, str, str | None, str | None]]:
    """(where, file, section number, section word) of every docs pointer in the sources."""
    found = []
    for path in _source_files():
        for i, line in enumerate(path.read_text().splitlines(), 1):
            for m in POINTER.finditer(line):
                word = m.group(3) or m.group(4)
                found.append((f"{path.relative_to(ROOT)}:{i}", m.group(1), m.group(2), word))
    return found


def _headings(name: str) -> list[str]:
    return [m.group(2) for m in HEADING.finditer((DOCS / name).read_text())]


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.lower()).replace(" ", "-")


def test_the_sources_point_into_the_docs():
    pointers = _pointers()
    files = {f for _, f, _, _ in pointers}
    # the code's pointers name these files and sections; losing them would lose the pointers
    assert {"model.md", "architecture.md", "real-box.md", "identification.md"} <= files
    assert {s for _, f, s, _ in pointers if f == "model.md" and s} >= {"1", "2", "3", "4", "5"}
    assert ("model.md", "traps") in {(f, w) for _, f, _, w in pointers}


def test_every_docs_pointer_in_the_sources_resolves():
    missing = []
    for where, name, number, word in _pointers():
        if not (DOCS / name).is_file():
            missing.append(f"{where}: docs/{name} does not exist")
            continue
        heads = _headings(name)
        if number and not any(re.match(rf"{number}\.\s", h) for h in heads):
            missing.append(f"{where}: docs/{name} has no heading '## {number}. ...'")
        if word and not any(word.lower() in h.lower() for h in heads):
            missing.append(f"{where}: docs/{name} has no heading with {word!r}")
    assert missing == []


def test_docs_link_nothing_outside_the_repository():
    problems = []
    pages = sorted(DOCS.glob("*.md"))
    assert {p.name for p in pages} >= {"README.md", "architecture.md", "model.md", "extending.md", "real-box.md",
                                       "identification.md"}
    for page in pages:
        text = page.read_text()
        for i, line in enumerate(text.splitlines(), 1):
            if OUTSIDE.search(line):
                problems.append(f"docs/{page.name}:{i}: {line.strip()}")
        for target in LINK.findall(text):
            path, _, anchor = target.partition("#")
            if target.startswith(("http:", "https:", "file:")):
                problems.append(f"docs/{page.name}: external link {target}")
                continue
            doc = (page.parent / path).resolve() if path else page
            if ROOT not in doc.parents or not doc.exists():
                problems.append(f"docs/{page.name}: link {target} leaves the repository or does not exist")
            elif anchor and doc.suffix == ".md" and anchor not in {_slug(h) for h in _headings(doc.name)}:
                problems.append(f"docs/{page.name}: link {target} names no heading")
    assert problems == []


def _parameter_rows() -> dict[str, list[str]]:
    rows = {}
    for line in (DOCS / "model.md").read_text().splitlines():
        m = re.match(r"\| `(\w+)` \|(.*)\|\s*$", line)
        if m:
            rows[m.group(1)] = [c.strip() for c in m.group(2).split("|")]
    return rows


@pytest.mark.parametrize("field", [f.name for f in fields(Parameters)])
def test_model_doc_lists_each_parameter_with_value_and_source(field):
    rows = _parameter_rows()
    assert field in rows, f"docs/model.md has no parameter row for {field}"
    unit, value, source = rows[field][:3]
    default = getattr(Parameters(), field)
    shown = f"{len(default)} rows" if isinstance(default, tuple) else f"{default:g}"
    assert value == shown, f"{field}: docs/model.md says {value}, Parameters says {shown}"
    assert source == Parameters.source(field).replace("|", "/")
    assert unit
