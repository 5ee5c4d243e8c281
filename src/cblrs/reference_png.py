"""PNG chunks of reference image files: insert the plane specification's ``tEXt`` chunk, read
the chunks back with their checksums, and check the image data against the header.

OpenCV encodes and decodes the pixels; these byte-level helpers are what it does not do for
:class:`cblrs.reference.ReferenceImage`: carry its metadata, and refuse a damaged file that
OpenCV would decode into garbage pixels.
"""

from __future__ import annotations

import struct
import zlib

from cblrs.errors import ReferenceImageError

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _insert_chunk(png: bytes, kind: bytes, body: bytes) -> bytes:
    """Insert a chunk right after IHDR (signature 8 bytes + IHDR 25 bytes)."""
    chunk = struct.pack(">I", len(body)) + kind + body
    chunk += struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)
    return png[:33] + chunk + png[33:]


def _check_image_data(chunks: list[tuple[bytes, bytes]], source: str) -> None:
    """Inflate the image data and check its length against the header.

    OpenCV's PNG decoder can return garbage pixels for a damaged compressed stream without
    an error; zlib's own checksum (Adler-32) catches that.
    """
    header = next((body for kind, body in chunks if kind == b"IHDR"), None)
    if header is None or len(header) != 13:
        raise ReferenceImageError(f"{source}: the PNG file has no valid IHDR header.")
    width, height, bit_depth, colour_type, _, _, interlace = struct.unpack(">IIBBBBB", header)
    try:
        raw = zlib.decompress(b"".join(body for kind, body in chunks if kind == b"IDAT"))
    except zlib.error:
        raise ReferenceImageError(f"{source}: the PNG image data is corrupt.") from None
    channels = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}.get(colour_type)
    if channels is None or interlace != 0:
        return  # not something save() writes; the checks after decoding will say so
    row_bytes = 1 + (width * channels * bit_depth + 7) // 8
    if len(raw) != height * row_bytes:
        raise ReferenceImageError(f"{source}: the PNG image data is corrupt (wrong length).")


def _read_chunks(data: bytes, source: str) -> list[tuple[bytes, bytes]]:
    chunks = []
    offset = len(_PNG_SIGNATURE)
    while offset < len(data):
        if offset + 8 > len(data):
            raise ReferenceImageError(f"{source}: the PNG file is truncated.")
        (length,) = struct.unpack(">I", data[offset : offset + 4])
        kind = data[offset + 4 : offset + 8]
        end = offset + 12 + length
        if end > len(data):
            raise ReferenceImageError(f"{source}: the PNG file is truncated.")
        body = data[offset + 8 : offset + 8 + length]
        (crc,) = struct.unpack(">I", data[end - 4 : end])
        if zlib.crc32(kind + body) & 0xFFFFFFFF != crc:
            raise ReferenceImageError(f"{source}: the PNG file is corrupt (bad {kind!r} checksum).")
        chunks.append((kind, body))
        offset = end
        if kind == b"IEND":
            break
    if not chunks or chunks[-1][0] != b"IEND":
        raise ReferenceImageError(f"{source}: the PNG file is truncated.")
    return chunks
