"""The documentation's site example (docs/sites.md) is complete and valid, and every camera in
it works."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.site import check_site, load_site


def test_example_example_validates_and_is_ready_for_everything(example_site):
    report = check_site(example_site)
    assert report["valid"], report["problems"]
    assert report["ready"] == {
        "render": True,
        "camera": True,
        "matcher": True,
        "track": True,
        "analytics": True,
    }
    assert [camera["name"] for camera in report["cameras"]] == [
        "gate",
        "east",
        "kiosk",
        "bridge",
        "north",
    ]
    for camera in report["cameras"]:
        assert camera["ok"], camera["error"]
        assert camera["position"] is not None, camera
        assert camera["coverage"] > 0.2, camera
    assert report["places"]["names"] == ["market", "gate-line"]


@pytest.mark.parametrize(
    ("name", "position", "tolerance"),
    [
        ("gate", (-4.0, -4.0, 6.0), 0.15),  # clicked with about 1 px of noise
        ("east", (36.0, 8.0, 5.0), 1e-3),  # exact clicks, world in map pixels
        ("kiosk", (31.0, 21.0, 4.5), 1e-3),  # homography + focal_px
        ("bridge", (15.0, -6.0, 8.0), 1e-4),
        ("north", (12.0, 27.0, 7.0), 1e-9),
    ],
)
def test_example_cameras_are_where_they_were_put(example_site, name, position, tolerance):
    camera = load_site(example_site).camera(name)
    np.testing.assert_allclose(camera.position, position, atol=tolerance)


def test_example_map_converts_map_pixels(example_site):
    site = load_site(example_site)
    assert site.map is not None
    np.testing.assert_allclose(site.map.to_world([[120, 880], [320, 680]]), [[0, 0], [10, 10]])
    np.testing.assert_allclose(site.map.to_map([[10, 10]]), [[320, 680]])
