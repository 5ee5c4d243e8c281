"""Fusion tracker: the Gaussian algebra, whitening and information-form fusion
(:mod:`cblrs.matching.fusion.gaussian`)."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.matching.fusion import (
    fuse,
    inverse_cholesky_2x2,
    ray_covariance,
)


def test_inverse_cholesky_whitens_like_numpy():
    rng = np.random.default_rng(4)
    factor = rng.normal(size=(50, 2, 2))
    covariance = factor @ np.swapaxes(factor, 1, 2) + 0.01 * np.eye(2)
    whitening = inverse_cholesky_2x2(covariance)
    assert whitening == pytest.approx(np.linalg.inv(np.linalg.cholesky(covariance)))
    # Whitened, each covariance is the identity.
    identity = whitening @ covariance @ np.swapaxes(whitening, 1, 2)
    assert identity == pytest.approx(np.broadcast_to(np.eye(2), identity.shape))


@pytest.mark.parametrize("along, lateral", [(1.0, 0.01), (0.04, 0.04)])
def test_fusing_two_crossing_rays(along, lateral):
    """Two views along x and along y: each pins the other's long axis."""
    direction = np.array([[1.0, 0.0], [0.0, 1.0]])
    covariance = ray_covariance(direction, np.full(2, along), np.full(2, lateral))
    world_xy = np.array([[1.0, 0.0], [0.0, 1.0]])
    position, fused, present = fuse(np.array([0, 0]), 2, world_xy, covariance)
    weight_x = (1 / along) / (1 / along + 1 / lateral)  # view 0 is long along x
    assert position[0] == pytest.approx([weight_x, weight_x])  # each axis trusts its precise view
    expected = 1.0 / (1 / along + 1 / lateral)
    assert fused[0] == pytest.approx(np.diag([expected, expected]))
    assert present.tolist() == [True, False] and np.isnan(position[1]).all()

