"""The docs' links resolve: every relative markdown link of README.md and docs/**/*.md names an
existing file, and every ``docs/PAGE.md`` path named in the code, scripts and configs exists."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# ``[text](target)`` outside fenced code; a target with a scheme (https:, mailto:) is not a file
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"```.*?```", re.S)
DOC_PATH = re.compile(r"\bdocs/[\w./-]*\w\.md\b")
# made at build time by the mkdocs hook scripts/mkdocs_api.py, so absent from the tree
GENERATED = ROOT / "docs" / "api"
SOURCES = (
    "envs",
    "trackers",
    "training",
    "tests",
    "experiments",
    "benchmarks",
    "scripts",
    "configs",
)


def markdown_files() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def broken_links(page: Path) -> list[str]:
    """The relative link targets of ``page`` (anchors dropped) that name no file."""
    broken = []
    for target in LINK.findall(FENCE.sub("", page.read_text())):
        path = target.partition("#")[0]
        if not path or re.match(r"[a-z]+:", path):
            continue
        dest = (page.parent / path).resolve()
        if not dest.exists() and dest.parent != GENERATED:
            broken.append(target)
    return broken


def test_every_relative_markdown_link_resolves():
    pages = markdown_files()
    assert ROOT / "docs" / "notes" / "checkpoints-history.md" in pages
    broken = {str(p.relative_to(ROOT)): b for p in pages if (b := broken_links(p))}
    assert not broken, broken


def test_every_docs_path_named_in_the_sources_exists():
    named: dict[str, set[str]] = {}
    for folder in SOURCES:
        for path in sorted((ROOT / folder).rglob("*")):
            if path.suffix not in {".py", ".sh", ".yaml", ".yml", ".md"} or not path.is_file():
                continue
            for doc in DOC_PATH.findall(path.read_text(errors="replace")):
                if not Path(doc).stem.isupper():  # a placeholder, e.g. docs/PAGE.md
                    named.setdefault(doc, set()).add(str(path.relative_to(ROOT)))
    assert "docs/design.md" in named  # the pattern finds the references there are
    missing = {
        doc: sorted(where)
        for doc, where in named.items()
        if not (ROOT / doc).is_file() and (ROOT / doc).parent != GENERATED
    }
    assert not missing, missing


def test_the_checker_sees_a_broken_link(tmp_path):
    page = tmp_path / "page.md"
    page.write_text(
        "[ok](page.md) [gone](missing.md#x) [web](https://example.org)\n"
        "```\n[in code](also-missing.md)\n```\n"
    )
    assert broken_links(page) == ["missing.md#x"]
