"""Every test a page names as its evidence exists (the threat model, "what cblrs guarantees",
the fault tables): a renamed or deleted test must not leave a claim without its test."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
NAMED = re.compile(r"`(test_[A-Za-z0-9_]+)(?![A-Za-z0-9_]|\.py)")  # a test, not a file
DEFINED = re.compile(r"^\s*(?:async\s+)?def (test_[A-Za-z0-9_]+)", re.M)


def test_every_test_a_page_names_exists():
    defined = {name for path in (ROOT / "tests").rglob("*.py")
               for name in DEFINED.findall(path.read_text(encoding="utf-8"))}
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    missing = {f"{page.relative_to(ROOT)}: {name}" for page in pages
               for name in NAMED.findall(page.read_text(encoding="utf-8"))
               if name not in defined}
    assert len(defined) > 500  # the scan found the suite
    assert not missing, sorted(missing)
