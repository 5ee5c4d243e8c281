"""Fixtures for ``cblrs up`` tests: a small live site and a broker binary."""

from __future__ import annotations

from pathlib import Path

import pytest
from up_helpers import small_site_text

from cblrs.runtime.broker.mosquitto_config import find_mosquitto


@pytest.fixture
def small_site(tmp_path, wildtrack_root) -> Path:
    """Two WILDTRACK cameras replaying 40 annotated frames each, in ``tmp_path/small.yaml``."""
    path = tmp_path / "small.yaml"
    path.write_text(small_site_text(Path(wildtrack_root).resolve()))
    return path


@pytest.fixture
def require_mosquitto() -> None:
    if find_mosquitto() is None:
        pytest.skip("mosquitto not installed")
