"""Wall and CPU seconds of a command's whole process tree.

    python scripts/tree_cpu.py COMMAND [ARGUMENT ...]

``/usr/bin/time`` counts only the children that their parents waited for: a matcher's tracker
forkserver, a broker a test killed and never reaped, are left out. This runs the command as a
child subreaper (Linux), so that every orphaned descendant is handed to it and reaped here, and
prints ``TREE wall W cpu C (user U sys S) rc R`` on stderr once the command and all of them
have ended; the command's exit code is returned.
"""

from __future__ import annotations

import ctypes
import os
import resource
import subprocess
import sys
import time

PR_SET_CHILD_SUBREAPER = 36


def main(argv: list[str]) -> int:
    """Run ``argv`` and print its tree's figures; its exit code (2 without a command)."""
    if not argv:
        print("usage: python scripts/tree_cpu.py COMMAND [ARGUMENT ...]", file=sys.stderr)
        return 2
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
        print("tree_cpu: this system cannot make a child subreaper (Linux only)", file=sys.stderr)
        return 2
    started = time.monotonic()
    try:
        code = subprocess.Popen(argv).wait()
    except OSError as error:
        print(f"tree_cpu: cannot run {argv[0]}: {error.strerror}", file=sys.stderr)
        return 2
    while True:  # the orphans handed to this process
        try:
            os.wait()
        except ChildProcessError:
            break
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    print(
        f"TREE wall {time.monotonic() - started:.2f} cpu {usage.ru_utime + usage.ru_stime:.2f}"
        f" (user {usage.ru_utime:.2f} sys {usage.ru_stime:.2f}) rc {code}",
        file=sys.stderr,
    )
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
