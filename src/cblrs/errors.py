"""Exceptions raised for bad user input.

Every error a user can cause (a corrupt file, a wrong size, an unknown camera) is a
:class:`CblrsError` whose message is one sentence; the CLI prints it and exits non-zero
without a traceback.
"""

from __future__ import annotations


class CblrsError(Exception):
    """Base class for errors caused by input the user can fix."""


class CalibrationError(CblrsError):
    """A calibration file is missing, unreadable or inconsistent."""


class ReferenceImageError(CblrsError):
    """A reference image is corrupt, has the wrong size or lacks its plane spec."""


class PlaneError(CblrsError):
    """A plane specification is invalid."""


class DatasetError(CblrsError):
    """A dataset folder or file does not have the expected layout."""
