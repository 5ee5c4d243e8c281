"""A plain homography + norfair multi-camera tracker for WILDTRACK: the yardstick of
``cblrs bench versus``.

It is what someone without cblrs would write to track WILDTRACK's annotated boxes on the
ground: each camera's ground homography from its calibration, every box's bottom centre
projected onto the ground, and norfair's tracker run on the ground points (euclidean distance
in metres). Two variants:

* ``merged`` (the default): first the points of one frame that lie within a metre of each
  other are merged into one, so that each person is one detection;
* ``every-box`` (``--every-box``): every camera's point is a detection of its own, the
  simplest pipeline of all (the same person seen by five cameras is five detections, and
  norfair keeps extra tracks for them).

It imports no cblrs module on purpose, so that running it as a script measures only what such
a pipeline costs::

    python src/cblrs/bench/norfair_baseline.py ../shared/data/wildtrack tracks.txt [--every-box]

It writes the AI City rows ``cblrs eval`` reads (camera -1 and no box: a world track only).
Needs norfair (``pip install -e ".[dev]"`` brings the maintained ``norfair-enough``, which
installs as ``norfair``: the original's numpy < 2 pin conflicts with TrackEval).
"""

from __future__ import annotations

import json
import sys
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import cv2
import numpy as np
from norfair import Detection, Tracker

CAMERAS = ("CVLab1", "CVLab2", "CVLab3", "CVLab4", "IDIAP1", "IDIAP2", "IDIAP3")
CENTIMETRES_TO_METRES = 0.01
MERGE_RADIUS_M = 1.0
DISTANCE_THRESHOLD_M = 1.5


def ground_homographies(root: Path) -> list[np.ndarray]:
    """Per camera the 3x3 homography from undistorted image pixels to ground metres."""
    homographies = []
    for name in CAMERAS:
        storage = cv2.FileStorage(
            str(root / "calibrations" / "intrinsic_zero" / f"intr_{name}.xml"),
            cv2.FILE_STORAGE_READ,
        )
        intrinsic = storage.getNode("camera_matrix").mat()
        storage.release()
        extrinsic = ElementTree.parse(root / "calibrations" / "extrinsic" / f"extr_{name}.xml")
        rvec = np.array(extrinsic.findtext("rvec", "").split(), dtype=np.float64)
        tvec = np.array(extrinsic.findtext("tvec", "").split(), dtype=np.float64)
        rotation, _ = cv2.Rodrigues(rvec)
        # The ground is z = 0: the projection of (x, y, 0) is K [r1 r2 t] (x, y, 1).
        world_to_image = intrinsic @ np.column_stack([rotation[:, 0], rotation[:, 1], tvec])
        homography = np.linalg.inv(world_to_image)
        homographies.append(np.diag([CENTIMETRES_TO_METRES, CENTIMETRES_TO_METRES, 1.0])
                            @ homography)
    return homographies


def frame_feet(path: Path) -> list[np.ndarray]:
    """Per camera the (N, 2) bottom centres of the annotated boxes of one frame file."""
    feet: list[list[tuple[float, float]]] = [[] for _ in CAMERAS]
    for person in json.loads(path.read_text()):
        for view in person["views"]:
            if view["xmax"] == -1:
                continue
            feet[view["viewNum"]].append(((view["xmin"] + view["xmax"]) / 2.0, view["ymax"]))
    return [np.array(points, dtype=np.float64).reshape(-1, 2) for points in feet]


def project(homography: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Ground points (N, 2) metres of pixels (N, 2)."""
    if len(pixels) == 0:
        return pixels
    return cv2.perspectiveTransform(pixels[None], homography)[0]


def merge(points: np.ndarray, radius: float = MERGE_RADIUS_M) -> np.ndarray:
    """One point per group of points within ``radius`` of a seed (greedy, seeds in order)."""
    merged = []
    free = np.ones(len(points), dtype=bool)
    for index in range(len(points)):
        if not free[index]:
            continue
        near = free & (np.linalg.norm(points - points[index], axis=1) < radius)
        merged.append(points[near].mean(axis=0))
        free &= ~near
    return np.array(merged).reshape(-1, 2)


def track(root: Path, out: Path, merge_views: bool = True) -> int:
    """Track the folder's annotated frames and write the rows; the number of rows."""
    homographies = ground_homographies(root)
    tracker = Tracker(
        distance_function="euclidean",
        distance_threshold=DISTANCE_THRESHOLD_M,
        hit_counter_max=4,
        initialization_delay=1,
    )
    rows = []
    for path in sorted((root / "annotations_positions").glob("*.json")):
        frame = int(path.stem)
        feet = frame_feet(path)
        ground = np.concatenate([project(homography, pixels)
                                 for homography, pixels in zip(homographies, feet, strict=True)])
        points = merge(ground) if merge_views else ground
        detections = [Detection(points=point[None]) for point in points]
        for tracked in tracker.update(detections=detections):
            x, y = tracked.estimate[0]
            rows.append(f"-1 {tracked.id} {frame} -1 -1 -1 -1 {x:.4f} {y:.4f}\n")
    out.write_text("".join(rows))
    return len(rows)


def main(argv: list[str]) -> int:
    """``norfair_baseline.py WILDTRACK OUT.txt [--every-box]``; the exit code."""
    words = [word for word in argv if word != "--every-box"]
    if len(words) != 2 or any(word.startswith("-") for word in words):
        print("usage: norfair_baseline.py WILDTRACK_FOLDER OUT.txt [--every-box]",
              file=sys.stderr)
        return 2
    root, out = Path(words[0]), Path(words[1])
    if not (root / "annotations_positions").is_dir():
        print(f"{root} is not a WILDTRACK folder (no annotations_positions/).", file=sys.stderr)
        return 1
    track(root, out, merge_views="--every-box" not in argv)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
