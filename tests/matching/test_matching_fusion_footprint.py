"""The footprint stage: a vehicle's box target moved along its ray to its footprint centre."""

import dataclasses
import math

import numpy as np
import pytest

from cblrs.camera import Camera
from cblrs.datasets.synthetic import MovingObject, SyntheticWorld, WaypointPath, WorldSpec
from cblrs.detections import CLASS_NAMES
from cblrs.evaluation.metrics import evaluate
from cblrs.matching.fusion.footprint import VEHICLE_SIZES, Footprint, half_extent
from cblrs.pipeline import camera_positions, render_scene_references, track_scene
from cblrs.plane import PlaneSpec
from cblrs.reference import render_reference

CAR = CLASS_NAMES.index("car")
PERSON = CLASS_NAMES.index("person")
LENGTH, WIDTH, HEIGHT = VEHICLE_SIZES["car"]


def _camera(pan_deg: float = 0.0) -> Camera:
    # 10 m up at the origin, looking along +x rotated by pan, 20 degrees down.
    return Camera.from_pose("a", (0.0, 0.0, 10.0), pan_deg, 20.0, 700.0, (1280, 720))


def _located(camera: Camera, centre, heading_deg: float, fraction: float = 0.85):
    """Where the target pixel of a car's exact box lands on the ground."""
    heading = np.radians(heading_deg)
    along = np.array([math.cos(heading), math.sin(heading)])
    side = np.array([-along[1], along[0]])
    corners = np.array(
        [
            (*(np.asarray(centre) + a * LENGTH / 2 * along + b * WIDTH / 2 * side), z)
            for a in (-1, 1)
            for b in (-1, 1)
            for z in (0.0, HEIGHT)
        ]
    )
    pixels, _ = camera.project_points(corners)
    left, top = pixels.min(axis=0)
    right, bottom = pixels.max(axis=0)
    target = np.array([[0.5 * (left + right), top + fraction * (bottom - top)]])
    world, valid = camera.pixel_to_world(target)
    assert valid.all()
    return world[0]


def _footprint(camera: Camera) -> Footprint:
    footprint = Footprint([camera.name], {camera.name: (0.0, 0.0, 10.0)})
    plane = PlaneSpec(1, (-5.0, -60.0), 80.0, 120.0)
    footprint.set_view(0, render_reference(camera, plane))
    return footprint


def _recovered(footprint: Footprint, located: np.ndarray, heading_deg: float | None):
    distance = float(np.hypot(*located))
    direction = (located / distance)[None]
    heading = None
    if heading_deg is not None:
        heading = np.array(
            [[math.cos(math.radians(heading_deg)), math.sin(math.radians(heading_deg))]]
        )
    shift = footprint.shift(
        np.array([distance]), direction, np.array([0]), np.array([CAR]), heading
    )
    return located + shift[0]


def test_half_extent_is_half_the_length_along_and_half_the_width_across():
    assert half_extent(4.5, 1.8, 1.0, 0.0) == pytest.approx(2.25)
    assert half_extent(4.5, 1.8, 0.0, 1.0) == pytest.approx(0.9)
    assert half_extent(4.5, 1.8, math.sqrt(0.5), -math.sqrt(0.5)) == pytest.approx(
        (2.25 + 0.9) * math.sqrt(0.5)
    )


def test_set_view_learns_the_viewing_direction_from_the_reference():
    camera = _camera(pan_deg=30.0)
    footprint = Footprint(["a"], {"a": (0.0, 0.0, 10.0)})
    plane = PlaneSpec(1, (-60.0, -60.0), 120.0, 120.0)
    footprint.set_view(0, render_reference(camera, plane))
    assert footprint.forward[0] == pytest.approx(
        [math.cos(math.radians(30.0)), math.sin(math.radians(30.0))], abs=0.01
    )


@pytest.mark.parametrize("centre", [(22.0, 0.0), (30.0, 8.0), (45.0, -10.0)])
@pytest.mark.parametrize("heading_deg", [0.0, 35.0, 90.0, 140.0])
def test_a_car_box_target_is_moved_to_its_footprint_centre(centre, heading_deg):
    camera = _camera()
    footprint = _footprint(camera)
    located = _located(camera, centre, heading_deg)
    ray = np.asarray(centre) / np.hypot(*centre)
    before = (located - centre) @ ray
    after = (_recovered(footprint, located, heading_deg) - centre) @ ray
    # Along the ray the box target lands up to 1.35 m short; moved by the heading, within
    # 8 cm; and within 15 cm in all (across the ray the box's centre column is not the
    # centre's: modelled without the camera's tilt, so a few centimetres remain).
    assert abs(after) < 0.08
    assert abs(after) < abs(before)
    assert np.linalg.norm(_recovered(footprint, located, heading_deg) - centre) < 0.15


def test_the_heading_matters_and_an_unknown_one_is_averaged():
    camera = _camera()
    footprint = _footprint(camera)
    errors = {}
    for heading_deg in (0.0, 90.0):
        located = _located(camera, (25.0, 0.0), heading_deg)
        errors[heading_deg] = (
            np.linalg.norm(_recovered(footprint, located, heading_deg) - (25.0, 0.0)),
            np.linalg.norm(_recovered(footprint, located, None) - (25.0, 0.0)),
        )
    # Along the ray the car's near edge is far nearer than across it: the average heading
    # is wrong both ways, the right heading right both ways.
    assert max(known for known, _ in errors.values()) < 0.1
    assert min(unknown for _, unknown in errors.values()) > 0.15
    assert max(unknown for _, unknown in errors.values()) > 0.5


def test_people_and_cameras_without_height_are_not_moved():
    footprint = Footprint(["a", "b"], {"a": (0.0, 0.0, 10.0), "b": (5.0, 0.0)})
    ray = np.array([[1.0, 0.0]] * 3)
    shift = footprint.shift(
        np.array([25.0, 25.0, 25.0]), ray, np.array([0, 0, 1]), np.array([PERSON, CAR, CAR])
    )
    assert (shift[0] == 0.0).all() and (shift[2] == 0.0).all()
    assert shift[1][0] > 0.3  # away from the camera, along its ray
    assert not Footprint(["a"], {"a": (0.0, 0.0)}).enabled
    assert not Footprint(["a"], None).enabled


def _car_world() -> WorldSpec:
    # Two cars driving through the middle of four corner cameras, 6 s at 10 fps.
    cameras = tuple(
        Camera.from_pose(
            name, (x, y, 10.0), math.degrees(math.atan2(-y, -x)), 20.0, 700.0, (1280, 720)
        )
        for name, x, y in (("NE", 27.0, 27.0), ("SW", -27.0, -27.0), ("SE", 27.0, -27.0))
    )
    objects = (
        MovingObject(
            1, "car", (4.5, 1.8, 1.5), WaypointPath(((-25.0, 2.0), (25.0, 2.0)), 7.0, 0.0)
        ),
        MovingObject(
            2, "car", (4.5, 1.8, 1.5), WaypointPath(((-2.0, -25.0), (-2.0, 25.0)), 7.0, 0.5)
        ),
    )
    return WorldSpec(
        name="cars",
        cameras=cameras,
        objects=objects,
        area=(-30.0, -30.0, 30.0, 30.0),
        duration_s=6.0,
        fps=10.0,
    )


def test_tracked_cars_land_nearer_their_footprint_centres():
    scene = SyntheticWorld(_car_world()).scene()
    references = render_scene_references(scene)
    located = {}
    for on in (False, True):
        tracks = track_scene(
            scene,
            references=references,
            vehicle_footprint=on,
            camera_positions=camera_positions(scene),
        ).tracks
        located[on] = evaluate(scene.ground_truth, tracks).LocA
    assert located[True] > located[False] + 1.0


def test_geometric_targeting_turns_the_stage_off():
    # Geometric targeting already aims at the footprint centre: moving it again would be
    # wrong, so track_scene turns the stage off unless told otherwise.
    world = dataclasses.replace(_car_world(), duration_s=1.5)
    scene = SyntheticWorld(world).scene()
    references = render_scene_references(scene)
    default = track_scene(scene, references=references, targeting="geometric").tracks
    off = track_scene(
        scene, references=references, targeting="geometric", vehicle_footprint=False
    ).tracks
    on = track_scene(
        scene, references=references, targeting="geometric", vehicle_footprint=True
    ).tracks
    assert np.array_equal(default.world_xy, off.world_xy)
    assert not np.array_equal(default.world_xy, on.world_xy)
