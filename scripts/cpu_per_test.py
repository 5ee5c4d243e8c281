"""CPU seconds per test and per test file: a pytest plugin, and the table of what it wrote.

    CBLRS_TEST_CPU=/tmp/cpu PYTHONPATH=$PWD/src:$PWD/scripts \\
        python -m pytest -p cpu_per_test -n 4 --dist loadfile
    python scripts/cpu_per_test.py /tmp/cpu [COUNT]

Each pytest process (every xdist worker) appends one line per test to its own file in
``$CBLRS_TEST_CPU``: the test's id, the CPU seconds (user + system) of the worker and of the
child processes it waited for during the test's setup, call and teardown, and the wall seconds.
A test's module fixtures count in the test that first needs them, and their teardown in the
file's last test. Processes nobody waited for (a process killed and never reaped, a matcher's
tracker fork server) are not counted: ``scripts/tree_cpu.py`` counts the whole tree.

The second form prints the COUNT (default 40) files with the most CPU seconds, and the totals.
"""

from __future__ import annotations

import os
import resource
import sys
import time
from collections import defaultdict
from pathlib import Path

import pytest

ENVIRONMENT = "CBLRS_TEST_CPU"
_files: dict[str, object] = {}


def _cpu_seconds() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """Time one test's setup, call and teardown (pytest calls this once per test)."""
    folder = os.environ.get(ENVIRONMENT)
    if not folder:
        yield
        return
    cpu, wall = _cpu_seconds(), time.monotonic()
    yield
    if "out" not in _files:
        Path(folder).mkdir(parents=True, exist_ok=True)
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        _files["out"] = open(Path(folder) / f"{worker}-{os.getpid()}.tsv", "a")
    out = _files["out"]
    out.write(f"{item.nodeid}\t{_cpu_seconds() - cpu:.2f}\t{time.monotonic() - wall:.2f}\n")
    out.flush()


def file_totals(folder: Path) -> dict[str, tuple[float, float, int]]:
    """``tests/...py`` -> (CPU seconds, wall seconds, tests), from the files in ``folder``."""
    totals: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0, 0])
    for path in sorted(folder.glob("*.tsv")):
        for line in path.read_text().splitlines():
            test, cpu, wall = line.rsplit("\t", 2)
            total = totals[test.split("::", 1)[0]]
            total[0] += float(cpu)
            total[1] += float(wall)
            total[2] += 1
    return {name: (cpu, wall, int(count)) for name, (cpu, wall, count) in totals.items()}


def main(argv: list[str]) -> int:
    """Print the table of the folder ``argv[0]``; 2 on a wrong command line."""
    if len(argv) not in (1, 2) or (len(argv) == 2 and not argv[1].isdigit()):
        print("usage: python scripts/cpu_per_test.py FOLDER [COUNT]", file=sys.stderr)
        return 2
    totals = file_totals(Path(argv[0]))
    if not totals:
        print(
            f"no per-test figures in {argv[0]} (run pytest with -p cpu_per_test and "
            f"{ENVIRONMENT}={argv[0]} first)",
            file=sys.stderr,
        )
        return 1
    count = int(argv[1]) if len(argv) == 2 else 40
    ranked = sorted(totals.items(), key=lambda item: -item[1][0])
    print(f"{'CPU s':>8} {'wall s':>8} {'tests':>6}  file")
    for name, (cpu, wall, tests) in ranked[:count]:
        print(f"{cpu:8.1f} {wall:8.1f} {tests:6d}  {name}")
    cpu = sum(value[0] for value in totals.values())
    tests = sum(value[2] for value in totals.values())
    print(f"{cpu:8.1f} {'':>8} {tests:6d}  all {len(totals)} files")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
