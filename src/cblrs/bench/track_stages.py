"""Where the CPU time of ``cblrs track`` on WILDTRACK goes, stage by stage, in a fresh process.

Run as a script (``python src/cblrs/bench/track_stages.py WILDTRACK``), not as a module of the
package: importing ``cblrs.bench`` first would load what the stages are meant to time. It
imports numpy (OpenCV is not loaded by ``cblrs track`` on WILDTRACK: the calibration files
are read and the cameras posed without it; SciPy's two solvers come with the matching
modules, :mod:`cblrs.matching.solvers`), then the cblrs modules ``cblrs track`` runs
(not the command line's own, which the library must not import), then runs the stages of
``cblrs track`` (load, the tracker's views of the ground from the reference colours, the
cameras' messages, ordering, tracking, writing) as
:func:`cblrs.pipeline.track_scene` does, and prints the CPU seconds of each
(``time.process_time``) as JSON. ``cblrs bench track`` runs it and reports the medians.
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path


def measure(root: Path) -> dict[str, float]:
    """CPU seconds of each stage of tracking ``root`` (imports included)."""
    seconds: dict[str, float] = {}
    start = time.process_time()
    import numpy  # noqa: F401

    seconds["numpy import"] = time.process_time() - start
    start = time.process_time()
    from cblrs.datasets import load_scene, write_tracks
    from cblrs.matching import make_matcher
    from cblrs.pipeline import (
        camera_messages,
        camera_positions,
        ordered_windows,
        run_matcher,
        scene_references,
    )

    seconds["cblrs imports"] = time.process_time() - start
    start = time.process_time()
    scene = load_scene(root)
    seconds["load the data set"] = time.process_time() - start
    start = time.process_time()
    references = scene_references(scene)
    matcher = make_matcher("fusion", references[0].planes, scene.camera_names,
                           camera_positions=camera_positions(scene))
    matcher.set_views(references)
    seconds["the tracker's views (reference colours)"] = time.process_time() - start
    start = time.process_time()
    messages = camera_messages(scene, references)
    seconds["cameras' messages"] = time.process_time() - start
    start = time.process_time()
    windows = list(ordered_windows(messages, scene.camera_names))
    seconds["ordering"] = time.process_time() - start
    start = time.process_time()
    tracks, *_ = run_matcher(matcher, windows)
    seconds["fusion tracker"] = time.process_time() - start
    start = time.process_time()
    with tempfile.TemporaryDirectory() as folder:
        write_tracks(Path(folder) / "tracks.txt", tracks,
                     frames_per_second=scene.frames_per_second)
    seconds["write the tracks"] = time.process_time() - start
    return seconds


if __name__ == "__main__":
    if len(sys.argv) != 2:
        print("usage: track_stages.py WILDTRACK_FOLDER", file=sys.stderr)
        sys.exit(2)
    print(json.dumps(measure(Path(sys.argv[1]))))
