"""The image files of a WILDTRACK / MultiviewX folder, matched to its annotated frames.

Both layouts keep one folder per camera, in view order::

    DATASET/Image_subsets/C1/0000.jpg ...     (MultiviewX; WILDTRACK: 00000000.png ...)

The number in an image's file name is its frame number, except in the first public
MultiviewX release (the one in ``../shared/data/multiviewx``), where image ``NNNN.jpg``
shows the instant of annotation file ``NNNN+1.json``. :func:`image_frame_offset` finds
the offset from the numbers themselves: 0 when the image numbers are the annotated frame
numbers, 1 when they are those numbers minus one (and then says so in the log); a frame
without its image is an error, so images are never paired with the wrong annotations.

An image file that is there but unusable — empty, cut short, undecodable — raises
:class:`UnusableImage`; a stream of frames skips it, counts it by reason
(:class:`SkippedImages`) and warns, so one bad file neither ends a run nor passes unnoticed.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cblrs.datasets.multiview import _annotation_files
from cblrs.errors import DatasetError

logger = logging.getLogger(__name__)

IMAGE_FOLDER = "Image_subsets"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")


class UnusableImage(DatasetError):
    """An image file that cannot give a whole frame: empty, cut short or undecodable.

    Attributes:
        reason: ``"empty"``, ``"truncated"`` or ``"undecodable"`` (a counter's key).
    """

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason


# How a whole file of each format ends: JPEG with its end-of-image marker, PNG with its IEND
# chunk (and its CRC). Cut short by a failed copy or a full disk, it does not — and OpenCV
# decodes the part it has, greys the rest and says nothing a caller can see.
_JPEG_START, _JPEG_END = b"\xff\xd8", b"\xff\xd9"
_PNG_START, _PNG_END = b"\x89PNG\r\n\x1a\n", b"IEND\xaeB`\x82"
_TAIL_BYTES = 64


def image_problem(path: str | Path) -> str | None:
    """Why an image file cannot give a whole frame (``"empty"``, ``"truncated"``), or None.

    Reads only the file's first and last bytes; whether OpenCV can decode it is
    :func:`read_image`'s to find out.
    """
    path = Path(path)
    size = path.stat().st_size
    if size == 0:
        return "empty"
    with path.open("rb") as handle:
        head = handle.read(16)
        handle.seek(max(0, size - _TAIL_BYTES))
        tail = handle.read()
    # Trailing padding after the end marker (some encoders add zeros or a newline) is fine.
    tail = tail.rstrip(b"\x00\r\n ")
    if head.startswith(_JPEG_START) and not tail.endswith(_JPEG_END):
        return "truncated"
    if head.startswith(_PNG_START) and not tail.endswith(_PNG_END):
        return "truncated"
    if head.startswith(b"BM") and len(head) >= 6:
        declared = int.from_bytes(head[2:6], "little")
        if 0 < declared and size < declared:
            return "truncated"
    return None


def read_image(path: str | Path) -> NDArray[np.uint8]:
    """An image file as an (H, W, 3) uint8 BGR array.

    Raises:
        DatasetError: the file is missing.
        UnusableImage: the file is empty, cut short (a JPEG without its end marker, a PNG
            without its last chunk, a BMP shorter than its header says) or not an image
            OpenCV can decode; callers that read a stream of frames skip it and count
            ``error.reason``.
    """
    # lazy: OpenCV takes ~80 ms to import; only this path needs it
    import cv2

    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"image {path} does not exist.")
    problem = image_problem(path)
    if problem == "empty":
        raise UnusableImage(f"image {path} is empty (0 bytes).", problem)
    if problem == "truncated":
        raise UnusableImage(
            f"image {path} is cut short (it lacks the end of its format); part of the frame "
            "would be grey.", problem,
        )
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise UnusableImage(
            f"cannot read image {path}: not an image file OpenCV can decode.", "undecodable"
        )
    return np.asarray(image, np.uint8)


class SkippedImages:
    """Frames skipped because their image file is unusable: counted by reason, each logged
    (a warning for the first few, then one every :attr:`every`), for a stream's summary."""

    def __init__(self, what: str, shown: int = 5, every: int = 100) -> None:
        self.what = what
        self.shown = shown
        self.every = every
        self.counts: dict[str, int] = {}

    def skip(self, error: UnusableImage) -> None:
        """Count and log one skipped image."""
        self.counts[error.reason] = self.counts.get(error.reason, 0) + 1
        total = self.total
        if total <= self.shown or total % self.every == 0:
            logger.warning("%s: image skipped (%d so far): %s", self.what, total, error)

    @property
    def total(self) -> int:
        """Images skipped, all reasons."""
        return sum(self.counts.values())


def camera_image_folders(root: str | Path, camera_count: int) -> list[Path]:
    """``Image_subsets/C1 .. C<camera_count>`` of a dataset folder, in view order.

    Raises:
        DatasetError: the image folder of a camera is missing.
    """
    root = Path(root)
    folders = [root / IMAGE_FOLDER / f"C{number}" for number in range(1, camera_count + 1)]
    missing = [folder for folder in folders if not folder.is_dir()]
    if missing:
        raise DatasetError(
            f"{root} has no images for {len(missing)} of its {camera_count} cameras "
            f"(expected {IMAGE_FOLDER}/C1..C{camera_count}/; missing {missing[0]})."
        )
    return folders


def numbered_images(folder: Path) -> dict[int, Path]:
    """Image files of a folder by the number in their names (``0042.jpg`` -> 42)."""
    images: dict[int, Path] = {}
    for path in folder.iterdir():
        if path.suffix.lower() not in IMAGE_SUFFIXES:
            continue
        match = re.fullmatch(r"\D*(\d+)", path.stem)
        if match is None:
            logger.debug("ignoring %s: no frame number in its name", path)
            continue
        images.setdefault(int(match.group(1)), path)
    return images


def image_frame_offset(image_numbers: set[int], frames: NDArray[np.int64]) -> int:
    """Frame number minus image number: 0, or 1 for the first MultiviewX release.

    The offset is the one under which the images cover more of ``frames`` (all the data
    set's annotated frames); a tie means 0.

    Args:
        image_numbers: the numbers in the image file names of one camera.
        frames: (F,) the annotated frame numbers.
    """
    wanted = {int(frame) for frame in frames}
    same = len(wanted & image_numbers)
    shifted = len({frame - 1 for frame in wanted} & image_numbers)
    if shifted > same:
        logger.info(
            "image NNNN shows annotated frame NNNN+1 (the first MultiviewX release's numbering)"
        )
        return 1
    return 0


def annotated_frames(root: str | Path) -> NDArray[np.int64]:
    """Every annotated frame number of a data set folder (its annotation file names)."""

    return np.array([frame for frame, _ in _annotation_files(Path(root))], dtype=np.int64)


def scene_image_paths(
    root: str | Path, camera_count: int, frames: NDArray[np.int64]
) -> list[list[Path]]:
    """``paths[f][c]``: the image of camera c at annotated frame ``frames[f]``.

    The numbering offset is found from all the data set's annotated frames, so that a
    selection of frames is paired exactly as the whole set.

    Raises:
        DatasetError: a camera's folder is missing or lacks an image for some frame.
    """
    everything = annotated_frames(root)
    paths: list[list[Path]] = [[] for _ in frames]
    for folder in camera_image_folders(root, camera_count):
        images = numbered_images(folder)
        offset = image_frame_offset(set(images), everything)
        for index, frame in enumerate(frames):
            path = images.get(int(frame) - offset)
            if path is None:
                raise DatasetError(
                    f"{folder} has no image for annotated frame {int(frame)} (expected one "
                    f"numbered {int(frame) - offset}"
                    + (", one less than the frame, as in the rest of this data set)." if offset
                       else ", the frame number).")
                )
            paths[index].append(path)
    return paths
