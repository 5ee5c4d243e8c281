"""A live site from a scene: ``cblrs demo``'s live part, which ``cblrs up`` runs.

:func:`write_scene_site` writes a site file whose cameras are a scene's cameras (inline
calibrations), its plane the scene's plane, and whose sources replay the scene's boxes
(one MOT detections file per camera, its people: a MOT file has no class)::

    <folder>/site.yaml                 the site: plane, cameras, sources
    <folder>/detections/<camera>.txt   the camera's boxes, frame by frame (MOT format)

A synthetic scene lasts seconds; to keep people on the map for minutes the replay plays the
scene forward, then backward, then forward again, ... for ``replay_s``: positions stay
continuous where the direction turns, so tracks go on rather than jump.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cblrs.detections import class_id_of
from cblrs.site.cameras import camera_entry
from cblrs.up.plan import safe_stem

LIVE_REPLAY_S = 300.0
"""How long the demo's live replay lasts (the scene played back and forth)."""
PERSON = class_id_of("person")
"""The class id of people (the synthetic scenes' cars are left out of the replay)."""


def ping_pong(count: int, total: int) -> np.ndarray:
    """Frame indices ``0..count-1``, then back to 0, then forth again, ``total`` in all.

    Example:
        >>> ping_pong(3, 7).tolist()
        [0, 1, 2, 1, 0, 1, 2]
    """
    if count <= 1:
        return np.zeros(total, dtype=np.int64)
    period = 2 * (count - 1)
    phase = np.arange(total) % period
    return np.where(phase < count, phase, period - phase).astype(np.int64)


def write_scene_site(scene: Any, folder: str | Path, replay_s: float = LIVE_REPLAY_S,
                     name: str | None = None) -> Path:
    """Write the live site of ``scene`` into ``folder`` (see the module docstring); its path.

    Args:
        scene: a :class:`~cblrs.datasets.scene.Scene` (cameras with a calibration, boxes).
        folder: where the site file and the detections go (created).
        replay_s: length of the replay, seconds (at least the scene once).
        name: the site's name (default ``<scene>-live``).
    """
    folder = Path(folder)
    (folder / "detections").mkdir(parents=True, exist_ok=True)
    interval = float(scene.frame_interval) or 0.1
    fps = 1.0 / interval
    total = max(len(scene.frames), round(replay_s * fps))
    order = ping_pong(len(scene.frames), total)
    cameras = []
    for index, camera in enumerate(scene.cameras):
        path = folder / "detections" / f"{safe_stem(camera.name)}.txt"
        lines = []
        for frame, position in enumerate(order, start=1):
            boxes = scene.detections[position][index]
            people = boxes.class_id == PERSON  # a MOT file's rows are read as people
            for box, confidence in zip(boxes.xyxy[people], boxes.confidence[people],
                                       strict=True):
                x1, y1, x2, y2 = (float(value) for value in box)
                lines.append(f"{frame},-1,{x1:.2f},{y1:.2f},{x2 - x1:.2f},{y2 - y1:.2f},"
                             f"{float(confidence):.3f},-1,-1,-1")
        path.write_text("\n".join(lines) + "\n")
        entry = camera_entry(camera)
        entry["source"] = {"kind": "detections", "path": f"detections/{path.name}",
                           "fps": round(fps, 6), "format": "mot"}
        cameras.append(entry)
    plane = scene.plane
    document = {
        "version": 1,
        "name": name or f"{scene.name}-live",
        "planes": [{"id": int(plane.plane_id), "name": plane.name or "ground",
                    "origin": [float(value) for value in plane.origin],
                    "size": [float(plane.width), float(plane.length)],
                    "bits": int(plane.bits)}],
        "cameras": cameras,
    }
    site = folder / "site.yaml"
    header = (f"# Written by cblrs demo: the {scene.name} scene replayed live by cblrs up "
              f"({len(scene.frames)} frames played back and forth for {total / fps:.0f} s).\n")
    site.write_text(header + yaml.safe_dump(document, sort_keys=False))
    return site
