"""Shared fixtures: the WILDTRACK and MultiviewX data folders, the shipped ONNX detector;
the order in which the test files run."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
FILE_DURATIONS = Path(__file__).with_name("file_durations.json")
"""Measured seconds per test file (scripts/file_durations.py writes it from a JUnit report)."""


def pytest_configure(config):
    """Under pytest-xdist, hand out the test files in collection order (see below) rather than
    by number of tests, xdist's default: that default starts the files of many quick
    parametrised tests and leaves the few long files (brokers, ``cblrs up``, browsers) to
    the end, where one of them runs alone while the other workers idle."""
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(config, items):
    """Run the longest files first (``--dist loadfile`` gives a worker one file at a time, so
    a long file started last ends the suite alone). Files not in file_durations.json (new
    ones) run first, since one of them may be long; the order within a file is kept."""
    try:
        seconds = json.loads(FILE_DURATIONS.read_text())
    except (OSError, ValueError):
        return
    root = Path(str(config.rootpath))

    def cost(item) -> float:
        try:
            name = Path(str(item.path)).relative_to(root).as_posix()
        except ValueError:
            return 0.0
        return float(seconds.get(name, float("inf")))

    items.sort(key=lambda item: -cost(item))  # stable: a file's tests stay in their order


def find_wildtrack() -> Path | None:
    """WILDTRACK from $CBLRS_WILDTRACK or ../shared/data/wildtrack beside the repository."""
    candidates = [os.environ.get("CBLRS_WILDTRACK"), REPO_ROOT.parent / "shared/data/wildtrack"]
    for candidate in candidates:
        if candidate and (Path(candidate) / "calibrations").is_dir():
            return Path(candidate)
    return None


@pytest.fixture(scope="session")
def wildtrack_root() -> Path:
    root = find_wildtrack()
    if root is None:
        pytest.skip("WILDTRACK data not found (set CBLRS_WILDTRACK or put it in ../shared/data)")
    return root


@pytest.fixture(scope="session")
def wildtrack_first_frames(wildtrack_root, tmp_path_factory):
    """``first(count)``: a folder of WILDTRACK's first ``count`` annotated frames (of 200):
    links to its calibrations and to those frames' annotation files, for the tests whose
    checks do not need every frame and that would otherwise track all 200 in a subprocess or
    under tracemalloc. WILDTRACK is at 2 fps: 40 frames are its first 20 seconds."""
    folders: dict[int, Path] = {}

    def first(count: int) -> Path:
        if count not in folders:
            root = tmp_path_factory.mktemp(f"wildtrack_first_{count}")
            (root / "calibrations").symlink_to(wildtrack_root / "calibrations")
            (root / "annotations_positions").mkdir()
            annotations = sorted((wildtrack_root / "annotations_positions").glob("*.json"))
            for path in annotations[:count]:
                (root / "annotations_positions" / path.name).symlink_to(path)
            folders[count] = root
        return folders[count]

    return first


def find_multiviewx() -> Path | None:
    """The real MultiviewX folder (images, annotations, left-handed calibrations) in ../shared."""
    candidates = [os.environ.get("CBLRS_MULTIVIEWX"), REPO_ROOT.parent / "shared/data/multiviewx"]
    for candidate in candidates:
        if candidate and (Path(candidate) / "calibrations").is_dir():
            return Path(candidate)
    return None


def find_yolox_model() -> Path | None:
    """The shipped YOLOX-Nano ONNX model (../shared/models/yolox_nano.onnx)."""
    path = REPO_ROOT.parent / "shared/models/yolox_nano.onnx"
    return path if path.is_file() else None


@pytest.fixture(scope="session")
def multiviewx_real_root() -> Path:
    root = find_multiviewx()
    if root is None:
        pytest.skip("MultiviewX data not found (set CBLRS_MULTIVIEWX or put it in ../shared/data)")
    return root


@pytest.fixture(scope="session")
def yolox_model() -> Path:
    path = find_yolox_model()
    if path is None:
        pytest.skip("the shipped detector ../shared/models/yolox_nano.onnx is missing")
    return path


@pytest.fixture(autouse=True)
def _camera_spools_in_a_temporary_folder(tmp_path_factory, monkeypatch):
    """``cblrs camera`` keeps a spool file per camera (default under ~/.local/state): tests
    that run it without --spool keep theirs in a folder of their own (a spool refuses
    another run's messages, so tests must not share one)."""
    monkeypatch.setenv("CBLRS_SPOOL_DIR", str(tmp_path_factory.mktemp("camera-spools")))
