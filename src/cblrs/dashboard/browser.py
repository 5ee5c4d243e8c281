"""A headless Chromium for the dashboard's tests and benchmark (Playwright, Debian's browser).

The browser is Debian's ``chromium`` package (``apt-get install chromium``; nothing is
downloaded at run time — never ``playwright install``), driven by Playwright for Python
(``pip install playwright``, in ``cblrs[dev]``), each run with a fresh profile folder.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from cblrs.errors import CblrsError

CHROMIUM_ARGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
)


class BrowserUnavailable(CblrsError):
    """No headless browser here (the reason says what to install)."""


def find_chromium() -> Path | None:
    """Debian's Chromium (``$CBLRS_CHROMIUM``, ``/usr/bin/chromium`` or on the PATH)."""
    for candidate in (os.environ.get("CBLRS_CHROMIUM"), "/usr/bin/chromium",
                      shutil.which("chromium")):
        if candidate and Path(candidate).is_file() and os.access(candidate, os.X_OK):
            return Path(candidate)
    return None


def browser_problem() -> str | None:
    """Why a browser cannot be started here, or None when it can."""
    if find_chromium() is None:
        return ("Debian's chromium is not installed (apt-get install -y chromium; .ci/run "
                "installs it)")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "Playwright for Python is not installed (pip install -e '.[dev]')"
    return None


@contextmanager
def chromium_page(
    viewport: tuple[int, int] = (1400, 820), profile: Path | None = None
) -> Iterator[Any]:
    """A page of a fresh headless Chromium (closed on exit).

    Args:
        viewport: width, height in CSS pixels.
        profile: the user-data folder (default: a new temporary one, removed afterwards).

    Raises:
        BrowserUnavailable: Chromium or Playwright is missing (the reason says which).
    """
    problem = browser_problem()
    if problem is not None:
        raise BrowserUnavailable(problem)
    # optional: only the browser benchmark and tests drive Chromium
    from playwright.sync_api import sync_playwright

    chromium = find_chromium()
    assert chromium is not None
    temporary = None
    if profile is None:
        temporary = tempfile.mkdtemp(prefix="cblrs-chromium-")
        profile = Path(temporary)
    try:
        with sync_playwright() as playwright:
            context = playwright.chromium.launch_persistent_context(
                str(profile), executable_path=str(chromium), headless=True,
                args=list(CHROMIUM_ARGS),
                viewport={"width": viewport[0], "height": viewport[1]},
            )
            try:
                page = context.pages[0] if context.pages else context.new_page()
                yield page
            finally:
                context.close()
    finally:
        if temporary is not None:
            shutil.rmtree(temporary, ignore_errors=True)
