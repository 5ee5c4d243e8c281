"""A camera's ``source:`` in the site file (what ``cblrs up`` runs): optional, checked, and
old site files stay valid."""

from __future__ import annotations

from pathlib import Path

import pytest

from cblrs.site import load_site, parse_site
from cblrs.site.schema import SiteError

REPO = Path(__file__).resolve().parents[2]
CAMERA = ("{name: gate, image_size: [1280, 720], homography: [[-27.66, 11.3, 654.0], "
          "[1.25, 0.87, 64.5], [-0.0207, -0.0145, 1]]%s}")


def site_with(source: str) -> str:
    extra = f", source: {source}" if source else ""
    return ("version: 1\nplanes: [{id: 1, origin: [0, 0], size: [20, 10]}]\ncameras:\n  - "
            + CAMERA % extra + "\n")


@pytest.mark.parametrize("path", sorted((REPO / "sites").glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_site_file_still_loads(path):
    site = load_site(path)
    live = path.name.endswith("-live.yaml")
    assert all((camera.source is not None) == live for camera in site.model.cameras)


def test_a_camera_without_a_source_is_valid():
    assert parse_site(site_with("")).model.cameras[0].source is None


@pytest.mark.parametrize(("source", "kind"), [
    ("{kind: dataset, path: ../data/wildtrack, frames: '0:195'}", "dataset"),
    ("{kind: detections, path: gate.txt, fps: 10, format: mot}", "detections"),
    ("{kind: video, path: gate.mp4, detector: {kind: onnx, model: m.onnx, confidence: 0.3}}",
     "video"),
    ("{kind: images, path: frames/, fps: 2, detector: {kind: blob, colour: [255, 0, 0]}}",
     "images"),
    ("{kind: url, url: 'rtsp://10.0.0.5/stream1', detector: {kind: yolo, weights: y.pt}}",
     "url"),
])
def test_sources_of_every_kind(source, kind):
    assert parse_site(site_with(source)).model.cameras[0].source.kind == kind


@pytest.mark.parametrize(("source", "message"), [
    ("{kind: webcam, path: x}", "cameras[0].source.kind"),
    ("{kind: dataset}", "a dataset source needs path"),
    ("{kind: url, path: x.mp4, detector: {kind: blob}}", "a url source needs url"),
    ("{kind: video, path: gate.mp4}", "a video source needs detector"),
    ("{kind: detections, path: gate.txt}", "needs fps"),
    ("{kind: dataset, path: x, detector: {kind: blob}}", "takes no detector"),
    ("{kind: dataset, path: x, frames: 'first:last'}", "must be FIRST:LAST"),
    ("{kind: video, path: v.mp4, detector: {kind: onnx}}", "an onnx detector needs model"),
    ("{kind: dataset, path: x, colour: red}", "unknown key (allowed: kind, path, url"),
])
def test_bad_sources_are_one_sentence(source, message):
    with pytest.raises(SiteError) as raised:
        parse_site(site_with(source))
    text = str(raised.value)
    assert message in text and text.count("\n") == 0 and text.startswith("site.yaml: cameras[0]")
