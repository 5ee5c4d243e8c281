"""``python -m cblrs``: the ``cblrs`` command, for a checkout run without installing it.

Useful with ``PYTHONPATH=src`` (e.g. from a git worktree), where the installed console script
would run another copy of the package.
"""

import sys

from cblrs.cli.main import main

if __name__ == "__main__":
    sys.exit(main())
