"""A strict, fast decoder for the PNG label images masks are stored as.

:func:`decode_png` decodes non-interlaced 8/16-bit greyscale and 8-bit palette PNGs,
whatever row filters their encoder chose (None, Sub, Up, Average, Paeth), several times
faster than ``cv2.imread`` on label masks (``scripts/bench_decode.py``): zlib-ng inflates
(into a buffer kept from frame to frame) and one compiled pass undoes every row's filter
(:func:`mistool.kernels.png.unfilter_rows`).

**Strict.** It returns None (the caller then decodes with OpenCV, which reports a bad
file) for anything it does not fully check: every chunk's CRC must be right, chunk types
are the critical ones in their order or those listed in :data:`ANCILLARY_OK`, the image
data must inflate to exactly the header's size with a correct Adler-32 and nothing after
it, every row's filter type must exist, palette indices must lie in the palette, and
nothing may follow ``IEND``. Whatever it decodes is exactly what OpenCV decodes
(``tests/test_png_decoder_fuzz.py``: hypothesis images with every filter, depths,
palettes; mutated, truncated and lying files).
"""

from __future__ import annotations

import struct
import threading
from typing import Any

import numpy as np

_SIGNATURE = b"\x89PNG\r\n\x1a\n"

#: Ancillary chunks a decodable file may hold (ignored by OpenCV and by this decoder);
#: any other ancillary chunk sends the file to OpenCV.
ANCILLARY_OK: frozenset[bytes] = frozenset({b"tEXt", b"zTXt", b"iTXt", b"pHYs", b"tIME"})


def _inflate_module() -> Any:
    """zlib-ng's inflate (several times faster than zlib 1.2 on masks) when installed."""
    try:
        from zlib_ng import zlib_ng
    except ImportError:  # optional: the standard library's zlib gives the same bytes
        import zlib

        return zlib
    return zlib_ng


_ZLIB = _inflate_module()


class PngImage:
    """A decoded PNG: its pixels as OpenCV's ``IMREAD_UNCHANGED`` gives them, except that
    a palette image keeps its indices and palette."""

    __slots__ = ("pixels", "palette")

    def __init__(self, pixels: np.ndarray, palette: np.ndarray | None) -> None:
        self.pixels = pixels
        """(H, W) uint8 or uint16 grey values; for a palette image, uint8 indices."""
        self.palette = palette
        """Palette images: (N,) uint32 colours packed ``r << 16 | g << 8 | b``; else None."""


def _chunks(data: bytes) -> tuple[list[tuple[bytes, int, int]], bool] | None:
    """``[(type, start, stop)]`` of every chunk's body, and whether every CRC is right;
    None when the chunk structure is broken (or bytes follow ``IEND``)."""
    crc32 = _ZLIB.crc32
    out = []
    pos, n = 8, len(data)
    ok = True
    unpack = struct.unpack_from
    while pos + 12 <= n:
        length, kind = unpack(">I4s", data, pos)
        stop = pos + 8 + length
        if length > 0x7FFFFFFF or stop + 4 > n:
            return None
        if crc32(data[pos + 4 : stop]) != unpack(">I", data, stop)[0]:
            ok = False
        out.append((kind, pos + 8, stop))
        pos = stop + 4
        if kind == b"IEND":
            return (out, ok) if pos == n else None
    return None


def decode_png(data: bytes, max_pixels: int) -> PngImage | None:
    """Decode a label-mask PNG exactly as OpenCV does, or None (see the module docs).

    Args:
        data: the file's bytes.
        max_pixels: decline a header claiming more pixels than this (before inflating).

    Returns:
        The image, or None when this decoder does not take the file (OpenCV decides).
    """
    if len(data) < 57 or data[:8] != _SIGNATURE or data[12:16] != b"IHDR":
        return None
    w, h, depth, ctype, comp, filt, interlace = struct.unpack_from(">IIBBBBB", data, 16)
    if (ctype, depth) not in ((0, 8), (0, 16), (3, 8)) or (comp, filt, interlace) != (0, 0, 0):
        return None
    if not (0 < w <= 0x7FFFFFFF and 0 < h <= 0x7FFFFFFF) or w * h > max_pixels:
        return None
    walked = _chunks(data)
    if walked is None or not walked[1] or walked[0][0] != (b"IHDR", 16, 29):
        return None
    palette = _idat_and_palette(walked[0], data, ctype)
    if palette is None:
        return None
    idat, plte = palette
    bpp = depth // 8
    size = h * (w * bpp + 1)  # filtered rows: one filter byte each
    filtered = _inflate_into(idat, size)
    if filtered is None:
        return None
    # imported at the first decode: numba (with scipy) costs ~0.4 s to import, which a
    # program that only imports mistool (the viewer before its first frame) need not pay
    from mistool.kernels.png import unfilter_rows

    rows = filtered.reshape(h, w * bpp + 1)
    unfiltered = np.empty((h, w * bpp), np.uint8)
    if not unfilter_rows(rows, bpp, unfiltered):
        return None  # a filter type over 4
    if bpp == 1:
        pixels = unfiltered
    else:  # big-endian samples
        pixels = unfiltered.view(">u2").astype(np.uint16)
    if plte is None:
        return PngImage(pixels, None)
    if int(pixels.max()) >= len(plte):  # OpenCV's colour for such an index: not ours to guess
        return None
    return PngImage(pixels, plte)


#: Inflate this many bytes at a time into the thread's scratch buffer.
_PIECE = 1 << 16

_local = threading.local()


#: Scratch buffers up to this size are kept from frame to frame (per thread); a larger
#: image's temporaries are allocated for it alone (not held after it).
SCRATCH_KEEP_BYTES = 16 << 20


def _scratch(name: str, size: int, dtype: type) -> np.ndarray:
    """The calling thread's reusable flat buffer ``name`` of at least ``size`` items.

    The decoder's large temporaries live here, kept from frame to frame: freed and
    allocated anew each frame, they made glibc hand memory back to the system and fault
    it in again (~180 page faults per 720x576 frame, a third of the decoding time)."""
    have = getattr(_local, name, None)
    if have is None or have.size < size:
        have = np.empty(size, dtype)
        if have.nbytes > SCRATCH_KEEP_BYTES:
            return have
        setattr(_local, name, have)
    return have[:size]


def _inflate_into(idat: bytes, size: int) -> np.ndarray | None:
    """The zlib stream ``idat`` inflated into the thread's scratch buffer, a piece at a
    time (never more than ``size`` bytes, so a bomb stops there); None unless it holds
    exactly ``size`` bytes, ends with a correct Adler-32 and nothing follows it."""
    out = _scratch("filtered", size, np.uint8)
    inflate = _ZLIB.decompressobj()
    pos, data = 0, idat
    try:
        while not inflate.eof:
            piece = inflate.decompress(data, _PIECE)
            data = inflate.unconsumed_tail
            if not piece:
                break  # no progress: the stream is cut
            end = pos + len(piece)
            if end > size:
                return None
            out[pos:end] = np.frombuffer(piece, np.uint8)
            pos = end
    except Exception:  # noqa: BLE001 - any inflate error: OpenCV decides and reports
        return None
    if pos != size or not inflate.eof or data or inflate.unused_data:
        return None
    return out


def _idat_and_palette(
    chunks: list[tuple[bytes, int, int]], data: bytes, ctype: int
) -> tuple[bytes, np.ndarray | None] | None:
    """The joined image data and the packed palette (palette images), or None when the
    chunk sequence is not one this decoder takes."""
    idat: list[bytes] = []
    plte: np.ndarray | None = None
    state = 0  # 0: before IDAT, 1: in the IDAT run, 2: after it
    alpha = False
    for kind, start, stop in chunks[1:]:
        if kind == b"IDAT":
            if state == 2:
                return None
            state = 1
            idat.append(data[start:stop])
            continue
        if state == 1:
            state = 2
        if kind == b"IEND":
            if stop != start:
                return None
            break
        if kind == b"PLTE":
            n = stop - start
            if ctype != 3 or plte is not None or state or n == 0 or n % 3 or n > 768:
                return None
            rgb = np.frombuffer(data, np.uint8, n, start).reshape(-1, 3).astype(np.uint32)
            plte = (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
        elif kind == b"tRNS":  # palette transparency: OpenCV adds alpha, labels ignore it
            if ctype != 3 or plte is None or alpha or state or stop - start > len(plte):
                return None
            alpha = True
        elif kind not in ANCILLARY_OK:
            return None
    if not idat or (ctype == 3 and plte is None):
        return None
    return b"".join(idat), plte
