"""OnDemandReference reads the very colours of the rendered image, pixel for pixel."""

from __future__ import annotations

import numpy as np
import pytest
from core_cameras import STRONG_LENS, posed_camera, wildtrack_plane

from cblrs.plane import PlaneSpec
from cblrs.reference import OnDemandReference, render_reference

FLOOR = PlaneSpec(1, (-15.0, -5.0), 30.0, 40.0, bits=16)
TABLE = PlaneSpec(2, (-1.0, 2.0), 2.0, 1.0, bits=16, height=1.0)
SHELF = PlaneSpec(3, (1.0, 8.0), 2.0, 2.0, bits=16, height=2.5)


def _probe_pixels(width: int, height: int, seed: int = 0) -> np.ndarray:
    """Random sub-pixel positions over and around the frame, plus edges and non-finite ones."""
    generator = np.random.default_rng(seed)
    inside = generator.uniform([-0.49, -0.49], [width - 0.51, height - 0.51], size=(4000, 2))
    around = generator.uniform([-20, -20], [width + 20, height + 20], size=(500, 2))
    special = np.array(
        [[0, 0], [width - 1, height - 1], [-0.5, 3], [width - 0.5, 3], [np.nan, 1], [2, np.inf]],
        dtype=np.float64,
    )
    return np.concatenate([inside, around, special])


@pytest.mark.parametrize(
    "distortion, planes",
    [
        (None, [FLOOR]),
        (None, [FLOOR, TABLE, SHELF]),
        (STRONG_LENS, [FLOOR]),
        (STRONG_LENS, [FLOOR, TABLE, SHELF]),
        (None, [PlaneSpec(1, (-15.0, -5.0), 30.0, 40.0, bits=8)]),
    ],
    ids=["pinhole", "pinhole-planes", "lens", "lens-planes", "8-bit"],
)
def test_on_demand_colours_equal_the_rendered_image(distortion, planes):
    camera = posed_camera(distortion=distortion)
    rendered = render_reference(camera, planes)
    on_demand = OnDemandReference(camera, planes)
    pixels = _probe_pixels(*camera.image_size)
    colours, valid = on_demand.colours_at(pixels)
    expected_colours, expected_valid = rendered.colours_at(pixels)
    assert colours.dtype == expected_colours.dtype == np.int64
    np.testing.assert_array_equal(colours, expected_colours)
    np.testing.assert_array_equal(valid, expected_valid)
    assert valid.sum() > 1000 and (~valid).sum() > 100  # both sides of the plane edges probed
    world, world_valid = on_demand.locate(pixels)
    expected_world, expected_world_valid = rendered.locate(pixels)
    np.testing.assert_array_equal(world_valid, expected_world_valid)
    np.testing.assert_array_equal(world[world_valid], expected_world[expected_world_valid])
    # The sampled grid (what the fusion tracker's set_views reads) without the whole image.
    for step in (1, 4, 7):
        sampled = OnDemandReference(camera, planes).sampled_colours(step)
        expected_sampled = rendered.pixels[::step, ::step].reshape(-1, 3)
        assert sampled.dtype == expected_sampled.dtype
        np.testing.assert_array_equal(sampled, expected_sampled)
        np.testing.assert_array_equal(rendered.sampled_colours(step), expected_sampled)
    assert "image" not in on_demand.__dict__  # nothing above rendered the whole frame
    on_demand.pixels  # noqa: B018 -- once rendered, sampling reads the image
    np.testing.assert_array_equal(on_demand.sampled_colours(4),
                                  rendered.pixels[::4, ::4].reshape(-1, 3))


def test_on_demand_whole_image_is_the_rendered_one(tmp_path):
    camera = posed_camera()
    on_demand = OnDemandReference(camera, FLOOR)
    rendered = render_reference(camera, FLOOR)
    assert on_demand.image_size == rendered.image_size and on_demand.bits == 16
    assert on_demand.camera_name == rendered.camera_name
    np.testing.assert_array_equal(on_demand.pixels, rendered.pixels)
    assert on_demand.coverage() == rendered.coverage()
    saved = on_demand.save(tmp_path / "c.png")
    np.testing.assert_array_equal(
        render_reference(camera, FLOOR).pixels, type(rendered).load(saved).pixels
    )


def test_on_demand_reads_no_pixels_for_no_points():
    reference = OnDemandReference(posed_camera(), FLOOR)
    colours, valid = reference.colours_at(np.zeros((0, 2)))
    assert colours.shape == (0, 3) and valid.shape == (0,)
    with pytest.raises(ValueError, match=r"shape \(N, 2\)"):
        reference.colours_at(np.zeros(3))


@pytest.mark.parametrize("view", [0, 4])
def test_on_demand_equals_rendered_on_wildtrack(
    view, wildtrack_cameras, wildtrack_distorted_cameras
):
    """WILDTRACK's cameras at full resolution, without and with their lens model."""
    plane = wildtrack_plane(16)
    for camera in (wildtrack_cameras[view], wildtrack_distorted_cameras[view]):
        pixels = _probe_pixels(*camera.image_size, seed=view)
        colours, valid = OnDemandReference(camera, plane).colours_at(pixels)
        expected, expected_valid = render_reference(camera, plane).colours_at(pixels)
        np.testing.assert_array_equal(colours, expected)
        np.testing.assert_array_equal(valid, expected_valid)
        assert valid.sum() > 500
