"""The synthetic world: paths, visibility, occlusion, presets."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from cblrs.camera import Camera
from cblrs.datasets.presets import make_scene, make_world
from cblrs.datasets.synthetic import (
    CLASS_SIZE_PRIORS,
    LanePath,
    LoopPath,
    MovingObject,
    RandomWalkPath,
    Structure,
    SyntheticWorld,
    WaypointPath,
    WorldSpec,
    class_size,
    occluded,
)
from cblrs.detections import CLASS_NAMES
from cblrs.errors import DatasetError

PERSON = (0.5, 0.5, 1.75)


def camera_pattern(scene, object_id: int) -> list[tuple[str, int]]:
    """Runs of which cameras see an object: 'A', 'B', 'AB' or '-' per frame, run-length coded."""
    names = scene.camera_names
    symbols = []
    for per_camera in scene.detections:
        seen = [n for n, d in zip(names, per_camera, strict=True) if object_id in d.object_id]
        symbols.append("".join(seen) or "-")
    return [(key, len(list(group))) for key, group in itertools.groupby(symbols)]


# ---------------------------------------------------------------------------- presets


def test_roundabout_car_is_handed_over_twice_through_two_overlaps():
    scene = make_scene("roundabout")
    assert scene.camera_names == ["A", "B"]
    pattern = camera_pattern(scene, 1)
    assert [key for key, _ in pattern] == ["A", "AB", "B", "AB", "A"]
    # Each stretch lasts long enough to matter (at 10 fps: at least 0.8 s).
    assert all(length >= 8 for _, length in pattern)


def test_roundabout_ground_truth_is_one_full_circle():
    scene = make_scene("roundabout")
    truth = scene.ground_truth
    assert set(truth.track_id.tolist()) == {1}
    assert len(truth) == len(scene.frames)
    radius = np.hypot(truth.world_xy[:, 0], truth.world_xy[:, 1])
    np.testing.assert_allclose(radius, 12.0, atol=1e-9)
    angles = np.unwrap(np.arctan2(truth.world_xy[:, 1], truth.world_xy[:, 0]))
    assert np.all(np.diff(angles) > 0)  # counter-clockwise throughout
    assert angles[-1] - angles[0] > 2 * np.pi
    assert scene.detections[0][0].class_id.tolist() == [CLASS_NAMES.index("car")]


def test_plaza_has_the_promised_cameras_and_crowd():
    scene = make_scene("plaza", duration_s=10.0)
    assert len(scene.cameras) >= 4
    truth = scene.ground_truth
    classes = {}
    for per_camera in scene.detections:
        for detections in per_camera:
            classes.update(
                zip(detections.object_id.tolist(), detections.class_id.tolist(), strict=True)
            )
    people = [i for i, c in classes.items() if c == CLASS_NAMES.index("person")]
    assert len(people) >= 20
    assert len(set(truth.track_id.tolist())) >= 20
    # The crowd is seen from several cameras at once (what the cameras overlap for).
    counts = {}
    for frame, per_camera in enumerate(scene.detections):
        for detections in per_camera:
            for identity in detections.object_id.tolist():
                counts[frame, identity] = counts.get((frame, identity), 0) + 1
    assert np.mean(list(counts.values())) > 2.0
    assert scene.plane.bits == 16
    inside = scene.plane.contains(truth.world_xy)
    assert inside.all()


def test_scene_is_deterministic_for_a_seed():
    first = make_scene("plaza", seed=4, duration_s=4.0)
    second = make_scene("plaza", seed=4, duration_s=4.0)
    other = make_scene("plaza", seed=5, duration_s=4.0)
    np.testing.assert_array_equal(first.ground_truth.world_xy, second.ground_truth.world_xy)
    for row_a, row_b in zip(first.detections, second.detections, strict=True):
        for a, b in zip(row_a, row_b, strict=True):
            np.testing.assert_array_equal(a.xyxy, b.xyxy)
            np.testing.assert_array_equal(a.object_id, b.object_id)
    assert not np.array_equal(first.ground_truth.world_xy[:10], other.ground_truth.world_xy[:10])


def test_duration_and_fps_set_the_frames():
    scene = make_scene("roundabout", duration_s=2.0, fps=5.0)
    np.testing.assert_array_equal(scene.frames, np.arange(10))
    np.testing.assert_allclose(scene.timestamps, np.arange(10) / 5.0)


def test_unknown_preset_lists_the_known_ones():
    with pytest.raises(
        DatasetError, match="unknown synthetic preset 'mall'; known presets: plaza, roundabout"
    ):
        make_scene("mall")
    assert make_world("plaza").name == "plaza"


# ---------------------------------------------------------------------------- paths


def test_loop_path_heading_is_tangent_and_laps_end_it():
    path = LoopPath((1.0, 2.0), 5.0, 2.0, start_angle_deg=0.0, laps=1.0)
    lap = 2 * np.pi * 5.0 / 2.0
    sample = path.sample(np.array([0.0, lap / 4, lap + 0.5]))
    np.testing.assert_allclose(sample.xy[:2], [[6.0, 2.0], [1.0, 7.0]], atol=1e-12)
    np.testing.assert_allclose(sample.heading_deg[:2], [90.0, 180.0])
    assert sample.present.tolist() == [True, True, False]
    clockwise = LoopPath((0.0, 0.0), 5.0, 2.0, clockwise=True).sample(np.array([0.0]))
    assert clockwise.heading_deg[0] == pytest.approx(-90.0)


def test_lane_path_exists_only_while_driving():
    path = LanePath((0.0, 0.0), (10.0, 0.0), 2.0, start_s=1.0)
    sample = path.sample(np.array([0.0, 1.0, 3.5, 6.0, 6.5]))
    assert sample.present.tolist() == [False, True, True, True, False]
    np.testing.assert_allclose(sample.xy[1:4, 0], [0.0, 5.0, 10.0])
    np.testing.assert_allclose(sample.heading_deg[1:4], 0.0)
    assert np.isnan(sample.xy[0]).all()


def test_waypoint_path_turns_corners():
    path = WaypointPath(((0.0, 0.0), (4.0, 0.0), (4.0, 4.0)), 1.0)
    sample = path.sample(np.array([2.0, 6.0]))
    np.testing.assert_allclose(sample.xy, [[2.0, 0.0], [4.0, 2.0]])
    np.testing.assert_allclose(sample.heading_deg, [0.0, 90.0])
    with pytest.raises(ValueError, match="at least two points"):
        WaypointPath(((0.0, 0.0),), 1.0)


def test_random_walk_stays_inside_and_ignores_the_frame_rate():
    path = RandomWalkPath((0.0, 0.0), (-3.0, -2.0, 3.0, 2.0), speed=1.5, seed=7)
    coarse = path.sample(np.arange(0, 60, 1.0))
    fine = path.sample(np.arange(0, 60, 0.5))
    np.testing.assert_allclose(coarse.xy, fine.xy[::2], atol=1e-9)
    assert (fine.xy[:, 0] >= -3).all() and (fine.xy[:, 0] <= 3).all()
    assert (fine.xy[:, 1] >= -2).all() and (fine.xy[:, 1] <= 2).all()
    steps = np.hypot(*np.diff(fine.xy, axis=0).T)
    assert steps.max() <= 1.5 * 0.5 + 1e-9
    assert steps.mean() > 0.5  # it walks, it does not stand still


def test_class_size_prior_and_variation():
    assert class_size("person") == CLASS_SIZE_PRIORS["person"] == (0.5, 0.5, 1.75)
    assert class_size("car") == (4.5, 1.8, 1.5)
    varied = np.array([class_size("car", np.random.default_rng(s)) for s in range(50)])
    assert np.allclose(varied.mean(axis=0), (4.5, 1.8, 1.5), rtol=0.05)
    assert (np.abs(varied / (4.5, 1.8, 1.5) - 1) <= 0.12 + 1e-12).all()
    with pytest.raises(ValueError, match="no size prior for class 'dragon'"):
        class_size("dragon")


# ---------------------------------------------------------------------------- visibility


def single_camera_world(objects, **options) -> WorldSpec:
    camera = Camera.from_pose("cam", (-10.0, 0.0, 1.8), 0.0, 5.0, 800.0, (1280, 720))
    options = {"area": (-10, -10, 20, 10), "duration_s": 0.1, **options}
    return WorldSpec("test", (camera,), tuple(objects), **options)


def standing(object_id: int, x: float, y: float, size=PERSON) -> MovingObject:
    return MovingObject(object_id, "person", size, LanePath((x, y), (x + 1e-3, y), 0.01))


def test_occlusion_drops_a_person_hidden_behind_a_nearer_one():
    objects = [standing(1, 0.0, 0.0), standing(2, 4.0, 0.0), standing(3, 4.0, 3.0)]
    scene = SyntheticWorld(single_camera_world(objects)).scene()
    assert sorted(scene.detections[0][0].object_id.tolist()) == [1, 3]
    # Hidden is not absent: the ground truth keeps it, and without occlusion it is detected.
    assert sorted(scene.ground_truth.track_id.tolist()) == [1, 2, 3]
    visible_all = SyntheticWorld(single_camera_world(objects, occlusion=False)).scene()
    assert sorted(visible_all.detections[0][0].object_id.tolist()) == [1, 2, 3]


def test_partly_covered_box_is_kept():
    # Side by side, 0.4 m apart sideways: a small part overlaps, not most of it.
    objects = [standing(1, 0.0, 0.0), standing(2, 3.0, 0.45)]
    scene = SyntheticWorld(single_camera_world(objects)).scene()
    assert sorted(scene.detections[0][0].object_id.tolist()) == [1, 2]


@pytest.mark.parametrize(
    ("position", "detected", "in_truth"),
    [
        ((5.0, 0.0), True, True),  # in the middle of the view
        ((-11.0, 0.0), False, False),  # behind the camera
        ((5.0, 60.0), False, False),  # far to the side
        ((400.0, 0.0), False, False),  # beyond the area and too small to see
    ],
)
def test_visibility_table(position, detected, in_truth):
    scene = SyntheticWorld(
        single_camera_world([standing(1, *position)], area=(-20, -70, 420, 70))
    ).scene()
    assert (len(scene.detections[0][0]) == 1) is detected
    assert (len(scene.ground_truth) == 1) is in_truth


def test_box_mostly_outside_the_image_is_not_reported():
    camera = Camera.from_pose("top", (0.0, 0.0, 10.0), 0.0, 90.0, 500.0, (640, 480))
    # Image x = 319.5 - 50 y: a 2 m wide flat-ish box centred at y = 6.6 is 40 % inside.
    box = (2.0, 2.0, 0.01)
    spec = WorldSpec(
        "edge",
        (camera,),
        (MovingObject(1, "car", box, LanePath((0.0, 6.6), (0.001, 6.6), 0.01)),),
        area=(-10, -10, 10, 10),
        duration_s=0.1,
        min_box_height_px=1,
    )
    assert len(SyntheticWorld(spec).scene().detections[0][0]) == 0
    spec_half = WorldSpec(
        "edge",
        (camera,),
        (MovingObject(1, "car", box, LanePath((0.0, 6.2), (0.001, 6.2), 0.01)),),
        area=(-10, -10, 10, 10),
        duration_s=0.1,
        min_box_height_px=1,
    )
    detections = SyntheticWorld(spec_half).scene().detections[0][0]
    assert len(detections) == 1
    assert detections.xyxy[0, 0] == pytest.approx(-0.5)


def test_occluded_function_table():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 9, 9], [5, 0, 15, 10], [np.nan] * 4], float)
    depth = np.array([1.0, 2.0, 3.0, 0.5])
    hidden = occluded(boxes, depth, np.ones(4, bool), max_fraction=0.75)
    assert hidden.tolist() == [False, True, False, False]
    assert occluded(np.zeros((0, 4)), np.zeros(0), np.zeros(0, bool), 0.75).tolist() == []


def _occluded_one_box_at_a_time(xyxy, depth, occluders, max_fraction, samples=12):
    """The definition, box by box: the share of a samples x samples grid inside each box
    that the union of nearer boxes covers."""
    hidden = np.zeros(len(xyxy), dtype=bool)
    rows = np.flatnonzero(occluders & np.isfinite(xyxy).all(axis=1) & np.isfinite(depth))
    fractions = (np.arange(samples) + 0.5) / samples
    for row in rows:
        nearer = rows[depth[rows] < depth[row]]
        x0, y0, x1, y1 = xyxy[row]
        grid_x, grid_y = x0 + fractions * (x1 - x0), y0 + fractions * (y1 - y0)
        covered = np.zeros((samples, samples), dtype=bool)
        for other in nearer:
            inside_x = (grid_x >= xyxy[other, 0]) & (grid_x <= xyxy[other, 2])
            inside_y = (grid_y >= xyxy[other, 1]) & (grid_y <= xyxy[other, 3])
            covered |= inside_y[:, None] & inside_x[None, :]
        hidden[row] = covered.mean() > max_fraction
    return hidden


@pytest.mark.parametrize("seed", range(6))
def test_occluded_equals_its_definition_on_random_crowds(seed):
    rng = np.random.default_rng(seed)
    count = int(rng.integers(2, 40))
    corner = rng.uniform(0, 300, size=(count, 2))
    boxes = np.column_stack([corner, corner + rng.uniform(5, 120, size=(count, 2))])
    boxes[rng.random(count) < 0.1] = np.nan
    depth = rng.uniform(1, 50, count)
    depth[:3] = depth[0]  # ties: a box at the same depth hides nothing
    occluders = rng.random(count) < 0.9
    for fraction in (0.3, 0.75):
        expected = _occluded_one_box_at_a_time(boxes, depth, occluders, fraction)
        np.testing.assert_array_equal(occluded(boxes, depth, occluders, fraction), expected)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"cameras": ()}, "at least one camera"),
        ({"duration_s": 0.0}, "duration and frame rate must be positive"),
        ({"area": (1, 1, 0, 5)}, "area must be"),
    ],
)
def test_world_spec_errors(change, message):
    camera = Camera.from_pose("cam", (0.0, 0.0, 5.0), 0.0, 45.0, 800.0, (640, 480))
    options = {"name": "w", "cameras": (camera,), "objects": (), "area": (0, 0, 1, 1)}
    options.update(change)
    with pytest.raises(DatasetError, match=message):
        WorldSpec(**options)


def test_world_spec_rejects_duplicate_ids_and_homography_cameras():
    camera = Camera.from_pose("cam", (0.0, 0.0, 5.0), 0.0, 45.0, 800.0, (640, 480))
    twins = (standing(1, 0, 0), standing(1, 1, 1))
    with pytest.raises(DatasetError, match="must be unique"):
        WorldSpec("w", (camera,), twins, area=(0, 0, 1, 1))
    flat = Camera.from_homography("flat", camera.homography, (640, 480))
    with pytest.raises(DatasetError, match="needs a pose"):
        WorldSpec("w", (flat,), (), area=(0, 0, 1, 1))


def test_empty_world_gives_an_empty_scene():
    camera = Camera.from_pose("cam", (0.0, 0.0, 5.0), 0.0, 45.0, 800.0, (640, 480))
    scene = SyntheticWorld(WorldSpec("w", (camera,), (), area=(0, 0, 1, 1), duration_s=1)).scene()
    assert len(scene.ground_truth) == 0
    assert all(len(d) == 0 for row in scene.detections for d in row)


def test_structure_hides_a_person_behind_it_but_not_one_beside_it():
    wall = Structure((2.0, 0.0), (0.5, 4.0, 3.0), 0.0, "wall")
    objects = [standing(1, 5.0, 0.0), standing(2, 5.0, 6.0)]
    scene = SyntheticWorld(single_camera_world(objects, structures=(wall,))).scene()
    assert scene.detections[0][0].object_id.tolist() == [2]
    assert sorted(scene.ground_truth.track_id.tolist()) == [1, 2]


@pytest.mark.parametrize(
    ("end", "blocked"),
    [
        ((5.0, 0.0, 1.0), True),  # straight through the block
        ((5.0, 0.0, 10.0), False),  # over it
        ((5.0, 5.0, 1.0), False),  # beside it
        ((0.5, 0.0, 1.0), False),  # stops before it
        ((1.6, 0.0, 1.0), True),  # ends inside it
    ],
)
def test_structure_blocks_table(end, blocked):
    block = Structure((2.0, 0.0), (1.0, 2.0, 3.0), 0.0)
    result = block.blocks(np.array([0.0, 0.0, 1.0]), np.array([end]))
    assert result.tolist() == [blocked]


def test_rotated_structure_blocks_along_its_length():
    beam = Structure((0.0, 0.0), (10.0, 0.4, 2.0), 90.0)  # a thin wall along world y
    origin = np.array([-3.0, 0.0, 1.0])
    assert beam.blocks(origin, np.array([[3.0, 4.0, 1.0]])).tolist() == [True]
    assert beam.blocks(origin, np.array([[-1.0, 4.0, 1.0]])).tolist() == [False]
