"""Reference images: rendering (several planes, distortion), PNG round trips, corrupt files."""

from __future__ import annotations

import json
import struct
import zlib

import cv2
import numpy as np
import pytest
from core_cameras import STRONG_LENS, posed_camera

from cblrs.camera import Camera
from cblrs.errors import ReferenceImageError
from cblrs.locate import HomographyLocator
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.reference import ReferenceImage, render_reference

GROUND = PlaneSpec(1, (-20.0, -5.0), 40.0, 60.0, bits=16)


def ground(bits: int) -> PlaneSpec:
    return PlaneSpec(1, (-20.0, -5.0), 40.0, 60.0, bits=bits)


@pytest.fixture(scope="module")
def references() -> dict[int, ReferenceImage]:
    camera = posed_camera()
    return {bits: render_reference(camera, ground(bits)) for bits in (8, 16)}


@pytest.mark.parametrize("bits", [8, 16])
def test_png_round_trip_is_exact(tmp_path, references, bits):
    reference = references[bits]
    path = reference.save(tmp_path / f"reference{bits}.png")
    loaded = ReferenceImage.load(path, expected_size=(640, 360))
    assert loaded.pixels.dtype == (np.uint8 if bits == 8 else np.uint16)
    np.testing.assert_array_equal(loaded.pixels, reference.pixels)
    assert loaded.planes == reference.planes
    assert loaded.camera_name == "synthetic"
    # An ordinary PNG reader sees the same pixels (BGR order on disk, as PNG stores RGB).
    plain = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(plain[..., ::-1], reference.pixels)


def test_render_matches_the_camera_geometry(references):
    """Every pixel's colour is the encoding of its ray's ground hit (exact, 16 bits)."""
    camera = posed_camera()
    reference = references[16]
    rows, columns = np.mgrid[0:360:7, 0:640:7]
    pixels = np.column_stack([columns.ravel(), rows.ravel()]).astype(np.float64)
    world_xy, valid = camera.pixel_to_world(pixels)
    expected, expected_valid = GROUND.encode(np.where(valid[:, None], world_xy, np.nan))
    colours, colour_valid = reference.colours_at(pixels)
    assert (colour_valid == expected_valid).mean() > 0.999
    both = colour_valid & expected_valid
    assert np.abs(colours[both] - expected[both].astype(np.int64)).max() <= 1
    # Above the horizon (row ~73) nothing is seen.
    assert not reference.pixels[:70, :, 2].any()
    assert reference.pixels[200:, :, 2].all()


def test_several_planes_nearest_wins():
    """A table (1 m high) in front of the ground hides it; B = 0 where no plane is seen."""
    camera = posed_camera()
    floor = PlaneSpec(1, (-3.0, 0.0), 6.0, 20.0, bits=16)
    table = PlaneSpec(2, (-1.0, 2.0), 2.0, 1.0, bits=16, height=1.0)
    shelf = PlaneSpec(3, (1.0, 8.0), 2.0, 2.0, bits=16, height=2.5)
    reference = render_reference(camera, [floor, table, shelf])
    plane_ids = reference.pixels[..., 2]
    assert set(np.unique(plane_ids).tolist()) == {0, 1, 2, 3}

    # Independent check: per pixel, intersect with each plane, keep the nearest hit inside.
    rows, columns = np.mgrid[0:360:3, 0:640:3]
    pixels = np.column_stack([columns.ravel(), rows.ravel()]).astype(np.float64)
    best_distance = np.full(len(pixels), np.inf)
    expected = np.zeros(len(pixels), dtype=np.int64)
    for plane in (floor, table, shelf):
        world_xy, valid = camera.pixel_to_world(pixels, plane.height)
        valid &= plane.contains(np.where(valid[:, None], world_xy, np.nan))
        points = np.column_stack([world_xy, np.full(len(pixels), plane.height)])
        distance = np.linalg.norm(points - camera.centre, axis=1)
        nearer = valid & (distance < best_distance)
        best_distance[nearer] = distance[nearer]
        expected[nearer] = plane.plane_id
    rendered = plane_ids[rows.ravel(), columns.ravel()]
    agreement = (rendered == expected).mean()
    assert agreement > 0.998, agreement  # disagreements only on plane edges
    assert (expected == 2).sum() > 50 and (expected == 3).sum() > 10

    # Each id decodes with its own plane.
    world_xy, valid, ids = reference.planes.decode(reference.pixels.reshape(-1, 3))
    assert set(np.unique(ids[valid]).tolist()) == {1, 2, 3}
    assert table.contains(world_xy[ids == 2]).all()


def test_plane_above_ground_needs_posed_camera():
    camera = Camera.from_homography("h", posed_camera().homography, (640, 360))
    with pytest.raises(Exception, match="known only by a homography"):
        render_reference(camera, PlaneSpec(1, (0, 0), 5, 5, height=1.0))


def test_strong_lens_colour_lookup_is_exact_and_homography_is_not():
    """Raw pixels of a k1 = -0.3 lens: the reference (rendered for the raw frame) is within
    one step of the exact ray hit; the plain homography, which ignores the lens, is not."""
    camera = posed_camera(distortion=STRONG_LENS)
    reference = render_reference(camera, GROUND)
    generator = np.random.default_rng(7)
    pixels = np.rint(generator.uniform([0, 0], [639, 359], size=(5000, 2)))
    exact, exact_valid = camera.pixel_to_world(pixels)
    colour_xy, colour_valid = reference.locate(pixels)
    homography_xy, homography_valid = HomographyLocator.from_camera(camera).locate(pixels)
    both = exact_valid & colour_valid & homography_valid
    assert both.sum() > 3000
    step = np.array(GROUND.step)
    colour_error = np.abs(colour_xy[both] - exact[both]) / step
    homography_error = np.hypot(*(homography_xy[both] - exact[both]).T)
    print(
        f"\nsynthetic k1=-0.3: colour error max {colour_error.max():.2f} steps; plain "
        f"homography error median {np.median(homography_error):.3f} m, "
        f"max {homography_error.max():.2f} m"
    )
    assert colour_error.max() <= 1.0
    assert np.median(homography_error) > 0.1  # > 100 quantisation steps
    assert np.median(homography_error) > 100 * step.max()


# ---------------------------------------------------------------------- corrupt files
def _chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    chunks, offset = [], 8
    while offset < len(data):
        (length,) = struct.unpack(">I", data[offset : offset + 4])
        chunks.append((data[offset + 4 : offset + 8], data[offset + 8 : offset + 8 + length]))
        offset += 12 + length
    return chunks


def _png(chunks: list[tuple[bytes, bytes]]) -> bytes:
    out = b"\x89PNG\r\n\x1a\n"
    for kind, body in chunks:
        out += struct.pack(">I", len(body)) + kind + body
        out += struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)
    return out


def _with_metadata(data: bytes, **changes) -> bytes:
    """The same PNG with fields of its cblrs metadata replaced."""
    chunks = []
    for kind, body in _chunks(data):
        if kind == b"tEXt" and body.startswith(b"cblrs\x00"):
            metadata = json.loads(body[6:])
            metadata.update(changes)
            body = b"cblrs\x00" + json.dumps(metadata).encode()
        chunks.append((kind, body))
    return _png(chunks)


def _without_metadata(data: bytes) -> bytes:
    return _png([chunk for chunk in _chunks(data) if chunk[0] != b"tEXt"])


def _flip_idat_byte(data: bytes) -> bytes:
    chunks = _chunks(data)
    index = next(i for i, (kind, _) in enumerate(chunks) if kind == b"IDAT")
    body = bytearray(chunks[index][1])
    body[len(body) // 2] ^= 0xFF
    # Recompute the CRC so that only the compressed stream is damaged.
    chunks[index] = (b"IDAT", bytes(body))
    return _png(chunks)


def _flip_byte_keep_crc(data: bytes) -> bytes:
    damaged = bytearray(data)
    damaged[len(damaged) // 2] ^= 0xFF
    return bytes(damaged)


def _eight_bit_pixels_sixteen_bit_spec(data: bytes, references) -> bytes:
    eight = references[8].to_png_bytes()
    sixteen_planes = references[16].planes.to_list()
    return _with_metadata(eight, bits=16, planes=sixteen_planes)


CORRUPTIONS = {
    "not a png": (lambda data, refs: b"GIF89a" + data[6:], "is not a PNG file"),
    "empty file": (lambda data, refs: b"", "is not a PNG file"),
    "truncated": (lambda data, refs: data[: len(data) // 2], "the PNG file is truncated"),
    "truncated header": (lambda data, refs: data[:12], "the PNG file is truncated"),
    "flipped byte": (lambda data, refs: _flip_byte_keep_crc(data), "corrupt"),
    "flipped compressed byte": (lambda data, refs: _flip_idat_byte(data), "image data is corrupt"),
    "missing spec": (lambda data, refs: _without_metadata(data), "has no cblrs plane spec"),
    "unknown bit depth": (lambda data, refs: _with_metadata(data, bits=12), "unknown bit depth 12"),
    "wrong format": (
        lambda data, refs: _with_metadata(data, format="other/9"),
        "unsupported reference format 'other/9'",
    ),
    "declared size differs": (
        lambda data, refs: _with_metadata(data, image_size=[100, 100]),
        "image is 640x360 but its specification says 100x100",
    ),
    "16-bit spec, 8-bit pixels": (
        _eight_bit_pixels_sixteen_bit_spec,
        "pixels are uint8 but the specification says 16-bit",
    ),
    "bad plane list": (
        lambda data, refs: _with_metadata(data, planes=[{"plane_id": 0}]),
        "invalid plane specification",
    ),
}


@pytest.mark.parametrize("case", list(CORRUPTIONS))
def test_corrupt_png_gives_clear_error(tmp_path, references, case):
    corrupt, message = CORRUPTIONS[case]
    path = tmp_path / "bad.png"
    path.write_bytes(corrupt(references[16].to_png_bytes(), references))
    with pytest.raises(ReferenceImageError, match=message) as info:
        ReferenceImage.load(path)
    assert "\n" not in str(info.value)


def test_plain_png_without_spec(tmp_path):
    path = tmp_path / "plain.png"
    cv2.imwrite(str(path), np.zeros((10, 10, 3), dtype=np.uint8))
    with pytest.raises(ReferenceImageError, match="has no cblrs plane specification"):
        ReferenceImage.load(path)


def test_wrong_size_for_the_camera(tmp_path, references):
    path = references[8].save(tmp_path / "ref.png")
    with pytest.raises(
        ReferenceImageError, match="image is 640x360 but the camera frame is 1920x1080"
    ):
        ReferenceImage.load(path, expected_size=(1920, 1080))


def test_missing_file_and_wrong_suffix(tmp_path, references):
    with pytest.raises(ReferenceImageError, match="does not exist"):
        ReferenceImage.load(tmp_path / "missing.png")
    with pytest.raises(ReferenceImageError, match=r"is not a \.png"):
        references[8].save(tmp_path / "ref.jpg")


@pytest.mark.parametrize(
    ("pixels", "planes", "message"),
    [
        (np.zeros((4, 4), dtype=np.uint8), ground(8), r"must have shape \(H, W, 3\)"),
        (np.zeros((4, 4, 3), dtype=np.uint8), ground(16), "16-bit planes need uint16 pixels"),
        (np.zeros((4, 4, 3), dtype=np.uint16), ground(8), "8-bit planes need uint8 pixels"),
    ],
)
def test_invalid_reference_arrays(pixels, planes, message):
    with pytest.raises(ReferenceImageError, match=message):
        ReferenceImage(pixels=pixels, planes=PlaneSet([planes]))


def test_colours_at_outside_image_and_coverage(references):
    reference = references[8]
    colours, valid = reference.colours_at(
        np.array([[-1.0, 200.0], [640.0, 200.0], [np.nan, 1.0], [320.0, 300.0]])
    )
    assert valid.tolist() == [False, False, False, True]
    assert colours[:3].tolist() == [[0, 0, 0]] * 3
    assert 0.5 < reference.coverage() < 0.9


@pytest.mark.parametrize("view", range(7))
def test_wildtrack_lens_colour_lookup_is_exact(view, wildtrack_distorted_cameras):
    """WILDTRACK's raw-video calibration (intrinsic_original): the reference rendered for the
    distorted frame reads within one 16-bit step of the exact ray hit; a plain homography
    (no undistortion) misses by centimetres to metres."""
    from core_cameras import wildtrack_plane

    camera = wildtrack_distorted_cameras[view]
    plane = wildtrack_plane(16)
    reference = render_reference(camera, plane)
    generator = np.random.default_rng(view)
    pixels = np.rint(generator.uniform([0, 0], [1919, 1079], size=(3000, 2)))
    exact, exact_valid = camera.pixel_to_world(pixels)
    colour_xy, colour_valid = reference.locate(pixels)
    homography_xy, homography_valid = HomographyLocator.from_camera(camera).locate(pixels)
    both = (
        exact_valid
        & colour_valid
        & homography_valid
        & plane.contains(np.where(exact_valid[:, None], exact, np.nan))
    )
    assert both.sum() > 1000
    colour_error = np.abs(colour_xy[both] - exact[both]) / np.array(plane.step)
    homography_error = np.hypot(*(homography_xy[both] - exact[both]).T)
    print(
        f"\n{camera.name} (distorted): colour error max {colour_error.max():.2f} steps; plain "
        f"homography median {np.median(homography_error):.3f} m, max {homography_error.max():.2f} m"
    )
    assert colour_error.max() <= 1.0
    assert np.median(homography_error) > 0.03  # > 50 steps of 0.55 mm
    assert homography_error.max() > 1.0
