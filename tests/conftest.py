"""Shared fixtures: the WILDTRACK data folder and small synthetic cameras."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def find_wildtrack() -> Path | None:
    """WILDTRACK from $CBLRS_WILDTRACK or ../shared/data/wildtrack beside the repository."""
    candidates = [os.environ.get("CBLRS_WILDTRACK"), REPO_ROOT.parent / "shared/data/wildtrack"]
    for candidate in candidates:
        if candidate and (Path(candidate) / "calibrations").is_dir():
            return Path(candidate)
    return None


@pytest.fixture(scope="session")
def wildtrack_root() -> Path:
    root = find_wildtrack()
    if root is None:
        pytest.skip("WILDTRACK data not found (set CBLRS_WILDTRACK or put it in ../shared/data)")
    return root
