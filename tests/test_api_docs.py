"""The API reference (docs/api/, pdoc) builds from the docstrings without a warning, and the
checked-in copy lists every library module."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def make_api_docs():
    """scripts/make_api_docs.py as a module, loaded when a test runs rather than when the
    file is collected: it imports pdoc (half a CPU-second), and every pytest-xdist worker
    collects this file."""
    spec = importlib.util.spec_from_file_location(
        "make_api_docs", ROOT / "scripts" / "make_api_docs.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules["make_api_docs"] = module
    spec.loader.exec_module(module)
    return module


def test_the_reference_builds_without_warnings(make_api_docs, tmp_path):
    assert make_api_docs.build(tmp_path) == []
    pages = {path.relative_to(tmp_path).as_posix() for path in tmp_path.rglob("*.html")}
    for module in make_api_docs.library_modules():
        assert module.replace(".", "/") + ".html" in pages, module
    tracker = (tmp_path / "cblrs" / "matching" / "fusion" / "tracker.html").read_text()
    assert "FusionTracker" in tracker and "Multi-camera fusion tracker" in tracker


def test_the_checked_in_reference_has_every_module(make_api_docs):
    checked_in = ROOT / "docs" / "api"
    for module in make_api_docs.library_modules():
        assert (checked_in / (module.replace(".", "/") + ".html")).is_file(), (
            f"docs/api lacks {module}: run python scripts/make_api_docs.py"
        )
