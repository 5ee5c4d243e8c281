"""The detector options of ``cblrs track`` and ``cblrs demo`` without importing the detectors."""

from __future__ import annotations

import subprocess
import sys

import cblrs.detectors as detectors
from cblrs.cli import detector_options


def test_defaults_are_the_detectors_own():
    for name in ("DEFAULT_CONFIDENCE", "DEFAULT_IOU", "DEFAULT_TILING", "LAYOUTS", "TILING_MODES"):
        assert getattr(detector_options, name) == getattr(detectors, name), name


def test_track_command_line_does_not_import_the_detectors():
    # A fresh interpreter: this test process has imported them above.
    done = subprocess.run(
        [sys.executable, "-c",
         "import sys, cblrs.cli.main as m, cblrs.cli.track, argparse\n"
         "p = argparse.ArgumentParser(); cblrs.cli.track.register(p.add_subparsers())\n"
         "print(sorted(n for n in sys.modules if n.startswith('cblrs.detectors')))"],
        capture_output=True, text=True, check=True,
    )
    assert done.stdout.strip() == "[]"
