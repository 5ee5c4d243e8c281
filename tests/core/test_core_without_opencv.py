"""`cblrs track` on WILDTRACK without OpenCV: the Rodrigues conversion and the plain XML
calibration reader give OpenCV's values bit for bit, and the process never imports cv2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from cblrs import calibration
from cblrs.geometry import rotation_from_vector

NAMES = ("camera_matrix", "distortion_coefficients", "rvec", "tvec")


def test_rotation_from_vector_is_opencv_bit_for_bit():
    generator = np.random.default_rng(19)
    scales = generator.choice([1e-9, 1e-3, 0.1, 1.0, 3.0, 10.0], 5000)
    vectors = generator.normal(size=(5000, 3)) * scales[:, None]
    vectors = np.vstack([vectors, np.zeros((1, 3)), [[np.pi, 0.0, 0.0]], [[1e-17, 0.0, 0.0]]])
    for vector in vectors:
        expected = cv2.Rodrigues(vector.reshape(3, 1))[0]
        mine = rotation_from_vector(vector)
        assert mine.dtype == expected.dtype and mine.shape == (3, 3)
        np.testing.assert_array_equal(mine, expected)


def _opencv_read(path: Path, monkeypatch) -> dict:
    """read_opencv_matrices through OpenCV's reader only."""
    with monkeypatch.context() as patch:
        patch.setattr(calibration, "_read_plain_opencv_xml", lambda *_: None)
        return calibration.read_opencv_matrices(path, NAMES)


def _assert_same(mine: dict, theirs: dict) -> None:
    assert mine.keys() == theirs.keys()
    for name, value in theirs.items():
        assert mine[name].dtype == value.dtype and mine[name].shape == value.shape, name
        np.testing.assert_array_equal(mine[name], value)


def test_plain_reader_reads_what_opencv_writes(tmp_path, monkeypatch):
    generator = np.random.default_rng(7)
    for index in range(20):
        path = tmp_path / f"intr_{index}.xml"
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        # Values across magnitudes and signs, including whole numbers ("0.", "1.").
        matrix = generator.normal(size=(3, 3)) * 10.0 ** generator.integers(-8, 8, (3, 3))
        matrix[2] = [0.0, 0.0, 1.0]
        storage.write("camera_matrix", matrix)
        storage.write("distortion_coefficients", generator.normal(size=(1, 5)) * 1e-6)
        storage.write("rvec", generator.normal(size=(3, 1)))
        storage.release()
        plain = calibration._read_plain_opencv_xml(path, NAMES)
        assert plain is not None and set(plain) == {"camera_matrix", "distortion_coefficients",
                                                    "rvec"}
        _assert_same(plain, _opencv_read(path, monkeypatch))


def test_plain_reader_reads_bare_numbers_like_opencv(tmp_path, monkeypatch):
    path = tmp_path / "extr.xml"
    path.write_text('<?xml version="1.0"?>\n<opencv_storage>\n  <rvec>\n'
                    "    1.759099006652832 0.46710100769996643 -0.331699013710022\n  </rvec>\n"
                    "  <tvec>-525.8941650390625 45 986.7235107421875</tvec>\n</opencv_storage>\n")
    plain = calibration._read_plain_opencv_xml(path, NAMES)
    assert plain is not None and plain["rvec"].shape == (3,)
    _assert_same(plain, _opencv_read(path, monkeypatch))


@pytest.mark.parametrize("text", [
    # no header: OpenCV refuses it, the XML fallback of read_opencv_matrices reads it
    "<opencv_storage><rvec>1 2 3</rvec></opencv_storage>",
    # words among the numbers, a float matrix, a name given twice, a 10-digit integer
    '<?xml version="1.0"?><opencv_storage><rvec>1 two 3</rvec></opencv_storage>',
    '<?xml version="1.0"?><opencv_storage><rvec type_id="opencv-matrix"><rows>1</rows>'
    "<cols>3</cols><dt>f</dt><data>1 2 3</data></rvec></opencv_storage>",
    '<?xml version="1.0"?><opencv_storage><rvec>1 2 3</rvec><rvec>4 5 6</rvec>'
    "</opencv_storage>",
    '<?xml version="1.0"?><opencv_storage><rvec>1234567890 2 3</rvec></opencv_storage>',
])
def test_other_files_go_to_opencv(tmp_path, text):
    path = tmp_path / "other.xml"
    path.write_text(text)
    assert calibration._read_plain_opencv_xml(path, NAMES) is None


def test_data_set_files_read_as_opencv_reads_them(wildtrack_root, monkeypatch):
    files = sorted(wildtrack_root.glob("calibrations/*/*.xml"))
    assert files
    for path in files:
        plain = calibration._read_plain_opencv_xml(path, NAMES)
        assert plain is not None, path
        _assert_same(plain, _opencv_read(path, monkeypatch))


def test_track_process_does_not_import_opencv(wildtrack_root, tmp_path):
    """The whole `cblrs track` on WILDTRACK in a fresh process: OpenCV is never loaded (a
    tenth of a second and some 25 MiB of every run)."""
    script = (
        "import json, sys\n"
        "from cblrs.cli.main import main\n"
        f"code = main(['track', '--dataset', {str(wildtrack_root)!r},"
        f" '--out', {str(tmp_path / 't.txt')!r}, '--quiet'])\n"
        "print(json.dumps([code, 'cv2' in sys.modules]))\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr
    code, opencv = json.loads(done.stdout.strip().splitlines()[-1])
    assert code == 0 and (tmp_path / "t.txt").stat().st_size > 0
    assert not opencv
