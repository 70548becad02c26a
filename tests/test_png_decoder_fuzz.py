"""Fuzzing mistool's PNG decoder (``mistool.pngdecode.decode_png``) like any parser:
arbitrary bytes, mutated files, header lies, truncation and inflate bombs; and
hypothesis-drawn images with every row filter, 8- and 16-bit grey and palettes.

The contract: it never raises, and it returns either None (OpenCV decides, and reports) or
exactly the image OpenCV decodes from the same bytes (palette images: the labels
``read_label_image`` gives from OpenCV's decoding).
"""

from __future__ import annotations

import struct
import tracemalloc
import zlib
from unittest import mock

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_sequence import _filter_rows  # the encoder's side of the row filters

from mistool import pngdecode
from mistool.errors import MaskFormatError
from mistool.kernels.instances import label_runs
from mistool.pngdecode import ANCILLARY_OK, decode_png, decode_png_runs
from mistool.sequence import FastPathGate, read_label_image


def decode_grey_png_fast(data: bytes) -> np.ndarray | None:
    """The decoder's pixels (grey files), or None where it declines."""
    got = decode_png(data, 10**8)
    return None if got is None else got.pixels


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


def _encode(img: np.ndarray, level: int | None = None) -> bytes:
    """OpenCV's PNG encoding: by default Sub-filtered rows; with a level, libpng's
    adaptive filters (Paeth, Up, Sub, None rows)."""
    params = [] if level is None else [cv2.IMWRITE_PNG_COMPRESSION, level]
    return cv2.imencode(".png", img, params)[1].tobytes()


def _opencv(data: bytes) -> np.ndarray | None:
    try:
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        return None


def _agrees_with_opencv(data: bytes) -> None:
    got = decode_png(data, 10**8)
    if got is None or got.palette is not None or got.pixels.dtype != np.uint8:
        assert decode_png_runs(data, 10**8) is None  # (runs: 8-bit grey only)
    else:
        assert _runs_fast(data) == _runs_of(got.pixels)
    if got is None:
        return
    ref = _opencv(data)
    assert ref is not None, "the fast path decoded what OpenCV refuses"
    if got.palette is None:
        assert got.pixels.dtype == ref.dtype and got.pixels.shape == ref.shape
        np.testing.assert_array_equal(got.pixels, ref)
    else:
        np.testing.assert_array_equal(_labels_fast(data), _labels_opencv(data))


def _read(data: bytes, gate: FastPathGate | None, **kw: bool) -> np.ndarray:
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "x.png"
        path.write_bytes(data)
        return read_label_image(path, gate=gate, **kw)


def _labels_fast(data: bytes, **kw: bool) -> np.ndarray:
    return _read(data, None, **kw)


def _labels_opencv(data: bytes, **kw: bool) -> np.ndarray:
    return _read(data, FastPathGate(patience=0), **kw)  # a closed gate: OpenCV only


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _png(w: int, h: int, idat: bytes, depth: int = 8, ctype: int = 0, extra: bytes = b"") -> bytes:
    ihdr = struct.pack(">IIBBBBB", w, h, depth, ctype, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", ihdr)
        + extra
        + _chunk(b"IDAT", idat)
        + _chunk(b"IEND", b"")
    )


@FUZZ
@given(st.binary(max_size=300))
def test_arbitrary_bytes_never_raise(data: bytes) -> None:
    got = decode_grey_png_fast(data)
    assert got is None or (got.dtype == np.uint8 and got.ndim == 2)
    assert decode_png_runs(data, 10**8) is None or got is not None


@FUZZ
@given(st.binary(max_size=200))
def test_arbitrary_bytes_after_a_valid_signature_and_header(tail: bytes) -> None:
    head = _encode(np.zeros((3, 4), np.uint8))[:33]  # signature + IHDR chunk
    _agrees_with_opencv(head + tail)


@FUZZ
@given(label_images(), st.sampled_from([None, 3, 9]), st.data())
def test_mutated_files_decode_as_opencv_or_not_at_all(
    img: np.ndarray, level: int | None, data: st.DataObject
) -> None:
    blob = bytearray(_encode(img, level))
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
@given(label_images(), st.sampled_from([None, 9]), st.data())
def test_every_truncation_is_refused(
    img: np.ndarray, level: int | None, data: st.DataObject
) -> None:
    blob = _encode(img, level)
    cut = data.draw(st.integers(0, len(blob) - 1))
    assert decode_grey_png_fast(blob[:cut]) is None
    assert decode_png_runs(blob[:cut], 10**8) is None


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


# --- every filter, depth and palette ------------------------------------------------------


def _raw_png(
    img_bytes: np.ndarray, filters: list[int], w: int, depth: int, ctype: int, extra: bytes = b""
) -> bytes:
    raw = np.concatenate([np.array(filters, np.uint8)[:, None], img_bytes], axis=1)
    return _png(w, len(filters), zlib.compress(raw.tobytes()), depth, ctype, extra)


@st.composite
def masks(draw: st.DrawFn, top: int = 255, widths: tuple[int, int] = (1, 48)) -> np.ndarray:
    """Label-like images (rectangles, a diagonal band) or, sometimes, noise; ``widths``:
    the least and most columns."""
    h = draw(st.integers(1, 48))
    w = draw(st.integers(*widths))
    if draw(st.integers(0, 5)) == 0:
        seed = draw(st.integers(0, 2**16))
        return np.random.default_rng(seed).integers(0, top + 1, (h, w))
    img = np.zeros((h, w), np.int64)
    for _ in range(draw(st.integers(0, 6))):
        y0, x0 = draw(st.integers(0, h - 1)), draw(st.integers(0, w - 1))
        y1, x1 = draw(st.integers(y0, h)), draw(st.integers(x0, w))
        img[y0:y1, x0:x1] = draw(st.integers(0, top))
    if draw(st.booleans()):  # a slanted edge: every row differs from the one above
        yy, xx = np.mgrid[:h, :w]
        img[xx > yy * draw(st.floats(0.2, 3.0)) + draw(st.integers(-10, 10))] = draw(
            st.integers(0, top)
        )
    return img


@FUZZ
@given(masks(), st.data())
def test_every_filter_8_bit_grey(img: np.ndarray, data: st.DataObject) -> None:
    img = img.astype(np.uint8)
    h, w = img.shape
    filters = data.draw(st.lists(st.integers(0, 4), min_size=h, max_size=h))
    blob = _raw_png(_filter_rows(img, filters, 1), filters, w, 8, 0)
    got = decode_png(blob, 10**8)
    assert got is not None and got.palette is None
    np.testing.assert_array_equal(got.pixels, img)
    _agrees_with_opencv(blob)


def _runs_of(pixels: np.ndarray) -> tuple:
    """``label_runs`` of an image, the arrays cut to their runs (what is compared)."""
    bounds, ry, rx0, rx1, rv, n = label_runs(np.ascontiguousarray(pixels))
    return bounds, ry[:n].tolist(), rx0[:n].tolist(), rx1[:n].tolist(), rv[:n].tolist(), n


def _runs_fast(data: bytes) -> tuple | None:
    got = decode_png_runs(data, 10**8)
    if got is None:
        return None
    bounds, ry, rx0, rx1, rv, n, shape = got
    for a in (ry, rx0, rx1, rv):
        assert a.dtype == np.int32 and len(a) >= n
    return bounds, ry[:n].tolist(), rx0[:n].tolist(), rx1[:n].tolist(), rv[:n].tolist(), n


@FUZZ
@given(masks(), st.data())
def test_every_filter_8_bit_grey_straight_to_runs(img: np.ndarray, data: st.DataObject) -> None:
    """``decode_png_runs`` (the rows unfiltered only where they are not zero, straight
    to runs) gives ``label_runs`` of the decoded image, bit for bit: any filter mix,
    rows of zeros between (every filter's shortcut under a zero row), noise (more runs
    than the first arrays hold)."""
    img = img.astype(np.uint8)
    h, w = img.shape
    if data.draw(st.booleans()):  # bands of zero rows: the filters' shortcuts under them
        img[data.draw(st.integers(0, h)) : data.draw(st.integers(0, h))] = 0
    filters = data.draw(st.lists(st.integers(0, 4), min_size=h, max_size=h))
    blob = _raw_png(_filter_rows(img, filters, 1), filters, w, 8, 0)
    assert _runs_fast(blob) == _runs_of(img)
    got = decode_png_runs(blob, 10**8)
    assert got is not None and got[6] == (h, w)


@FUZZ
@given(masks(widths=(60, 400)), st.data())
def test_straight_to_runs_wide_rows(img: np.ndarray, data: st.DataObject) -> None:
    """As above with rows of 60 to 400 bytes: the kernel's 64-byte steps (zero
    stretches, Sub's and Paeth's unchanged stretches, runs of one value, the Adler-32's
    sums) and their tails."""
    img = img.astype(np.uint8)
    h, w = img.shape
    if data.draw(st.booleans()):
        img[data.draw(st.integers(0, h)) : data.draw(st.integers(0, h))] = 0
    filters = data.draw(st.lists(st.integers(0, 4), min_size=h, max_size=h))
    blob = _raw_png(_filter_rows(img, filters, 1), filters, w, 8, 0)
    assert _runs_fast(blob) == _runs_of(img)
    assert decode_png_runs(_wrong_adler(blob), 10**8) is None


def test_straight_to_runs_takes_8_bit_grey_only_and_declines_as_decode_png() -> None:
    img = np.zeros((9, 70), np.uint8)
    img[2:7, 5:60] = 160
    img[4:6, 30:65] = 70
    filters = [0, 1, 2, 3, 4, 4, 3, 2, 1]
    rows = _filter_rows(img, filters, 1)
    assert _runs_fast(_raw_png(rows, filters, 70, 8, 0)) == _runs_of(img)
    for bad in (5, 255):  # a filter type that does not exist, on a zero row or not
        for y in (0, 3):
            assert (
                _runs_fast(_raw_png(rows, filters[:y] + [bad] + filters[y + 1 :], 70, 8, 0)) is None
            )
    palette = _raw_png(rows, filters, 70, 8, 3, _chunk(b"PLTE", bytes(3 * 256)))
    assert decode_png(palette, 10**8) is not None and _runs_fast(palette) is None
    sixteen = img.astype(">u2").view(np.uint8).reshape(9, 140)
    blob16 = _raw_png(_filter_rows(sixteen, filters, 2), filters, 70, 16, 0)
    assert decode_png(blob16, 10**8) is not None and _runs_fast(blob16) is None
    assert _runs_fast(_raw_png(np.zeros((4, 8), np.uint8), [0, 2, 4, 1], 8, 8, 0)) == (
        (0, 0, 0, 0),
        [],
        [],
        [],
        [],
        0,
    )


def _wrong_adler(blob: bytes, flip: int = 1) -> bytes:
    """The file with its image data's Adler-32 (the stream's last 4 bytes) xor ``flip``
    (not 0), the chunk's CRC made right again (a single IDAT)."""
    n = struct.unpack(">I", blob[33:37])[0]
    body = _idat_body(blob)
    check = struct.unpack(">I", body[-4:])[0] ^ flip
    idat = _chunk(b"IDAT", body[:-4] + struct.pack(">I", check))
    return blob[:33] + idat + blob[41 + n + 4 :]


@FUZZ
@given(masks(), st.data())
def test_straight_to_runs_checks_the_adler32_itself(img: np.ndarray, data: st.DataObject) -> None:
    """``decode_png_runs`` inflates with zlib-ng's Adler-32 check off (the stream's
    check still read, not compared) and compares the rows' Adler-32 in
    ``unfilter_runs``, from the sums of the bytes and of the bytes times their places:
    the runs of a right file as before, and every wrong Adler-32 refused as
    ``decode_png`` (zlib) refuses it, whatever the filters and zero rows."""
    img = img.astype(np.uint8)
    h, w = img.shape
    if data.draw(st.booleans()):
        img[data.draw(st.integers(0, h)) : data.draw(st.integers(0, h))] = 0
    filters = data.draw(st.lists(st.integers(0, 4), min_size=h, max_size=h))
    blob = _raw_png(_filter_rows(img, filters, 1), filters, w, 8, 0)
    assert _runs_fast(blob) == _runs_of(img)
    bad = _wrong_adler(blob, data.draw(st.integers(1, 2**32 - 1)))
    assert decode_png(bad, 10**8) is None and decode_png_runs(bad, 10**8) is None
    idat = _idat_body(bad)
    size = h * (w + 1)
    assert pngdecode._inflate_into(idat, size) is None  # zlib's check
    assert pngdecode._inflate_into(idat, size, check=False) is not None  # left to the kernel
    assert pngdecode._inflate_into(idat[:-1], size, check=False) is None  # (still read)


def test_unfilter_runs_adler32_against_zlib() -> None:
    """``unfilter_runs``' Adler-32 is zlib's (RFC 1950): -3 for any other value; rows of
    every filter with noise (every byte's sums), and rows longer than 2 ** 20 bytes
    (their sums taken in pieces, reduced between)."""
    from mistool.kernels.png import unfilter_runs

    rng = np.random.default_rng(3)
    noise = rng.integers(0, 256, (40, 90)).astype(np.uint8)
    noise[5:12] = 0
    wide = np.zeros((3, (1 << 20) + 77), np.uint8)
    wide[1, 1000:] = 200
    wide[2, 5:9] = 7
    wide[2, -3000:] = 255
    cases = ((noise, [y % 5 for y in range(40)]), (wide, [1, 4, 2]), (wide, [1, 1, 0]))
    for img, filters in cases:  # (Sub rows over Paeth and over Sub: written or not)
        h, w = img.shape
        raw = np.concatenate(
            [np.array(filters, np.uint8)[:, None], _filter_rows(img, filters, 1)], 1
        )
        adler = zlib.adler32(raw.tobytes())
        cap = min(h * w, 4096) + 64  # (every run of the noise)
        args = (np.empty(2 * w, np.uint8), *(np.empty(cap, np.int32) for _ in range(4)))
        bounds = np.zeros(4, np.int64)
        n = unfilter_runs(raw, *args, bounds, adler)
        assert n == _runs_of(img)[5] and tuple(bounds) == _runs_of(img)[0]
        for wrong in (adler ^ 1, adler ^ (1 << 16), (adler + 65521) % 2**32):
            assert unfilter_runs(raw, *args, bounds, wrong) == -3


@FUZZ
@given(masks(widths=(1, 200)), st.data())
def test_sub_rows_read_as_runs_from_their_filtered_bytes(
    img: np.ndarray, data: st.DataObject
) -> None:
    """A Sub row that the row below does not read (None or Sub below, or the last row)
    gives its runs straight from its filtered bytes, the row not written
    (``png._sub_runs``); one that the row below reads (Up, Average, Paeth) is written as
    before: rows mostly Sub, each followed by any filter, give ``label_runs`` of the
    image, and run arrays one run too short, or shorter, are refused (-1)."""
    from mistool.kernels.png import unfilter_runs

    img = img.astype(np.uint8)
    h, w = img.shape
    filters = [1 if data.draw(st.integers(0, 2)) else data.draw(st.integers(0, 4)) for _ in img]
    raw = np.concatenate([np.array(filters, np.uint8)[:, None], _filter_rows(img, filters, 1)], 1)
    want = _runs_of(img)
    cap = data.draw(st.integers(0, want[5] + 2))
    runs = [np.empty(cap, np.int32) for _ in range(4)]
    bounds = np.zeros(4, np.int64)
    n = unfilter_runs(raw, np.empty(2 * w, np.uint8), *runs, bounds, zlib.adler32(raw.tobytes()))
    if cap < want[5]:
        assert n == -1
        return
    ry, rx0, rx1, rv = (a[:n].tolist() for a in runs)
    assert (tuple(bounds), ry, rx0, rx1, rv, n) == want


@FUZZ
@given(masks(top=65535), st.data())
def test_every_filter_16_bit_grey(img: np.ndarray, data: st.DataObject) -> None:
    img = img.astype(np.uint16)
    h, w = img.shape
    filters = data.draw(st.lists(st.integers(0, 4), min_size=h, max_size=h))
    big_endian = img.astype(">u2").view(np.uint8).reshape(h, 2 * w)
    blob = _raw_png(_filter_rows(big_endian, filters, 2), filters, w, 16, 0)
    got = decode_png(blob, 10**8)
    assert got is not None and got.pixels.dtype == np.uint16
    np.testing.assert_array_equal(got.pixels, img)
    _agrees_with_opencv(blob)


@FUZZ
@given(masks(top=20), st.data())
def test_every_filter_palette(img: np.ndarray, data: st.DataObject) -> None:
    """Palette files: the labels are the lowest index of each pixel's colour (entries
    may share a colour), or packed colours; with or without transparency."""
    img = img.astype(np.uint8)
    h, w = img.shape
    n = data.draw(st.integers(int(img.max()) + 1, 256))
    colours = data.draw(st.lists(st.integers(0, 3), min_size=3 * n, max_size=3 * n))
    extra = _chunk(b"PLTE", bytes(c * 80 for c in colours))
    if data.draw(st.booleans()):
        extra += _chunk(b"tRNS", bytes(data.draw(st.lists(st.integers(0, 255), max_size=n))))
    filters = data.draw(st.lists(st.integers(0, 4), min_size=h, max_size=h))
    blob = _raw_png(_filter_rows(img, filters, 1), filters, w, 8, 3, extra)
    got = decode_png(blob, 10**8)
    assert got is not None and got.palette is not None
    np.testing.assert_array_equal(got.pixels, img)
    for colour in (False, True):
        np.testing.assert_array_equal(
            _labels_fast(blob, colour=colour), _labels_opencv(blob, colour=colour)
        )


@pytest.mark.parametrize("depth", [1, 2, 4])
@pytest.mark.parametrize("ctype", [0, 3])
def test_sub_byte_depths_are_left_to_opencv(depth: int, ctype: int) -> None:
    rng = np.random.default_rng(depth)
    w, h = 13, 7
    per_byte = 8 // depth
    packed = rng.integers(0, 256, (h, -(-w // per_byte))).astype(np.uint8)
    extra = _chunk(b"PLTE", bytes(range(3 * 2**depth))) if ctype == 3 else b""
    blob = _raw_png(packed, [0] * h, w, depth, ctype, extra)
    assert decode_png(blob, 10**8) is None
    assert _opencv(blob) is not None
    np.testing.assert_array_equal(_labels_fast(blob), _labels_opencv(blob))


def test_interlaced_files_are_left_to_opencv() -> None:
    img = np.zeros((20, 30), np.uint8)
    img[5:12, 3:25] = 160
    raw = bytearray(_encode(img))
    ihdr = bytes(raw[16:28]) + b"\x01"
    adam7 = []  # the seven passes, each row None-filtered
    for y0, x0, dy, dx in (
        (0, 0, 8, 8),
        (0, 4, 8, 8),
        (4, 0, 8, 4),
        (0, 2, 4, 4),
        (2, 0, 4, 2),
        (0, 1, 2, 2),
        (1, 0, 2, 1),
    ):
        sub = img[y0::dy, x0::dx]
        if sub.size:
            adam7.append(np.concatenate([np.zeros((sub.shape[0], 1), np.uint8), sub], 1))
    idat = zlib.compress(b"".join(a.tobytes() for a in adam7))
    blob = (
        b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")
    )
    assert decode_png(blob, 10**8) is None
    np.testing.assert_array_equal(_opencv(blob), img)
    np.testing.assert_array_equal(_labels_fast(blob), img)


def _idat_body(blob: bytes) -> bytes:
    n = struct.unpack(">I", blob[33:37])[0]
    assert blob[37:41] == b"IDAT"
    return blob[41 : 41 + n]


@pytest.mark.parametrize(
    "case",
    [
        "bad adler",
        "no adler",
        "extra data after the stream",
        "short data",
        "long data",
        "split IDAT with a chunk between",
        "unknown critical chunk",
        "unlisted ancillary chunk",
        "PLTE in a grey file",
        "index outside the palette",
        "second IHDR",
        "IEND with a body",
    ],
)
def test_files_the_decoder_leaves_to_opencv(case: str, tmp_path) -> None:
    """Each broken or unusual file: declined by the fast decoder, and read exactly as
    OpenCV decodes it (or refused with the one-line error when OpenCV refuses it)."""
    img = np.zeros((30, 40), np.uint8)
    img[5:20, 8:30] = 160
    img[10:25, 20:35] = 70
    blob = _encode(img, 9)
    idat = _idat_body(blob)
    raw = zlib.decompress(idat)
    w, h = 40, 30
    make = {
        "bad adler": lambda: _png(w, h, idat[:-4] + bytes(4)),
        "no adler": lambda: _png(w, h, idat[:-4]),
        "extra data after the stream": lambda: _png(w, h, idat + b"\x03\x00"),
        "short data": lambda: _png(w, h, zlib.compress(raw[:-41])),
        "long data": lambda: _png(w, h, zlib.compress(raw + bytes(41))),
        "split IDAT with a chunk between": lambda: b"".join(
            [
                blob[:33],
                _chunk(b"IDAT", idat[:9]),
                _chunk(b"tEXt", b"a\x00b"),
                _chunk(b"IDAT", idat[9:]),
                _chunk(b"IEND", b""),
            ]
        ),
        "unknown critical chunk": lambda: _png(w, h, idat, extra=_chunk(b"ABCD", b"x")),
        "unlisted ancillary chunk": lambda: _png(
            w, h, idat, extra=_chunk(b"gAMA", b"\x00\x00\xb1\x8f")
        ),
        "PLTE in a grey file": lambda: _png(w, h, idat, extra=_chunk(b"PLTE", bytes(6))),
        "index outside the palette": lambda: _png(
            w, h, idat, 8, 3, _chunk(b"PLTE", bytes(range(3 * 60)))
        ),
        "second IHDR": lambda: _png(w, h, idat, extra=blob[8:33]),
        "IEND with a body": lambda: blob[:-12] + _chunk(b"IEND", b"x"),
    }
    data = make[case]()
    assert decode_png(data, 10**8) is None
    assert decode_png_runs(data, 10**8) is None
    path = tmp_path / "odd.png"
    path.write_bytes(data)
    if _opencv(data) is None:
        with pytest.raises(MaskFormatError, match=r"odd\.png: cannot decode"):
            read_label_image(path)
        return
    try:
        want = _labels_opencv(data)
    except MaskFormatError as exc:  # e.g. colours outside the palette: the same error
        with pytest.raises(MaskFormatError, match=str(exc).split(": ", 1)[1]):
            read_label_image(path)
        return
    np.testing.assert_array_equal(read_label_image(path), want)


@pytest.mark.parametrize("kind", sorted(k.decode() for k in ANCILLARY_OK))
def test_listed_ancillary_chunks_decode_as_opencv_even_when_malformed(kind: str) -> None:
    img = np.zeros((12, 16), np.uint8)
    img[3:9, 2:11] = 160
    idat = _idat_body(_encode(img, 9))
    for body in (b"", b"\xff" * 7, b"Title\x00mask", bytes(range(40))):
        data = _png(16, 12, idat, extra=_chunk(kind.encode(), body))
        _agrees_with_opencv(data)
        if _opencv(data) is not None:
            np.testing.assert_array_equal(_labels_fast(data), img)


def test_synth_frames_every_one_accepted(tmp_path) -> None:
    """``mistool synth`` writes PNG level 3 (libpng's adaptive filters): every frame is
    decoded by the fast path, exactly as OpenCV decodes it."""
    from mistool.synth import synthesize
    from mistool.synth.corrupt import Corruptions

    every = Corruptions(jitter_px=1.0, holes=2.0, speckle=2.0, occluders=1, bias_px=0.5)
    synthesize(tmp_path / "s", frames=6, instruments=3, seed=4, corruptions=every)
    frames = sorted((tmp_path / "s").glob("*.png"))
    assert frames
    for path in frames:
        data = path.read_bytes()
        got = decode_png(data, 10**8)
        assert got is not None, path.name
        np.testing.assert_array_equal(got.pixels, _opencv(data))


def _fix_crcs(blob: bytes) -> bytes:
    """Every chunk's CRC recomputed (a corruption only the inflate or the decoder sees)."""
    out = bytearray(blob)
    pos = 8
    while pos + 12 <= len(out):
        n = struct.unpack(">I", out[pos : pos + 4])[0]
        if pos + 12 + n > len(out):
            break
        out[pos + 8 + n : pos + 12 + n] = struct.pack(
            ">I", zlib.crc32(bytes(out[pos + 4 : pos + 8 + n]))
        )
        pos += 12 + n
    return bytes(out)


def test_corrupted_synth_frames_are_refused_as_opencv_refuses_them(tmp_path) -> None:
    """300 corrupted copies of ``mistool synth`` frames (bytes overwritten, with the CRCs
    left wrong or recomputed; truncations): whatever the fast decoder accepts, OpenCV
    accepts with the same pixels (so every file OpenCV refuses is refused)."""
    from mistool.synth import synthesize

    synthesize(tmp_path / "s", frames=3, instruments=2, seed=5)
    frames = [p.read_bytes() for p in sorted((tmp_path / "s").glob("*.png"))]
    rng = np.random.default_rng(0)
    refused = 0
    for k in range(300):
        blob = bytearray(frames[k % len(frames)])
        if k % 3 == 2:
            blob = blob[: int(rng.integers(8, len(blob)))]
        else:
            for _ in range(int(rng.integers(1, 5))):
                blob[int(rng.integers(8, len(blob)))] = int(rng.integers(0, 256))
            if k % 3 == 1:
                blob = bytearray(_fix_crcs(bytes(blob)))
        refused += _opencv(bytes(blob)) is None
        _agrees_with_opencv(bytes(blob))
    assert refused > 200  # (the corruptions do break files)


def test_large_images_scratch_is_not_kept() -> None:
    """A frame's temporaries are kept per thread for the next frame, up to a size: a
    large image's are not held after it (and Sub rows are summed in batches)."""
    import threading

    from mistool import pngdecode

    img = np.zeros((4200, 4100), np.uint8)  # 17 MB of filtered rows
    cv2.circle(img, (2000, 2200), 1500, 160, -1)
    blob = _encode(img)  # Sub rows: the integral buffers
    kept: dict[str, int] = {}

    def run() -> None:
        got = decode_png(blob, 10**8)
        assert got is not None
        np.testing.assert_array_equal(got.pixels, img)
        local = pngdecode._local
        for name in ("filtered", "sub", "integral", "sums", "mini"):
            buf = getattr(local, name, None)
            kept[name] = 0 if buf is None else buf.nbytes

    t = threading.Thread(target=run)  # a fresh thread: its own scratch buffers
    t.start()
    t.join()
    assert kept and max(kept.values()) <= pngdecode.SCRATCH_KEEP_BYTES


@FUZZ
@given(label_images(), st.sampled_from([None, 9]), st.data())
def test_zlib_ngs_inflate_called_directly_agrees_with_decompressobj(
    img: np.ndarray, level: int | None, data: st.DataObject
) -> None:
    """The image data inflated by zlib-ng's own inflate (ctypes, one call into the
    scratch buffer) or by ``decompressobj`` a piece at a time: the same bytes, and the
    same refusals (cut, mutated, longer or shorter than the header says, data after
    the stream)."""
    assert pngdecode._native_inflate() is not None  # (zlib-ng 2.x is installed here)
    h, w = img.shape
    idat = _idat_body(_encode(img, level))
    mutated = bytearray(idat)
    mutated[data.draw(st.integers(0, len(idat) - 1))] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(idat) - 1))
    size = h * (w + 1)
    for stream in (idat, idat[:cut], idat + b"\x00", bytes(mutated)):
        for n in (size, size - 1, size + 1):
            native = pngdecode._inflate_into(stream, n)
            native = None if native is None else native.tobytes()
            with mock.patch.object(pngdecode, "_native_inflate", lambda check=True: None):
                pieces = pngdecode._inflate_into(stream, n)
            assert native == (None if pieces is None else pieces.tobytes())
