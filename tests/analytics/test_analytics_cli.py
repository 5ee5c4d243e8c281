"""``cblrs analytics`` end to end on real WILDTRACK tracks, the site files, bad input."""

from __future__ import annotations

import csv
import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from cblrs.analytics.site import load_site_places
from cblrs.cli.main import main
from cblrs.datasets import (
    apply_track_metadata,
    read_track_metadata,
    read_tracks,
    write_tracks,
)
from cblrs.datasets.aicity import metadata_path, metadata_timestamps
from cblrs.detections import Tracks
from cblrs.errors import DatasetError

REPOSITORY = Path(__file__).resolve().parents[2]
SITES = REPOSITORY / "sites"
WILDTRACK = REPOSITORY.parent / "shared" / "data" / "wildtrack"
needs_wildtrack = pytest.mark.skipif(
    not (WILDTRACK / "calibrations").is_dir(), reason="WILDTRACK not found in ../shared/data"
)


@pytest.fixture(scope="module")
def wildtrack_tracks(tmp_path_factory) -> Path:
    if not (WILDTRACK / "calibrations").is_dir():
        pytest.skip("WILDTRACK not found in ../shared/data")
    path = tmp_path_factory.mktemp("tracks") / "tracks.txt"
    assert main(["track", str(WILDTRACK), "--out", str(path), "--quiet"]) == 0
    return path


@needs_wildtrack
def test_analytics_on_wildtrack_writes_tables_and_pictures(wildtrack_tracks, tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["analytics", str(wildtrack_tracks), "--site", str(SITES / "wildtrack.yaml"),
                 "--out", str(out), "--json"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames_per_second"] == 10.0 and summary["classes_known"]
    north = {row["direction"]: row["count"] for row in summary["lines"]
             if row["line"] == "north_flow"}
    assert north["positive"] > 80  # the main flow walks north-west through this line
    names = {path.name for path in out.iterdir()}
    assert {"lines.csv", "zones.csv", "od.csv", "crossings.csv", "visits.csv", "occupancy.csv",
            "counts_over_time.csv", "heatmap.csv", "analytics.json", "places.png",
            "counts_over_time.png", "dwell.png", "heatmap.png", "od.png"} <= names
    for name in ("heatmap.png", "od.png", "counts_over_time.png"):
        image = cv2.imread(str(out / name))
        assert image is not None and image.shape[0] > 200 and image.std() > 5
    crossings = (out / "crossings.csv").read_text().splitlines()
    assert crossings[0] == "timestamp_s,line,track_id,direction,class,x_m,y_m"
    assert len(crossings) - 1 == sum(row["count"] for row in summary["lines"])
    assert "person" in crossings[1]


def test_the_checked_in_site_files_load_with_places():
    for path in sorted(SITES.glob("*.yaml")):
        site = load_site_places(path)
        assert site.name == path.stem and len(site.places) and site.planes, path


def run_cli(args: list[str], capsys) -> tuple[int, str]:
    code = main(args)
    return code, capsys.readouterr().err


def small_tracks(tmp_path: Path, shift: float = 0.0, rate: float | None = 10.0,
                 first_frame: int = 0) -> Path:
    x = np.linspace(-2, 8, 30) + shift
    frames = np.arange(30) + first_frame
    tracks = Tracks(frames, frames / 10.0, np.ones(30, int),
                    np.c_[x, np.full(30, 17.0 + shift)], class_id=np.zeros(30, int))
    path = tmp_path / "t.txt"
    write_tracks(path, tracks, frames_per_second=rate)
    return path


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("no places", "has no places, so there is nothing to count"),
        ("other site", "lie outside every plane of site wildtrack: are these tracks from another"),
        ("missing tracks", "does not exist"),
        ("garbage tracks", "expected 9 columns"),
        # Issue 21: negative frame numbers were taken silently (and changed the counts).
        ("negative frame", "t.txt:1: frame_id must not be negative in '-1 1 -5 "),
        ("no rate", "carries no time: no .meta.json sidecar (cblrs track and cblrs matcher "
                    "--out-tracks write one)"),
        ("stale sidecar", "belongs to another version of t.txt"),
        ("bad yaml", "is not valid YAML"),
        ("unknown key", "colour: unknown key"),
    ],
)
def test_bad_input_gets_one_sentence_and_a_non_zero_exit(case, message, tmp_path, capsys):
    site = SITES / "wildtrack.yaml"
    tracks = small_tracks(tmp_path)
    if case == "no places":
        site = tmp_path / "empty.yaml"
        site.write_text("version: 1\nname: empty\n")
    elif case == "other site":
        tracks = small_tracks(tmp_path, shift=1000.0)
    elif case == "missing tracks":
        tracks = tmp_path / "missing.txt"
    elif case == "garbage tracks":
        tracks = tmp_path / "garbage.txt"
        tracks.write_text("this is not a tracks file\n")
    elif case == "negative frame":
        tracks = small_tracks(tmp_path, first_frame=-5)
    elif case == "no rate":
        tracks = small_tracks(tmp_path, rate=None)
        tracks.with_name("t.txt.meta.json").unlink()
    elif case == "stale sidecar":
        tracks.write_text(tracks.read_text().replace("17.0000", "17.5000", 1))
    elif case == "bad yaml":
        site = tmp_path / "bad.yaml"
        site.write_text("version: 1\nplaces: {zones: [\n")
    elif case == "unknown key":
        site = tmp_path / "extra.yaml"
        site.write_text("version: 1\ncolour: red\nplaces: {lines: []}\n")
    code, err = run_cli(["analytics", str(tracks), "--site", str(site), "--out",
                         str(tmp_path / "out")], capsys)
    assert code != 0
    assert message in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_no_sidecar_but_fps_given_works_without_classes(tmp_path, capsys):
    tracks = small_tracks(tmp_path, rate=None)
    tracks.with_name("t.txt.meta.json").unlink()
    code = main(["analytics", str(tracks), "--site", str(SITES / "wildtrack.yaml"), "--out",
                 str(tmp_path / "out"), "--fps", "10", "--json", "--no-plots"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert not summary["classes_known"]
    assert not (tmp_path / "out" / "heatmap.png").exists()


def test_the_sidecar_round_trips_classes_and_rate_and_the_text_file_is_unchanged(tmp_path):
    tracks = Tracks(np.array([0, 0, 5, 5]), np.zeros(4), np.array([1, 2, 1, 2]),
                    np.zeros((4, 2)), class_id=np.array([0, 1, 0, -1]))
    path = tmp_path / "t.txt"
    write_tracks(path, tracks, frames_per_second=10.0)
    assert all(len(line.split()) == 9 for line in path.read_text().splitlines())
    metadata = read_track_metadata(path)
    assert metadata is not None and metadata.frames_per_second == 10.0
    assert metadata.classes == {1: 0, 2: 1}
    loaded = apply_track_metadata(read_tracks(path), metadata)
    assert loaded.class_id.tolist() == [0, 1, 0, 1]
    write_tracks(path, Tracks(np.zeros(1), np.zeros(1), np.ones(1), np.zeros((1, 2))))
    assert read_track_metadata(path) is None  # no classes, no rate: the old sidecar goes


def test_a_sidecar_that_is_not_one_is_refused(tmp_path):
    path = small_tracks(tmp_path)
    path.with_name("t.txt.meta.json").write_text('{"schema": "other"}')
    with pytest.raises(DatasetError, match=r"is not a cblrs\.tracks-meta/1 sidecar"):
        read_track_metadata(path)


@pytest.mark.parametrize("matcher", ["fusion", "paper"])
def test_both_matchers_report_the_class_of_their_detections(matcher):
    from cblrs.datasets.presets import make_scene
    from cblrs.detections import class_id_of
    from cblrs.pipeline import track_scene

    scene = make_scene("plaza", duration_s=8.0)
    tracks = track_scene(scene, matcher).tracks
    assert set(tracks.class_id.tolist()) <= {class_id_of("person"), class_id_of("car")}
    assert class_id_of("person") in tracks.class_id
    assert set(scene.ground_truth.class_id.tolist()) >= {class_id_of("person")}


def test_the_heatmap_is_drawn_over_the_site_map(tmp_path, capsys):
    plan = np.full((400, 200, 3), 235, np.uint8)
    cv2.rectangle(plan, (40, 40), (160, 360), (90, 160, 90), -1)  # a lawn
    cv2.imwrite(str(tmp_path / "plan.png"), plan)
    places = (SITES / "wildtrack.yaml").read_text().split("places:", 1)[1]
    (tmp_path / "site.yaml").write_text(
        "version: 1\nname: mapped\n"
        "map: {image: plan.png, metres_per_pixel: 0.1, origin_px: [50, 290], y_up: true}\n"
        "places:" + places
    )
    tracks = small_tracks(tmp_path)
    with_map, without_map = tmp_path / "with", tmp_path / "without"
    for site, out in ((tmp_path / "site.yaml", with_map), (SITES / "wildtrack.yaml", without_map)):
        assert main(["analytics", str(tracks), "--site", str(site), "--out", str(out),
                     "--quiet"]) == 0
    capsys.readouterr()
    mapped = cv2.imread(str(with_map / "heatmap.png"))
    plain = cv2.imread(str(without_map / "heatmap.png"))
    assert mapped is not None and plain is not None
    lawn = np.array([90, 160, 90])  # BGR, blended with alpha 0.6 over white
    blended = 0.6 * lawn + 0.4 * 255
    assert (np.abs(mapped.astype(float) - blended).sum(axis=2) < 40).sum() > 1000
    assert (np.abs(plain.astype(float) - blended).sum(axis=2) < 40).sum() < 100


def test_a_sidecar_without_time_is_named(tmp_path, capsys):
    # A sidecar that carries classes only (no frame rate, no timestamps): the error says what
    # the sidecar lacks instead of claiming there is none.
    tracks = Tracks(
        frame=np.array([0, 1], dtype=np.int64), timestamp=np.array([0.0, 1.0]),
        track_id=np.array([1, 1], dtype=np.int64), world_xy=np.array([[0.0, 0.0], [1.0, 0.0]]),
        camera_id=np.array([-1, -1], dtype=np.int64), xyxy=np.full((2, 4), np.nan),
        class_id=np.array([0, 0], dtype=np.int64),
    )
    path = tmp_path / "tracks.txt"
    write_tracks(path, tracks)
    site = tmp_path / "site.yaml"
    site.write_text("version: 1\nplaces:\n  lines:\n"
                    "    - {name: l, start: [0.5, -1], end: [0.5, 1]}\n")
    code = main(["analytics", str(path), "--site", str(site), "--out", str(tmp_path / "out")])
    assert code == 1
    err = capsys.readouterr().err
    assert "its sidecar tracks.txt.meta.json has neither a frame rate nor timestamps" in err
    assert "give --fps" in err


def test_timestamps_kept_in_the_sidecar_time_the_rows(tmp_path):
    # One time per frame (a synchronised matcher) and one per row (frames of different times).
    rows = 6
    base = Tracks(
        frame=np.array([10, 10, 11, 11, 12, 12], dtype=np.int64),
        timestamp=1.7e9 + np.array([0.0, 0.0, 0.1, 0.1, 0.2, 0.2]),
        track_id=np.array([1, 2, 1, 2, 1, 2], dtype=np.int64),
        world_xy=np.zeros((rows, 2)), camera_id=np.full(rows, -1, dtype=np.int64),
        xyxy=np.full((rows, 4), np.nan),
    )
    shifted = base.timestamp + np.array([0, 0.03, 0, 0, 0, 0])
    for tracks, form in ((base, "frames"), (replace(base, timestamp=shifted), "rows")):
        path = tmp_path / f"{form}.txt"
        write_tracks(path, tracks, keep_timestamps=True)
        assert form in json.loads(metadata_path(path).read_text())["timestamps"]
        metadata = read_track_metadata(path)
        assert metadata is not None and metadata.has_timestamps
        times = metadata_timestamps(read_tracks(path), metadata)
        np.testing.assert_array_equal(times, tracks.timestamp)


def test_which_rule_counted_is_said_and_common_tools_rule_is_offered(wildtrack_root, tmp_path,
                                                                     capsys):
    # Issue 21: on WILDTRACK's ground truth cblrs counted fewer crossings than a plain
    # sign-change rule without saying which rule it used. Now every count says its rule, and
    # --line-rule side_change counts as common tools do (supervision's LineZone).
    from cblrs.datasets import load_scene

    scene = load_scene(wildtrack_root)
    truth = tmp_path / "truth.txt"
    write_tracks(truth, scene.ground_truth, frames_per_second=scene.frames_per_second)
    totals, rules = {}, {}
    for rule in ("hysteresis", "side_change"):
        out = tmp_path / rule
        code = main(["analytics", str(truth), "--site", str(SITES / "wildtrack.yaml"), "--out",
                     str(out), "--line-rule", rule, "--no-plots"])
        printed = capsys.readouterr().out
        assert code == 0
        rows = list(csv.DictReader((out / "lines.csv").open()))
        totals[rule] = sum(int(row["count"]) for row in rows if row["class"] == "all")
        rules[rule] = {row["rule"] for row in rows}
        assert "counted when" in printed and next(iter(rules[rule])) in printed
    assert totals == {"hysteresis": 145, "side_change": 154}
    assert rules == {"hysteresis": {"past 0.5 m each side, through the segment"},
                     "side_change": {"side change within the segment's extent"}}
