"""PNG row filters undone in one pass (PNG specification, section 9: "Filtering").

Plain index loops throughout: numba compiles them to vector code, while a slice
assignment (``out[y, :] = rows[y, 1:]``) takes a generic path about 15x slower. Along a
row, a one-byte neighbour is kept in a register: reloaded from ``out``, every byte would
wait for the store of the one before."""

from __future__ import annotations

import numpy as np

from mistool.kernels import helper, kernel
from mistool.kernels.boxes import ctz, load8


@helper
def _none(rows: np.ndarray, y: int, bpp: int, out: np.ndarray) -> None:
    for x in range(out.shape[1]):
        out[y, x] = rows[y, x + 1]


@helper
def _sub(rows: np.ndarray, y: int, bpp: int, out: np.ndarray) -> None:
    w = out.shape[1]
    if bpp == 1:
        run = np.uint8(0)
        for x in range(w):
            run = np.uint8(rows[y, x + 1] + run)
            out[y, x] = run
        return
    for x in range(min(bpp, w)):
        out[y, x] = rows[y, x + 1]
    for x in range(bpp, w):
        out[y, x] = rows[y, x + 1] + out[y, x - bpp]


@helper
def _up(rows: np.ndarray, y: int, bpp: int, out: np.ndarray) -> None:
    for x in range(out.shape[1]):
        out[y, x] = rows[y, x + 1] + out[y - 1, x]


@helper
def _average(rows: np.ndarray, y: int, bpp: int, out: np.ndarray) -> None:
    """floor((left + above) / 2); the row above the first is zero."""
    w = out.shape[1]
    for x in range(min(bpp, w)):
        up = 0 if y == 0 else np.int32(out[y - 1, x])
        out[y, x] = rows[y, x + 1] + (up >> 1)
    for x in range(bpp, w):
        up = 0 if y == 0 else np.int32(out[y - 1, x])
        out[y, x] = rows[y, x + 1] + ((np.int32(out[y, x - bpp]) + up) >> 1)


@helper
def _paeth(rows: np.ndarray, y: int, bpp: int, out: np.ndarray) -> None:
    """Paeth's predictor, not on the first row (there it is Sub's)."""
    w = out.shape[1]
    for x in range(min(bpp, w)):  # left and upper-left are 0: the byte above
        out[y, x] = rows[y, x + 1] + out[y - 1, x]
    a = np.int32(out[y, 0])  # bpp == 1: the left byte, kept in a register
    for x in range(bpp, w):
        if bpp != 1:
            a = np.int32(out[y, x - bpp])
        b = np.int32(out[y - 1, x])
        c = np.int32(out[y - 1, x - bpp])
        pa = abs(b - c)
        pb = abs(a - c)
        pc = abs(a + b - 2 * c)
        if pa <= pb and pa <= pc:
            pred = a
        elif pb <= pc:
            pred = b
        else:
            pred = c
        a = np.int32(np.uint8(rows[y, x + 1] + pred))
        out[y, x] = a


@kernel("boolean(uint8[:, ::1], int64, uint8[:, ::1])")
def unfilter_rows(rows: np.ndarray, bpp: int, out: np.ndarray) -> bool:
    """Undo every row's filter: ``rows`` (H, 1 + W) holds each row's filter type then its
    filtered bytes, ``out`` (H, W) receives the bytes; ``bpp`` bytes per pixel (the filters'
    "left" neighbour is ``bpp`` bytes back; the row above the first is zero). All sums are
    modulo 256 (uint8). False (``out`` unfinished) at a filter type over 4."""
    for y in range(rows.shape[0]):
        kind = rows[y, 0]
        if kind == 0 or (kind == 2 and y == 0):  # None; Up on the first row
            _none(rows, y, bpp, out)
        elif kind == 1 or (kind == 4 and y == 0):  # Sub; Paeth on the first row
            _sub(rows, y, bpp, out)
        elif kind == 2:
            _up(rows, y, bpp, out)
        elif kind == 3:
            _average(rows, y, bpp, out)
        elif kind == 4:
            _paeth(rows, y, bpp, out)
        else:
            return False
    return True


# --- 8-bit grey rows straight to runs of equal values --------------------------------------

_BROADCAST = np.uint64(0x0101010101010101)


@helper
def _zero_bytes(buf: np.ndarray, lo: int, hi: int) -> bool:
    """Whether ``buf[lo:hi]`` are all zero (64 bytes at a time)."""
    i = lo
    while i + 64 <= hi:
        word = load8(buf, i) | load8(buf, i + 8) | load8(buf, i + 16) | load8(buf, i + 24)
        word |= load8(buf, i + 32) | load8(buf, i + 40) | load8(buf, i + 48) | load8(buf, i + 56)
        if word != 0:
            return False
        i += 64
    while i + 8 <= hi:
        if load8(buf, i) != 0:
            return False
        i += 8
    while i < hi:
        if buf[i] != 0:
            return False
        i += 1
    return True


@helper
def _row_runs(
    buf: np.ndarray,
    base: int,
    w: int,
    y: int,
    ry: np.ndarray,
    rx0: np.ndarray,
    rx1: np.ndarray,
    rv: np.ndarray,
    n: int,
) -> int:
    """Append the runs of equal non-zero bytes of the row ``buf[base:base + w]`` (row
    ``y``) from run ``n``: the new number of runs, or -1 when the arrays are full. 32 or
    8 bytes at a time: words of the current value are passed over, otherwise the first
    byte that differs is found from the word's trailing zero bits (``kernels.instances``'
    ``_runs_u8``)."""
    cap = ry.shape[0]
    x = 0
    start = 0
    v = buf[base]
    while True:
        if x + 32 <= w:  # four words of v: passed over at once
            vv = np.uint64(v) * _BROADCAST
            i = base + x
            same = (load8(buf, i) ^ vv) | (load8(buf, i + 8) ^ vv)
            same |= (load8(buf, i + 16) ^ vv) | (load8(buf, i + 24) ^ vv)
            if same == 0:
                x += 32
                continue
        if x + 8 <= w:
            diff = load8(buf, base + x) ^ (np.uint64(v) * _BROADCAST)
            if diff == 0:
                x += 8
                continue
            x += np.int64(ctz(diff) >> np.uint64(3))
        else:
            while x < w and buf[base + x] == v:
                x += 1
        if v != 0:  # the run of v ends at x
            if n == cap:
                return -1
            ry[n] = y
            rx0[n] = start
            rx1[n] = x
            rv[n] = v
            n += 1
        if x >= w:
            return n
        start = x
        v = buf[base + x]


@helper
def _fill(buf: np.ndarray, lo: int, hi: int, v: np.uint8) -> None:
    """``buf[lo:hi] = v`` (unsigned indices: no wraparound test, so vector stores)."""
    for x in range(np.uint64(lo), np.uint64(hi)):
        buf[x] = v


@helper
def _copy(src: np.ndarray, at: int, dst: np.ndarray, to: int, w: int) -> None:
    """``dst[to:to + w] = src[at:at + w]``."""
    d = np.uint64(to) - np.uint64(at)
    for x in range(np.uint64(at), np.uint64(at + w)):
        dst[x + d] = src[x]


@helper
def _add(src: np.ndarray, at: int, out: np.ndarray, up: int, cur: int, w: int) -> None:
    """Up: ``out[cur:cur + w] = src[at:at + w] + out[up:up + w]`` (modulo 256)."""
    a, u, c = np.uint64(at), np.uint64(up), np.uint64(cur)
    for x in range(np.uint64(0), np.uint64(w)):
        out[c + x] = src[a + x] + out[u + x]


@helper
def _sub_row(flat: np.ndarray, at: int, w: int, out: np.ndarray, cur: int) -> None:
    """Sub: each byte plus the one on its left; where the filtered bytes are zero the
    value stays, so they are passed over 8 at a time and the stretch filled."""
    a = np.uint8(0)
    x = 0
    while x < w:
        if x + 8 <= w:
            word = load8(flat, at + x)
            if word == 0:
                _fill(out, cur + x, cur + x + 8, a)
                x += 8
                continue
            skip = np.int64(ctz(word) >> np.uint64(3))
            _fill(out, cur + x, cur + x + skip, a)
            x += skip
        a = np.uint8(flat[at + x] + a)
        out[cur + x] = a
        x += 1


@helper
def _paeth_row(flat: np.ndarray, at: int, w: int, out: np.ndarray, cur: int, up: int) -> None:
    """Paeth, the row above (``out[up:up + w]``) not zero. Where the row above does not
    change (b == c) the predictor is the left byte (pa = 0), so where moreover the
    filtered byte is zero the value stays: such stretches are passed over 8 at a time."""
    a = np.int32(np.uint8(flat[at] + out[up]))  # left and upper-left are 0: the byte above
    out[cur] = a
    x = 1
    while x < w:
        if x + 8 <= w:
            word = load8(flat, at + x) | (load8(out, up + x) ^ load8(out, up + x - 1))
            if word == 0:
                _fill(out, cur + x, cur + x + 8, np.uint8(a))
                x += 8
                continue
            skip = np.int64(ctz(word) >> np.uint64(3))
            _fill(out, cur + x, cur + x + skip, np.uint8(a))
            x += skip
        b = np.int32(out[up + x])
        c = np.int32(out[up + x - 1])
        pa = abs(b - c)
        pb = abs(a - c)
        pc = abs(a + b - 2 * c)
        if pa <= pb and pa <= pc:
            pred = a
        elif pb <= pc:
            pred = b
        else:
            pred = c
        a = np.int32(np.uint8(flat[at + x] + pred))
        out[cur + x] = a
        x += 1


@helper
def _unfilter_row(
    flat: np.ndarray,
    at: int,
    w: int,
    kind: int,
    out: np.ndarray,
    cur: int,
    up: int,
    up_zero: bool,
) -> None:
    """Row ``flat[at:at + w]`` of filter ``kind`` (1 to 4; Up and Paeth with a row above
    that is not zero) unfiltered into ``out[cur:cur + w]``; the row above is
    ``out[up:up + w]``, or zero (``up_zero``)."""
    if kind == 1:
        _sub_row(flat, at, w, out, cur)
    elif kind == 2:
        _add(flat, at, out, up, cur, w)
    elif kind == 3:
        left = np.int32(0)
        for x in range(w):
            above = 0 if up_zero else np.int32(out[up + x])
            left = np.int32(np.uint8(flat[at + x] + ((left + above) >> 1)))
            out[cur + x] = left
    else:
        _paeth_row(flat, at, w, out, cur, up)


@helper
def _to_bounds(
    ry: np.ndarray, rx0: np.ndarray, rx1: np.ndarray, n: int, bounds: np.ndarray
) -> None:
    """``bounds`` gets the (x, y, w, h) bounds of ``n`` runs in raster order (``(0, 0,
    0, 0)``: none); the runs' coordinates then made relative to (x, y)
    (``kernels.instances._run_bounds``)."""
    bounds[0] = bounds[1] = bounds[2] = bounds[3] = 0
    if n == 0:
        return
    x0, x1 = rx0[0], rx1[0]
    for i in range(n):
        x0 = min(x0, rx0[i])
        x1 = max(x1, rx1[i])
    y0, y1 = ry[0], ry[n - 1] + 1
    for i in range(n):
        ry[i] -= y0
        rx0[i] -= x0
        rx1[i] -= x0
    bounds[0], bounds[1], bounds[2], bounds[3] = x0, y0, x1 - x0, y1 - y0


@kernel(
    "int64(uint8[:, ::1], uint8[::1], int32[::1], int32[::1], int32[::1], int32[::1], int64[::1])"
)
def unfilter_runs(
    rows: np.ndarray,
    scratch: np.ndarray,
    ry: np.ndarray,
    rx0: np.ndarray,
    rx1: np.ndarray,
    rv: np.ndarray,
    bounds: np.ndarray,
) -> int:
    """The runs of equal non-zero values of an 8-bit grey image given as its filtered
    rows (``rows`` (H, 1 + W), as :func:`unfilter_rows` takes them, ``bpp`` 1), without
    writing the image: ``mistool.kernels.instances.label_runs`` of
    ``unfilter_rows``' output, bit for bit.

    A row of zero bytes under a zero row (or the first) is zero whatever its filter, so
    the background is passed over 64 bytes at a time; a None row (or Up under a zero
    row) is read where it lies; the other rows are unfiltered into ``scratch`` ((2 W,):
    this row and the one above), Sub and Paeth passing over the stretches where the
    value stays 8 bytes at a time (mask rows are long runs).

    Returns the number of runs (raster order; coordinates then relative to ``bounds``,
    which gets their ``(x, y, w, h)``, ``(0, 0, 0, 0)`` for none), -1 when the run
    arrays are full (call again with longer ones), -2 at a filter type over 4."""
    h, stride = rows.shape
    w = stride - 1
    flat = rows.reshape(-1)
    up = 0  # where the row above lies in scratch, when not zero
    up_zero = True  # the row above is zero (the first row's is)
    slot = 0  # the half of scratch the next row goes to
    n = 0
    for y in range(h):
        at = y * stride + 1
        kind = flat[at - 1]
        if kind > 4:
            return -2
        if up_zero:
            if kind == 2:  # Up under zero: None
                kind = 0
            elif kind == 4:  # Paeth under zero: Sub (a = left; b = c = 0)
                kind = 1
            if _zero_bytes(flat, at, at + w):  # zero whatever the filter
                continue
        if kind == 0:
            m = _row_runs(flat, at, w, y, ry, rx0, rx1, rv, n)
            if m < 0:
                return -1
            up_zero = m == n
            n = m
            if not up_zero and y + 1 < h and flat[at + w] >= 2:  # the row below needs it
                up = slot * w
                _copy(flat, at, scratch, up, w)
                slot = 1 - slot
            continue
        cur = slot * w
        _unfilter_row(flat, at, w, kind, scratch, cur, up, up_zero)
        m = _row_runs(scratch, cur, w, y, ry, rx0, rx1, rv, n)
        if m < 0:
            return -1
        up_zero = m == n
        n = m
        up = cur
        slot = 1 - slot
    _to_bounds(ry, rx0, rx1, n, bounds)
    return n
