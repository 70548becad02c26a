"""PNG row filters undone in one pass (PNG specification, section 9: "Filtering").

Plain index loops throughout: numba compiles them to vector code, while a slice
assignment (``out[y, :] = rows[y, 1:]``) takes a generic path about 15x slower. Along a
row, a one-byte neighbour is kept in a register: reloaded from ``out``, every byte would
wait for the store of the one before. Stretches of 64 bytes (all zero, all one value, or
equal to the row above's) are tested with one vector load and an or-reduction
(:func:`or64`, :func:`xor64`, :func:`ne64`: LLVM intrinsics numba does not spell)."""

from __future__ import annotations

from typing import Any

import numpy as np
from llvmlite import ir  # type: ignore[import-untyped]
from numba import types
from numba.core import cgutils
from numba.core.extending import intrinsic

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


def _or64_typed(typingctx: object, arr: types.Array, i: types.Integer) -> tuple[object, object]:
    """The bitwise or of the 64 bytes of a C-contiguous uint8 array from flat index
    ``i``, folded to one uint64 (one unaligned vector load and an or-reduction: 64
    bytes in a few instructions; the caller keeps ``i + 64`` within the array)."""
    sig = types.uint64(arr, types.int64)

    def codegen(context: Any, builder: ir.IRBuilder, signature: Any, args: list) -> object:
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        return _fold_or(builder, _load64(builder, ary, args[1]))

    return sig, codegen


def _xor64_typed(
    typingctx: object, arr: types.Array, i: types.Integer, j: types.Integer
) -> tuple[object, object]:
    """The bitwise or of the 64 bytes from flat index ``i`` xor those from ``j`` (zero
    exactly when the two stretches are equal), as :func:`or64`."""
    sig = types.uint64(arr, types.int64, types.int64)

    def codegen(context: Any, builder: ir.IRBuilder, signature: Any, args: list) -> object:
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        diff = builder.xor(_load64(builder, ary, args[1]), _load64(builder, ary, args[2]))
        return _fold_or(builder, diff)

    return sig, codegen


def _ne64_typed(
    typingctx: object, arr: types.Array, i: types.Integer, word: types.Integer
) -> tuple[object, object]:
    """The bitwise or of the 64 bytes from flat index ``i`` each xor ``word`` (a byte
    broadcast to a uint64): zero exactly when they all equal that byte."""
    sig = types.uint64(arr, types.int64, types.uint64)

    def codegen(context: Any, builder: ir.IRBuilder, signature: Any, args: list) -> object:
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        splat = builder.insert_element(
            ir.Constant(_VEC64, None), args[2], ir.Constant(ir.IntType(32), 0)
        )
        splat = builder.shuffle_vector(
            splat, splat, ir.Constant(ir.VectorType(ir.IntType(32), 8), None)
        )
        return _fold_or(builder, builder.xor(_load64(builder, ary, args[1]), splat))

    return sig, codegen


_VEC64 = ir.VectorType(ir.IntType(64), 8)


def _load64(builder: ir.IRBuilder, ary: Any, i: object) -> object:
    """64 bytes of ``ary`` from flat index ``i`` as eight uint64 lanes (unaligned)."""
    ptr = builder.bitcast(builder.gep(ary.data, [i]), _VEC64.as_pointer())
    return builder.load(ptr, align=1)


def _fold_or(builder: ir.IRBuilder, vec: object) -> object:
    fnty = ir.FunctionType(ir.IntType(64), [_VEC64])
    fold = cgutils.get_or_insert_function(builder.module, fnty, "llvm.vector.reduce.or.v8i64")
    return builder.call(fold, [vec])


or64: Any = intrinsic(_or64_typed)
xor64: Any = intrinsic(_xor64_typed)
ne64: Any = intrinsic(_ne64_typed)


@helper
def _zero_bytes(buf: np.ndarray, lo: int, hi: int) -> bool:
    """Whether ``buf[lo:hi]`` are all zero (64 bytes at a time)."""
    i = lo
    while i + 64 <= hi:
        if or64(buf, i) != 0:
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


#: Adler-32's modulus (RFC 1950, section 9: the largest prime below 2 ** 16).
_ADLER_BASE = 65521
_LANES = np.uint64(0x00FF00FF00FF00FF)  # a word's even bytes, as four 16-bit lanes
_SUM = np.uint64(0x0001000100010001)  # (lanes * _SUM) >> 48: the lanes' sum
_AT_EVEN = np.uint64(0x0000000200040006)  # ... weighted by the bytes' places 0, 2, 4, 6
_AT_ODD = np.uint64(0x0001000300050007)  # ... 1, 3, 5, 7
_TOP = np.uint64(48)


@helper
def _byte_sums(buf: np.ndarray, lo: int, hi: int, s: int, t: int) -> tuple[int, int]:
    """``(s, t)`` plus the sums over ``buf[lo:hi]`` of the bytes and of each byte times
    its place in ``buf`` (:func:`_span_sums` :data:`_SUMS_PIECE` bytes at a time)."""
    while lo < hi:
        end = min(hi, lo + _SUMS_PIECE)
        ps, pt = _span_sums(buf, lo, end - lo)
        s, t = _fold(s, t, lo, ps, pt)
        lo = end
    return s, t


@helper
def _fold(s: int, t: int, at: int, ps: np.uint64, pt: np.uint64) -> tuple[int, int]:
    """Adler-32's two sums (see :func:`unfilter_runs`; modulo :data:`_ADLER_BASE`) plus
    those of bytes from place ``at``: ``ps`` their sum, ``pt`` that of each byte times
    its place from ``at``."""
    pm = np.int64(ps % np.uint64(_ADLER_BASE))
    s = (s + pm) % _ADLER_BASE
    t = (t + (at % _ADLER_BASE) * pm + np.int64(pt % np.uint64(_ADLER_BASE))) % _ADLER_BASE
    return s, t


#: The longest stretch whose sums :func:`_span_sums` and the row helpers take in uint64
#: (bytes): below 2 ** 20 * 255 and 2 ** 40 * 255, nothing wraps.
_SUMS_PIECE = 1 << 20


@helper
def _adler32(n: int, s: int, t: int) -> int:
    """Adler-32 (RFC 1950) of ``n`` bytes whose sum is ``s`` and sum of each byte times
    its place (0-based) is ``t`` (both modulo :data:`_ADLER_BASE`): ``A = 1 + s`` and
    ``B`` = the sum of A after each byte = ``n + n s - t``."""
    m = n % _ADLER_BASE
    a = (1 + s) % _ADLER_BASE
    b = (m * a - t) % _ADLER_BASE
    if b < 0:
        b += _ADLER_BASE
    return (b << 16) | a


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
        if x + 64 <= w and ne64(buf, base + x, np.uint64(v) * _BROADCAST) == 0:
            x += 64  # 64 bytes of v: passed over at once
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


#: The row helpers below return the sums of the row's filtered bytes beside it (as
#: :func:`_span_sums`; exact for rows of at most :data:`_SUMS_PIECE` bytes).
_ZERO = np.uint64(0)


@helper
def _sub_row(
    flat: np.ndarray, at: int, w: int, out: np.ndarray, cur: int
) -> tuple[np.uint64, np.uint64]:
    """Sub: each byte plus the one on its left; where the filtered bytes are zero the
    value stays, so they are passed over 8 at a time and the stretch filled."""
    a = np.uint8(0)
    x = 0
    ps = pt = _ZERO
    while x < w:
        if x + 64 <= w and or64(flat, at + x) == 0:
            _fill(out, cur + x, cur + x + 64, a)
            x += 64
            continue
        if x + 8 <= w:
            word = load8(flat, at + x)
            if word == 0:
                _fill(out, cur + x, cur + x + 8, a)
                x += 8
                continue
            skip = np.int64(ctz(word) >> np.uint64(3))
            _fill(out, cur + x, cur + x + skip, a)
            x += skip
        f = flat[at + x]
        ps += np.uint64(f)
        pt += np.uint64(x) * np.uint64(f)
        a = np.uint8(f + a)
        out[cur + x] = a
        x += 1
    return ps, pt


@helper
def _paeth_row(
    flat: np.ndarray, at: int, w: int, out: np.ndarray, cur: int, up: int
) -> tuple[np.uint64, np.uint64]:
    """Paeth, the row above (``out[up:up + w]``) not zero. Where the row above does not
    change (b == c) the predictor is the left byte (pa = 0), so where moreover the
    filtered byte is zero the value stays: such stretches are passed over 8 at a time."""
    f = flat[at]
    ps, pt = np.uint64(f), _ZERO
    a = np.int32(np.uint8(f + out[up]))  # left and upper-left are 0: the byte above
    out[cur] = a
    x = 1
    while x < w:
        if x + 64 <= w and (or64(flat, at + x) | xor64(out, up + x, up + x - 1)) == 0:
            _fill(out, cur + x, cur + x + 64, np.uint8(a))
            x += 64
            continue
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
        f = flat[at + x]
        ps += np.uint64(f)
        pt += np.uint64(x) * np.uint64(f)
        a = np.int32(np.uint8(f + pred))
        out[cur + x] = a
        x += 1
    return ps, pt


@helper
def _sub_runs(
    flat: np.ndarray,
    at: int,
    w: int,
    y: int,
    ry: np.ndarray,
    rx0: np.ndarray,
    rx1: np.ndarray,
    rv: np.ndarray,
    n: int,
) -> tuple[int, np.uint64, np.uint64]:
    """A Sub row's runs (:func:`_row_runs` of :func:`_sub_row`'s output), read from its
    filtered bytes ``flat[at:at + w]`` without writing the row: each byte adds itself to
    the value on its left, so the value changes exactly where the filtered byte is not
    zero (mask rows: a few such bytes; the zero stretches passed over 64 and 8 bytes at
    a time). Returns the new number of runs (-1: the arrays are full) and the row's sums
    (as :func:`_sub_row`)."""
    cap = ry.shape[0]
    a = np.uint8(0)  # the value from ``start`` on
    start = 0
    x = 0
    ps = pt = _ZERO
    while x < w:
        if x + 64 <= w and or64(flat, at + x) == 0:
            x += 64
            continue
        if x + 8 <= w:
            word = load8(flat, at + x)
            if word == 0:
                x += 8
                continue
            x += np.int64(ctz(word) >> np.uint64(3))
        f = flat[at + x]
        if f != 0:  # the run of a ends here
            if a != 0:
                if n == cap:
                    return -1, ps, pt
                ry[n] = y
                rx0[n] = start
                rx1[n] = x
                rv[n] = a
                n += 1
            ps += np.uint64(f)
            pt += np.uint64(x) * np.uint64(f)
            a = np.uint8(f + a)
            start = x
        x += 1
    if a != 0:
        if n == cap:
            return -1, ps, pt
        ry[n] = y
        rx0[n] = start
        rx1[n] = w
        rv[n] = a
        n += 1
    return n, ps, pt


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
) -> tuple[np.uint64, np.uint64]:
    """Row ``flat[at:at + w]`` of filter ``kind`` (1 to 4; Up and Paeth with a row above
    that is not zero) unfiltered into ``out[cur:cur + w]``; the row above is
    ``out[up:up + w]``, or zero (``up_zero``). Returns the row's sums (see
    :func:`_span_sums`)."""
    if kind == 1:
        return _sub_row(flat, at, w, out, cur)
    if kind == 2:
        _add(flat, at, out, up, cur, w)
        return _span_sums(flat, at, w)
    if kind == 3:
        left = np.int32(0)
        ps = pt = _ZERO
        for x in range(w):
            f = flat[at + x]
            ps += np.uint64(f)
            pt += np.uint64(x) * np.uint64(f)
            above = 0 if up_zero else np.int32(out[up + x])
            left = np.int32(np.uint8(f + ((left + above) >> 1)))
            out[cur + x] = left
        return ps, pt
    return _paeth_row(flat, at, w, out, cur, up)


@helper
def _span_sums(buf: np.ndarray, lo: int, n: int) -> tuple[np.uint64, np.uint64]:
    """The sums of ``buf[lo:lo + n]`` (``n`` at most :data:`_SUMS_PIECE`): of the bytes,
    and of each byte times its place from ``lo``. Zero bytes add nothing: stretches of
    them are passed over 64 and 8 bytes at a time, and a word's eight bytes are summed
    at once (16-bit lanes and a multiplication; no lane reaches 2 ** 16)."""
    ps = pt = _ZERO
    i = 0
    while i + 8 <= n:
        if i + 64 <= n and or64(buf, lo + i) == 0:
            i += 64
            continue
        word = load8(buf, lo + i)
        if word != 0:
            even = word & _LANES
            odd = (word >> np.uint64(8)) & _LANES
            ws = ((even + odd) * _SUM) >> _TOP
            ps += ws
            pt += np.uint64(i) * ws + ((even * _AT_EVEN) >> _TOP) + ((odd * _AT_ODD) >> _TOP)
        i += 8
    while i < n:
        c = np.uint64(buf[lo + i])
        ps += c
        pt += np.uint64(i) * c
        i += 1
    return ps, pt


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
    "int64(uint8[:, ::1], uint8[::1], int32[::1], int32[::1], int32[::1], int32[::1],"
    " int64[::1], int64)"
)
def unfilter_runs(
    rows: np.ndarray,
    scratch: np.ndarray,
    ry: np.ndarray,
    rx0: np.ndarray,
    rx1: np.ndarray,
    rv: np.ndarray,
    bounds: np.ndarray,
    adler: int,
) -> int:
    """The runs of equal non-zero values of an 8-bit grey image given as its filtered
    rows (``rows`` (H, 1 + W), as :func:`unfilter_rows` takes them, ``bpp`` 1), without
    writing the image: ``mistool.kernels.instances.label_runs`` of
    ``unfilter_rows``' output, bit for bit; and the rows' Adler-32 (RFC 1950: the zlib
    stream's check, which the inflate then need not compute) checked against ``adler``.

    A row of zero bytes under a zero row (or the first) is zero whatever its filter, so
    the background is passed over 64 bytes at a time; a None
    row (or Up under a zero row) is read where it lies; the other rows are unfiltered
    into ``scratch`` ((2 W,): this row and the one above), Sub and Paeth passing over
    the stretches where the value stays 8 bytes at a time (mask rows are long runs);
    a Sub row that the row below does not read (None or Sub below, or none) is not
    written at all: its runs come from its filtered bytes that are not zero
    (:func:`_sub_runs`: ~3 us less a crossing frame's rows).

    Adler-32 from two sums: that of the bytes and that of each byte times its place,
    to which zero bytes add nothing (:func:`_adler32`): a zero row adds its filter byte.

    Returns the number of runs (raster order; coordinates then relative to ``bounds``,
    which gets their ``(x, y, w, h)``, ``(0, 0, 0, 0)`` for none), -1 when the run
    arrays are full (call again with longer ones), -2 at a filter type over 4, -3 when
    the rows' Adler-32 is not ``adler``."""
    h, stride = rows.shape
    w = stride - 1
    flat = rows.reshape(-1)
    up = 0  # where the row above lies in scratch, when not zero
    up_zero = True  # the row above is zero (the first row's is)
    slot = 0  # the half of scratch the next row goes to
    n = 0
    s = np.int64(0)  # the bytes' sum and the sum of each byte times its place (Adler-32)
    t = np.int64(0)
    for y in range(h):
        at = y * stride + 1
        raw = flat[at - 1]
        kind = raw
        if kind > 4:
            return -2
        if up_zero:
            if _zero_bytes(flat, at, at + w):  # zero whatever the filter
                s, t = _fold(s, t, at - 1, np.uint64(raw), _ZERO)  # (its filter byte)
                continue
            if kind == 2:  # Up under zero: None
                kind = 0
            elif kind == 4:  # Paeth under zero: Sub (a = left; b = c = 0)
                kind = 1
        if kind == 0:
            s, t = _byte_sums(flat, at - 1, at + w, s, t)
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
        if kind == 1 and not (y + 1 < h and flat[at + w] >= 2):  # (not read below)
            m, ps, pt = _sub_runs(flat, at, w, y, ry, rx0, rx1, rv, n)
        else:
            ps, pt = _unfilter_row(flat, at, w, kind, scratch, cur, up, up_zero)
            m = _row_runs(scratch, cur, w, y, ry, rx0, rx1, rv, n)
        if m < 0:
            return -1
        if w > _SUMS_PIECE:  # (the row's sums may have overflowed)
            s, t = _byte_sums(flat, at - 1, at + w, s, t)
        else:  # the filter byte, then the row's bytes
            s, t = _fold(s, t, at - 1, np.uint64(raw), _ZERO)
            s, t = _fold(s, t, at, ps, pt)
        up_zero = m == n
        n = m
        up = cur
        slot = 1 - slot
    if _adler32(h * stride, s, t) != adler:
        return -3
    _to_bounds(ry, rx0, rx1, n, bounds)
    return n
