"""The site owner's secret: a keyed rigid transform from site metres to pseudo metres.

A :class:`PseudoKey` holds 32 random bytes. Everything else is derived from them with
HMAC-SHA256 under fixed labels, so a key generated before a plane existed still places that
plane:

* the transform ``pseudo = Q(theta) @ site + b`` — a rotation by ``theta`` (uniform in
  0..360 degrees) and a translation ``b`` (uniform in +-:data:`TRANSLATION_RANGE_M` per axis).
  Heights are unchanged. A rotation and a translation keep every distance and speed, so the
  fusion tracker's metric gates and noise model work in pseudo space exactly as on the site;
  a scale change would not, and a reflection would add one bit that any attack with three
  landmarks resolves (see ``docs/privacy.md``), so neither is used;
* each plane's pseudo rectangle (:meth:`PseudoKey.pseudo_plane`): an axis-aligned square of
  side :data:`PLANE_PAD` x the plane's diagonal, the transformed plane placed in it at a keyed
  random offset. Its size depends on the diagonal only, never on the rotation, so a reference
  image's plane specification tells nothing about ``theta``; the offset keeps the square's
  centre from being the transformed plane centre (which would be a free landmark for anyone
  who knows the plane).

The key file is JSON (:data:`KEY_FORMAT`) with the secret in hex and a random public
``key_id`` that names the key in pseudo site files; it is written 0600 and refused when
anyone but its owner may read it.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import math
import os
import secrets
import stat
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cblrs.errors import CblrsError
from cblrs.plane import PlaneSet, PlaneSpec

FloatArray = NDArray[np.float64]

KEY_FORMAT = "cblrs.pseudo-key/1"
SECRET_BYTES = 32
TRANSLATION_RANGE_M = 5000.0
"""The translation is uniform in +-this many metres along each axis."""
PLANE_PAD = 1.5
"""A pseudo plane's side, as a multiple of the real plane's diagonal (>= 1)."""


class PseudoKeyError(CblrsError):
    """A pseudo-coordinate key file is missing, unreadable, malformed or readable by others."""


@dataclass(frozen=True)
class PseudoKey:
    """A secret rigid transform of the site plane (see the module docstring).

    Attributes:
        secret: 32 random bytes; never printed (``repr`` leaves it out).
        key_id: a random public name of the key (8 hex digits), written into pseudo sites.

    Example:
        >>> key = PseudoKey(bytes(32), "00000000")
        >>> points = np.array([[1.0, 2.0], [4.0, 6.0]])
        >>> pseudo = key.to_pseudo(points)
        >>> round(float(np.linalg.norm(pseudo[1] - pseudo[0])), 9)  # distances are kept
        5.0
        >>> np.allclose(key.to_site(pseudo), points)
        True
    """

    secret: bytes = field(repr=False)
    key_id: str

    def __post_init__(self) -> None:
        if not isinstance(self.secret, bytes) or len(self.secret) != SECRET_BYTES:
            raise PseudoKeyError(f"a pseudo-coordinate key needs {SECRET_BYTES} secret bytes.")
        if not (
            isinstance(self.key_id, str) and len(self.key_id) == 8
            and all(character in "0123456789abcdef" for character in self.key_id)
        ):
            raise PseudoKeyError(f"a key id is 8 lower-case hex digits, got {self.key_id!r}.")

    @classmethod
    def generate(cls) -> PseudoKey:
        """A new key from the operating system's random source."""
        return cls(secrets.token_bytes(SECRET_BYTES), secrets.token_hex(4))

    # ------------------------------------------------------------------ derived parameters
    def _unit(self, label: str) -> float:
        """A number in [0, 1) derived from the secret under ``label``."""
        digest = hmac.new(self.secret, label.encode("ascii"), hashlib.sha256).digest()
        return int.from_bytes(digest[:8], "big") / 2.0**64

    @cached_property
    def rotation_rad(self) -> float:
        """The rotation angle, radians in [0, 2 pi)."""
        return 2.0 * math.pi * self._unit("rotation")

    @cached_property
    def rotation(self) -> FloatArray:
        """(2, 2) rotation matrix ``Q``."""
        cosine, sine = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        return np.array([[cosine, -sine], [sine, cosine]])

    @cached_property
    def translation(self) -> FloatArray:
        """(2,) translation ``b``, metres."""
        return np.array(
            [(2.0 * self._unit(f"translation/{axis}") - 1.0) * TRANSLATION_RANGE_M
             for axis in "xy"]
        )

    @property
    def matrix(self) -> FloatArray:
        """(3, 3) homogeneous site -> pseudo transform of ground points."""
        matrix = np.eye(3)
        matrix[:2, :2] = self.rotation
        matrix[:2, 2] = self.translation
        return matrix

    # ------------------------------------------------------------------ mapping
    def to_pseudo(self, site_xy: ArrayLike) -> FloatArray:
        """Site points (N, 2) metres -> pseudo points (N, 2) metres (NaN stays NaN)."""
        points = _points(site_xy)
        return points @ self.rotation.T + self.translation

    def to_site(self, pseudo_xy: ArrayLike) -> FloatArray:
        """Pseudo points (N, 2) metres -> site points (N, 2) metres: the inverse."""
        points = _points(pseudo_xy)
        return (points - self.translation) @ self.rotation

    def direction_to_pseudo(self, site_vectors: ArrayLike) -> FloatArray:
        """Site vectors (N, 2) (directions, velocities) -> pseudo vectors: rotated only."""
        return _points(site_vectors) @ self.rotation.T

    def direction_to_site(self, pseudo_vectors: ArrayLike) -> FloatArray:
        """Pseudo vectors (N, 2) -> site vectors: the inverse rotation."""
        return _points(pseudo_vectors) @ self.rotation

    # ------------------------------------------------------------------ planes
    def pseudo_plane(self, plane: PlaneSpec) -> PlaneSpec:
        """The pseudo plane that encodes ``plane``: same id, bits and height, no name.

        An axis-aligned square of side ``PLANE_PAD * diagonal`` that holds the transformed
        plane at a keyed offset; its step is coarser than the real plane's by
        ``PLANE_PAD * diagonal / side`` along each side (16 bits: still under a millimetre for
        a 40 m plane; 8 bits: see ``docs/privacy.md``).
        """
        diagonal = math.hypot(plane.width, plane.length)
        side = PLANE_PAD * diagonal
        centre = np.array(
            [plane.origin[0] + plane.width / 2.0, plane.origin[1] + plane.length / 2.0]
        )
        pseudo_centre = self.to_pseudo(centre[None])[0]
        # The transformed plane lies within diagonal / 2 of its centre for any rotation; the
        # square's centre is moved from it by up to (side - diagonal) / 2 along each axis.
        slack = (side - diagonal) / 2.0
        offset = np.array(
            [(2.0 * self._unit(f"plane/{plane.plane_id}/{axis}") - 1.0) * slack for axis in "xy"]
        )
        square_centre = pseudo_centre + offset
        origin = (float(square_centre[0] - side / 2.0), float(square_centre[1] - side / 2.0))
        return PlaneSpec(plane.plane_id, origin, side, side, plane.bits, plane.height)

    def pseudo_planes(self, planes: PlaneSet | PlaneSpec) -> PlaneSet:
        """:meth:`pseudo_plane` of every plane."""
        if isinstance(planes, PlaneSpec):
            planes = PlaneSet([planes])
        return PlaneSet(self.pseudo_plane(plane) for plane in planes)

    # ------------------------------------------------------------------ files
    def to_dict(self) -> dict[str, str]:
        """The key file's content (holds the secret: keep it 0600)."""
        return {"format": KEY_FORMAT, "key_id": self.key_id, "secret": self.secret.hex()}

    def save(self, path: str | Path, overwrite: bool = False) -> Path:
        """Write the key file with mode 0600 (created so, never widened afterwards).

        Raises:
            PseudoKeyError: the file exists (and ``overwrite`` is False) or cannot be written.
        """
        path = Path(path)
        flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if overwrite else os.O_EXCL)
        try:
            descriptor = os.open(path, flags, 0o600)
        except FileExistsError:
            raise PseudoKeyError(
                f"{path} exists; a new key would make every reference image and pseudo "
                "site made with the old one unreadable (remove the file first)."
            ) from None
        except OSError as error:
            raise PseudoKeyError(f"cannot write key file {path}: {error.strerror}.") from None
        with os.fdopen(descriptor, "w") as handle:
            os.fchmod(handle.fileno(), 0o600)
            handle.write(json.dumps(self.to_dict(), indent=2) + "\n")
        return path

    @classmethod
    def load(cls, path: str | Path) -> PseudoKey:
        """Read a key file written by :meth:`save`.

        Raises:
            PseudoKeyError: missing, unreadable, not a key file, or readable or writable by
                anyone but its owner (like ssh refuses such a private key).
        """
        path = Path(path)
        try:
            status = path.stat()
            text = path.read_text()
        except FileNotFoundError:
            raise PseudoKeyError(f"key file {path} does not exist.") from None
        except (OSError, UnicodeDecodeError) as error:
            reason = getattr(error, "strerror", None) or str(error)
            raise PseudoKeyError(f"cannot read key file {path}: {reason}.") from None
        mode = stat.S_IMODE(status.st_mode)
        if mode & 0o077:
            raise PseudoKeyError(
                f"key file {path} is accessible to others (mode {mode:04o}); "
                f"run `chmod 600 {path}` (and consider the key seen)."
            )
        try:
            data = json.loads(text)
        except ValueError:
            raise PseudoKeyError(f"{path} is not a cblrs key file (not JSON).") from None
        if not isinstance(data, dict) or data.get("format") != KEY_FORMAT:
            raise PseudoKeyError(f"{path} is not a cblrs key file (format {KEY_FORMAT} expected).")
        try:
            secret = bytes.fromhex(str(data["secret"]))
            return cls(secret, str(data["key_id"]))
        except (KeyError, ValueError, PseudoKeyError):
            raise PseudoKeyError(
                f"{path}: the key's secret or key_id is missing or malformed."
            ) from None


def _points(values: ArrayLike) -> FloatArray:
    array = np.asarray(values, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 2:
        raise ValueError(f"points must have shape (N, 2), got {array.shape}")
    return array
