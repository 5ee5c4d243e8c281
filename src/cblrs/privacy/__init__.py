"""Pseudo coordinates: the paper's "virtual pseudo environment", keyed and measured.

The site owner holds a secret key (:class:`PseudoKey`, a file made by ``cblrs pseudo
keygen``); the cameras' reference images encode a keyed rigid transform of the site plane, so
colours on the wire, the broker, the matcher, its database, tracks and events carry pseudo
coordinates only (:mod:`cblrs.privacy.frame`). What that hides and what it does not — an
adversary with the database and some knowledge of the site recovers the transform — is
measured by :mod:`cblrs.privacy.attack` (``cblrs experiment pseudo``; ``docs/privacy.md``).
"""

from cblrs.privacy.frame import (
    pseudo_camera,
    pseudo_places,
    pseudo_site_document,
    render_pseudo_reference,
    tracks_to_pseudo,
    tracks_to_site,
)
from cblrs.privacy.key import KEY_FORMAT, PseudoKey, PseudoKeyError

__all__ = [
    "KEY_FORMAT",
    "PseudoKey",
    "PseudoKeyError",
    "pseudo_camera",
    "pseudo_places",
    "pseudo_site_document",
    "render_pseudo_reference",
    "tracks_to_pseudo",
    "tracks_to_site",
]
