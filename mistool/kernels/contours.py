"""A part mask's outer contours, compiled (:mod:`mistool.pose.measure`'s
``cv2.findContours(mask, RETR_EXTERNAL, CHAIN_APPROX_NONE)`` on one crop).

:func:`outer_contour` answers for the common case, a crop holding one 8-connected
component, with the points OpenCV gives (``contours_new.cpp`` of OpenCV 4.10+ / 5.0,
Suzuki's border following): the component's outer border traced from its first pixel in
raster order, clockwise on screen (x right, y down), every pixel the border visits, a
pixel again each time the border comes back to it. Pixels outside the crop are
background (OpenCV pads the image with a zero frame). :func:`external_contours` answers
for any number of components (a shaft cut across, two tools touching) where none can lie
in another's hole (no component's bounding box holds another's): OpenCV 5 returns one
contour per component, each traced as above, in the reverse raster order of their first
pixels; a crop where one box holds another is left to OpenCV (which leaves a component
in a hole out). ``tests/test_pose_contours.py`` compares the points, their order and
the answers with OpenCV's on random masks.
"""

from __future__ import annotations

import numpy as np

from mistool.kernels import helper, kernel
from mistool.kernels.boxes import ctz as _ctz
from mistool.kernels.boxes import load8 as _load8

__all__ = ["external_contours", "outer_contour"]

# chain codes E, NE, N, NW, W, SW, S, SE (OpenCV's)
_DX = np.array([1, 1, 0, -1, -1, -1, 0, 1], np.int64)
_DY = np.array([0, -1, -1, -1, 0, 1, 1, 1], np.int64)


def _next_table() -> np.ndarray:
    """``[code * 8 + s]``: the first chain code after ``s`` counter-clockwise (``s + 1``,
    ``s + 2``, ... ``s + 8``, modulo 8) whose bit is set in the neighbourhood ``code``
    (bit ``k``: the neighbour along chain code ``k`` is foreground); 8 when none is."""
    table = np.full(256 * 8, 8, np.uint8)
    for code in range(256):
        for s in range(8):
            for k in range(1, 9):
                if code >> ((s + k) & 7) & 1:
                    table[code * 8 + s] = (s + k) & 7
                    break
    return table


_NEXT = _next_table()


_LOW7 = np.uint64(0x7F7F7F7F7F7F7F7F)
_HIGH = np.uint64(0x8080808080808080)
_BYTE_ONES = np.uint64(0x0101010101010101)


@helper
def _next_change(flat: np.ndarray, i: int, end: int, inside: bool) -> int:
    """The first flat index from ``i`` (below ``end``) whose byte is zero when
    ``inside``, non-zero when not; ``end`` when none is. 32 bytes at a time where none
    changes (0/1 bytes: four words all zero, or all 0x01 bytes), then eight."""
    if inside:
        while i + 32 <= end:
            if (
                _load8(flat, i) & _load8(flat, i + 8) & _load8(flat, i + 16) & _load8(flat, i + 24)
            ) != _BYTE_ONES:
                break
            i += 32
    else:
        while i + 32 <= end:
            if (
                _load8(flat, i) | _load8(flat, i + 8) | _load8(flat, i + 16) | _load8(flat, i + 24)
            ) != 0:
                break
            i += 32
    want = _HIGH if inside else np.uint64(0)
    while i + 8 <= end:
        word = _load8(flat, i)
        set_ = (((word & _LOW7) + _LOW7) | word) & _HIGH  # bit 7: byte non-zero
        if set_ != want:
            return i + np.int64(_ctz(set_ ^ want) >> np.uint64(3))
        i += 8
    while i < end and (flat[i] != 0) == inside:
        i += 1
    return i


@helper
def _components(flat: np.ndarray, h: int, w: int, first: np.ndarray) -> int:
    """The number of 8-connected components of a (h, w) 0/1 crop (``flat``: its bytes),
    counting stops at 2; ``first[0], first[1]``: the first foreground pixel in raster
    order (x, y). Row runs joined by union-find with the previous row's runs
    (:func:`_count_components`, its union-find parents in an array of a fixed size,
    again in one that holds any crop's where they do not fit: no array grown, and so no
    reference counts, inside the scan)."""
    rows = np.empty((6, w + 1), np.int64)  # the previous and the current row's runs
    parent = np.empty(2 * h + 16, np.int64)
    count = _count_components(flat, h, w, first, rows, parent)
    if count < 0:  # a row holds at most one run per two columns
        parent = np.empty(h * ((w + 1) // 2) + 1, np.int64)
        count = _count_components(flat, h, w, first, rows, parent)
    return count


@helper
def _count_components(
    flat: np.ndarray, h: int, w: int, first: np.ndarray, rows: np.ndarray, parent: np.ndarray
) -> int:
    """:func:`_components`' scan (``rows``: (6, w + 1) scratch, ``parent``: one entry per
    run); -1 when the runs do not fit in ``parent``."""
    cap = len(parent)
    n_prev = 0
    n_runs = 0
    roots = 0
    first[0] = first[1] = -1
    for y in range(h):
        base = y * w
        n_cur = 0
        x = 0
        while True:
            x0 = _next_change(flat, base + x, base + w, False) - base
            if x0 >= w:
                break
            x = _next_change(flat, base + x0, base + w, True) - base
            if first[0] < 0:
                first[0], first[1] = x0, y
            r = n_runs
            if r == cap:
                return -1
            parent[r] = r
            n_runs += 1
            roots += 1
            for j in range(n_prev):  # 8-connected: the runs above within one pixel
                if rows[0, j] <= x and rows[1, j] >= x0:
                    a = rows[2, j]
                    while parent[a] != a:
                        a = parent[a]
                    b = r
                    while parent[b] != b:
                        b = parent[b]
                    if a != b:
                        parent[max(a, b)] = min(a, b)
                        roots -= 1
            rows[3, n_cur], rows[4, n_cur], rows[5, n_cur] = x0, x, r
            n_cur += 1
        # a component is complete when none of its runs reaches the next row; two roots
        # alive at once can still join, so only count at the end (rows are few)
        for j in range(n_cur):
            rows[0, j], rows[1, j], rows[2, j] = rows[3, j], rows[4, j], rows[5, j]
        n_prev = n_cur
    return min(roots, 2)


@helper
def _pixel(flat: np.ndarray, h: int, w: int, x: int, y: int) -> np.uint64:
    """1 when the crop holds foreground at ``(x, y)`` (any integers), else 0."""
    if x < 0 or y < 0 or x >= w or y >= h:
        return np.uint64(0)
    return np.uint64(flat[y * w + x] != 0)


@helper
def _code(flat: np.ndarray, h: int, w: int, x: int, y: int) -> np.uint64:
    """The neighbourhood of pixel ``(x, y)`` (any integers): bit ``k`` set when its
    neighbour along chain code ``k`` is foreground."""
    return (
        _pixel(flat, h, w, x + 1, y)
        | _pixel(flat, h, w, x + 1, y - 1) << np.uint64(1)
        | _pixel(flat, h, w, x, y - 1) << np.uint64(2)
        | _pixel(flat, h, w, x - 1, y - 1) << np.uint64(3)
        | _pixel(flat, h, w, x - 1, y) << np.uint64(4)
        | _pixel(flat, h, w, x - 1, y + 1) << np.uint64(5)
        | _pixel(flat, h, w, x, y + 1) << np.uint64(6)
        | _pixel(flat, h, w, x + 1, y + 1) << np.uint64(7)
    )


@helper
def _trace(
    flat: np.ndarray, h: int, w: int, x0: int, y0: int, points: np.ndarray, start: int
) -> int:
    """The outer border of the 8-connected component whose first pixel in raster order
    is ``(x0, y0)`` (its west neighbour is background), traced as OpenCV traces it, into
    ``points[start:]``: the number of points, or -2 when they do not fit.

    One step per border pixel: its neighbourhood's code, then the next chain code from
    one table look-up (:data:`_NEXT`). The pixel's flat index is carried along (moved by
    the chain code's offset) and unsigned (no wrap-around checks on the eight loads)."""
    cap = points.shape[0] - start
    if cap < 1:
        return -2
    one = np.uint64(1)
    code = _code(flat, h, w, x0, y0)
    s = 4  # the start pixel's first move: west of it is background
    while True:
        s = (s - 1) & 7
        if (code >> np.uint64(s)) & one or s == 4:
            break
    if s == 4:  # a single pixel
        points[start, 0], points[start, 1] = x0, y0
        return 1
    x1, y1 = x0 + _DX[s], y0 + _DY[s]  # the second pixel
    step = np.empty(8, np.uint64)  # each chain code's flat offset (modulo 2**64)
    for d in range(8):
        step[d] = np.uint64(_DX[d] + _DY[d] * w)
    uw = np.uint64(w)
    x, y = x0, y0
    k = np.uint64(y0 * w + x0)
    sn = np.uint64(s)
    n = 0
    while True:
        if 0 < x < w - 1 and 0 < y < h - 1:  # all eight neighbours in the crop
            code = (
                np.uint64(flat[k + one])
                | np.uint64(flat[k + one - uw]) << one
                | np.uint64(flat[k - uw]) << np.uint64(2)
                | np.uint64(flat[k - one - uw]) << np.uint64(3)
                | np.uint64(flat[k - one]) << np.uint64(4)
                | np.uint64(flat[k - one + uw]) << np.uint64(5)
                | np.uint64(flat[k + uw]) << np.uint64(6)
                | np.uint64(flat[k + one + uw]) << np.uint64(7)
            )
        else:
            code = _code(flat, h, w, x, y)
        sn = np.uint64(_NEXT[code * np.uint64(8) + sn])
        if n == cap:
            return -2
        at = np.uint64(start + n)
        points[at, 0], points[at, 1] = x, y
        n += 1
        xn, yn = x + _DX[sn], y + _DY[sn]
        if xn == x0 and yn == y0 and x == x1 and y == y1:
            return n
        x, y = xn, yn
        k += step[sn]
        sn = (sn + np.uint64(4)) & np.uint64(7)


@kernel("int64(boolean[:, ::1], int32[:, ::1])")
def outer_contour(mask: np.ndarray, points: np.ndarray) -> int:
    """The outer contour of a crop holding one 8-connected component, as
    ``cv2.findContours(mask, RETR_EXTERNAL, CHAIN_APPROX_NONE)[0][0]`` (see the module
    docstring), into ``points`` (crop px, x then y).

    Returns:
        The number of points; 0 for an empty crop; -1 when the crop holds several
        components (:func:`external_contours`); -2 when ``points`` is too short (the
        border needs at most ``4 * h * w`` rows).
    """
    h, w = mask.shape
    flat = mask.view(np.uint8).ravel()
    first = np.empty(2, np.int64)
    count = _components(flat, h, w, first)
    if count == 0:
        return 0
    if count > 1:
        return -1
    return _trace(flat, h, w, first[0], first[1], points, 0)


#: :func:`external_contours`' answers besides a count.
CONTOURS_NESTED, CONTOURS_SHORT, CONTOURS_MANY = -1, -2, -3


@kernel("Tuple((int64, int64[:, ::1]))(boolean[:, ::1], int32[:, ::1], int64[::1])")
def external_contours(
    mask: np.ndarray, points: np.ndarray, starts: np.ndarray
) -> tuple[int, np.ndarray]:
    """The outer contours of a crop's 8-connected components, as ``cv2.findContours(mask,
    RETR_EXTERNAL, CHAIN_APPROX_NONE)`` gives them when no component lies in another's
    hole: one per component, in the reverse raster order of their first pixels (OpenCV
    5's order, ``tests/test_pose_contours.py``), each traced as :func:`outer_contour`.

    Args:
        mask: (h, w) the crop.
        points: receives the contours one after the other (crop px, x then y); at most
            ``4 * h * w`` rows are needed.
        starts: receives where each contour starts in ``points``, then the end; its
            length bounds the number of components (``C + 1`` entries for ``C``).

    Returns:
        ``(C, runs)``: the number of contours ``C`` (0 for an empty crop), or
        :data:`CONTOURS_NESTED` when a component's bounding box holds another's strictly
        (it may lie in a hole, where OpenCV would leave it out: ask OpenCV),
        :data:`CONTOURS_SHORT` when ``points`` is too short, :data:`CONTOURS_MANY` when
        ``starts`` is; and the crop's row runs in raster order, ``(R, 4)``: row, first
        column, column after the last, and the run's contour plus one (``k + 1``).
    """
    h, w = mask.shape
    flat = mask.view(np.uint8).ravel()
    runs, n_comp = _labelled_runs(flat, h, w)
    if n_comp + 1 > len(starts):
        return CONTOURS_MANY, runs
    first = np.empty((n_comp, 2), np.int64)
    if _nested(runs, n_comp, h, w, first):
        return CONTOURS_NESTED, runs
    for r in range(len(runs)):
        runs[r, 3] = n_comp - runs[r, 3]  # contour n_comp - 1 - c, plus one
    n = 0
    for k in range(n_comp):
        c = n_comp - 1 - k
        starts[k] = n
        got = _trace(flat, h, w, first[c, 0], first[c, 1], points, n)
        if got < 0:
            return CONTOURS_SHORT, runs
        n += got
    starts[n_comp] = n
    return n_comp, runs


@helper
def _labelled_runs(flat: np.ndarray, h: int, w: int) -> tuple[np.ndarray, int]:
    """A (h, w) 0/1 crop's row runs in raster order, ``(R, 4)``: row, first column,
    column after the last, and the run's 8-connected component (numbered in the raster
    order of their first pixels); and the number of components. Runs joined by
    union-find with the previous row's; a root is its set's first run (the smaller index
    wins). (The runs found into arrays of a fixed size, :func:`_scan_runs`, again into
    arrays that hold any crop's where they do not fit: no array grown, and so no
    reference counts, inside the scan.)"""
    cap = 2 * h + 16
    runs = np.empty((cap, 4), np.int64)
    parent = np.empty(cap, np.int64)
    n_runs = _scan_runs(flat, h, w, runs, parent)
    if n_runs < 0:  # a row holds at most one run per two columns
        cap = h * ((w + 1) // 2) + 1
        runs = np.empty((cap, 4), np.int64)
        parent = np.empty(cap, np.int64)
        n_runs = _scan_runs(flat, h, w, runs, parent)
    n_comp = 0
    for r in range(n_runs):
        a = r
        while parent[a] != a:
            a = parent[a]
        if a == r:
            runs[r, 3] = n_comp
            n_comp += 1
        else:
            runs[r, 3] = runs[a, 3]
    return runs[:n_runs], n_comp


@helper
def _scan_runs(flat: np.ndarray, h: int, w: int, runs: np.ndarray, parent: np.ndarray) -> int:
    """:func:`_labelled_runs`' scan: each run's row, first column and column after the
    last into ``runs``, its union-find parent into ``parent``; the number of runs, or -1
    when they do not fit."""
    n_runs = 0
    cap = len(parent)
    prev_lo = prev_hi = 0  # the previous row's runs: [prev_lo, prev_hi)
    for y in range(h):
        base = y * w
        lo = n_runs
        x = 0
        while True:
            x0 = _next_change(flat, base + x, base + w, False) - base
            if x0 >= w:
                break
            x = _next_change(flat, base + x0, base + w, True) - base
            r = n_runs
            if r == cap:
                return -1
            runs[r, 0], runs[r, 1], runs[r, 2], parent[r] = y, x0, x, r
            n_runs += 1
            for j in range(prev_lo, prev_hi):  # 8-connected: the runs above within one pixel
                if runs[j, 1] <= x and runs[j, 2] >= x0:
                    a = j  # joined: the smaller root stays the root
                    while parent[a] != a:
                        a = parent[a]
                    b = r
                    while parent[b] != b:
                        b = parent[b]
                    if a != b:
                        parent[max(a, b)] = min(a, b)
        prev_lo, prev_hi = lo, n_runs
    return n_runs


@helper
def _nested(runs: np.ndarray, n_comp: int, h: int, w: int, first: np.ndarray) -> bool:
    """Whether a component's bounding box holds another's strictly; ``first[c]``
    receives component ``c``'s first pixel (x, y)."""
    box = np.empty((n_comp, 4), np.int64)  # x0, y0, x1, y1 (inclusive)
    for c in range(n_comp):
        box[c, 0], box[c, 1], box[c, 2], box[c, 3] = w, h, -1, -1
    for r in range(len(runs)):
        c = runs[r, 3]
        if box[c, 2] < 0:  # its first run
            first[c, 0], first[c, 1] = runs[r, 1], runs[r, 0]
        box[c, 0] = min(box[c, 0], runs[r, 1])
        box[c, 1] = min(box[c, 1], runs[r, 0])
        box[c, 2] = max(box[c, 2], runs[r, 2] - 1)
        box[c, 3] = max(box[c, 3], runs[r, 0])
    for i in range(n_comp):
        for j in range(n_comp):
            if (
                box[i, 0] < box[j, 0]
                and box[i, 1] < box[j, 1]
                and box[j, 2] < box[i, 2]
                and box[j, 3] < box[i, 3]
            ):
                return True
    return False
