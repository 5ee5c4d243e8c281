"""Copy the generated tables of docs/results/ into README.md and the pages under docs/.

    python scripts/fill_docs.py [--check]

A page holds a generated table between ``<!-- BEGIN generated: NAME -->`` and
``<!-- END generated: NAME -->``; this replaces what lies between them with
``docs/results/NAME.md`` (written by the ``cblrs bench`` and ``cblrs experiment`` commands that
``scripts/make_docs.sh`` runs, which calls this at its end). ``--check`` changes nothing and exits
1 naming the pages whose tables differ from their files (``tests/docs/test_docs_site.py``).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results"
MARKERS = re.compile(r"<!-- BEGIN generated: (\S+) -->.*?<!-- END generated: \1 -->", re.S)


def pages(root: Path = ROOT) -> list[Path]:
    """README.md and every markdown page directly under docs/."""
    return [root / "README.md", *sorted((root / "docs").glob("*.md"))]


def fill(text: str, results: Path = RESULTS) -> str:
    """``text`` with every generated block replaced by its results file."""

    def table(match: re.Match[str]) -> str:
        name = match.group(1)
        source = results / f"{name}.md"
        body = (source.read_text().strip() if source.exists()
                else f"(run scripts/make_docs.sh: {name})")
        return f"<!-- BEGIN generated: {name} -->\n{body}\n<!-- END generated: {name} -->"

    return MARKERS.sub(table, text)


def main(argv: list[str]) -> int:
    check = argv == ["--check"]
    if argv and not check:
        print("usage: python scripts/fill_docs.py [--check]", file=sys.stderr)
        return 2
    stale = []
    for page in pages():
        text = page.read_text()
        filled = fill(text)
        if filled != text:
            stale.append(page.relative_to(ROOT).as_posix())
            if not check:
                page.write_text(filled)
    if check and stale:
        print(f"generated tables differ from docs/results in {', '.join(stale)}: "
              "run python scripts/fill_docs.py", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
