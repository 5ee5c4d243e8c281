"""Pseudo references, the pseudo site and the analytics in pseudo space."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from cblrs.analytics.config import AnalyticsConfig
from cblrs.analytics.tables import analyse_tracks
from cblrs.cli.main import main
from cblrs.datasets import load_scene
from cblrs.pipeline import scene_planes
from cblrs.places import CountingLine, Places, Zone
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.privacy import (
    PseudoKey,
    pseudo_camera,
    pseudo_places,
    pseudo_site_document,
    render_pseudo_reference,
    tracks_to_pseudo,
)
from cblrs.reference import render_reference
from cblrs.site import load_site
from cblrs.site.core import site_from_document

KEY = PseudoKey(bytes(range(32)), "0123abcd")
REPO_ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def wildtrack(wildtrack_root):
    return load_scene(wildtrack_root)


def test_pseudo_reference_sees_what_the_plain_one_sees_in_the_keyed_frame(wildtrack):
    camera = wildtrack.cameras[1]
    planes = scene_planes(wildtrack)
    plain = render_reference(camera, planes)
    pseudo = render_pseudo_reference(camera, planes, KEY)
    # The real plane decides which pixels are located, not the larger pseudo square.
    np.testing.assert_array_equal(plain.pixels[..., 2] != 0, pseudo.pixels[..., 2] != 0)
    assert pseudo.planes == KEY.pseudo_planes(planes)
    pixels = np.random.default_rng(0).uniform([0, 0], [1919, 1079], (5000, 2))
    site_xy, valid = plain.locate(pixels)
    pseudo_xy, pseudo_valid = pseudo.locate(pixels)
    np.testing.assert_array_equal(valid, pseudo_valid)
    # Within the two quantisation steps (16 bits: under a millimetre each).
    error = np.linalg.norm(KEY.to_site(pseudo_xy[valid]) - site_xy[valid], axis=1)
    assert error.max() < 1.5e-3
    # And nothing like the site's coordinates: every located point is moved far.
    assert np.linalg.norm(pseudo_xy[valid] - site_xy[valid], axis=1).min() > 10.0


def test_pseudo_reference_survives_its_png(wildtrack, tmp_path):
    planes = PlaneSet([PlaneSpec(1, (-5, -11), 16, 40, bits=8), PlaneSpec(2, (0, 0), 4, 4,
                                                                           bits=8, height=1)])
    reference = render_pseudo_reference(wildtrack.cameras[0], planes, KEY)
    loaded = type(reference).load(reference.save(tmp_path / "c.png"))
    assert loaded.planes == KEY.pseudo_planes(planes)
    np.testing.assert_array_equal(loaded.pixels, reference.pixels)


def test_encoded_planes_must_match_the_planes(wildtrack):
    plane = PlaneSpec(1, (0, 0), 10, 10)
    other = PlaneSet([PlaneSpec(2, (0, 0), 10, 10)])
    with pytest.raises(Exception, match="ids and bits"):
        render_reference(wildtrack.cameras[0], plane, encode_as=(np.eye(3), other))


def test_pseudo_camera_is_where_the_key_puts_it_and_sees_the_same_pixels(wildtrack):
    camera = wildtrack.cameras[2]
    moved = pseudo_camera(camera, KEY)
    np.testing.assert_allclose(moved.centre[:2], KEY.to_pseudo(camera.centre[None, :2])[0],
                               atol=1e-6)
    assert moved.centre[2] == pytest.approx(camera.centre[2])
    site_points = np.array([[1.0, 2.0], [5.0, 20.0], [-2.0, 10.0]])
    pixels, _ = camera.world_to_pixel(site_points)
    pseudo_pixels, _ = moved.world_to_pixel(KEY.to_pseudo(site_points))
    np.testing.assert_allclose(pseudo_pixels, pixels, atol=1e-6)


def test_pseudo_site_carries_cameras_places_and_nothing_real(wildtrack_root, tmp_path):
    path = tmp_path / "site.yaml"
    assert main(["site", "init", "--dataset", str(wildtrack_root), "--out", str(path)]) == 0
    document = yaml.safe_load(path.read_text())
    document["places"] = load_site(REPO_ROOT / "sites" / "wildtrack.yaml").places.to_dict()
    path.write_text(yaml.safe_dump(document))
    site = load_site(path)
    pseudo_document = pseudo_site_document(site, KEY)
    pseudo = site_from_document(pseudo_document, None)
    assert pseudo.pseudo_key_id == KEY.key_id
    assert pseudo.map is None and "wildtrack" not in yaml.safe_dump(pseudo_document).lower()
    for name, (x, y, height) in site.camera_positions().items():
        px, py, pheight = pseudo.camera_positions()[name]
        np.testing.assert_allclose([px, py], KEY.to_pseudo(np.array([[x, y]]))[0], atol=1e-6)
        assert pheight == pytest.approx(height)
    # No point of the real site (cameras, places, plane corners) is a point of the pseudo one.
    distances = np.linalg.norm(_points(site)[:, None] - _points(pseudo)[None], axis=2)
    assert distances.min() > 10.0
    assert pseudo.places.names == site.places.names


def _points(site) -> np.ndarray:
    points = [position[:2] for position in site.camera_positions().values()]
    points += [point for zone in site.places.zones for point in zone.polygon]
    points += [point for line in site.places.lines for point in (line.start, line.end)]
    for plane in site.planes:
        x0, y0 = plane.origin
        points += [(x0, y0), (x0 + plane.width, y0 + plane.length)]
    return np.array(points, dtype=float)


def test_points_and_homography_cameras_keep_their_positions(example_site):
    site = load_site(example_site)
    pseudo = site_from_document(pseudo_site_document(site, KEY), None)
    expected = site.camera_positions()
    carried = pseudo.camera_positions()
    assert set(carried) == set(expected)
    for name, position in expected.items():
        np.testing.assert_allclose(
            carried[name][:2], KEY.to_pseudo(np.array([position[:2]]))[0], atol=0.01)
    # No clicked point, file name or frame picture reaches the matcher's file.
    text = yaml.safe_dump(pseudo_site_document(site, KEY))
    assert "points" not in text and "calibration" not in text and "plan.png" not in text


def test_analytics_count_the_same_in_pseudo_space(wildtrack):
    places = Places(
        (Zone("crossing", np.array([[1.0, 11.5], [6.5, 11.5], [6.5, 15.5], [1.0, 15.5]])),),
        (CountingLine("north", (-2.0, 17.0), (8.5, 17.0)),
         CountingLine("middle", (-2.5, 6.0), (8.5, 6.0), direction=(0.3, -1.0))),
    )
    config = AnalyticsConfig()
    truth = wildtrack.ground_truth
    plain = analyse_tracks(truth, places, config)
    moved = analyse_tracks(tracks_to_pseudo(truth, KEY), pseudo_places(places, KEY), config)
    assert moved.lines == plain.lines
    # Counts exactly; dwell times (interpolated crossing instants) to rounding.
    assert len(moved.zones) == len(plain.zones)
    for got, expected in zip(moved.zones, plain.zones, strict=True):
        assert got.keys() == expected.keys()
        for name, value in expected.items():
            assert got[name] == (value if isinstance(value, str | int) else pytest.approx(value))
    assert sum(row["count"] for row in plain.lines if row["class"] == "all") > 10
