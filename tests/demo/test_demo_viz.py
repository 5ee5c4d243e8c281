"""Pictures: bird's-eye trajectories and per-camera overlays."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cblrs.camera import Camera
from cblrs.datasets.synthetic import GroundMarking, box_corners_3d
from cblrs.detections import Detections, Tracks
from cblrs.plane import PlaneSpec
from cblrs.reference import render_reference
from cblrs.viz.overlay import (
    camera_overlay,
    draw_boxes_3d,
    id_colour,
    save_image,
    world_frame,
)
from cblrs.viz.trajectories import camera_footprint, data_extent, plot_trajectories

TOP = Camera.from_pose("top", (0.0, 0.0, 10.0), 0.0, 90.0, 500.0, (320, 240))
SIDE = Camera.from_pose("side", (-10.0, 0.0, 4.0), 0.0, 10.0, 400.0, (320, 240))


def line_tracks(identity: int, start: tuple[float, float], count: int = 5) -> Tracks:
    frames = np.arange(count)
    xy = np.column_stack([start[0] + frames * 0.5, np.full(count, start[1])])
    return Tracks(frames, frames * 0.5, np.full(count, identity), xy)


# ---------------------------------------------------------------------------- trajectories


def test_named_predictions_give_a_panel_each_plus_ground_truth(tmp_path):
    truth = Tracks.concatenate([line_tracks(1, (0, 0)), line_tracks(2, (0, 3))])
    predictions = {"paper": line_tracks(7, (0, 0.2)), "fusion": truth}
    figure = plot_trajectories(
        truth, predictions, cameras=[TOP], title="demo",
        markings=[GroundMarking(((0, 0), (1, 0), (1, 1)), (90, 90, 90))],
    )
    titles = [axis.get_title() for axis in figure.axes]
    assert titles == ["paper  (1 ids)", "fusion  (2 ids)", "ground truth  (2 ids)"]
    assert all(axis.get_aspect() == 1.0 for axis in figure.axes)
    assert figure.axes[0].get_xlabel() == "x [m]"
    path = tmp_path / "trajectories.png"
    figure.savefig(path, dpi=50)
    image = cv2.imread(str(path))
    assert image is not None and image.std() > 5


def test_single_prediction_draws_into_a_given_axes():
    from matplotlib.figure import Figure

    figure = Figure()
    axis = figure.subplots()
    returned = plot_trajectories(line_tracks(1, (0, 0)), line_tracks(3, (0, 0)), ax=axis)
    assert returned is figure
    assert axis.get_title() == "predicted  (1 ids)"
    # ground truth (dashed) and the prediction (solid) are both drawn
    styles = {line.get_linestyle() for line in axis.get_lines()}
    assert {"--", "-"} <= styles


@pytest.mark.parametrize(
    ("predictions", "axes_count", "message"),
    [
        ({}, None, "at least one set of tracks"),
        ({"a": Tracks.empty(), "b": Tracks.empty()}, 1, "3 panel\\(s\\) to draw but 1 Axes"),
    ],
)
def test_plot_errors(predictions, axes_count, message):
    from matplotlib.figure import Figure

    axes = None
    if axes_count:
        axes = list(np.atleast_1d(Figure().subplots(1, axes_count)))
    with pytest.raises(ValueError, match=message):
        plot_trajectories(Tracks.empty(), predictions, ax=axes)


def test_empty_tracks_still_make_a_picture():
    figure = plot_trajectories(Tracks.empty(), Tracks.empty())
    assert len(figure.axes) == 1
    assert data_extent(Tracks.empty()) == (-1.0, -1.0, 1.0, 1.0)


def test_camera_footprint_of_a_straight_down_camera_is_its_image_rectangle():
    # 320 x 240 px at 500 px focal length from 10 m: 6.4 x 4.8 m (x across is world y).
    grid_x, grid_y, seen = camera_footprint(TOP, (-5.0, -5.0, 5.0, 5.0), resolution=101)
    xs, ys = grid_x[seen], grid_y[seen]
    assert xs.min() == pytest.approx(-2.4, abs=0.15) and xs.max() == pytest.approx(2.4, abs=0.15)
    assert ys.min() == pytest.approx(-3.2, abs=0.15) and ys.max() == pytest.approx(3.2, abs=0.15)


# ---------------------------------------------------------------------------- overlays


def reference_of(camera: Camera):
    return render_reference(camera, PlaneSpec(1, (-20.0, -20.0), 40.0, 40.0))


def test_overlay_draws_boxes_targets_and_labels():
    reference = reference_of(TOP)
    detections = Detections(np.array([[100.0, 60.0, 160.0, 180.0]]), object_id=np.array([4]))
    image = camera_overlay(reference, detections, np.array([[130.0, 170.0]]), grid_m=None)
    assert image.shape == (240, 320, 3) and image.dtype == np.uint8
    # the target dot: id colour ring with a white centre
    assert tuple(image[170, 130]) == (255, 255, 255)
    assert tuple(image[170, 133]) == id_colour(4)
    # the box edge in the id colour
    assert tuple(image[120, 100]) == id_colour(4)


def test_overlay_labels_by_given_identities_and_handles_no_boxes():
    reference = reference_of(TOP)
    detections = Detections(np.array([[100.0, 60.0, 160.0, 180.0]]))
    image = camera_overlay(reference, detections, np.array([[np.nan, np.nan]]),
                           identities=np.array([9]), grid_m=None, title="t", caption="c")
    assert tuple(image[120, 100]) == id_colour(9)
    empty = camera_overlay(reference, Detections.empty(), np.zeros((0, 2)), grid_m=None)
    assert empty.shape == (240, 320, 3)


@pytest.mark.parametrize(
    ("targets", "identities", "message"),
    [
        (np.zeros((2, 2)), None, "target_pixels has 2 rows but there are 1 detections"),
        (np.zeros((1, 2)), np.array([1, 2]), "identities has 2 rows"),
    ],
)
def test_overlay_errors(targets, identities, message):
    detections = Detections(np.array([[1.0, 1.0, 5.0, 5.0]]))
    with pytest.raises(ValueError, match=message):
        camera_overlay(reference_of(TOP), detections, targets, identities=identities)


def test_solid_box_below_a_top_camera_covers_the_image_centre():
    canvas = np.zeros((240, 320, 3), dtype=np.uint8)
    corners = box_corners_3d(np.array([[0.0, 0.0]]), (2.0, 2.0, 1.0), 0.0)
    drawn = draw_boxes_3d(canvas, TOP, corners, colours=np.array([[200, 100, 50]]))
    centre = drawn[120, 160].astype(int)
    # the top face, lit from above: a shade of the colour, same hue order
    assert centre[0] > centre[1] > centre[2] > 0
    assert (drawn[5, 5] == 0).all()  # outside the box untouched
    assert (canvas == 0).all()  # the input is not modified
    behind = box_corners_3d(np.array([[-20.0, 0.0]]), (2.0, 2.0, 1.0), 0.0)
    assert (draw_boxes_3d(canvas, SIDE, behind) == 0).all()


def test_world_frame_has_sky_above_the_horizon_and_ground_below():
    frame = world_frame(SIDE, [GroundMarking(((0, -1), (4, -1), (4, 1), (0, 1)), (10, 20, 30))])
    assert tuple(frame[0, 160]) != tuple(frame[239, 160])
    # the painted patch on the ground in front of the camera: the ray through (160, y)
    pixel, _ = SIDE.world_to_pixel(np.array([[2.0, 0.0]]))
    x, y = np.round(pixel[0]).astype(int)
    assert tuple(frame[y, x]) == (10, 20, 30)


def test_save_image_writes_rgb_png(tmp_path):
    image = np.zeros((4, 5, 3), dtype=np.uint8)
    image[..., 0] = 255  # red
    path = save_image(tmp_path / "sub" / "red.png", image)
    read_back = cv2.imread(str(path))  # BGR
    assert tuple(read_back[0, 0]) == (0, 0, 255)
