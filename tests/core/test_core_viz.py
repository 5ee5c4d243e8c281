"""Reference visualisation: colours, metric grid, overlay."""

from __future__ import annotations

import numpy as np
import pytest
from core_cameras import posed_camera

from cblrs.camera import Camera
from cblrs.plane import PlaneSpec
from cblrs.reference import render_reference
from cblrs.viz.reference import (
    X_LINE_COLOUR,
    Y_LINE_COLOUR,
    colourise_reference,
    draw_metric_grid,
    reference_overlay,
    reference_world_map,
)


@pytest.fixture(scope="module")
def top_down():
    """Straight down from 10 m, 10 px per metre: world x -> image x, world y -> image -y."""
    camera = Camera.from_pose("top", (0.0, 0.0, 10.0), 90.0, 90.0, 100.0, (201, 161))
    plane = PlaneSpec(1, (-8.0, -6.0), 16.0, 12.0, bits=16)
    return render_reference(camera, plane)


def test_colourise_stretches_codes_and_blackens_unseen(top_down):
    image = colourise_reference(top_down)
    assert image.dtype == np.uint8 and image.shape == (161, 201, 3)
    seen = top_down.pixels[..., 2] != 0
    assert not image[~seen].any()
    # R grows with world x (to the right), G with world y (upwards in this view).
    row = image[80, seen[80]]
    assert row[0, 0] < 10 and row[-1, 0] > 245
    column = image[seen[:, 100], 100]
    assert column[0, 1] > 245 and column[-1, 1] < 10


def test_world_map_matches_decoding(top_down):
    world = reference_world_map(top_down)
    assert world.shape == (161, 201, 2)
    np.testing.assert_allclose(world[80, 100], [0.0, 0.0], atol=1e-3)
    assert np.isnan(world[0, 0]).all()  # outside the 16 x 12 m plane


def test_grid_lines_sit_on_whole_metres(top_down):
    blank = np.zeros((161, 201, 3), dtype=np.uint8)
    image = draw_metric_grid(blank, top_down, grid_m=2.0, labels=False, thickness=1)
    x_lines = np.all(image == X_LINE_COLOUR, axis=2)
    y_lines = np.all(image == Y_LINE_COLOUR, axis=2)
    # World x = -6, -4, ..., 8 m are columns 100 + 10 x (a line marks the pixel just past
    # it; the plane's right edge, x = 8 m, is the last pixel inside it).
    columns = np.flatnonzero(x_lines[80])
    expected = 100 + 10 * np.arange(-6, 10, 2)
    assert all(np.min(np.abs(columns - value)) <= 1 for value in expected)
    assert len(columns) == len(expected)
    rows = np.flatnonzero(y_lines[:, 50])
    assert len(rows) == len(range(-4, 8, 2))  # y = -4 .. 6 m (the top edge included)
    assert not x_lines[:20].any()  # beyond the plane (y > 6 m): nothing drawn


def test_labels_are_written(top_down):
    blank = np.zeros((161, 201, 3), dtype=np.uint8)
    plain = draw_metric_grid(blank, top_down, grid_m=4.0, labels=False)
    labelled = draw_metric_grid(blank, top_down, grid_m=4.0, labels=True)
    assert (labelled != plain).any()


def test_overlay_blends_only_where_a_plane_is_seen():
    reference = render_reference(posed_camera(), PlaneSpec(1, (-20.0, -5.0), 40.0, 60.0))
    frame = np.full((360, 640, 3), 200, dtype=np.uint8)
    image = reference_overlay(reference, frame, grid_m=None, alpha=0.5)
    seen = reference.pixels[..., 2] != 0
    assert (image[~seen] == 200).all()
    assert (image[seen] != 200).any()
    blank = reference_overlay(reference, None, grid_m=1.0)
    assert blank.shape == (360, 640, 3) and blank.dtype == np.uint8
    assert not blank[:60].any()  # above the horizon: black


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda ref: reference_overlay(ref, np.zeros((10, 10, 3), np.uint8)), "frame is 10x10"),
        (lambda ref: reference_overlay(ref, alpha=1.5), "alpha must be within 0..1"),
        (lambda ref: draw_metric_grid(np.zeros((161, 201, 3), np.uint8), ref, 0.0), "positive"),
        (lambda ref: draw_metric_grid(np.zeros((5, 5, 3), np.uint8), ref), "image is 5x5"),
    ],
)
def test_bad_arguments(top_down, call, message):
    with pytest.raises(ValueError, match=message):
        call(top_down)
