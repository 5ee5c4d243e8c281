"""Seconds per test file from a pytest JUnit XML report, for tests/file_durations.json.

    PYTHONPATH=$PWD/src python -m pytest -n 2 --dist loadfile --junitxml=/tmp/suite.xml
    python scripts/file_durations.py /tmp/suite.xml > tests/file_durations.json

tests/conftest.py starts the longest files first, so that under ``--dist loadfile`` no long
file is left to run alone at the end of the suite (see its ``pytest_collection_modifyitems``).
A file's figure is the sum of its tests' setup, call and teardown times, rounded to 0.1 s.
"""

from __future__ import annotations

import json
import sys
import xml.etree.ElementTree as ElementTree
from collections import defaultdict


def file_seconds(report: str) -> dict[str, float]:
    """``tests/...py`` -> seconds, the longest first."""
    totals: dict[str, float] = defaultdict(float)
    for case in ElementTree.parse(report).iter("testcase"):
        module = case.get("classname", "")
        parts = module.split(".")
        # classname is the dotted module path, plus the class for tests in a class
        while parts and not parts[-1].startswith("test_"):
            parts.pop()
        if not parts:
            continue
        totals["/".join(parts) + ".py"] += float(case.get("time", "0"))
    return {name: round(seconds, 1)
            for name, seconds in sorted(totals.items(), key=lambda item: -item[1])}


def main(argv: list[str]) -> int:
    """Print the JSON table of the report named by ``argv[0]``."""
    if len(argv) != 1:
        print("usage: python scripts/file_durations.py REPORT.xml", file=sys.stderr)
        return 2
    try:
        table = file_seconds(argv[0])
    except (OSError, ElementTree.ParseError) as error:
        print(f"cannot read the JUnit report {argv[0]}: {error}", file=sys.stderr)
        return 1
    print(json.dumps(table, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
