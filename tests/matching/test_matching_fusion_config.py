"""Fusion tracker: its options are checked (:mod:`cblrs.matching.fusion.config`)."""

from __future__ import annotations

import pytest
from fusion_scenes import (
    CAMERAS,
    PLANES,
)

from cblrs.matching import FusionTracker, MatcherError, make_matcher


@pytest.mark.parametrize(
    ("options", "expected"),
    [
        ({"measurement_sigma_m": 0}, "measurement_sigma_m must be a positive number"),
        ({"gate_sigmas": -2}, "gate_sigmas must be a positive number"),
        ({"max_age_s": float("inf")}, "max_age_s must be a positive number"),
        ({"report_coasting_s": -1}, "report_coasting_s must be zero or a positive number"),
        ({"confirm_evidence": 0}, "confirm_evidence must be a whole number >= 1"),
        ({"confirm_evidence": 1.5}, "confirm_evidence must be a whole number >= 1"),
        ({"adapt_noise": "yes"}, "adapt_noise must be true or false"),
        ({"class_acceleration_sigma": {"tank": 2.0}}, "unknown class 'tank'"),
        ({"class_measurement_sigma_m": {"car": 0}}, "must be a positive number"),
        ({"camera_positions": {"west": (0, 0)}}, "camera_positions names unknown camera"),
        ({"camera_positions": {"north": (0, float("nan"))}},
         "must be finite (x, y) or (x, y, height) metres"),
        ({"camera_positions": {"north": (0, 1, 2, 3)}}, "must be finite (x, y) or (x, y, height)"),
        ({"camera_positions": {"north": (0, 1, -2)}},
         "camera height of 'north' must be above the ground, got -2 m"),
        ({"kalman": True}, "unknown option(s) for the fusion matcher: kalman"),
        ({"association_orders": 0}, "association_orders must be a whole number >= 1, got 0"),
        ({"association_orders": 2.5}, "association_orders must be a whole number >= 1"),
    ],
)
def test_bad_options(options, expected):
    with pytest.raises(MatcherError) as error:
        make_matcher("fusion", PLANES, CAMERAS, **options)
    assert expected in str(error.value)


def test_motion_model_options_are_checked():
    with pytest.raises(MatcherError, match="one entry per model, got 2 and 1"):
        FusionTracker(PLANES, CAMERAS, model_sojourn_s=(5.0,))
    with pytest.raises(MatcherError, match="model_acceleration_factors must be a non-empty"):
        FusionTracker(PLANES, CAMERAS, model_acceleration_factors=())

