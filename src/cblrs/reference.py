"""Colour reference images: render from a calibration, save and load as PNG.

A reference image has the size of the camera frame; pixel (i, j) holds the colour of the
plane point its ray meets (see :mod:`cblrs.plane`). It is rendered for the *raw* frame, so
lens distortion is baked in and a lookup needs no undistortion on the camera.

PNG files carry their plane specification in a ``tEXt`` chunk (keyword ``cblrs``), so a file
alone can be decoded. Pixels are stored 8 or 16 bits per channel.

The rendered image and :class:`OnDemandReference` (which renders only the pixels read) must
give the very same colours, so both call one renderer, kept here; the PNG chunks (the
``tEXt`` chunk written, the integrity checks on reading) are in :mod:`cblrs.reference_png`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from cblrs.camera import Camera
from cblrs.errors import PlaneError, ReferenceImageError
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.reference_png import _PNG_SIGNATURE, _check_image_data, _insert_chunk, _read_chunks

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

FORMAT = "cblrs.reference/1"
_TEXT_KEYWORD = b"cblrs"


@dataclass(frozen=True, eq=False)
class ReferenceImage:
    """A camera's colour reference image.

    Attributes:
        pixels: (H, W, 3) uint8 or uint16 RGB array.
        planes: the planes whose colours it holds.
        camera_name: the camera it was rendered for.
    """

    pixels: NDArray[np.unsignedinteger]
    planes: PlaneSet
    camera_name: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.planes, PlaneSet):
            object.__setattr__(self, "planes", PlaneSet(self.planes))
        pixels = self.pixels
        if pixels.ndim != 3 or pixels.shape[2] != 3:
            raise ReferenceImageError(
                f"a reference image must have shape (H, W, 3), got {pixels.shape}."
            )
        expected = np.uint8 if self.planes.bits == 8 else np.uint16
        if pixels.dtype != expected:
            raise ReferenceImageError(
                f"{self.planes.bits}-bit planes need {np.dtype(expected).name} pixels, "
                f"got {pixels.dtype}."
            )

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.pixels.shape[1], self.pixels.shape[0]

    @property
    def bits(self) -> int:
        """Bits per colour channel (8 or 16)."""
        return self.planes.bits

    @cached_property
    def packed(self) -> NDArray[np.uint64]:
        """Flat (H*W,) array with R | G << 16 | B << 32 per pixel, built once.

        One integer gather per point replaces three channel reads.
        """
        pixels = self.pixels.astype(np.uint64)
        packed = pixels[..., 0] | (pixels[..., 1] << 16) | (pixels[..., 2] << 32)
        return np.asarray(packed.ravel(), dtype=np.uint64)

    def coverage(self) -> float:
        """Fraction of pixels that see a plane."""
        return float(np.mean(self.pixels[..., 2] != 0))

    def sampled_colours(self, step: int) -> NDArray[np.unsignedinteger]:
        """``pixels[::step, ::step]`` as (M, 3) rows (row-major)."""
        return self.pixels[::step, ::step].reshape(-1, 3)

    def pixel_indices(self, pixels: NDArray) -> tuple[NDArray[np.int64], BoolArray]:
        """Flat indices of the nearest pixel centres and an inside-the-image mask."""
        return nearest_pixel_indices(pixels, self.image_size)

    def colours_at(self, pixels: NDArray) -> tuple[NDArray[np.int64], BoolArray]:
        """Colours (N, 3) at pixel positions (N, 2); pixels outside the image read (0, 0, 0).

        This is all a camera needs to send: the colour, not the image.
        """
        indices, inside = self.pixel_indices(pixels)
        packed = np.where(inside, self.packed[indices], 0).astype(np.int64)
        colours = np.column_stack([packed & 0xFFFF, (packed >> 16) & 0xFFFF, packed >> 32])
        return colours, inside & (colours[:, 2] != 0)

    def locate(self, pixels: NDArray) -> tuple[FloatArray, BoolArray]:
        """World positions (N, 2) metres of pixels (N, 2), with a validity mask."""
        colours, _ = self.colours_at(pixels)
        world_xy, valid, _ = self.planes.decode(colours)
        return world_xy, valid

    # ------------------------------------------------------------------ files
    def metadata(self) -> dict:
        """What the PNG's ``tEXt`` chunk carries: format, size, planes."""
        width, height = self.image_size
        return {
            "format": FORMAT,
            "camera": self.camera_name,
            "image_size": [width, height],
            "bits": self.bits,
            "planes": self.planes.to_list(),
        }

    def to_png_bytes(self) -> bytes:
        """The reference as PNG bytes (8 or 16 bit, its plane spec in a ``tEXt`` chunk)."""
        import cv2  # lazy: reading a reference's colours needs no OpenCV (cblrs track)

        ok, encoded = cv2.imencode(".png", np.ascontiguousarray(self.pixels[..., ::-1]))
        if not ok:
            raise ReferenceImageError("OpenCV could not encode the reference image as PNG.")
        text = _TEXT_KEYWORD + b"\x00" + json.dumps(self.metadata()).encode("latin-1")
        return _insert_chunk(encoded.tobytes(), b"tEXt", text)

    def save(self, path: str | Path) -> Path:
        """Write the image and its plane specification to a PNG file."""
        path = Path(path)
        if path.suffix.lower() != ".png":
            raise ReferenceImageError(f"reference images are PNG files; {path} is not a .png.")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(self.to_png_bytes())
        return path

    @classmethod
    def load(cls, path: str | Path, expected_size: tuple[int, int] | None = None) -> ReferenceImage:
        """Read a reference PNG written by :meth:`save`.

        Args:
            path: the PNG file.
            expected_size: (width, height) of the camera, checked when given.

        Raises:
            ReferenceImageError: the file is missing, not a PNG, corrupt, lacks its plane
                specification, or has an unexpected size or bit depth.
        """
        path = Path(path)
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            raise ReferenceImageError(f"reference image {path} does not exist.") from None
        except OSError as error:
            raise ReferenceImageError(f"cannot read reference image {path}: {error}.") from None
        return cls.from_png_bytes(data, expected_size=expected_size, source=str(path))

    @classmethod
    def from_png_bytes(
        cls, data: bytes, expected_size: tuple[int, int] | None = None, source: str = "<bytes>"
    ) -> ReferenceImage:
        """A reference from PNG bytes, validated like :meth:`load`."""
        if not data.startswith(_PNG_SIGNATURE):
            raise ReferenceImageError(f"{source} is not a PNG file.")
        chunks = _read_chunks(data, source)
        texts = [body for kind, body in chunks if kind == b"tEXt"]
        metadata = None
        for body in texts:
            keyword, _, value = body.partition(b"\x00")
            if keyword == _TEXT_KEYWORD:
                try:
                    metadata = json.loads(value.decode("latin-1"))
                except ValueError:
                    raise ReferenceImageError(
                        f"{source}: its cblrs plane specification is not valid JSON."
                    ) from None
        if metadata is None:
            raise ReferenceImageError(
                f"{source} has no cblrs plane specification; render it with `cblrs render`."
            )
        if not isinstance(metadata, dict) or metadata.get("format") != FORMAT:
            found = metadata.get("format") if isinstance(metadata, dict) else None
            raise ReferenceImageError(
                f"{source}: unsupported reference format {found!r}, expected {FORMAT!r}."
            )
        bits = metadata.get("bits")
        if bits not in (8, 16):
            raise ReferenceImageError(f"{source}: unknown bit depth {bits!r}; expected 8 or 16.")
        try:
            plane_list: Any = metadata.get("planes")
            planes = PlaneSet.from_list(plane_list)
        except PlaneError as error:
            raise ReferenceImageError(f"{source}: {error}") from None
        if planes.bits != bits:
            raise ReferenceImageError(
                f"{source}: planes are {planes.bits}-bit but the image says {bits}-bit."
            )
        _check_image_data(chunks, source)
        import cv2  # lazy: reading a reference's colours needs no OpenCV (cblrs track)

        decoded = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if decoded is None:
            raise ReferenceImageError(f"{source}: the PNG image data is corrupt.")
        if decoded.ndim != 3 or decoded.shape[2] != 3:
            raise ReferenceImageError(
                f"{source}: a reference image needs 3 colour channels, got shape {decoded.shape}."
            )
        expected_dtype = np.uint8 if bits == 8 else np.uint16
        if decoded.dtype != expected_dtype:
            raise ReferenceImageError(
                f"{source}: pixels are {decoded.dtype} but the specification says {bits}-bit."
            )
        height, width = decoded.shape[:2]
        declared = tuple(metadata.get("image_size") or ())
        if declared != (width, height):
            raise ReferenceImageError(
                f"{source}: image is {width}x{height} but its specification says "
                f"{'x'.join(map(str, declared)) or 'nothing'}."
            )
        if expected_size is not None and tuple(expected_size) != (width, height):
            raise ReferenceImageError(
                f"{source}: image is {width}x{height} but the camera frame is "
                f"{expected_size[0]}x{expected_size[1]}."
            )
        pixels = cast(NDArray[np.unsignedinteger], np.ascontiguousarray(decoded[..., ::-1]))
        return cls(pixels=pixels, planes=planes, camera_name=str(metadata.get("camera", "")))


class OnDemandReference:
    """A camera's reference image that renders only the pixels read.

    :meth:`colours_at` returns exactly what :func:`render_reference`'s image holds at those
    pixels (the same arithmetic, point by point) without rendering or keeping the whole
    frame: a simulated camera that reads a few target pixels a frame needs neither the
    tens of megabytes of a full-resolution 16-bit image nor the time to render it. The whole
    image is rendered on first use of :attr:`pixels` (for saving or drawing) and kept.

    Args:
        camera: the camera; planes above the ground need a posed camera.
        planes: one plane or several.
        encode_as: as for :func:`render_reference` (pseudo-coordinate references).

    Example:
        >>> camera = Camera.from_pose("c", (0, -10, 8), 90, 35, 900, (640, 360))
        >>> plane = PlaneSpec(1, (-20, -5), 40, 40, bits=8)
        >>> reference = OnDemandReference(camera, plane)
        >>> pixels = np.array([[320.0, 300.0]])
        >>> bool((reference.colours_at(pixels)[0]
        ...       == render_reference(camera, plane).colours_at(pixels)[0]).all())
        True
    """

    def __init__(
        self,
        camera: Camera,
        planes: PlaneSet | PlaneSpec | list[PlaneSpec],
        encode_as: tuple[NDArray, PlaneSet] | None = None,
    ):
        self._rendered_planes, self.planes, self._encode_matrix = _planes_to_encode(
            planes, encode_as
        )
        self._encode_as = encode_as
        self.camera = camera
        self.camera_name = camera.name

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.camera.image_size

    @property
    def bits(self) -> int:
        """Bits per colour channel (8 or 16)."""
        return self.planes.bits

    @cached_property
    def _matrices(self) -> list[_CodeMatrices]:
        return _code_matrices(self.camera, self._rendered_planes, self.planes, self._encode_matrix)

    @cached_property
    def image(self) -> ReferenceImage:
        """The whole reference image, rendered on first use."""
        return render_reference(self.camera, self._rendered_planes, self._encode_as)

    @property
    def pixels(self) -> NDArray[np.unsignedinteger]:
        """(H, W, 3) uint8 or uint16 RGB array of the whole image (rendered on first use)."""
        return self.image.pixels

    def coverage(self) -> float:
        """Fraction of pixels that see a plane (renders the whole image)."""
        return self.image.coverage()

    def sampled_colours(self, step: int) -> NDArray[np.unsignedinteger]:
        """``pixels[::step, ::step]`` as (M, 3) rows, rendered for those pixels only (a
        16th of the image for ``step`` 4) unless the whole image already is."""
        if "image" in self.__dict__:
            return self.image.sampled_colours(step)
        rows = np.arange(0, self.image_size[1], step)[:, None]
        columns = np.arange(0, self.image_size[0], step)[None, :]
        channels = _plane_codes(self._rendered_planes, self._matrices,
                                *self._ideal(rows, columns), (rows.size, columns.size))
        return np.stack(channels, axis=-1).reshape(-1, 3)

    def _ideal(self, rows: NDArray, columns: NDArray) -> tuple[FloatArray, FloatArray]:
        """Ideal pinhole ``(x, y)`` of the raw pixels at ``rows``, ``columns`` (broadcast)."""
        if not self.camera.has_distortion:
            return columns.astype(np.float64), rows.astype(np.float64)
        grid_x, grid_y = self.camera.undistorted_grid()
        return grid_x[rows, columns].astype(np.float64), grid_y[rows, columns].astype(np.float64)

    def pixel_indices(self, pixels: NDArray) -> tuple[NDArray[np.int64], BoolArray]:
        """Flat indices of the nearest pixel centres and an inside-the-image mask."""
        return nearest_pixel_indices(pixels, self.image_size)

    def colours_at(self, pixels: NDArray) -> tuple[NDArray[np.int64], BoolArray]:
        """Colours (N, 3) at pixel positions (N, 2); pixels outside the image read (0, 0, 0).

        The same as :meth:`ReferenceImage.colours_at` on the rendered image.
        """
        indices, inside = self.pixel_indices(pixels)
        rows, columns = np.divmod(indices[inside], self.image_size[0])
        map_x, map_y = self._ideal(rows, columns)
        channels = _plane_codes(
            self._rendered_planes, self._matrices, map_x, map_y, (len(map_x),)
        )
        colours = np.zeros((len(indices), 3), dtype=np.int64)
        colours[inside] = np.column_stack(channels)
        return colours, inside & (colours[:, 2] != 0)

    def locate(self, pixels: NDArray) -> tuple[FloatArray, BoolArray]:
        """World positions (N, 2) metres of pixels (N, 2), with a validity mask."""
        colours, _ = self.colours_at(pixels)
        world_xy, valid, _ = self.planes.decode(colours)
        return world_xy, valid

    def metadata(self) -> dict:
        """What the PNG's ``tEXt`` chunk carries (see :meth:`ReferenceImage.metadata`)."""
        return self.image.metadata()

    def to_png_bytes(self) -> bytes:
        """The whole reference as PNG bytes (see :meth:`ReferenceImage.to_png_bytes`)."""
        return self.image.to_png_bytes()

    def save(self, path: str | Path) -> Path:
        """Write the whole image and its plane specification to a PNG file."""
        return self.image.save(path)


# What a camera reads colours from: a rendered image, or one that renders the pixels read.
Reference = ReferenceImage | OnDemandReference


def load_reference(
    path: str | Path, expected_size: tuple[int, int] | None = None
) -> ReferenceImage:
    """Read a reference PNG (as written by :meth:`ReferenceImage.save` or ``cblrs render``).

    The same as :meth:`ReferenceImage.load`.

    Example:
        >>> reference = load_reference("refs/CVLab1.png")  # doctest: +SKIP
        >>> world_xy, valid = reference.locate(pixels)  # doctest: +SKIP
    """
    return ReferenceImage.load(path, expected_size=expected_size)


def nearest_pixel_indices(
    pixels: NDArray, image_size: tuple[int, int]
) -> tuple[NDArray[np.int64], BoolArray]:
    """Flat row-major indices of the pixel centres nearest to ``pixels``.

    Args:
        pixels: (N, 2) float pixel coordinates (x, y).
        image_size: (width, height).

    Returns:
        ``(indices, inside)``: (N,) int64 indices into an (H*W,) array (0 where outside) and
        (N,) bool, False for pixels outside the image or not finite.
    """
    pixels = np.asarray(pixels, dtype=np.float64)
    if pixels.ndim != 2 or pixels.shape[1] != 2:
        raise ValueError(f"pixels must have shape (N, 2), got {pixels.shape}")
    width, height = image_size
    finite = np.isfinite(pixels).all(axis=1)
    columns = np.floor(np.where(finite, pixels[:, 0], -1) + 0.5).astype(np.int64)
    rows = np.floor(np.where(finite, pixels[:, 1], -1) + 0.5).astype(np.int64)
    inside = finite & (columns >= 0) & (columns < width) & (rows >= 0) & (rows < height)
    return np.where(inside, rows * width + columns, 0), inside


def render_reference(
    camera: Camera,
    planes: PlaneSet | PlaneSpec | list[PlaneSpec],
    encode_as: tuple[NDArray, PlaneSet] | None = None,
) -> ReferenceImage:
    """Render a camera's reference image for one or several planes.

    Each raw pixel is undistorted (when the camera has a lens model), its ray intersected
    with every plane, and the nearest plane in front of the camera that contains the hit
    point gives the colour. Pixels that see no plane get B = 0.

    Args:
        camera: the camera; planes above the ground need a posed camera.
        planes: one plane or several.
        encode_as: ``(matrix, encoded_planes)``: colour each hit point ``p`` (found on
            ``planes``, as without it) by its image ``matrix @ p`` (a (3, 3) homogeneous
            affine map of ground points) encoded in the plane of ``encoded_planes`` with the
            same id; the image then carries ``encoded_planes``. Pseudo-coordinate references
            (:mod:`cblrs.privacy`) are rendered so.

    Returns:
        The reference image, (H, W, 3) in the planes' bit depth.

    Example:
        >>> camera = Camera.from_pose("c", (0, -10, 8), 90, 35, 900, (640, 360))
        >>> plane = PlaneSpec(1, (-20, -5), 40, 40, bits=8)
        >>> render_reference(camera, plane).pixels.shape
        (360, 640, 3)
    """
    planes, encoded_planes, encode_matrix = _planes_to_encode(planes, encode_as)
    width, height = camera.image_size
    if camera.has_distortion:
        map_x, map_y = (grid.astype(np.float64) for grid in camera.undistorted_grid())
    else:
        # Without a lens model the grid is separable: broadcasting a row and a column
        # halves the work of the first multiply-adds.
        map_x = np.arange(width, dtype=np.float64)[None, :]
        map_y = np.arange(height, dtype=np.float64)[:, None]
    matrices = _code_matrices(camera, planes, encoded_planes, encode_matrix)
    channels = _plane_codes(planes, matrices, map_x, map_y, (height, width))
    import cv2  # lazy: reading a reference's colours needs no OpenCV (cblrs track)

    pixels = cast(NDArray[np.unsignedinteger], cv2.merge(channels))
    return ReferenceImage(pixels=pixels, planes=encoded_planes, camera_name=camera.name)


def _planes_to_encode(
    planes: PlaneSet | PlaneSpec | list[PlaneSpec],
    encode_as: tuple[NDArray, PlaneSet] | None,
) -> tuple[PlaneSet, PlaneSet, NDArray[np.float64] | None]:
    """``(planes, encoded_planes, encode_matrix)`` of :func:`render_reference`'s arguments."""
    if isinstance(planes, PlaneSpec):
        planes = PlaneSet([planes])
    elif not isinstance(planes, PlaneSet):
        planes = PlaneSet(planes)
    if encode_as is None:
        return planes, planes, None
    encode_matrix, encoded_planes = np.asarray(encode_as[0], np.float64), encode_as[1]
    if sorted(encoded_planes.ids) != sorted(planes.ids) or encoded_planes.bits != planes.bits:
        raise PlaneError("the encoded planes must have the ids and bits of the planes.")
    return planes, encoded_planes, encode_matrix


@dataclass(frozen=True)
class _CodeMatrices:
    """What turns ideal pinhole pixels into one plane's colour codes.

    ``matrix`` maps a pixel to the plane's (fractional) R and G codes and the projective
    scale: it folds "world -> colour code" into the inverse homography, so that one projective
    division gives the codes directly. With pseudo coordinates, ``encoded`` maps it to the
    codes of the transformed point in its encoded plane (same scale), whose largest code is
    ``encoded_limit``.
    """

    matrix: FloatArray
    encoded: FloatArray | None = None
    encoded_limit: float = 0.0


def _to_code(plane: PlaneSpec) -> FloatArray:
    """(3, 3) from plane metres to (fractional) colour codes."""
    step_x, step_y = plane.step
    return np.array(
        [
            [1.0 / step_x, 0.0, -plane.origin[0] / step_x],
            [0.0, 1.0 / step_y, -plane.origin[1] / step_y],
            [0.0, 0.0, 1.0],
        ]
    )


def _code_matrices(
    camera: Camera,
    planes: PlaneSet,
    encoded_planes: PlaneSet | None = None,
    encode_matrix: NDArray[np.float64] | None = None,
) -> list[_CodeMatrices]:
    """Per plane of ``planes`` its :class:`_CodeMatrices` for ``camera``."""
    matrices = []
    for plane in planes:
        to_plane = np.linalg.inv(camera.plane_homography(plane.height))
        if encode_matrix is None or encoded_planes is None:
            matrices.append(_CodeMatrices(_to_code(plane) @ to_plane))
            continue
        encoded = encoded_planes.by_id(plane.plane_id)
        matrices.append(_CodeMatrices(
            _to_code(plane) @ to_plane,
            _to_code(encoded) @ encode_matrix @ to_plane,
            encoded.max_value + 0.5,
        ))
    return matrices


def _plane_codes(
    planes: PlaneSet,
    matrices: list[_CodeMatrices],
    map_x: FloatArray,
    map_y: FloatArray,
    shape: tuple[int, ...],
) -> list[NDArray[np.unsignedinteger]]:
    """The R, G and B channels seen at ideal pinhole pixels ``(map_x, map_y)``.

    ``matrices`` are :func:`_code_matrices`' for the camera. ``map_x`` and ``map_y``
    broadcast to ``shape``: a whole frame's grid for :func:`render_reference`, a few target
    pixels for :class:`OnDemandReference`. Every value is computed elementwise by the same
    operations in the same order, so a pixel gets the same colour either way.
    """
    dtype = np.uint8 if planes.bits == 8 else np.uint16
    channels = [np.zeros(shape, dtype=dtype) for _ in range(3)]
    best_scale = np.zeros(shape, dtype=np.float64)  # 1 / depth; larger is nearer
    for plane, codes in zip(planes, matrices, strict=True):
        matrix = codes.matrix
        scale = matrix[2, 0] * map_x + matrix[2, 1] * map_y + matrix[2, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            inverse_scale = 1.0 / scale
            code_x = (matrix[0, 0] * map_x + matrix[0, 1] * map_y + matrix[0, 2]) * inverse_scale
            code_y = (matrix[1, 0] * map_x + matrix[1, 1] * map_y + matrix[1, 2]) * inverse_scale
        limit = plane.max_value + 0.5
        with np.errstate(invalid="ignore"):
            hit = (scale > best_scale) & (code_x >= -0.5) & (code_x < limit)
            hit &= (code_y >= -0.5) & (code_y < limit)
        if codes.encoded is not None:
            # The hit test above stays on the real plane; the colour is the code of the
            # transformed point in its encoded plane (the same projective division).
            encoded = codes.encoded
            with np.errstate(divide="ignore", invalid="ignore"):
                code_x = (encoded[0, 0] * map_x + encoded[0, 1] * map_y
                          + encoded[0, 2]) * inverse_scale
                code_y = (encoded[1, 0] * map_x + encoded[1, 1] * map_y
                          + encoded[1, 2]) * inverse_scale
                hit &= (code_x >= -0.5) & (code_x < codes.encoded_limit)
                hit &= (code_y >= -0.5) & (code_y < codes.encoded_limit)
        np.copyto(best_scale, scale, where=hit)
        np.copyto(channels[0], np.rint(code_x), where=hit, casting="unsafe")
        np.copyto(channels[1], np.rint(code_y), where=hit, casting="unsafe")
        channels[2][hit] = plane.plane_id
    return channels
