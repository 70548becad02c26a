"""PNG row filters undone in one pass (PNG specification, section 9: "Filtering").

Plain index loops throughout: numba compiles them to vector code, while a slice
assignment (``out[y, :] = rows[y, 1:]``) takes a generic path about 15x slower. Along a
row, a one-byte neighbour is kept in a register: reloaded from ``out``, every byte would
wait for the store of the one before."""

from __future__ import annotations

import numpy as np

from mistool.kernels import helper, kernel


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
