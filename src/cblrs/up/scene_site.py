"""A live site from a scene: ``cblrs demo``'s live part, which ``cblrs up`` runs.

:func:`write_scene_site` writes a site file whose cameras are a scene's cameras (inline
calibrations), its plane the scene's plane, and whose sources replay the scene's boxes
(one MOT detections file per camera, its people: a MOT file has no class)::

    <folder>/site.yaml                 the site: plane, cameras, sources, places, alerts
    <folder>/detections/<camera>.txt   the camera's boxes, frame by frame (MOT format)

The site also gets the scene's places (its zones and counting lines) and alert rules when
given: :func:`scene_places` reads the places of the scene's checked-in site file
(``sites/<scene>.yaml``, the ones the offline analytics and ``cblrs experiment counts`` use),
and :data:`DEMO_ALERT_RULES` holds the demo's rules, so the live map shows counts and an alert
fires and clears while the replay runs.

A synthetic scene lasts seconds; to keep people on the map for minutes the replay plays the
scene forward, then backward, then forward again, ... for ``replay_s``: positions stay
continuous where the direction turns, so tracks go on rather than jump.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cblrs.detections import class_id_of
from cblrs.site import load_site
from cblrs.site.cameras import camera_entry
from cblrs.up.plan import safe_stem

SITES = Path(__file__).resolve().parents[3] / "sites"
"""The repository's checked-in site files (absent from an installed wheel)."""
DEMO_ALERT_RULES: dict[str, tuple[dict[str, Any], ...]] = {
    # The plaza's centre (8 x 6 m) holds 1 to 7 people most of the time; twice in each 60 s
    # of the back-and-forth replay (from its 11th and 45th second) 9 to 11 gather there for
    # about 5 s (4 s as the tracker counts confirmed tracks): the episode fires about 15 s
    # after the replay's first capture time (the matcher's 2 s window included) and clears
    # 2 s later.
    "plaza": ({"name": "crowd", "kind": "occupancy", "zone": "centre", "above": 7,
               "for_s": 2.0},),
}
"""The demo's alert rules per scene (site file ``alerts: rules:`` entries; no webhook: the
dashboard and ``cblrs up`` show them)."""
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


def scene_places(scene_name: str, sites: str | Path = SITES) -> dict[str, Any] | None:
    """The ``places:`` of the scene's checked-in site file ``<sites>/<scene_name>.yaml`` as
    written there (zones and counting lines); None when there is no such file (an installed
    wheel has no ``sites/``) or it has no places.

    Raises:
        cblrs.site.SiteError: the file exists but is not a valid site file.
    """
    path = Path(sites) / f"{scene_name}.yaml"
    if not path.is_file():
        return None
    load_site(path)  # a broken file is one sentence, not a live site that fails later
    document = yaml.safe_load(path.read_text()) or {}
    return document.get("places") or None


def demo_places_and_rules(scene_name: str, sites: str | Path = SITES
                          ) -> tuple[dict[str, Any] | None, tuple[dict[str, Any], ...]]:
    """What ``cblrs demo``'s live site of a scene counts and watches: the places of its
    checked-in site file (:func:`scene_places`) and, with them, :data:`DEMO_ALERT_RULES`
    (none without places: the rules name them)."""
    places = scene_places(scene_name, sites)
    return places, (DEMO_ALERT_RULES.get(scene_name, ()) if places else ())


def write_scene_site(scene: Any, folder: str | Path, replay_s: float = LIVE_REPLAY_S,
                     name: str | None = None, places: dict[str, Any] | None = None,
                     alert_rules: Sequence[dict[str, Any]] = ()) -> Path:
    """Write the live site of ``scene`` into ``folder`` (see the module docstring); its path.

    Args:
        scene: a :class:`~cblrs.datasets.scene.Scene` (cameras with a calibration, boxes).
        folder: where the site file and the detections go (created).
        replay_s: length of the replay, seconds (at least the scene once).
        name: the site's name (default ``<scene>-live``).
        places: the site file's ``places:`` (zones and lines, metres on the scene's plane),
            e.g. :func:`scene_places`; None: none.
        alert_rules: the site file's ``alerts: rules:`` (they name the places' zones and
            lines), e.g. :data:`DEMO_ALERT_RULES`; empty: no alerts.
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
    if places:
        document["places"] = places
    if alert_rules:
        document["alerts"] = {"rules": [dict(rule) for rule in alert_rules]}
    site = folder / "site.yaml"
    header = (f"# Written by cblrs demo: the {scene.name} scene replayed live by cblrs up "
              f"({len(scene.frames)} frames played back and forth for {total / fps:.0f} s).\n")
    site.write_text(header + yaml.safe_dump(document, sort_keys=False))
    return site
