"""Fuzzing the hand-written grey-PNG decoder (``mistool.sequence.decode_grey_png_fast``)
like any parser: arbitrary bytes, mutated files, header lies, truncation and inflate bombs.

The contract: it never raises, and it returns either None (OpenCV decides, and reports) or
exactly the image OpenCV decodes from the same bytes.
"""

from __future__ import annotations

import struct
import tracemalloc
import zlib

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mistool.errors import MaskFormatError
from mistool.sequence import decode_grey_png_fast, read_label_image

# Derandomized: the same examples on every run, so CI never fails on a newly drawn one.
FUZZ = settings(
    max_examples=100,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)


@st.composite
def label_images(draw: st.DrawFn) -> np.ndarray:
    """Small label images: a few filled rectangles of label values on background."""
    h = draw(st.integers(1, 40))
    w = draw(st.integers(1, 40))
    img = np.zeros((h, w), np.uint8)
    for _ in range(draw(st.integers(0, 5))):
        y0, x0 = draw(st.integers(0, h - 1)), draw(st.integers(0, w - 1))
        y1, x1 = draw(st.integers(y0, h)), draw(st.integers(x0, w))
        img[y0:y1, x0:x1] = draw(st.sampled_from([1, 70, 160, 255]))
    return img


def _encode(img: np.ndarray) -> bytes:
    """OpenCV's default PNG encoding (Sub-filtered rows: the decoder's own case)."""
    return cv2.imencode(".png", img)[1].tobytes()


def _opencv(data: bytes) -> np.ndarray | None:
    try:
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        return None


def _agrees_with_opencv(data: bytes) -> None:
    got = decode_grey_png_fast(data)
    if got is None:
        return
    ref = _opencv(data)
    assert ref is not None, "the fast path decoded what OpenCV refuses"
    assert got.dtype == np.uint8 and got.shape == ref.shape
    np.testing.assert_array_equal(got, ref)


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _png(w: int, h: int, idat: bytes) -> bytes:
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")
    )


@FUZZ
@given(st.binary(max_size=300))
def test_arbitrary_bytes_never_raise(data: bytes) -> None:
    got = decode_grey_png_fast(data)
    assert got is None or (got.dtype == np.uint8 and got.ndim == 2)


@FUZZ
@given(st.binary(max_size=200))
def test_arbitrary_bytes_after_a_valid_signature_and_header(tail: bytes) -> None:
    head = _encode(np.zeros((3, 4), np.uint8))[:33]  # signature + IHDR chunk
    _agrees_with_opencv(head + tail)


@FUZZ
@given(label_images(), st.data())
def test_mutated_files_decode_as_opencv_or_not_at_all(img: np.ndarray, data: st.DataObject) -> None:
    blob = bytearray(_encode(img))
    if decode_grey_png_fast(bytes(blob)) is not None:  # the valid file itself
        np.testing.assert_array_equal(decode_grey_png_fast(bytes(blob)), img)
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, len(blob) - 1))
        blob[i] = data.draw(st.integers(0, 255))
    _agrees_with_opencv(bytes(blob))


@FUZZ
@given(label_images(), st.integers(1, 300), st.integers(1, 300))
def test_header_lies_about_the_size(img: np.ndarray, w: int, h: int) -> None:
    """IHDR rewritten (with a correct CRC) to another size than the image data holds."""
    blob = bytearray(_encode(img))
    ihdr = struct.pack(">II", w, h) + bytes(blob[24:29])
    blob[16:29] = ihdr
    blob[29:33] = struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    got = decode_grey_png_fast(bytes(blob))
    # One filter byte per row: the inflated data has the claimed size only when h x (w + 1)
    # equals the real rows x (cols + 1) (a 1x3 image claimed as 2x2 is a valid 2x2 PNG).
    if h * (w + 1) != img.shape[0] * (img.shape[1] + 1):
        assert got is None
    _agrees_with_opencv(bytes(blob))


@FUZZ
@given(label_images(), st.data())
def test_every_truncation_is_refused(img: np.ndarray, data: st.DataObject) -> None:
    blob = _encode(img)
    cut = data.draw(st.integers(0, len(blob) - 1))
    assert decode_grey_png_fast(blob[:cut]) is None


def test_truncated_file_is_one_error(tmp_path) -> None:
    blob = _encode(np.full((30, 40), 160, np.uint8))
    path = tmp_path / "cut.png"
    path.write_bytes(blob[: len(blob) // 2])
    with pytest.raises(MaskFormatError, match=r"cut\.png: cannot decode"):
        read_label_image(path)


@pytest.mark.parametrize("claimed", [(8, 8), (100_000, 100_000)])
def test_inflate_bomb_is_refused_without_inflating_it(claimed: tuple[int, int]) -> None:
    """64 MB of filtered rows in ~64 kB of IDAT, behind a header that claims 8x8 pixels
    (or 10^10 pixels): refused, and never inflated beyond what the header allows."""
    w, h = claimed
    bomb = zlib.compress(b"\x01" + bytes(64 * 2**20), 9)
    data = _png(w, h, bomb)
    assert len(data) < 100_000
    tracemalloc.start()
    try:
        got = decode_grey_png_fast(data)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert got is None
    assert peak < 8 * 2**20, f"inflated {peak / 2**20:.0f} MB for a {w}x{h} header"
