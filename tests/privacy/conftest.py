"""Fixtures for the pseudo-coordinate tests: the documentation's example site
(docs/sites.md, from tests/site)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

_spec = importlib.util.spec_from_file_location(
    "site_fixtures", Path(__file__).resolve().parents[1] / "site" / "conftest.py"
)
assert _spec is not None and _spec.loader is not None
_site_fixtures = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_site_fixtures)

example_site = _site_fixtures.example_site
