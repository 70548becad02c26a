"""One frame's instruments, compiled (:func:`mistool.tracking.observe_frame`): the label
image's foreground bounds, its row runs of equal values, the instruments' connected
components from those runs, and Algorithm 1 of a selection of them
(:func:`mistool.kernels.boxes.fit_runs_box`).

Each kernel gives what the OpenCV and numpy steps it replaces gave (tests compare them):

- components are those of ``cv2.connectedComponents(mask, connectivity=8)`` on the
  union of the part masks dilated by a 3x3 square (``instances.MERGE_GAP_PX``), labelled
  in OpenCV's order: by the first 2x2 block of the image (rows 0-1, 2-3, ...; then
  columns) that holds a pixel of the component (its block-based labelling numbers
  provisional labels in that order and keeps the smallest of each set);
- their bounds are ``connectedComponentsWithStats``' (x, y, w, h) of the dilated mask
  (clipped to the image), their pixel counts those of the part masks.

Runs are ``(ry, rx0, rx1, rv)``: run ``i`` covers ``rx0[i] <= x < rx1[i]`` of row
``ry[i]``, value ``rv[i]``, in raster order, coordinates relative to the scanned window.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mistool.kernels import helper, kernel
from mistool.kernels.boxes import ctz, fit_runs_box, join_runs, load8, load8_bytes

_BOUNDS = "UniTuple(int64, 4)"


@kernel(
    "int64(uint8[:, ::1], int64, int64)",
    "int64(uint16[:, ::1], int64, int64)",
    "int64(int32[:, ::1], int64, int64)",
)
def _first_set(img: np.ndarray, lo: int, hi: int) -> int:
    """The first non-zero pixel among pixels ``lo`` to ``hi - 1`` (flat indices) of
    ``img``, or -1: 64 bytes at a time, then the byte from the word's trailing zeros."""
    size = img.itemsize
    i, end = lo * size, hi * size
    while i + 64 <= end:
        word = load8_bytes(img, i) | load8_bytes(img, i + 8)
        word |= load8_bytes(img, i + 16) | load8_bytes(img, i + 24)
        word |= load8_bytes(img, i + 32) | load8_bytes(img, i + 40)
        word |= load8_bytes(img, i + 48) | load8_bytes(img, i + 56)
        if word != 0:
            break
        i += 64
    while i + 8 <= end:
        word = load8_bytes(img, i)
        if word != 0:
            return (i + np.int64(ctz(word) >> np.uint64(3))) // size
        i += 8
    flat = img.reshape(-1)
    for j in range(i // size, hi):  # (i: a whole number of pixels from lo)
        if flat[j] != 0:
            return j
    return -1


@kernel(
    "int64(uint8[:, ::1], int64, int64)",
    "int64(uint16[:, ::1], int64, int64)",
    "int64(int32[:, ::1], int64, int64)",
)
def _last_set(img: np.ndarray, lo: int, hi: int) -> int:
    """The last non-zero pixel among pixels ``lo`` to ``hi - 1`` of ``img``, or -1."""
    size = img.itemsize
    start, i = lo * size, hi * size
    while i - 64 >= start:
        word = load8_bytes(img, i - 64) | load8_bytes(img, i - 56)
        word |= load8_bytes(img, i - 48) | load8_bytes(img, i - 40)
        word |= load8_bytes(img, i - 32) | load8_bytes(img, i - 24)
        word |= load8_bytes(img, i - 16) | load8_bytes(img, i - 8)
        if word != 0:
            break
        i -= 64
    while i - 8 >= start:
        word = load8_bytes(img, i - 8)
        if word != 0:
            k = 7
            while (word >> np.uint64(8 * k)) & np.uint64(0xFF) == 0:
                k -= 1
            return (i - 8 + k) // size
        i -= 8
    flat = img.reshape(-1)
    for j in range(i // size - 1, lo - 1, -1):
        if flat[j] != 0:
            return j
    return -1


@kernel(
    _BOUNDS + "(uint8[:, ::1])",
    _BOUNDS + "(uint16[:, ::1])",
    _BOUNDS + "(int32[:, ::1])",
)
def foreground(labels: np.ndarray) -> tuple[int, int, int, int]:
    """``(x, y, w, h)`` bounds of the non-zero pixels (``cv2.boundingRect`` of them;
    ``(0, 0, 0, 0)`` when there is none). Rows, and the parts of rows outside the bounds
    found so far, are searched 64 bytes at a time."""
    h, w = labels.shape
    first = _first_set(labels, 0, h * w)
    if first < 0:
        return 0, 0, 0, 0
    y0, y1 = first // w, _last_set(labels, 0, h * w) // w
    x0, x1 = w, -1  # first and last non-zero column found so far
    for y in range(y0, y1 + 1):
        first = _first_set(labels, y * w, y * w + x0)
        if first >= 0:
            x0 = first - y * w
        last = _last_set(labels, y * w + x1 + 1, (y + 1) * w)
        if last >= 0:
            x1 = last - y * w
    return x0, y0, x1 - x0 + 1, y1 - y0 + 1


_BROADCAST = np.uint64(0x0101010101010101)


@kernel(
    "int64(uint8[:, ::1], int64, int64, int64, int64, int32[::1], int32[::1], int32[::1], "
    "int32[::1])"
)
def _runs_u8(
    labels: np.ndarray,
    x0: int,
    y0: int,
    x1: int,
    y1: int,
    ry: np.ndarray,
    rx0: np.ndarray,
    rx1: np.ndarray,
    rv: np.ndarray,
) -> int:
    """:func:`label_runs` of an 8-bit image into arrays of a given size (-1: too short).
    32 or 8 pixels at a time: words of eight pixels of the current value are passed
    over; otherwise the first pixel that differs is found from the word's bits."""
    w = labels.shape[1]
    cap = ry.shape[0]
    n = 0
    for y in range(y0, y1):
        base = y * w
        if _first_set(labels, base + x0, base + x1) < 0:  # a row of background
            continue
        x = x0
        start = x0
        v = labels[y, x0]
        while True:
            if x + 32 <= x1:  # four words of v: passed over at once
                vv = np.uint64(v) * _BROADCAST
                i = base + x
                same = (load8(labels, i) ^ vv) | (load8(labels, i + 8) ^ vv)
                same |= (load8(labels, i + 16) ^ vv) | (load8(labels, i + 24) ^ vv)
                if same == 0:
                    x += 32
                    continue
            if x + 8 <= x1:
                diff = load8(labels, base + x) ^ (np.uint64(v) * _BROADCAST)
                if diff == 0:
                    x += 8
                    continue
                x += np.int64(ctz(diff) >> np.uint64(3))
            else:
                while x < x1 and labels[y, x] == v:
                    x += 1
            if v != 0:  # the run of v ends at x
                if n == cap:
                    return -1
                ry[n] = y - y0
                rx0[n] = start - x0
                rx1[n] = x - x0
                rv[n] = v
                n += 1
            if x >= x1:
                break
            start = x
            v = labels[y, x]
    return n


@kernel(
    "int64(uint16[:, ::1], int64, int64, int64, int64, int32[::1], int32[::1], int32[::1], "
    "int32[::1])",
    "int64(int32[:, ::1], int64, int64, int64, int64, int32[::1], int32[::1], int32[::1], "
    "int32[::1])",
)
def _runs_any(
    labels: np.ndarray,
    x0: int,
    y0: int,
    x1: int,
    y1: int,
    ry: np.ndarray,
    rx0: np.ndarray,
    rx1: np.ndarray,
    rv: np.ndarray,
) -> int:
    """:func:`label_runs` of a 16- or 32-bit image, a pixel at a time."""
    w = labels.shape[1]
    cap = ry.shape[0]
    n = 0
    for y in range(y0, y1):
        if _first_set(labels, y * w + x0, y * w + x1) < 0:  # a row of background
            continue
        start = x0
        v = labels[y, x0]
        for x in range(x0 + 1, x1 + 1):
            if x < x1 and labels[y, x] == v:
                continue
            if v != 0:
                if n == cap:
                    return -1
                ry[n] = y - y0
                rx0[n] = start - x0
                rx1[n] = x - x0
                rv[n] = v
                n += 1
            if x < x1:
                start = x
                v = labels[y, x]
    return n


def label_runs(
    labels: np.ndarray, bounds: tuple[int, int, int, int] | None = None
) -> tuple[tuple[int, int, int, int], np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """The runs of equal non-zero values of ``labels`` (2-D C-contiguous uint8, uint16
    or int32) within ``bounds`` = (x, y, w, h) (None: the whole image, rows of
    background passed over 64 bytes at a time): ``(bounds, ry, rx0, rx1, rv, n)``,
    ``bounds`` then :func:`foreground`'s, coordinates relative to its (x, y)."""
    x, y, w, h = (0, 0, labels.shape[1], labels.shape[0]) if bounds is None else bounds
    runs = _runs_u8 if labels.dtype == np.uint8 else _runs_any
    cap = 4 * h + 64
    while True:
        ry = np.empty(cap, np.int32)
        rx0 = np.empty(cap, np.int32)
        rx1 = np.empty(cap, np.int32)
        rv = np.empty(cap, np.int32)
        n = runs(labels, x, y, x + w, y + h, ry, rx0, rx1, rv)
        if n >= 0:
            break
        cap *= 4
    if bounds is None:
        bounds = _run_bounds(ry, rx0, rx1, n)
    return bounds, ry, rx0, rx1, rv, n


@kernel(_BOUNDS + "(int32[::1], int32[::1], int32[::1], int64)")
def _run_bounds(
    ry: np.ndarray, rx0: np.ndarray, rx1: np.ndarray, n: int
) -> tuple[int, int, int, int]:
    """The (x, y, w, h) bounds of ``n`` runs in raster order (``(0, 0, 0, 0)``: none);
    the runs' coordinates then made relative to (x, y)."""
    if n == 0:
        return 0, 0, 0, 0
    x0, x1 = rx0[0], rx1[0]
    for i in range(n):
        x0 = min(x0, rx0[i])
        x1 = max(x1, rx1[i])
    y0, y1 = ry[0], ry[n - 1] + 1
    for i in range(n):
        ry[i] -= y0
        rx0[i] -= x0
        rx1[i] -= x0
    return x0, y0, x1 - x0, y1 - y0


@kernel("int64[::1](int32[::1], int32[::1], int32[::1], int64)")
def value_counts(rv: np.ndarray, rx0: np.ndarray, rx1: np.ndarray, n: int) -> np.ndarray:
    """Pixels per value 0..255 of ``n`` runs of 8-bit values."""
    hist = np.zeros(256, np.int64)
    for i in range(n):
        hist[rv[i]] += rx1[i] - rx0[i]
    return hist


@kernel("int64[::1](int32[::1], int32[::1], int32[::1], int64, boolean[::1], int64)")
def values_present(
    rv: np.ndarray, rx0: np.ndarray, rx1: np.ndarray, n: int, wanted: np.ndarray, min_px: int
) -> np.ndarray:
    """The values 0..255 (ascending) that ``n`` runs of 8-bit values cover with at least
    ``min_px`` pixels, among those ``wanted`` (True at the value): ``np.flatnonzero`` of
    :func:`value_counts` at least ``min_px`` where ``wanted``."""
    hist = np.zeros(256, np.int64)
    for i in range(n):
        hist[rv[i]] += rx1[i] - rx0[i]
    k = 0
    for v in range(256):
        k += wanted[v] and hist[v] >= min_px
    out = np.empty(k, np.int64)
    k = 0
    for v in range(256):
        if wanted[v] and hist[v] >= min_px:
            out[k] = v
            k += 1
    return out


@kernel(
    "int64(int32[::1], int32[::1], int32[::1], int32[::1], int64, int64[:, ::1], int64[::1], "
    "int32[::1], int32[::1], int32[::1])"
)
def _union_runs(
    ry: np.ndarray,
    rx0: np.ndarray,
    rx1: np.ndarray,
    rv: np.ndarray,
    n: int,
    ranges: np.ndarray,
    of_run: np.ndarray,
    uy: np.ndarray,
    ux0: np.ndarray,
    ux1: np.ndarray,
) -> int:
    """The runs of the union of the part masks (value runs with a value in one of
    ``ranges``, adjacent ones of a row merged) into ``uy, ux0, ux1``; ``of_run`` gets
    each value run's union run (-1: none); returns their number."""
    m = 0
    for i in range(n):
        of_run[i] = -1
        inside = False
        for p in range(ranges.shape[0]):
            if ranges[p, 0] <= rv[i] <= ranges[p, 1]:
                inside = True
        if not inside:
            continue
        if m > 0 and uy[m - 1] == ry[i] and ux1[m - 1] == rx0[i]:
            ux1[m - 1] = rx1[i]
        else:
            uy[m], ux0[m], ux1[m] = ry[i], rx0[i], rx1[i]
            m += 1
        of_run[i] = m - 1
    return m


@kernel("void(int32[::1], int32[::1], int32[::1], int32[::1], int64, int64, int32[::1])")
def _opencv_labels(
    uy: np.ndarray,
    ux0: np.ndarray,
    ux1: np.ndarray,
    parent: np.ndarray,
    m: int,
    count: int,
    of_root: np.ndarray,
) -> None:
    """``of_root[r]``: the label 1..count ``cv2.connectedComponents`` gives the dilated
    component of root run ``r``: components in the order of their first 2x2 block (row
    pair, then column). A union run of row y lights rows y - 1 .. y + 1, columns
    x0 - 1 .. x1 (clipped at 0)."""
    block_row = np.full(max(m, 1), 1 << 40, np.int64)  # per root
    for j in range(m):
        r = parent[j]
        block_row[r] = min(block_row[r], max(uy[j] - 1, 0) // 2)
    key = np.full(max(m, 1), 1 << 62, np.int64)
    for j in range(m):
        r = parent[j]
        k = block_row[r]  # rows 2k, 2k + 1 of the dilated component: union rows 2k-1..2k+2
        if 2 * k - 1 <= uy[j] <= 2 * k + 2:
            key[r] = min(key[r], k * (1 << 32) + max(ux0[j] - 1, 0) // 2)
    roots = np.empty(count, np.int64)
    c = 0
    for j in range(m):
        if parent[j] == j:
            roots[c] = j
            c += 1
    order = np.argsort(key[roots])
    for t in range(count):
        of_root[roots[order[t]]] = t + 1


_COMPONENTS = "Tuple((int64, int32[::1], int64[:, ::1]))"
#: Columns of :func:`components`' table: the dilated component's bounds (x, y, w, h),
#: its part and shaft pixels, whether it touches the image border (1) or not (0).
STAT_X, STAT_Y, STAT_W, STAT_H, STAT_COUNT, STAT_SHAFT, STAT_BORDER = range(7)


@kernel(
    _COMPONENTS + "(int32[::1], int32[::1], int32[::1], int32[::1], int64, int64[:, ::1], "
    "int64, int64, int64, int64, int64, int64, int64)"
)
def components(
    ry: np.ndarray,
    rx0: np.ndarray,
    rx1: np.ndarray,
    rv: np.ndarray,
    n: int,
    ranges: np.ndarray,
    shaft: int,
    fx: int,
    fy: int,
    fw: int,
    fh: int,
    img_w: int,
    img_h: int,
) -> tuple[int, np.ndarray, np.ndarray]:
    """The instruments' components of a window's value runs (merged masks): the part
    pixels (values in any of ``ranges``, (P, 2) inclusive) bridged over one background
    pixel (8-connected once dilated by a 3x3 square), labelled 1.. in OpenCV's order.

    Args:
        ry, rx0, rx1, rv, n: the window's value runs (:func:`label_runs`).
        ranges: (P, 2) inclusive part value ranges.
        shaft: index in ``ranges`` of the shaft's (-1: none).
        fx, fy, fw, fh: the window (x, y, w, h) in the image.
        img_w, img_h: the image's size (its border).

    Returns:
        ``(count, label, table)``: ``count`` components + 1 (the background, label 0);
        ``label``: each value run's component (0: a value of no part); ``table``:
        (count, 7) int64, a row per component (row 0 zero): (x, y, w, h) bounds of the
        dilated component in the window, its part pixels, its shaft pixels, 1 where it
        touches the image border (:data:`STAT_X` ... :data:`STAT_BORDER`; one array
        instead of four: each array handed back to Python costs ~0.4 us).
    """
    size = max(n, 1)
    of_run = np.empty(size, np.int64)
    uy = np.empty(size, np.int32)
    ux0 = np.empty(size, np.int32)
    ux1 = np.empty(size, np.int32)
    m = _union_runs(ry, rx0, rx1, rv, n, ranges, of_run, uy, ux0, ux1)
    parent = np.empty(max(m, 1), np.int32)
    count = join_runs(uy, ux0, ux1, parent, m, 3)  # 3: 8-connected once dilated
    of_root = np.zeros(max(m, 1), np.int32)
    _opencv_labels(uy, ux0, ux1, parent, m, count, of_root)
    lo = np.full((count + 1, 2), 1 << 40, np.int64)  # x0, y0 of each dilated component
    hi = np.full((count + 1, 2), -(1 << 40), np.int64)  # x1, y1 (inclusive)
    table = np.zeros((count + 1, 7), np.int64)
    for j in range(m):
        t = of_root[parent[j]]
        lo[t, 0] = min(lo[t, 0], ux0[j] - 1)
        lo[t, 1] = min(lo[t, 1], uy[j] - 1)
        hi[t, 0] = max(hi[t, 0], ux1[j])
        hi[t, 1] = max(hi[t, 1], uy[j] + 1)
        table[t, STAT_COUNT] += ux1[j] - ux0[j]
    for t in range(1, count + 1):
        xa, ya = max(lo[t, 0], 0), max(lo[t, 1], 0)
        xb, yb = min(hi[t, 0], fw - 1), min(hi[t, 1], fh - 1)
        table[t, STAT_X], table[t, STAT_Y] = xa, ya
        table[t, STAT_W], table[t, STAT_H] = xb - xa + 1, yb - ya + 1
        table[t, STAT_BORDER] = (
            xa + fx <= 0 or ya + fy <= 0 or xb + 1 + fx >= img_w or yb + 1 + fy >= img_h
        )
    label = np.zeros(size, np.int32)
    for i in range(n):
        if of_run[i] >= 0:
            t = of_root[parent[of_run[i]]]
            label[i] = t
            if shaft >= 0 and ranges[shaft, 0] <= rv[i] <= ranges[shaft, 1]:
                table[t, STAT_SHAFT] += rx1[i] - rx0[i]
    return count + 1, label, table


_BOXED = "Tuple((UniTuple(int64, 5), boolean[:, ::1], UniTuple(float64, 5), float64[:, ::1]))"


@kernel(
    _BOXED + "(int32[::1], int32[::1], int32[::1], int32[::1], int32[::1], int64, int64, int64, "
    "boolean[::1], int64, int64, int64)"
)
def fit_selected(
    ry: np.ndarray,
    rx0: np.ndarray,
    rx1: np.ndarray,
    rv: np.ndarray,
    label: np.ndarray,
    n: int,
    lo: int,
    hi: int,
    members: np.ndarray,
    min_area: int,
    ox: int,
    oy: int,
) -> tuple[tuple[int, int, int, int, int], np.ndarray, tuple[float, ...], np.ndarray]:
    """:func:`mistool.kernels.boxes.fit_runs_box` of the pixels of the value runs whose
    value lies in ``[lo, hi]`` and whose ``label`` is one of ``members`` (True at the
    labels wanted; ``members[0]`` with every ``label`` 0 takes all): one part of one
    instance, its box included. Adjacent selected runs of a row are merged first."""
    sy = np.empty(max(n, 1), np.int32)
    sx0 = np.empty(max(n, 1), np.int32)
    sx1 = np.empty(max(n, 1), np.int32)
    m = _select(ry, rx0, rx1, rv, label, n, lo, hi, members, sy, sx0, sx1)
    return fit_runs_box(sy, sx0, sx1, m, min_area, ox, oy)


@helper
def _select(
    ry: np.ndarray,
    rx0: np.ndarray,
    rx1: np.ndarray,
    rv: np.ndarray,
    label: np.ndarray,
    n: int,
    lo: int,
    hi: int,
    members: np.ndarray,
    sy: np.ndarray,
    sx0: np.ndarray,
    sx1: np.ndarray,
) -> int:
    """:func:`fit_selected`'s runs (value in ``[lo, hi]``, label among ``members``),
    adjacent ones of a row merged, into ``sy, sx0, sx1``; how many."""
    m = 0
    for i in range(n):
        if lo <= rv[i] <= hi and members[label[i]]:
            if m > 0 and sy[m - 1] == ry[i] and sx1[m - 1] == rx0[i]:
                sx1[m - 1] = rx1[i]
            else:
                sy[m], sx0[m], sx1[m] = ry[i], rx0[i], rx1[i]
                m += 1
    return m


_PARTS = (
    "Tuple((int64[:, ::1], float64[:, ::1], float64[:, :, ::1], UniTuple(boolean[:, ::1], 3), "
    "UniTuple(float64, 2), UniTuple(int64, 6), UniTuple(uint8[::1], 3)))"
)


@kernel(
    _PARTS + "(int32[::1], int32[::1], int32[::1], int32[::1], int32[::1], int64, int64[:, ::1], "
    "boolean[::1], int64, int64, int64)"
)
def fit_parts(
    ry: np.ndarray,
    rx0: np.ndarray,
    rx1: np.ndarray,
    rv: np.ndarray,
    label: np.ndarray,
    n: int,
    ranges: np.ndarray,
    members: np.ndarray,
    min_area: int,
    ox: int,
    oy: int,
) -> tuple[Any, ...]:
    """:func:`fit_selected` of each of up to three part value ranges (``ranges``, (P, 2)
    inclusive) and the instance they make, in one call.

    Returns:
        ``(info, boxes, corners, crops, centroid, bounds, bits)``: ``info`` (P, 5) int64: each
        part's area (0: no pixel kept), crop offset (x, y) in the image, crop height and
        width; ``boxes`` (P, 5) and ``corners`` (P, 4, 2): its box (``fit_selected``'s);
        ``crops``: its kept pixels' crop (three, (0, 0) past P or when empty);
        ``centroid``: (x, y) of the parts' pixels together, summed as
        ``tracking.instances.make_instance`` sums them (part by part, in float64);
        ``bounds``: (parts with pixels, their pixels, x, y, w, h of their crops'
        union); ``bits``: each crop's ``np.packbits(crop.reshape(-1))``, set from its
        runs (:func:`_packed_crop`: what a worker sends of the mask, no bool pass).
    """
    p_count = ranges.shape[0]
    info = np.zeros((p_count, 5), np.int64)
    boxes = np.zeros((p_count, 5))
    corners = np.zeros((p_count, 4, 2))
    crop0 = crop1 = crop2 = np.zeros((0, 0), np.bool_)
    bits0 = bits1 = bits2 = np.zeros(0, np.uint8)
    total = 0
    sx = sy = 0.0
    x0 = y0 = 1 << 62
    x1 = y1 = -(1 << 62)
    found = 0
    sel_y = np.empty(max(n, 1), np.int32)  # (each part's selected runs in turn)
    sel_x0 = np.empty(max(n, 1), np.int32)
    sel_x1 = np.empty(max(n, 1), np.int32)
    for k in range(p_count):
        m = _select(
            ry, rx0, rx1, rv, label, n, ranges[k, 0], ranges[k, 1], members, sel_y, sel_x0, sel_x1
        )
        fit, crop, box, corner = fit_runs_box(sel_y, sel_x0, sel_x1, m, min_area, ox, oy)
        area = fit[0]
        if area == 0:
            continue
        h, w = crop.shape
        px, py = ox + fit[1], oy + fit[2]
        info[k, 0], info[k, 1], info[k, 2], info[k, 3], info[k, 4] = area, px, py, h, w
        for j in range(5):
            boxes[k, j] = box[j]
        for a in range(4):
            corners[k, a, 0] = corner[a, 0]
            corners[k, a, 1] = corner[a, 1]
        bits = _packed_crop(sel_y, sel_x0, sel_x1, m, crop, fit[1], fit[2])
        if k == 0:
            crop0, bits0 = crop, bits
        elif k == 1:
            crop1, bits1 = crop, bits
        else:
            crop2, bits2 = crop, bits
        total += area
        sx += np.float64(fit[3]) + np.float64(px * area)
        sy += np.float64(fit[4]) + np.float64(py * area)
        x0, y0 = min(x0, px), min(y0, py)
        x1, y1 = max(x1, px + w), max(y1, py + h)
        found += 1
    crops = (crop0, crop1, crop2)
    packed = (bits0, bits1, bits2)
    if found == 0:
        return info, boxes, corners, crops, (0.0, 0.0), (0, 0, 0, 0, 0, 0), packed
    bounds = (found, total, x0, y0, x1 - x0, y1 - y0)
    return info, boxes, corners, crops, (sx / total, sy / total), bounds, packed


@helper
def _packed_crop(
    ry: np.ndarray, rx0: np.ndarray, rx1: np.ndarray, m: int, crop: np.ndarray, x0: int, y0: int
) -> np.ndarray:
    """``np.packbits(crop.reshape(-1))`` of a crop painted from runs ``0 .. m - 1`` (in
    the runs' coordinates its top-left pixel is ``(x0, y0)``): each run whose first
    pixel the crop holds (a kept run: runs never share a pixel, so a dropped speck's run
    has none painted) sets its bits (pixel ``k`` is bit ``0x80 >> k % 8`` of byte
    ``k // 8``): its first and last bytes' by a mask each, the whole bytes between at
    once, without reading the crop's other pixels."""
    kh, kw = crop.shape
    out = np.zeros((kh * kw + 7) // 8, np.uint8)
    for i in range(m):
        y = ry[i] - y0
        a = rx0[i] - x0
        if y < 0 or y >= kh or a < 0 or a >= kw or not crop[y, a]:
            continue
        s = np.int64(y) * kw + a
        e = s + (rx1[i] - rx0[i])
        first, last = s >> 3, e >> 3
        head = np.uint8(0xFF >> (s & 7))  # bits s % 8 .. 7 of the first byte
        tail = np.uint8(0xFF ^ (0xFF >> (e & 7)))  # bits 0 .. e % 8 - 1 of the last
        if first == last:
            out[first] |= head & tail
            continue
        out[first] |= head
        for j in range(np.uint64(first + 1), np.uint64(last)):  # (unsigned: a memset)
            out[j] = 0xFF
        if tail:
            out[last] |= tail
    return out


@kernel("int32[:, ::1](int32[::1], int32[::1], int32[::1], int32[::1], int64, int64, int64)")
def paint_components(
    ry: np.ndarray, rx0: np.ndarray, rx1: np.ndarray, label: np.ndarray, n: int, w: int, h: int
) -> np.ndarray:
    """The (h, w) image of the dilated components (:func:`components`' labels): each
    labelled run's pixels and their 8 neighbours get its label (the label image
    ``cv2.connectedComponents`` gave of the dilated union)."""
    out = np.zeros((h, w), np.int32)
    flat = out.reshape(-1)
    for i in range(n):
        t = label[i]
        if t == 0:
            continue
        a, b = max(rx0[i] - 1, 0), min(rx1[i] + 1, w)
        for y in range(max(ry[i] - 1, 0), min(ry[i] + 2, h)):
            row = y * w
            for x in range(np.uint64(row + a), np.uint64(row + b)):
                flat[x] = t
    return out


#: ``cv2.distanceTransform``'s DIST_L2 3x3 mask weights (float32 0.955 and 1.3693, as
#: OpenCV's ``getDistanceTransformMask`` gives them): its distance between two pixels
#: (dx, dy) apart is ``HV * (M - m) + DIAG * m`` (M, m: the larger and smaller of |dx|,
#: |dy|), summed in float32 along the way, so within ~1e-3 px of that sum in real numbers
#: at the distances the grouping measures (tests/test_instances_speed.py).
CHAMFER_HV = float(np.float32(0.955))
CHAMFER_DIAG = float(np.float32(1.3693))


@kernel(
    "float64(int32[::1], int32[::1], int32[::1], int32[::1], int64, boolean[::1], "
    "boolean[::1], int64, int64, int64, int64, int64, int64)"
)
def chamfer_gap(
    ry: np.ndarray,
    rx0: np.ndarray,
    rx1: np.ndarray,
    label: np.ndarray,
    n: int,
    in_a: np.ndarray,
    in_b: np.ndarray,
    wx0: int,
    wy0: int,
    wx1: int,
    wy1: int,
    w: int,
    h: int,
) -> float:
    """The smallest chamfer distance (:data:`CHAMFER_HV`, :data:`CHAMFER_DIAG`, in real
    numbers) from a pixel of the dilated components ``in_a`` (True at their labels) to
    one of ``in_b`` within the window ``wx0 <= x < wx1``, ``wy0 <= y < wy1`` (inf: none
    there): what ``instances._pixel_gap`` measures with ``cv2.distanceTransform`` on the
    component image (:func:`paint_components`, ``w`` x ``h``), without it.

    Each labelled run lights a rectangle (its pixels and their 8 neighbours, clipped to
    the image); the distance of two rectangles is that of their gaps along x and y. For
    each of b's rectangles, a's rectangles (in raster order) are walked only over the
    rows that could still beat the best distance so far."""
    ax0 = np.empty(max(n, 1), np.int64)
    ax1 = np.empty(max(n, 1), np.int64)
    ay0 = np.empty(max(n, 1), np.int64)
    ay1 = np.empty(max(n, 1), np.int64)
    na = 0
    for i in range(n):
        if in_a[label[i]]:
            ax0[na], ax1[na] = max(rx0[i] - 1, 0), min(rx1[i], w - 1)
            ay0[na], ay1[na] = max(ry[i] - 1, 0), min(ry[i] + 1, h - 1)
            na += 1
    best = np.inf
    start = 0
    for i in range(n):
        if not in_b[label[i]]:
            continue
        bx0, bx1 = max(rx0[i] - 1, 0, wx0), min(rx1[i], w - 1, wx1 - 1)
        by0, by1 = max(ry[i] - 1, 0, wy0), min(ry[i] + 1, h - 1, wy1 - 1)
        if bx0 > bx1 or by0 > by1:
            continue
        reach = best / CHAMFER_HV  # rows farther than this cannot beat best
        # a's rectangles start at most 2 rows above where they end: skip the rows above
        while start > 0 and ay0[start - 1] >= by0 - reach - 2:
            start -= 1
        while start < na and ay0[start] < by0 - reach - 2:
            start += 1
        for k in range(start, na):
            if ay0[k] > by1 + reach:
                break
            dx = max(bx0 - ax1[k], ax0[k] - bx1, 0)
            dy = max(by0 - ay1[k], ay0[k] - by1, 0)
            big, small = max(dx, dy), min(dx, dy)
            d = CHAMFER_HV * (big - small) + CHAMFER_DIAG * small
            if d < best:
                best = d
                reach = best / CHAMFER_HV
    return best


@kernel("UniTuple(int64, 2)(uint8[:, ::1])")
def mask_sums(mask: np.ndarray) -> tuple[int, int]:
    """``(sum of x * value, sum of y * value)`` over a mask's pixels (crop coordinates;
    a bool mask's values are 0 and 1), exactly: what ``tracking.make_instance`` had from
    ``cv2.reduce``'s column and row sums dotted with their indices."""
    h, w = mask.shape
    sx = 0
    sy = 0
    for y in range(h):
        row = 0
        wx = 0
        for x in range(w):
            v = np.int64(mask[y, x])
            row += v
            wx += x * v
        sx += wx
        sy += y * row
    return sx, sy
