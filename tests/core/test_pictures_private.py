"""Pictures drawn over a camera's frame are their owner's alone (real `cblrs show`).

A frame shows people. `cblrs show --frame` (and `cblrs calibrate --picture`, the demo's
overlays: :func:`cblrs.viz.overlay.save_image`) wrote its picture with OpenCV, so with the
usual umask 022 every user of the machine could read it (0644), whatever the frame's own mode.
"""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys

import cv2
import numpy as np
from core_cameras import posed_camera

from cblrs.calibration import camera_to_dict
from cblrs.cli.main import main
from cblrs.reference import ReferenceImage


def test_a_picture_over_a_frame_is_readable_by_its_owner_only(tmp_path):
    camera_file = tmp_path / "camera.json"
    camera_file.write_text(json.dumps(camera_to_dict(posed_camera())))
    assert main(["render", str(camera_file), "--out", str(tmp_path), "--plane", "-10,-5,20,40",
                 "--quiet"]) == 0
    reference = tmp_path / "synthetic.png"
    width, height = ReferenceImage.load(reference).image_size
    frame = tmp_path / "frame.png"
    cv2.imwrite(str(frame), np.full((height, width, 3), 128, dtype=np.uint8))
    frame.chmod(0o600)
    out = tmp_path / "shown.png"
    out.write_bytes(b"")
    out.chmod(0o644)  # an older picture, open to all: made private too
    result = subprocess.run(
        [sys.executable, "-m", "cblrs", "show", str(reference),
         "--frame", str(frame), "--out", str(out)],
        capture_output=True, text=True, timeout=120,
        preexec_fn=lambda: os.umask(0o022),
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert result.returncode == 0, result.stderr
    assert stat.S_IMODE(out.stat().st_mode) == 0o600  # before: 0o644
    picture = cv2.imread(str(out))
    assert picture.shape == (height, width, 3) and abs(int(picture[20, 20, 0]) - 128) <= 2
