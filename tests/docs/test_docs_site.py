"""The documentation: README.md is a landing page, the pages under docs/ build into the MkDocs
site without a warning, every relative link (and anchor) of README.md and the pages resolves, and
the generated tables are what their results files say."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
spec = importlib.util.spec_from_file_location("fill_docs", ROOT / "scripts" / "fill_docs.py")
assert spec is not None and spec.loader is not None
fill_docs = importlib.util.module_from_spec(spec)
sys.modules["fill_docs"] = fill_docs
spec.loader.exec_module(fill_docs)

# [text](target "title") and ![alt](target); the target up to the first blank or ")".
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
HTML_LINK = re.compile(r"<(?:a|img)\b[^>]*\b(?:href|src)=\"([^\"]+)\"", re.I)
FENCE = re.compile(r"^(```|~~~)")


def markdown_files() -> list[Path]:
    """README.md and every markdown page under docs/ (not the HTML API reference)."""
    pages = sorted(path for path in DOCS.rglob("*.md") if "api" not in path.relative_to(DOCS).parts)
    return [ROOT / "README.md", *pages]


def prose_lines(text: str) -> list[str]:
    """The lines outside fenced code blocks, with inline code spans blanked."""
    lines, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line.lstrip()):
            fenced = not fenced
            continue
        if not fenced:
            lines.append(re.sub(r"`[^`]*`", "``", line))
    return lines


def slug(heading: str) -> str:
    """GitHub's anchor for a heading (also Python-Markdown's for the headings used here)."""
    text = re.sub(r"`([^`]*)`", r"\1", heading.strip())
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", text)  # a link's text stays
    text = "".join(c for c in unicodedata.normalize("NFC", text.lower())
                   if c.isalnum() or c in " -_")
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading anchor of a markdown page (a repeated heading gets -1, -2, ...)."""
    found: set[str] = set()
    seen: dict[str, int] = {}
    fenced = False
    for line in path.read_text().splitlines():
        if FENCE.match(line.lstrip()):
            fenced = not fenced
            continue
        match = re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if fenced or not match:
            continue
        base = slug(match.group(1))
        count = seen.get(base, 0)
        seen[base] = count + 1
        found.add(base if count == 0 else f"{base}-{count}")
    return found


def relative_links(path: Path) -> list[str]:
    """The links of a page that point inside the repository."""
    links = []
    for line in prose_lines(path.read_text()):
        for target in LINK.findall(line) + HTML_LINK.findall(line):
            if not re.match(r"[a-z][a-z0-9+.-]*:", target, re.I):  # http:, mailto:, ...
                links.append(target)
    return links


def broken_links(path: Path) -> list[str]:
    """The relative links of a page whose file, or whose heading, does not exist."""
    broken = []
    for target in relative_links(path):
        file_part, _, anchor = target.partition("#")
        resolved = (path.parent / file_part).resolve() if file_part else path
        if not resolved.exists():
            broken.append(f"{target}: no file {resolved}")
        elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
            broken.append(f"{target}: no heading #{anchor} in {resolved.name}")
    return broken


def test_every_relative_link_and_anchor_resolves():
    pages = markdown_files()
    assert len(pages) > 10, pages  # README and the pages under docs/ were found
    checked = sum(len(relative_links(page)) for page in pages)
    assert checked > 50  # the links were found: the README alone links every page
    problems = {page.relative_to(ROOT).as_posix(): broken_links(page) for page in pages}
    assert {page: found for page, found in problems.items() if found} == {}


def test_the_link_check_catches_a_broken_link_and_a_missing_anchor(tmp_path):
    (tmp_path / "other.md").write_text("# Title\n\n## What `cblrs` guarantees\n")
    page = tmp_path / "page.md"
    page.write_text(
        "[ok](other.md#what-cblrs-guarantees) [ok](#here) ![ok](other.md)\n"
        "[gone](missing.md) [anchor](other.md#nowhere) [web](https://example.org/x)\n"
        "```bash\n[in code](nowhere.md)\n```\n`[inline](nowhere.md)`\n\n## Here\n"
    )
    assert broken_links(page) == [
        f"missing.md: no file {tmp_path / 'missing.md'}",
        "other.md#nowhere: no heading #nowhere in other.md",
    ]


def test_the_site_builds_without_a_warning(tmp_path):
    if importlib.util.find_spec("mkdocs") is None:
        pytest.skip("mkdocs is not installed (pip install -e \".[dev]\")")
    # mkdocs.yml sets strict and turns missing pages, files and anchors into warnings.
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file",
         str(ROOT / "mkdocs.yml"), "--site-dir", str(tmp_path / "site")],
        capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr + result.stdout
    assert "WARNING" not in result.stderr
    site = tmp_path / "site"
    for page in ("index.html", "sites/index.html", "security/index.html", "api/cblrs.html",
                 "figures/dashboard_live.png", "results/RESULTS/index.html"):
        assert (site / page).is_file(), page
    assert "market square" in (site / "sites" / "index.html").read_text()


def test_every_page_is_in_the_site_navigation():
    config = (ROOT / "mkdocs.yml").read_text()
    listed = set(re.findall(r":\s*([\w/.-]+\.md)\s*$", config, re.M))
    pages = {path.relative_to(DOCS).as_posix() for path in DOCS.glob("*.md")}
    assert pages <= listed, sorted(pages - listed)
    assert all((DOCS / page).is_file() for page in listed), sorted(listed)


def test_the_readme_is_a_landing_page():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 300
    quick = re.search(r"^## Quick start\n+```bash\n(.*?)```", text, re.S | re.M)
    assert quick, "README.md has no Quick start block"
    commands = [line.split("#")[0].strip() for line in quick.group(1).splitlines()]
    # CI (.ci/run) runs the second command; the first installs and runs the demo.
    assert [command for command in commands if command] == [
        'pip install -e ".[live]" && cblrs demo', "bash scripts/test.sh"]
    assert "bash scripts/test.sh" in (ROOT / ".ci" / "run").read_text()
    linked = {target.partition("#")[0] for target in relative_links(ROOT / "README.md")}
    for page in ("security", "privacy", "tracking", "operate", "alerts", "speed", "planes"):
        assert f"docs/{page}.md" in linked, page


def test_generated_tables_are_their_results_files():
    names = []
    for page in fill_docs.pages():
        text = page.read_text()
        names += re.findall(r"<!-- BEGIN generated: (\S+) -->", text)
        assert fill_docs.fill(text) == text, (
            f"{page.name}: a generated table differs from docs/results; "
            "run python scripts/fill_docs.py")
    assert len(names) > 10  # the README and the pages do hold generated tables
    missing = [name for name in names if not (fill_docs.RESULTS / f"{name}.md").is_file()]
    assert missing == []
