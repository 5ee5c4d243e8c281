"""Fixtures of the core tests: WILDTRACK cameras and their reference images."""

from __future__ import annotations

import pytest
from core_cameras import wildtrack_plane

from cblrs.calibration import read_wildtrack_cameras
from cblrs.reference import render_reference


@pytest.fixture(scope="session")
def wildtrack_cameras(wildtrack_root):
    return read_wildtrack_cameras(wildtrack_root)


@pytest.fixture(scope="session")
def wildtrack_distorted_cameras(wildtrack_root):
    return read_wildtrack_cameras(wildtrack_root, distorted=True)


@pytest.fixture(scope="session")
def wildtrack_references(wildtrack_cameras):
    """16-bit reference images of the seven undistorted WILDTRACK cameras."""
    plane = wildtrack_plane(16)
    return [render_reference(camera, plane) for camera in wildtrack_cameras]
