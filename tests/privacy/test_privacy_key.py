"""The pseudo-coordinate key: a rigid transform, derived from its secret, kept in a 0600 file."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cblrs.plane import PlaneSpec
from cblrs.privacy import PseudoKey, PseudoKeyError
from cblrs.privacy.key import PLANE_PAD, TRANSLATION_RANGE_M

coordinates = st.floats(-1e4, 1e4, allow_nan=False)


def _key(seed: int) -> PseudoKey:
    return PseudoKey(bytes([seed]) * 32, f"{seed:08x}")


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 255), st.lists(st.tuples(coordinates, coordinates), min_size=2,
                                     max_size=20))
def test_the_transform_is_rigid_and_inverts(seed, points):
    key = _key(seed)
    site = np.array(points)
    pseudo = key.to_pseudo(site)
    np.testing.assert_allclose(key.to_site(pseudo), site, atol=1e-6)
    # Distances (and so speeds) are kept exactly: the tracker's metric gates do not change.
    site_distances = np.linalg.norm(site[:, None] - site[None], axis=2)
    pseudo_distances = np.linalg.norm(pseudo[:, None] - pseudo[None], axis=2)
    np.testing.assert_allclose(pseudo_distances, site_distances, atol=1e-6)
    # No reflection: the orientation of a turn is kept.
    assert np.linalg.det(key.rotation) == pytest.approx(1.0)


def test_parameters_come_from_the_secret_and_differ_between_keys():
    first, second = _key(1), _key(2)
    assert _key(1).rotation_rad == first.rotation_rad
    assert first.rotation_rad != second.rotation_rad
    assert 0 <= first.rotation_rad < 2 * math.pi
    assert np.all(np.abs(first.translation) <= TRANSLATION_RANGE_M)
    assert not np.allclose(first.translation, second.translation)
    # The secret never shows in a repr (logs, tracebacks).
    assert first.secret.hex() not in repr(first) and "secret" not in repr(first)


@pytest.mark.parametrize("seed", range(8))
def test_a_pseudo_plane_holds_its_plane_and_its_size_says_nothing_of_the_rotation(seed):
    key = _key(seed)
    plane = PlaneSpec(3, (-5.0, -11.0), 16.0, 40.0, bits=16, height=1.5, name="ground")
    pseudo = key.pseudo_plane(plane)
    assert (pseudo.plane_id, pseudo.bits, pseudo.height, pseudo.name) == (3, 16, 1.5, "")
    assert pseudo.width == pseudo.length == pytest.approx(PLANE_PAD * math.hypot(16, 40))
    corners = np.array([[-5, -11], [11, -11], [11, 29], [-5, 29]], dtype=float)
    assert pseudo.contains(key.to_pseudo(corners)).all()
    # The square's centre is not the transformed plane centre (no free landmark).
    centre = key.to_pseudo(np.array([[3.0, 9.0]]))[0]
    square_centre = np.array(pseudo.origin) + pseudo.width / 2
    assert np.linalg.norm(square_centre - centre) > 1e-3


def test_keygen_file_is_0600_round_trips_and_is_never_overwritten(tmp_path):
    path = tmp_path / "site.key"
    key = PseudoKey.generate()
    key.save(path)
    assert os.stat(path).st_mode & 0o777 == 0o600
    loaded = PseudoKey.load(path)
    assert loaded == key
    with pytest.raises(PseudoKeyError, match="exists"):
        PseudoKey.generate().save(path)
    assert PseudoKey.load(path) == key


@pytest.mark.parametrize(
    ("content", "mode", "message"),
    [
        (None, 0o600, "does not exist"),
        ("{}", 0o644, r"accessible to others \(mode 0644\)"),
        ("{}", 0o640, "accessible to others"),
        ("not json", 0o600, "not a cblrs key file"),
        ('{"format": "other"}', 0o600, "not a cblrs key file"),
        ('{"format": "cblrs.pseudo-key/1", "key_id": "00000000"}', 0o600, "malformed"),
        ('{"format": "cblrs.pseudo-key/1", "key_id": "00000000", "secret": "abcd"}', 0o600,
         "malformed"),
        ('{"format": "cblrs.pseudo-key/1", "key_id": "XYZ", "secret": "' + "00" * 32 + '"}',
         0o600, "malformed"),
    ],
)
def test_bad_key_files_are_one_sentence(tmp_path, content, mode, message):
    path = tmp_path / "site.key"
    if content is not None:
        path.write_text(content)
        path.chmod(mode)
    with pytest.raises(PseudoKeyError, match=message):
        PseudoKey.load(path)


def test_key_file_holds_the_secret_and_nothing_derived(tmp_path):
    key = PseudoKey.generate()
    key.save(tmp_path / "k")
    data = json.loads((tmp_path / "k").read_text())
    assert set(data) == {"format", "key_id", "secret"}
