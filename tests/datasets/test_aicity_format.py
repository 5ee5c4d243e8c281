"""AI City 2024 text format: write/read round trips and clear errors for malformed rows."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from cblrs.datasets.aicity import read_tracks, write_tracks
from cblrs.detections import Tracks
from cblrs.errors import DatasetError

ROW = "1 7 3 10.00 20.00 30.00 40.00 1.5000 -2.2500"


def test_read_one_row(tmp_path: Path) -> None:
    path = tmp_path / "tracks.txt"
    path.write_text(ROW + "\n")
    tracks = read_tracks(path)
    np.testing.assert_array_equal(tracks.camera_id, [1])
    np.testing.assert_array_equal(tracks.track_id, [7])
    np.testing.assert_array_equal(tracks.frame, [3])
    np.testing.assert_allclose(tracks.xyxy, [[10, 20, 40, 60]])  # width/height -> xyxy
    np.testing.assert_allclose(tracks.world_xy, [[1.5, -2.25]])
    # No timing in the format: the frame number stands in for the timestamp.
    np.testing.assert_allclose(tracks.timestamp, [3.0])
    np.testing.assert_allclose(read_tracks(path, frames_per_second=2.0).timestamp, [1.5])


def test_write_format_and_order(tmp_path: Path) -> None:
    tracks = Tracks(
        frame=[5, 0],
        timestamp=[0.5, 0.0],
        track_id=[2, 1],
        world_xy=[[1.0, 2.0], [3.25, -4.5]],
        camera_id=[0, -1],
        xyxy=[[10, 20, 40, 60], [np.nan] * 4],
    )
    path = tmp_path / "out.txt"
    write_tracks(path, tracks)
    assert path.read_text().splitlines() == [
        "0 2 5 10.00 20.00 30.00 40.00 1.0000 2.0000",
        "-1 1 0 -1.00 -1.00 -1.00 -1.00 3.2500 -4.5000",
    ]
    back = read_tracks(path)
    np.testing.assert_array_equal(back.frame, [5, 0])  # file order kept, not sorted
    assert np.isnan(back.xyxy[1]).all()


def test_a_tracks_file_is_readable_by_its_owner_only(tmp_path: Path) -> None:
    import os
    import stat

    path = tmp_path / "tracks.txt"
    path.write_text("old")
    os.chmod(path, 0o644)  # an earlier file readable by everyone
    write_tracks(path, Tracks.empty())
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    write_tracks(tmp_path / "new.txt", Tracks.empty())
    assert stat.S_IMODE(os.stat(tmp_path / "new.txt").st_mode) == 0o600


def test_empty(tmp_path: Path) -> None:
    path = tmp_path / "empty.txt"
    write_tracks(path, Tracks.empty())
    assert path.read_text() == ""
    assert len(read_tracks(path)) == 0
    path.write_text("\n  \n")
    assert len(read_tracks(path)) == 0


def test_blank_and_trailing_lines_are_tolerated(tmp_path: Path) -> None:
    path = tmp_path / "tracks.txt"
    path.write_text(f"{ROW}\n\n{ROW}\n\n")
    assert len(read_tracks(path)) == 2
    path.write_text(f"{ROW}\t\n{ROW}")  # tabs, no final newline
    assert len(read_tracks(path)) == 2


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (f"{ROW}\n1 7 3 10 20 30 40 1.5\n", r"tracks\.txt:2: expected 9 columns .* got 8"),
        (f"{ROW}\n\n{ROW} 5\n", r"tracks\.txt:3: expected 9 columns .* got 10"),
        ("1 7 3 10 20 30 40 x 1.5\n", r"tracks\.txt:1: xworld 'x' is not a number"),
        ("1,7,3,10,20,30,40,1,1\n", r"tracks\.txt:1: expected 9 columns"),
        (f"{ROW}\n1 7 3 10 20 30 40 nan 1.5\n", r"tracks\.txt:2: a value is not finite"),
        (f"\n{ROW}\n1 7 3 10 20 30 40 inf 1.5\n", r"tracks\.txt:3: a value is not finite"),
        ("1 7.5 3 10 20 30 40 1 1\n", r"tracks\.txt:1: obj_id must be an integer"),
        ("1 7 3.25 10 20 30 40 1 1\n", r"tracks\.txt:1: frame_id must be an integer"),
    ],
)
def test_malformed_rows_name_file_and_line(tmp_path: Path, content: str, message: str) -> None:
    path = tmp_path / "tracks.txt"
    path.write_text(content)
    with pytest.raises(DatasetError, match=message):
        read_tracks(path)


def test_missing_file_and_bad_rate(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="does not exist"):
        read_tracks(tmp_path / "missing.txt")
    (tmp_path / "ok.txt").write_text(ROW)
    with pytest.raises(DatasetError, match="frames per second must be positive"):
        read_tracks(tmp_path / "ok.txt", frames_per_second=0)


def test_write_rejects_non_finite_positions(tmp_path: Path) -> None:
    tracks = Tracks(frame=[1], timestamp=[0.0], track_id=[4], world_xy=[[np.nan, 1.0]])
    with pytest.raises(DatasetError, match=r"row 0 \(frame 1, track 4\) has a non-finite"):
        write_tracks(tmp_path / "out.txt", tracks)
    with pytest.raises(DatasetError, match="cannot write"):
        write_tracks(tmp_path / "no" / "such" / "dir.txt", Tracks.empty())


coordinates = st.floats(-1000, 1000, allow_nan=False)


@settings(max_examples=40, deadline=None)
@given(
    count=st.integers(0, 20),
    data=st.data(),
)
def test_round_trip(tmp_path_factory: pytest.TempPathFactory, count: int, data) -> None:
    integers = hnp.arrays(np.int64, count, elements=st.integers(-1, 10**6))
    corner = data.draw(hnp.arrays(np.float64, (count, 2), elements=st.floats(0, 4000)))
    size = data.draw(hnp.arrays(np.float64, (count, 2), elements=st.floats(1, 500)))
    xyxy = np.concatenate([corner, corner + size], axis=1)
    no_box = data.draw(hnp.arrays(np.bool_, count))
    xyxy[no_box] = np.nan
    tracks = Tracks(
        frame=data.draw(hnp.arrays(np.int64, count, elements=st.integers(0, 10**6))),
        timestamp=np.zeros(count),
        track_id=data.draw(integers),
        world_xy=data.draw(hnp.arrays(np.float64, (count, 2), elements=coordinates)),
        camera_id=data.draw(integers),
        xyxy=xyxy,
    )
    path = tmp_path_factory.mktemp("aicity") / "tracks.txt"
    write_tracks(path, tracks)
    back = read_tracks(path)
    np.testing.assert_array_equal(back.frame, tracks.frame)
    np.testing.assert_array_equal(back.track_id, tracks.track_id)
    np.testing.assert_array_equal(back.camera_id, tracks.camera_id)
    np.testing.assert_allclose(back.world_xy, tracks.world_xy, atol=5e-5)
    np.testing.assert_allclose(back.xyxy, tracks.xyxy, atol=0.011)  # 2 decimals, NaN == NaN
    np.testing.assert_allclose(back.timestamp, tracks.frame.astype(float))


def test_track_files_are_readable_by_their_owner_only(tmp_path: Path) -> None:
    """People's positions: a new track file is 0600, and so is one that existed as 0644."""
    import stat

    tracks = read_tracks_from_text(tmp_path, "1 7 0 10 20 30 40 1.5 2.5\n")
    fresh = tmp_path / "fresh.txt"
    write_tracks(fresh, tracks)
    existing = tmp_path / "existing.txt"
    existing.write_text("old\n")
    existing.chmod(0o644)
    write_tracks(existing, tracks)
    for path in (fresh, existing):
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
        assert read_tracks(path).track_id.tolist() == [7]


def read_tracks_from_text(folder: Path, text: str) -> Tracks:
    source = folder / "source.txt"
    source.write_text(text)
    return read_tracks(source)
