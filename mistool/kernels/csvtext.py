"""CSV cells as text: floats to at most 6 decimals, exactly as Python's ``f"{v:.6f}"``
(trailing zeros and a bare point stripped, ``-0`` written ``0``), integers, and text
cells given already encoded; a block of rows at a time into one byte buffer."""

from __future__ import annotations

import numpy as np

from mistool.kernels import helper, kernel

#: Floats below this magnitude are formatted here (their scaled value fits an int64
#: exactly); larger ones are left to Python.
FLOAT_LIMIT = 9.0e9

_SPLIT = 134217729.0  # 2^27 + 1: Veltkamp's split of a double into two 26-bit halves


@helper
def _put_int(out: np.ndarray, pos: int, value: int) -> int:
    """``str(value)`` at ``out[pos:]``; the position after it (the magnitude taken as
    uint64, so the most negative int64 too)."""
    if value < 0:
        out[pos] = 45  # "-"
        pos += 1
        mag = np.uint64(-(value + 1)) + np.uint64(1)
    else:
        mag = np.uint64(value)
    ten = np.uint64(10)
    digits = 1
    probe = mag
    while probe >= ten:
        probe //= ten
        digits += 1
    for i in range(digits - 1, -1, -1):
        out[pos + i] = np.uint8(np.uint64(48) + mag % ten)
        mag //= ten
    return pos + digits


@helper
def scaled_micro(a: float) -> int:
    """``a * 10^6`` (``0 <= a < FLOAT_LIMIT``) rounded to the nearest integer, ties to even,
    from the exact product: Dekker's product gives ``a * 10^6 = p + e`` exactly (``p`` the
    rounded product), so the rounding decision is exact, as in Python's correctly
    rounded ``%.6f``."""
    m = 1e6
    p = a * m
    c = _SPLIT * a
    ah = c - (c - a)
    al = a - ah
    # 10^6 = 1e6 exactly: its split is (1e6, 0)
    e = (ah * m - p) + al * m  # the product's rounding error, exact
    f = np.floor(p)
    d = (p - f) - 0.5  # exact near the tie (Sterbenz), where it matters
    n = np.int64(f)
    if d > -e:
        n += 1
    elif d == -e and n % 2 == 1:  # an exact tie: to even
        n += 1
    return n


@helper
def _put_float(out: np.ndarray, pos: int, v: float) -> int:
    """``v`` (finite, ``|v| < FLOAT_LIMIT``) as ``f"{v:.6f}"`` without trailing zeros."""
    n = scaled_micro(-v if v < 0 else v)
    if n == 0:
        out[pos] = 48  # "0", also for -0 and what rounds to it
        return pos + 1
    if v < 0:
        out[pos] = 45
        pos += 1
    pos = _put_int(out, pos, n // 1000000)
    frac = n % 1000000
    if frac == 0:
        return pos
    out[pos] = 46  # "."
    pos += 1
    width = 6
    while frac % 10 == 0:
        frac //= 10
        width -= 1
    for i in range(width - 1, -1, -1):
        out[pos + i] = 48 + frac % 10
        frac //= 10
    return pos + width


@kernel(
    "int64(int64, float64[:, ::1], int64[:, ::1], int64[:, ::1], int64[:, ::1], uint8[::1],"
    " int64[::1], uint8[::1])"
)
def format_rows(
    rows: int,
    floats: np.ndarray,
    ints: np.ndarray,
    texts: np.ndarray,
    plan: np.ndarray,
    text_bytes: np.ndarray,
    text_offsets: np.ndarray,
    out: np.ndarray,
) -> int:
    """``rows`` rows of cells, comma-separated, a ``\\n`` after each, into ``out``; bytes written.

    ``plan`` (C, 2) gives each output column's kind (0 float, 1 int, 2 text) and its
    column in ``floats`` (R, F), ``ints`` (R, I) or ``texts`` (R, T) (text: an index into
    the encoded strings ``text_bytes[text_offsets[k]:text_offsets[k + 1]]``). A float
    NaN is an empty cell, +-inf ``inf`` / ``-inf``; the caller leaves any other float of
    magnitude ``FLOAT_LIMIT`` or more to Python. ``out`` must hold every cell (at most 25
    bytes per number)."""
    pos = 0
    ncol = plan.shape[0]
    for r in range(rows):
        for c in range(ncol):
            if c:
                out[pos] = 44  # ","
                pos += 1
            kind = plan[c, 0]
            j = plan[c, 1]
            if kind == 0:
                v = floats[r, j]
                if v != v:
                    continue
                if v == np.inf or v == -np.inf:
                    if v < 0:
                        out[pos] = 45
                        pos += 1
                    out[pos] = 105  # "inf"
                    out[pos + 1] = 110
                    out[pos + 2] = 102
                    pos += 3
                    continue
                pos = _put_float(out, pos, v)
            elif kind == 1:
                pos = _put_int(out, pos, ints[r, j])
            else:
                k = texts[r, j]
                for b in range(text_offsets[k], text_offsets[k + 1]):
                    out[pos] = text_bytes[b]
                    pos += 1
        out[pos] = 10  # "\n"
        pos += 1
    return pos
