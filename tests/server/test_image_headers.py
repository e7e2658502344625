"""The walk of a JPEG's markers that counts its scans before anything is decoded
(``server/image_headers.py``): files written by OpenCV (baseline, progressive, with restart
markers), truncated files, and synthetic files of too many scans or segments; and the checks
of an upload's header that every image upload makes. No server."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from server.image_headers import (
    MAX_JPEG_SCANS,
    MAX_JPEG_SEGMENTS,
    UploadHeader,
    UploadHeaderError,
    check_upload_header,
    image_size,
    jpeg_markers,
    jpeg_problem,
)

W, H = 64, 48


def picture() -> np.ndarray:
    """A smooth picture, so that the encoder writes entropy-coded data of every kind."""
    noise = np.random.default_rng(7).integers(0, 256, (H, W, 3), dtype=np.uint8)
    return cv2.GaussianBlur(noise, (5, 5), 0)


def encoded(*params: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", picture(), list(params))
    assert ok
    return buf.tobytes()


def progressive() -> bytes:
    return encoded(cv2.IMWRITE_JPEG_PROGRESSIVE, 1)


def with_extra_scans(data: bytes, extra: int) -> bytes:
    """``data`` with its first scan (the SOS segment and its entropy-coded data) repeated
    ``extra`` more times: a small file of many scans, like a scan bomb."""
    sos = data.index(b"\xff\xda")
    end = sos + 2 + int.from_bytes(data[sos + 2 : sos + 4], "big")  # after the SOS header
    # The scan's data ends at the first marker: a 0xFF not followed by a stuffed 0x00 or RSTn.
    while not (data[end] == 0xFF and data[end + 1] != 0x00 and not 0xD0 <= data[end + 1] <= 0xD7):
        end += 1
    return data[:end] + data[sos:end] * extra + data[end:]


def test_a_progressive_jpeg_written_by_opencv_has_its_scans_counted() -> None:
    data = progressive()
    found = jpeg_markers(data)
    # OpenCV writes libjpeg's standard progressive script; a SOS marker cannot occur inside
    # entropy-coded data (a 0xFF there is followed by 0x00), so the bytes count the scans too.
    assert found.scans == data.count(b"\xff\xda") and 2 <= found.scans <= 20
    assert found.segments > found.scans
    assert jpeg_problem(data) is None
    decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert decoded.shape == (H, W, 3) and image_size(data) == (W, H)


@pytest.mark.parametrize(
    "params",
    [(), (cv2.IMWRITE_JPEG_RST_INTERVAL, 1), (cv2.IMWRITE_JPEG_OPTIMIZE, 1)],
    ids=["baseline", "restart-markers", "optimized"],
)
def test_a_baseline_jpeg_has_one_scan(params: tuple[int, ...]) -> None:
    """Restart markers (RST0-RST7) inside the entropy-coded data are not segments."""
    data = encoded(*params)
    assert jpeg_markers(data).scans == 1
    assert jpeg_problem(data) is None


def test_restart_markers_inside_progressive_scans_are_skipped() -> None:
    data = encoded(cv2.IMWRITE_JPEG_PROGRESSIVE, 1, cv2.IMWRITE_JPEG_RST_INTERVAL, 1)
    assert b"\xff\xd0" in data
    assert jpeg_markers(data).scans == jpeg_markers(progressive()).scans


def test_truncated_files_count_the_scans_up_to_where_they_end() -> None:
    data = progressive()
    total = jpeg_markers(data).scans
    counts = [jpeg_markers(data[:cut]).scans for cut in range(0, len(data) + 1, 97)]
    assert counts == sorted(counts)  # never more for less of the file, and never an exception
    assert counts[0] == 0 and max(counts) <= total
    assert jpeg_markers(data[:-2]).scans == total  # without its EOI marker
    first_sos = data.index(b"\xff\xda")
    assert jpeg_markers(data[: first_sos + 3]).scans == 0  # cut inside the SOS header
    assert jpeg_markers(data[: first_sos + 40]).scans == 1  # cut inside the first scan's data


@pytest.mark.parametrize("data", [b"", b"\xff\xd8", b"\xff\xd8\xff", b"\xff\xd8\x00\x00\x00"])
def test_files_too_short_or_without_markers_have_no_scans(data: bytes) -> None:
    assert jpeg_markers(data) == (0, 0)
    assert jpeg_problem(data) is None  # the decoder refuses them


def test_more_than_the_most_scans_is_refused_and_the_walk_stops_there() -> None:
    data = progressive()
    scans = jpeg_markers(data).scans
    at_limit = with_extra_scans(data, MAX_JPEG_SCANS - scans)
    assert jpeg_markers(at_limit).scans == MAX_JPEG_SCANS
    assert jpeg_problem(at_limit) is None
    over = with_extra_scans(data, MAX_JPEG_SCANS - scans + 1)
    assert jpeg_markers(over).scans == MAX_JPEG_SCANS + 1
    problem = jpeg_problem(over)
    assert problem is not None and f"more than {MAX_JPEG_SCANS} scans" in problem
    bomb = with_extra_scans(data, 5000)  # small (the first scan is the DC coefficients)
    assert len(bomb) < 5000 * len(data)
    assert jpeg_markers(bomb).scans == MAX_JPEG_SCANS + 1  # stopped counting there
    assert jpeg_markers(bomb, max_scans=10**4, max_segments=10**5).scans == scans + 5000
    assert jpeg_problem(bomb) == problem


def test_more_than_the_most_segments_is_refused() -> None:
    data = progressive()
    comment = b"\xff\xfe\x00\x02"  # an empty COM segment
    padded = data[:2] + comment * MAX_JPEG_SEGMENTS + data[2:]
    found = jpeg_markers(padded)
    assert found.segments == MAX_JPEG_SEGMENTS + 1 and found.scans == 0  # stopped there
    problem = jpeg_problem(padded)
    assert problem is not None and f"more than {MAX_JPEG_SEGMENTS} marker segments" in problem
    assert jpeg_problem(data[:2] + comment * 100 + data[2:]) is None


def test_png_files_are_not_walked() -> None:
    ok, buf = cv2.imencode(".png", picture())
    assert ok and jpeg_problem(buf.tobytes()) is None


def png_file(width: int = W, height: int = H) -> bytes:
    """A PNG of ``picture()`` whose header declares ``width`` x ``height`` pixels."""
    ok, buf = cv2.imencode(".png", picture())
    assert ok
    data = buf.tobytes()
    return data[:16] + width.to_bytes(4, "big") + height.to_bytes(4, "big") + data[24:]


def test_png_and_jpeg_uploads_pass_the_header_checks() -> None:
    for data, fmt in ((png_file(), ".png"), (encoded(), ".jpg"), (progressive(), ".jpg")):
        assert check_upload_header(data, "color", W * H) == UploadHeader(fmt, (W, H))


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"", "color: empty file"),
        (b"GIF89a" + bytes(40), "color: not a PNG or JPEG file"),
        (png_file()[:20], "color: unreadable PNG header"),
        (b"\xff\xd8\xff\xe0\x00\x02\xff\xd9", "color: unreadable JPEG header"),
        (png_file(0, H), f"color: 0 x {H} pixels is an empty image"),
        (png_file(W, 0), f"color: {W} x 0 pixels is an empty image"),
        (
            png_file(W + 1, H),
            f"color: {W + 1} x {H} pixels exceeds the limit of {W * H} pixels",
        ),
        (
            png_file(100_000, 100_000),
            f"color: 100000 x 100000 pixels exceeds the limit of {W * H} pixels",
        ),
    ],
    ids=["empty", "gif", "png-header", "jpeg-header", "no-width", "no-height", "one-over", "huge"],
)
def test_uploads_failing_a_header_check_are_refused_naming_the_field(
    data: bytes, message: str
) -> None:
    with pytest.raises(UploadHeaderError) as e:
        check_upload_header(data, "color", W * H)
    assert str(e.value) == message and e.value.where == "color"


def test_jpeg_uploads_of_too_many_scans_or_segments_are_refused_naming_the_field() -> None:
    data = progressive()
    scan_bomb = with_extra_scans(data, MAX_JPEG_SCANS)
    padded = data[:2] + b"\xff\xfe\x00\x02" * (MAX_JPEG_SEGMENTS + 1) + data[2:]
    for bad in (scan_bomb, padded):
        with pytest.raises(UploadHeaderError) as e:
            check_upload_header(bad, "archive:color/0.jpg", W * H)
        assert e.value.where == "archive:color/0.jpg"
        assert str(e.value) == f"archive:color/0.jpg: {jpeg_problem(bad)}"
    assert "more than" in str(e.value) and "marker segments" in str(e.value)
