"""Fixtures for site tests: the documentation's example site (docs/sites.md) with the files it
refers to."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from cblrs.calibration import camera_to_dict
from cblrs.camera import Camera

REPO_ROOT = Path(__file__).resolve().parents[2]


SITES_PAGE = REPO_ROOT / "docs" / "sites.md"


def site_example() -> str:
    """The YAML block after ``<!-- site-example -->`` in docs/sites.md."""
    text = SITES_PAGE.read_text()
    match = re.search(r"<!-- site-example -->\s*```yaml\n(.*?)```", text, re.S)
    assert match, "docs/sites.md has no site example"
    return match.group(1)


@pytest.fixture
def example_site(tmp_path) -> Path:
    """The documented example written to ``tmp_path/site.yaml`` with its map, CSV and JSON files.

    The files it names are made here from known cameras: ``north`` is a posed camera in
    cblrs camera JSON, ``east``'s clicks are exact projections given in map pixels.
    """
    path = tmp_path / "site.yaml"
    path.write_text(site_example())
    cv2.imwrite(str(tmp_path / "plan.png"), np.full((900, 1000, 3), 230, np.uint8))
    north = Camera.from_pose("north", (12.0, 27.0, 7.0), -90, 30, 1100, (1920, 1080))
    (tmp_path / "calibrations").mkdir()
    (tmp_path / "calibrations" / "north.json").write_text(json.dumps(camera_to_dict(north)))
    east = Camera.from_pose("east", (36.0, 8.0, 5.0), 180, 25, 950, (1280, 720))
    world = np.array([[x, y] for x in (10.0, 18.0, 26.0) for y in (1.0, 7.0, 13.0)])
    pixels, _ = east.world_to_pixel(world)
    # map pixel = origin + world / scale, y up: origin (120, 880), 0.05 m per pixel
    map_px = np.column_stack([120 + world[:, 0] / 0.05, 880 - world[:, 1] / 0.05])
    rows = ["u,v,x,y,name"] + [
        f"{u:.3f},{v:.3f},{mx:.1f},{my:.1f},p{index}"
        for index, ((u, v), (mx, my)) in enumerate(zip(pixels, map_px, strict=True))
    ]
    (tmp_path / "clicks").mkdir()
    (tmp_path / "clicks" / "east.csv").write_text("\n".join(rows) + "\n")
    return path
