"""A strict, fast decoder for the PNG label images masks are stored as.

:func:`decode_png` decodes non-interlaced 8/16-bit greyscale and 8-bit palette PNGs,
whatever row filters their encoder chose (None, Sub, Up, Average, Paeth), several times
faster than ``cv2.imread`` on label masks (``scripts/bench_decode.py``): zlib-ng inflates
(into a buffer kept from frame to frame; its own ``zng_inflate`` called through ctypes
when the ``zlib_ng`` module exports zlib-ng 2.x's API, else ``decompressobj``) and one
compiled pass undoes every row's filter (:func:`mistool.kernels.png.unfilter_rows`).
:func:`decode_png_runs` gives an 8-bit grey file's runs of equal values instead of its
pixels (what the per-frame work reads), unfiltering only the rows that are not zero; its
kernel checks the rows' Adler-32 too (from the non-zero bytes alone), so zlib-ng's
inflate skips its own pass over them.

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

import contextlib
import ctypes
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


def _filtered_rows(
    data: bytes, max_pixels: int, check: bool = True
) -> tuple[np.ndarray, int, np.ndarray | None, int] | None:
    """The checks of :func:`decode_png` up to the inflated rows: ``(rows, bpp, palette,
    adler)`` (``rows``: (H, 1 + W * bpp) filter type then filtered bytes, in the thread's
    scratch buffer; ``adler``: the Adler-32 the zlib stream ends with), or None. With
    ``check`` False the inflate may leave the rows' Adler-32 unchecked: the caller checks
    it (:func:`mistool.kernels.png.unfilter_runs`)."""
    if len(data) < 57 or data[:8] != _SIGNATURE or data[12:16] != b"IHDR":
        return None
    w, h, depth, ctype, comp, filt, interlace = _HEADER.unpack_from(data, 16)
    if (ctype, depth) not in _TAKEN or comp or filt or interlace:
        return None
    if not (0 < w <= 0x7FFFFFFF and 0 < h <= 0x7FFFFFFF) or w * h > max_pixels:
        return None
    got = _image_data(data, ctype)
    if got is None:
        return None
    idat, plte = got
    bpp = depth // 8
    size = h * (w * bpp + 1)  # filtered rows: one filter byte each
    filtered = _inflate_into(idat, size, check)
    if filtered is None:
        return None
    # (a stream that inflated ends with its Adler-32, big-endian: nothing follows it)
    return filtered.reshape(h, w * bpp + 1), bpp, plte, _CRC.unpack_from(idat, len(idat) - 4)[0]


#: ``(colour type, bit depth)`` decoded here: 8/16-bit grey, 8-bit palette.
_TAKEN = frozenset({(0, 8), (0, 16), (3, 8)})
_HEADER = struct.Struct(">IIBBBBB")  # IHDR: width, height, depth, colour type, methods
_CHUNK = struct.Struct(">I4s")  # a chunk's length and type
_CRC = struct.Struct(">I")


def _image_data(data: bytes, ctype: int) -> tuple[bytes, np.ndarray | None] | None:
    """The joined image data and the packed palette (palette images) of a file whose
    header is checked, walking its chunks once; None when a chunk's CRC is wrong, the
    chunk structure is broken (or bytes follow ``IEND``), or the chunk sequence is not
    one this decoder takes (the first: ``IHDR`` of 13 bytes; then the critical chunks in
    their order or those in :data:`ANCILLARY_OK`)."""
    crc32 = _ZLIB.crc32
    chunk, crc = _CHUNK.unpack_from, _CRC.unpack_from
    n = len(data)
    pos = 8
    idat: list[bytes] = []
    plte: np.ndarray | None = None
    state = 0  # 0: before IDAT, 1: in the IDAT run, 2: after it
    alpha = False
    while pos + 12 <= n:
        length, kind = chunk(data, pos)
        start = pos + 8
        stop = start + length
        if length > 0x7FFFFFFF or stop + 4 > n:
            return None
        if crc32(data[pos + 4 : stop]) != crc(data, stop)[0]:
            return None
        pos = stop + 4
        if start == 16:  # the first chunk
            if kind != b"IHDR" or stop != 29:
                return None
            continue
        if kind == b"IDAT":
            if state == 2:
                return None
            state = 1
            idat.append(data[start:stop])
            continue
        if state == 1:
            state = 2
        if kind == b"IEND":
            if stop != start or pos != n:
                return None
            if not idat or (ctype == 3 and plte is None):
                return None
            return b"".join(idat), plte
        side = _side_chunk(kind, data, start, stop, ctype, plte, alpha, state)
        if side is None:
            return None
        plte, alpha = side
    return None  # no IEND


def _side_chunk(
    kind: bytes,
    data: bytes,
    start: int,
    stop: int,
    ctype: int,
    plte: np.ndarray | None,
    alpha: bool,
    state: int,
) -> tuple[np.ndarray | None, bool] | None:
    """A chunk other than ``IHDR``, ``IDAT`` and ``IEND`` (body ``data[start:stop]``)
    met in :func:`_image_data`'s walk (``state``: 0 before the image data, 2 after it):
    the palette so far and whether a ``tRNS`` came, or None when it is not taken."""
    if kind == b"PLTE":
        size = stop - start
        if ctype != 3 or plte is not None or state or size == 0 or size % 3 or size > 768:
            return None
        rgb = np.frombuffer(data, np.uint8, size, start).reshape(-1, 3).astype(np.uint32)
        return (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2], alpha
    if kind == b"tRNS":  # palette transparency: OpenCV adds alpha, labels ignore it
        if ctype != 3 or plte is None or alpha or state or stop - start > len(plte):
            return None
        return plte, True
    return (plte, alpha) if kind in ANCILLARY_OK else None


def decode_png(data: bytes, max_pixels: int) -> PngImage | None:
    """Decode a label-mask PNG exactly as OpenCV does, or None (see the module docs).

    Args:
        data: the file's bytes.
        max_pixels: decline a header claiming more pixels than this (before inflating).

    Returns:
        The image, or None when this decoder does not take the file (OpenCV decides).
    """
    got = _filtered_rows(data, max_pixels)
    if got is None:
        return None
    rows, bpp, plte, _ = got
    unfilter_rows = _png_kernels().unfilter_rows
    h, w = rows.shape[0], (rows.shape[1] - 1) // bpp
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


_PNG_KERNELS: list[Any] = []


def _png_kernels() -> Any:
    """:mod:`mistool.kernels.png`, imported at the first decode: numba (with scipy) costs
    ~0.4 s to import, which a program that only imports mistool (the viewer before its
    first frame) need not pay."""
    if not _PNG_KERNELS:
        from mistool.kernels import png

        _PNG_KERNELS.append(png)
    return _PNG_KERNELS[0]


def grey8(data: bytes) -> bool:
    """Whether the file's header says an 8-bit greyscale PNG (what
    :func:`decode_png_runs` takes)."""
    return data[:8] == _SIGNATURE and data[24:26] == b"\x08\x00"


#: ``(bounds, ry, rx0, rx1, rv, n, shape)``: see :func:`decode_png_runs`.
PngRuns = tuple[
    tuple[int, int, int, int], np.ndarray, np.ndarray, np.ndarray, np.ndarray, int, tuple[int, int]
]


def decode_png_runs(data: bytes, max_pixels: int) -> PngRuns | None:
    """The runs of equal non-zero values of an 8-bit greyscale PNG that
    :func:`decode_png` decodes, without the image (one pass from the filtered rows:
    :func:`mistool.kernels.png.unfilter_runs`); None where :func:`decode_png` returns
    None or the file is not 8-bit grey (:func:`grey8`).

    Returns:
        ``(bounds, ry, rx0, rx1, rv, n, (H, W))``: what
        ``mistool.kernels.instances.label_runs`` gives of :func:`decode_png`'s pixels
        (``bounds``: the non-zero pixels' (x, y, w, h); the first ``n`` items of each
        int32 array: the runs' rows and columns relative to the bounds, and values).
    """
    if not grey8(data):
        return None
    got = _filtered_rows(data, max_pixels, False)
    if got is None:
        return None
    rows, _, _, adler = got
    unfilter_runs = _png_kernels().unfilter_runs
    h, w = rows.shape[0], rows.shape[1] - 1
    scratch = _scratch("rowpair", 2 * w, np.uint8)
    bounds = np.zeros(4, np.int64)
    cap = 4 * h + 64
    while True:
        ry = np.empty(cap, np.int32)
        rx0 = np.empty(cap, np.int32)
        rx1 = np.empty(cap, np.int32)
        rv = np.empty(cap, np.int32)
        n = unfilter_runs(rows, scratch, ry, rx0, rx1, rv, bounds, adler)
        if n != -1:
            break
        cap *= 4
    if n < 0:
        return None  # a filter type over 4, or a wrong Adler-32
    x, y, bw, bh = bounds.tolist()
    return (x, y, bw, bh), ry, rx0, rx1, rv, n, (h, w)


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
    return _scratch_at(name, size, dtype)[0]


def _scratch_at(name: str, size: int, dtype: type) -> tuple[np.ndarray, int]:
    """:func:`_scratch` and the address of its first item (kept with the buffer:
    ``ndarray.ctypes.data`` costs ~1.4 us)."""
    have = getattr(_local, name, None)
    if have is None or have.size < size:
        have = np.empty(size, dtype)
        at = have.ctypes.data
        if have.nbytes > SCRATCH_KEEP_BYTES:
            return have, at
        setattr(_local, name, have)
        setattr(_local, name + "_at", at)
        return have[:size], at
    return have[:size], getattr(_local, name + "_at")


def _inflate_into(idat: bytes, size: int, check: bool = True) -> np.ndarray | None:
    """The zlib stream ``idat`` inflated into the thread's scratch buffer (never more
    than ``size`` bytes, so a bomb stops there); None unless it holds exactly ``size``
    bytes, ends with a correct Adler-32 (with ``check`` False, zlib-ng's inflate leaves
    the Adler-32 to the caller: still there, not compared) and nothing follows it.
    zlib-ng's inflate is called directly when it can be (:class:`_NativeInflate`), else
    a piece at a time."""
    out, at = _scratch_at("filtered", size, np.uint8)
    native = _native_inflate(check)
    if native is not None and size < 1 << 32 and len(idat) < 1 << 32:
        return out if native.inflate(idat, out, at) else None
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


class _ZngStream(ctypes.Structure):
    """zlib-ng 2.x's ``zng_stream`` (``zlib-ng.h``, its native API)."""

    _fields_ = (
        ("next_in", ctypes.c_char_p),  # (a bytes object's own buffer, kept while set)
        ("avail_in", ctypes.c_uint32),
        ("total_in", ctypes.c_size_t),
        ("next_out", ctypes.c_void_p),
        ("avail_out", ctypes.c_uint32),
        ("total_out", ctypes.c_size_t),
        ("msg", ctypes.c_char_p),
        ("state", ctypes.c_void_p),
        ("zalloc", ctypes.c_void_p),
        ("zfree", ctypes.c_void_p),
        ("opaque", ctypes.c_void_p),
        ("data_type", ctypes.c_int),
        ("adler", ctypes.c_uint32),
        ("reserved", ctypes.c_ulong),
    )


_Z_FINISH = 4
_Z_STREAM_END = 1


class _NativeInflate:
    """One thread's zlib-ng inflate stream, called through ctypes: the whole stream in
    one call straight into the scratch buffer (~0.03 ms a 720x576 mask, against ~0.05
    for the pieces ``decompressobj`` returns, each a new bytes object copied over)."""

    def __init__(self, lib: Any, check: bool = True) -> None:
        """``check`` False: the stream's Adler-32 is read, not compared (the caller
        compares it: ~0.006 ms less a 720x576 mask, the check's pass over the rows)."""
        self._lib = lib
        self._stream = _ZngStream()
        self._ref = ctypes.byref(self._stream)
        if lib.zng_inflateInit2(self._ref, 15) != 0:  # 15: a zlib header, 32 KB window
            raise OSError("zng_inflateInit2 failed")
        if not check and lib.zng_inflateValidate(self._ref, 0) != 0:  # (kept by a reset)
            raise OSError("zng_inflateValidate failed")

    def inflate(self, data: bytes, out: np.ndarray, out_at: int | None = None) -> bool:
        """Inflate the zlib stream ``data`` into ``out`` (C-contiguous uint8; ``out_at``:
        its address when the caller knows it): whether it filled ``out`` exactly, its
        Adler-32 right, with nothing after it."""
        s = self._stream
        if self._lib.zng_inflateReset(self._ref) != 0:
            return False
        s.next_in = data
        s.avail_in = len(data)
        s.next_out = out.ctypes.data if out_at is None else out_at
        s.avail_out = out.size
        done = self._lib.zng_inflate(self._ref, _Z_FINISH) == _Z_STREAM_END
        s.next_in = s.next_out = None  # (no pointer kept into data or out)
        return done and s.avail_out == 0 and s.avail_in == 0

    def __del__(self) -> None:
        with contextlib.suppress(Exception):  # (at exit ctypes may be gone)
            self._lib.zng_inflateEnd(self._ref)


def _native_library() -> Any:
    """zlib-ng 2.x's library (the ``zlib_ng`` extension module exports its API), its
    functions typed and checked on a known stream; None when not available."""
    try:
        from zlib_ng import zlib_ng
    except ImportError:
        return None
    if not str(getattr(zlib_ng, "ZLIBNG_VERSION", "")).startswith("2."):
        return None  # (the stream's layout is 2.x's)
    try:
        lib = ctypes.CDLL(zlib_ng.__file__)
        stream = ctypes.POINTER(_ZngStream)
        for name, args in (
            ("zng_inflateInit2", [stream, ctypes.c_int32]),
            ("zng_inflate", [stream, ctypes.c_int32]),
            ("zng_inflateReset", [stream]),
            ("zng_inflateEnd", [stream]),
            ("zng_inflateValidate", [stream, ctypes.c_int32]),
        ):
            fn = getattr(lib, name)
            fn.argtypes, fn.restype = args, ctypes.c_int32
        probe = bytes(range(256)) * 64 + bytes(5000)
        packed = zlib_ng.compress(probe)
        out = np.zeros(len(probe), np.uint8)
        check = _NativeInflate(lib)
        if not check.inflate(packed, out) or out.tobytes() != probe:
            return None
        if check.inflate(packed[:-1], out) or check.inflate(packed + b"x", out):
            return None
        wrong = packed[:-1] + bytes([packed[-1] ^ 1])  # a wrong Adler-32
        unchecked = _NativeInflate(lib, check=False)
        if check.inflate(wrong, out) or not unchecked.inflate(wrong, out):
            return None
        if unchecked.inflate(packed[:-1], out):  # (the Adler-32 is still read)
            return None
    except (OSError, AttributeError):
        return None
    return lib


_NATIVE: list[Any] = []


def _native_inflate(check: bool = True) -> _NativeInflate | None:
    """The calling thread's :class:`_NativeInflate` (that leaving the Adler-32 to the
    caller with ``check`` False), or None (zlib-ng 2.x not there)."""
    name = "inflate" if check else "inflate_unchecked"
    have = getattr(_local, name, None)
    if have is not None:
        return have
    if not _NATIVE:
        _NATIVE.append(_native_library())
    if _NATIVE[0] is None:
        return None
    have = _NativeInflate(_NATIVE[0], check)
    setattr(_local, name, have)
    return have
