"""Image format and size from the first bytes of a file, before anything is decoded.

Decoding a tiny PNG that claims 100000 x 100000 pixels would allocate tens of gigabytes;
reading the header first lets the upload be refused instead. Likewise a small progressive
JPEG of thousands of scans takes the decoder minutes (it goes over the whole image once per
scan): :func:`jpeg_problem` counts the scans by walking the file's markers first.
:func:`check_upload_header` makes every one of these checks of an uploaded image.
"""

from __future__ import annotations

import re
import struct
from typing import NamedTuple

from csa_core.errors import CSAInputError

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
JPEG_MAGIC = b"\xff\xd8"

# JPEG start-of-frame markers that carry the image size (not DHT 0xC4, JPG 0xC8, DAC 0xCC).
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_SOS, _EOI = 0xDA, 0xD9

# The most scans a JPEG upload may hold: a baseline JPEG has one, a progressive JPEG of a real
# encoder about ten (libjpeg's default script: 10), and each scan is another pass of the
# decoder over the whole image. libjpeg-turbo itself stops at 1000.
MAX_JPEG_SCANS = 100
# The most marker segments (APPn, DQT, DHT, SOF, SOS, COM, ...) of a JPEG upload: real files
# have a few dozen (a large ICC profile or XMP packet adds one per 64 KiB); the bound keeps the
# walk of the markers itself cheap.
MAX_JPEG_SEGMENTS = 4096

# The next marker in entropy-coded data: 0xFF followed by a byte that is neither a stuffed
# zero nor a restart marker RST0-RST7 (0xD0-0xD7); a second 0xFF is a fill byte before one.
_MARKER_IN_SCAN = re.compile(rb"\xff[^\x00\xd0-\xd7]")


def image_format(data: bytes) -> str | None:
    """``".png"``, ``".jpg"`` or None from the file's magic bytes."""
    if data.startswith(PNG_MAGIC):
        return ".png"
    if data.startswith(JPEG_MAGIC):
        return ".jpg"
    return None


def _png_size(data: bytes) -> tuple[int, int] | None:
    if len(data) < 24 or data[12:16] != b"IHDR":
        return None
    w, h = struct.unpack(">II", data[16:24])
    return int(w), int(h)


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    i, n = 2, len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # markers without a length
            i += 2
            continue
        (length,) = struct.unpack(">H", data[i + 2 : i + 4])
        if marker in _SOF:
            if i + 9 > n:
                return None
            h, w = struct.unpack(">HH", data[i + 5 : i + 9])
            return int(w), int(h)
        if length < 2:
            return None
        i += 2 + length
    return None


class JpegMarkers(NamedTuple):
    """What a walk of a JPEG's markers found: scans (SOS segments) and segments of any kind."""

    scans: int
    segments: int


def jpeg_markers(
    data: bytes, max_scans: int = MAX_JPEG_SCANS, max_segments: int = MAX_JPEG_SEGMENTS
) -> JpegMarkers:
    """The scans and marker segments of the JPEG ``data`` (after its SOI marker), walked up to
    EOI without decoding anything: each segment's length is skipped, and after each SOS
    segment its entropy-coded data up to the next marker. The walk stops as soon as it has
    counted more than ``max_scans`` scans or ``max_segments`` segments, and where the file is
    truncated or malformed (what it counted so far: the decoder refuses or crops such a
    file)."""
    i, n = 2, len(data)
    scans = segments = 0
    while i + 1 < n and scans <= max_scans and segments <= max_segments:
        if data[i] != 0xFF:
            break  # not a marker where one must be
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker == _EOI:
            break
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # markers without a length
            i += 2
            continue
        if i + 4 > n:
            break
        (length,) = struct.unpack(">H", data[i + 2 : i + 4])
        if length < 2:
            break
        segments += 1
        i += 2 + length
        if marker == _SOS:
            scans += 1
            found = _MARKER_IN_SCAN.search(data, i)
            if found is None:
                break  # the scan runs to the end of the file (truncated)
            i = found.start()
    return JpegMarkers(scans, segments)


def jpeg_problem(data: bytes) -> str | None:
    """Why ``data`` must not reach the decoder: a JPEG of more than :data:`MAX_JPEG_SCANS`
    scans or :data:`MAX_JPEG_SEGMENTS` marker segments; None for any other file (PNG too)."""
    if image_format(data) != ".jpg":
        return None
    found = jpeg_markers(data)
    if found.scans > MAX_JPEG_SCANS:
        return (
            f"JPEG has more than {MAX_JPEG_SCANS} scans (a progressive JPEG has about 10, and "
            "each scan is another pass of the decoder over the whole image); save it again as "
            "a baseline or an ordinary progressive JPEG, or as PNG"
        )
    if found.segments > MAX_JPEG_SEGMENTS:
        return (
            f"JPEG has more than {MAX_JPEG_SEGMENTS} marker segments (an image has a few dozen);"
            " save it again as an ordinary JPEG or as PNG"
        )
    return None


def image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) declared by a PNG or JPEG header, or None when it cannot be read."""
    fmt = image_format(data)
    if fmt == ".png":
        return _png_size(data)
    if fmt == ".jpg":
        return _jpeg_size(data)
    return None


class UploadHeaderError(CSAInputError):
    """An uploaded image refused from its first bytes: ``where`` is the field or file,
    ``problem`` what is wrong with it."""


class UploadHeader(NamedTuple):
    """What the header of an accepted upload declares: ``".png"`` or ``".jpg"``, and
    (width, height)."""

    fmt: str
    size: tuple[int, int]


def check_upload_header(data: bytes, field: str, max_pixels: int) -> UploadHeader:
    """Format and size of the uploaded image ``data`` from its header, before anything is
    decoded; raises :class:`UploadHeaderError` naming ``field`` where the file is empty, not a
    PNG or JPEG, has a header that cannot be read, is not 1 to ``max_pixels`` pixels, or is a
    JPEG the decoder must not see (:func:`jpeg_problem`; a walk of the whole file)."""
    if not data:
        raise UploadHeaderError(field, "empty file")
    fmt = image_format(data)
    if fmt is None:
        raise UploadHeaderError(field, "not a PNG or JPEG file")
    size = image_size(data)
    if size is None:
        raise UploadHeaderError(field, f"unreadable {'PNG' if fmt == '.png' else 'JPEG'} header")
    w, h = size
    if w < 1 or h < 1:
        raise UploadHeaderError(field, f"{w} x {h} pixels is an empty image")
    if w * h > max_pixels:
        raise UploadHeaderError(field, f"{w} x {h} pixels exceeds the limit of {max_pixels} pixels")
    if (problem := jpeg_problem(data)) is not None:
        raise UploadHeaderError(field, problem)
    return UploadHeader(fmt, size)
