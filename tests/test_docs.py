"""The README, docs/, studies/ and the benchmarks' results: every relative link resolves, and no internal work-item
numbers leak into the README, docs/ or the code."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

# [text](target) and ![alt](target), with an optional "title"; the text may hold nested [..] (badges).
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.M | re.S)
INLINE_CODE = re.compile(r"`[^`\n]*`")
WORK_ITEM = re.compile(r"\bissue \d+|#\d+\b|\btask \d+", re.I)


def prose(text: str) -> str:
    """The markdown without code blocks and inline code (a link shown as code is not a link)."""
    return INLINE_CODE.sub("", FENCE.sub("", text))


def links(text: str) -> list[str]:
    return LINK.findall(prose(text))


def broken_links(path: Path) -> list[str]:
    """Relative link targets of ``path`` that name no existing file (``#anchor`` parts stripped)."""
    bad = []
    for target in links(path.read_text(encoding="utf-8")):
        if re.match(r"(?i)^(https?:|mailto:)", target) or target.startswith("#"):
            continue
        file = target.split("#", 1)[0].split("?", 1)[0]
        if not (path.parent / file).exists():
            bad.append(target)
    return bad


def test_docs_exist():
    assert (ROOT / "docs").is_dir() and len(DOCS) > 1
    assert (ROOT / "LICENSE").is_file() and (ROOT / "CITATION.cff").is_file()


@pytest.mark.parametrize("path", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(path: Path):
    assert broken_links(path) == [], f"{path.relative_to(ROOT)}: links to missing files"


# the studies' pages (studies/README.md, each study's README.md) and the results files they hold or link
STUDY_PAGES = sorted((ROOT / "studies").rglob("*.md")) + sorted((ROOT / "benchmarks" / "results").glob("*.md"))


def test_study_pages_exist():
    assert (ROOT / "studies" / "README.md").is_file()
    studies = sorted(p for p in (ROOT / "studies").iterdir() if p.is_dir() and not p.name.startswith((".", "_")))
    missing = [p.name for p in studies if not (p / "README.md").is_file()]
    assert studies and missing == [], f"studies without a README.md: {missing}"


@pytest.mark.parametrize("path", STUDY_PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_study_and_benchmark_links_resolve(path: Path):
    assert broken_links(path) == [], f"{path.relative_to(ROOT)}: links to missing files"


def test_no_work_item_numbers_in_code_or_tests():
    """Tests and code say what they check, not which ticket asked for it."""
    files = sorted((ROOT / "tests").glob("*.py")) + sorted((ROOT / "ssm_ms").rglob("*.py"))
    files += sorted((ROOT / "datamodules").glob("*.py")) + sorted((ROOT / "benchmarks").glob("*.py"))
    files += sorted((ROOT / "studies").glob("*/*.py"))
    hits = {
        str(p.relative_to(ROOT)): WORK_ITEM.findall(p.read_text(encoding="utf-8"))
        for p in files
        if p.name != "test_docs.py"
    }
    assert {k: v for k, v in hits.items() if v} == {}


@pytest.mark.parametrize("path", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_internal_work_item_numbers(path: Path):
    hits = [m.group(0) for m in WORK_ITEM.finditer(path.read_text(encoding="utf-8"))]
    assert hits == [], f"{path.relative_to(ROOT)}: internal work-item references {hits}"


def test_every_docs_page_is_in_the_readme_index():
    linked = {
        Path(t.split("#", 1)[0]).name
        for t in links((ROOT / "README.md").read_text(encoding="utf-8"))
        if t.startswith("docs/")
    }
    missing = sorted(p.name for p in DOCS[1:] if p.name not in linked)
    assert missing == [], f"docs pages the README does not link to: {missing}"


def test_the_checker_sees_a_broken_link(tmp_path: Path):
    page = tmp_path / "page.md"
    (tmp_path / "there.md").write_text("# there\n")
    page.write_text(
        "[ok](there.md#a) [web](https://example.org/x.md) [mail](mailto:a@b.c) [anchor](#top)\n"
        "![img](missing.png) [gone](nowhere.md#x)\n"
        "```\n[in code](not-a-link.md)\n```\n"
    )
    assert broken_links(page) == ["missing.png", "nowhere.md#x"]
    assert WORK_ITEM.search("see issue 12") and WORK_ITEM.search("(#13)") and WORK_ITEM.search("Task 4")
    assert not WORK_ITEM.search("C# 10 and colour #ff0000 and a 3-issue list")
