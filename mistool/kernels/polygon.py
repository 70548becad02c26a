"""OpenCV's convex hull and convex polygon fill, compiled (the pose's quality IoU,
:mod:`mistool.pose.quality`: a cylinder's image is the hull of its two rims, filled with
4 fractional bits and compared with the part's mask).

Each reproduces the OpenCV function bit for bit (OpenCV 5.0; ``tests/test_pose_contours.py``
compares them on random input):

- :func:`convex_hull`: ``cv2.convexHull(points, returnPoints=False)`` of float32 points
  (``convhull.cpp``: the points sorted by x then y, Sklansky's scan of the four
  quarter-chains with each turn's two edges normalised in float, the indices rotated
  into an ascending or descending run where possible);
- :func:`fill_convex`: ``cv2.fillConvexPoly(img, points, 1, LINE_8, shift)`` on a uint8
  image (``drawing.cpp``' ``FillConvexPoly``: the outline drawn with ``Line2``'s 16-bit
  fixed point, clipped to the image, then the scanlines between the left and right edge
  stepped in fixed point). Integer arithmetic: C's division rounds toward zero, which is
  written out here (numba's ``//`` floors).
"""

from __future__ import annotations

import math

import numpy as np

from mistool.kernels import helper, kernel

__all__ = ["convex_hull", "fill_convex"]

#: A turn of the hull whose sine is below this is "near straight": whether OpenCV keeps
#: its middle point depends on the last bits of its float arithmetic (numbers of its
#: build), so :func:`convex_hull` does not answer for such points.
_NEAR_STRAIGHT = 1e-6

_XY_SHIFT = 16
_XY_ONE = 1 << _XY_SHIFT


@helper
def _sign(v: float) -> int:
    """``CV_SIGN``."""
    return (v > 0) - (v < 0)


@helper
def _cdiv(a: int, b: int) -> int:
    """C's integer division (rounds toward zero)."""
    q = abs(a) // abs(b)
    return q if (a < 0) == (b < 0) else -q


@helper
def _same(pts: np.ndarray, i: int, j: int) -> bool:
    return pts[i, 0] == pts[j, 0] and pts[i, 1] == pts[j, 1]


@helper
def _normalised(x: np.float32, y: np.float32) -> tuple[np.float32, np.float32]:
    """``cv::normalize(Vec2f)``: the norm in double, each entry scaled in double and
    rounded to float."""
    xd, yd = float(x), float(y)
    nv = math.sqrt(0.0 + xd * xd + yd * yd)
    alpha = 1.0 / nv if nv else 0.0
    return np.float32(xd * alpha), np.float32(yd * alpha)


@helper
def _sklansky(
    pts: np.ndarray,
    order: np.ndarray,
    start: int,
    end: int,
    stack: np.ndarray,
    s0: int,
    nsign: int,
    sign2: int,
) -> int:
    """``Sklansky_<float, double>`` over the sorted points ``pts[order[...]]`` from
    ``start`` to ``end``, its stack at ``stack[s0:]``; the stack's length."""
    incr = 1 if end > start else -1
    pprev, pcur = start, start + incr
    pnext = pcur + incr
    size = 3
    if start == end or _same(pts, order[start], order[end]):
        stack[s0] = start
        return 1
    stack[s0], stack[s0 + 1], stack[s0 + 2] = pprev, pcur, pnext
    end += incr
    while pnext != end:
        c, nx, pv = order[pcur], order[pnext], order[pprev]
        if _same(pts, c, nx):
            pnext += incr
            stack[s0 + size - 1] = pnext
            continue
        cury, nexty = pts[c, 1], pts[nx, 1]
        by = np.float32(nexty - cury)
        if _sign(by) != nsign:
            a0, a1 = _normalised(np.float32(pts[c, 0] - pts[pv, 0]), np.float32(cury - pts[pv, 1]))
            b0, b1 = _normalised(np.float32(pts[nx, 0] - pts[c, 0]), by)
            convexity = float(a1) * float(b0) - float(a0) * float(b1)
            if abs(convexity) < _NEAR_STRAIGHT:
                return -1
            if _sign(convexity) == sign2 and (a0 != 0 or a1 != 0):
                pprev = pcur
                pcur = pnext
                pnext += incr
                stack[s0 + size] = pnext
                size += 1
            elif pprev == start:
                pcur = pnext
                stack[s0 + 1] = pcur
                pnext += incr
                stack[s0 + 2] = pnext
            else:
                stack[s0 + size - 2] = pnext
                pcur = pprev
                pprev = stack[s0 + size - 4]
                size -= 1
        else:
            pnext += incr
            stack[s0 + size - 1] = pnext
    return size - 1


@helper
def _before(pts: np.ndarray, p: int, q: int) -> bool:
    """Point ``p`` sorts before or with point ``q``: by x, then y."""
    return pts[p, 0] < pts[q, 0] or (pts[p, 0] == pts[q, 0] and pts[p, 1] <= pts[q, 1])


@helper
def _sorted_points(pts: np.ndarray) -> np.ndarray:
    """The points' indices sorted by x, then y, then index (a stable sort): the rims'
    points come in a few runs of ascending or descending x (two ellipses), merged
    pairwise (a natural merge sort); with a NaN among them, an insertion sort (the
    order of its comparisons then decides)."""
    total = len(pts)
    order = np.empty(total, np.int64)
    for i in range(total):
        if math.isnan(pts[i, 0]) or math.isnan(pts[i, 1]):
            return _inserted(pts)
    tmp = np.empty(total, np.int64)
    bounds = np.empty(total + 1, np.int64)
    n_runs = 0
    i = 0
    while i < total:  # the runs: ascending as they are, strictly descending reversed
        j = i + 1
        if j < total and not _before(pts, j - 1, j):
            while j < total and not _before(pts, j - 1, j):
                j += 1
            for k in range(j - i):
                order[i + k] = j - 1 - k
        else:
            while j < total and _before(pts, j - 1, j):
                j += 1
            for k in range(i, j):
                order[k] = k
        bounds[n_runs] = i
        n_runs += 1
        i = j
    bounds[n_runs] = total
    while n_runs > 1:  # merge neighbouring runs pairwise (the left one first on ties)
        m = 0
        for r in range(0, n_runs, 2):
            lo, mid = bounds[r], bounds[r + 1]
            hi = bounds[r + 2] if r + 2 <= n_runs else mid
            a, b, k = lo, mid, lo
            while a < mid and b < hi:
                if _before(pts, order[a], order[b]):
                    tmp[k] = order[a]
                    a += 1
                else:
                    tmp[k] = order[b]
                    b += 1
                k += 1
            while a < mid:
                tmp[k] = order[a]
                a += 1
                k += 1
            while b < hi:
                tmp[k] = order[b]
                b += 1
                k += 1
            bounds[m] = lo
            m += 1
        bounds[m] = total
        n_runs = m
        order, tmp = tmp, order
    return order


@helper
def _inserted(pts: np.ndarray) -> np.ndarray:
    """The points' indices sorted by x, then y, then index (insertion sort: 48 points;
    the former :func:`_sorted_points`)."""
    total = len(pts)
    order = np.empty(total, np.int64)
    for i in range(total):
        j = i
        while j > 0:
            p = order[j - 1]
            if pts[p, 0] < pts[i, 0] or (pts[p, 0] == pts[i, 0] and pts[p, 1] <= pts[i, 1]):
                break
            order[j] = p
            j -= 1
        order[j] = i
    return order


@helper
def _chains(
    pts: np.ndarray, order: np.ndarray, miny: int, maxy: int, stack: np.ndarray, out: np.ndarray
) -> int:
    """``convexHull``'s four chains (``clockwise=False``) into ``out``: its length, or -1
    for a turn too close to straight."""
    total = len(pts)
    nout = 0
    tl = _sklansky(pts, order, 0, maxy, stack, 0, -1, 1)  # upper half
    tr = _sklansky(pts, order, total - 1, maxy, stack, max(tl, 0), -1, -1)
    if tl < 0 or tr < 0:
        return -1
    # counter-clockwise: the two upper stacks swapped
    for i in range(tr - 1):
        out[nout] = order[stack[tl + i]]
        nout += 1
    for i in range(tl - 1, 0, -1):
        out[nout] = order[stack[i]]
        nout += 1
    stop = stack[1] if tl > 2 else (stack[tl + tr - 2] if tr > 2 else -1)
    bl = _sklansky(pts, order, 0, miny, stack, 0, 1, -1)  # lower half
    br = _sklansky(pts, order, total - 1, miny, stack, max(bl, 0), 1, 1)
    if bl < 0 or br < 0:
        return -1
    if stop >= 0:
        check = stack[1] if bl > 2 else (stack[2] if bl + br > 2 else -1)
        if check == stop or (check >= 0 and _same(pts, order[check], order[stop])):
            bl = min(bl, 2)  # all points on one line: the lower part mirrors the upper
            br = min(br, 2)
    for i in range(bl - 1):
        out[nout] = order[stack[i]]
        nout += 1
    for i in range(br - 1, 0, -1):
        out[nout] = order[stack[bl + i]]
        nout += 1
    return nout


@helper
def _rotate_run(out: np.ndarray, nout: int, tmp: np.ndarray) -> None:
    """``convexHull``'s last step: the indices cyclically shifted into an ascending or
    descending run where they form one."""
    mn = mx = lt = 0
    for i in range(1, nout):
        idx = out[i]
        lt += out[i - 1] < idx
        if lt > 1 and lt <= i - 2:
            break
        if idx < out[mn]:
            mn = i
        if idx > out[mx]:
            mx = i
    mm = abs(mx - mn)
    if not ((mm == 1 or mm == nout - 1) and (lt <= 1 or lt >= nout - 2)):
        return
    ascending = (mx + 1) % nout == mn
    j = mn if ascending else mx
    if j == 0:
        return
    i = 0
    while i < nout:
        cur = tmp[i] = out[j]
        nj = j + 1 if j + 1 < nout else 0
        if i < nout - 1 and ascending != (cur < out[nj]):
            return
        j = nj
        i += 1
    for k in range(nout):
        out[k] = tmp[k]


@kernel("int64(float32[:, ::1], int32[::1])")
def convex_hull(pts: np.ndarray, hull: np.ndarray) -> int:
    """``cv2.convexHull(pts, returnPoints=False)`` (counter-clockwise in OpenCV's sense)
    into ``hull`` (at least ``len(pts)`` long); the number of hull points, or -1 where
    the answer would rest on float rounding (two equal points, a turn whose sine is
    below :data:`_NEAR_STRAIGHT`): ask OpenCV then."""
    total = len(pts)
    if total == 0:
        return 0
    order = _sorted_points(pts)
    miny = maxy = 0
    for i in range(1, total):
        y = pts[order[i], 1]
        if pts[order[miny], 1] > y:
            miny = i
        if pts[order[maxy], 1] < y:
            maxy = i
    for i in range(1, total):  # equal points: OpenCV's order among them is std::sort's
        if _same(pts, order[i - 1], order[i]):
            return -1
    if total == 1:
        hull[0] = 0
        return 1
    stack = np.empty(total + 2, np.int64)
    out = np.empty(total, np.int64)
    nout = _chains(pts, order, miny, maxy, stack, out)
    if nout < 0:
        return -1
    if nout >= 3:
        _rotate_run(out, nout, stack)
    for k in range(nout):
        hull[k] = out[k]
    return nout


@helper
def _clip_line(w: int, h: int, p: np.ndarray) -> bool:
    """``cv::clipLine(Size2l, Point2l&, Point2l&)`` on ``p = [x1, y1, x2, y2]``."""
    right, bottom = w - 1, h - 1
    if w <= 0 or h <= 0:
        return False
    x1, y1, x2, y2 = p[0], p[1], p[2], p[3]
    c1 = (x1 < 0) + (x1 > right) * 2 + (y1 < 0) * 4 + (y1 > bottom) * 8
    c2 = (x2 < 0) + (x2 > right) * 2 + (y2 < 0) * 4 + (y2 > bottom) * 8
    if (c1 & c2) == 0 and (c1 | c2) != 0:
        if c1 & 12:
            a = 0 if c1 < 8 else bottom
            x1 += _cdiv((a - y1) * (x2 - x1), y2 - y1)
            y1 = a
            c1 = (x1 < 0) + (x1 > right) * 2
        if c2 & 12:
            a = 0 if c2 < 8 else bottom
            x2 += _cdiv((a - y2) * (x2 - x1), y2 - y1)
            y2 = a
            c2 = (x2 < 0) + (x2 > right) * 2
        if (c1 & c2) == 0 and (c1 | c2) != 0:
            if c1:
                a = 0 if c1 == 1 else right
                y1 += _cdiv((a - x1) * (y2 - y1), x2 - x1)
                x1 = a
                c1 = 0
            if c2:
                a = 0 if c2 == 1 else right
                y2 += _cdiv((a - x2) * (y2 - y1), x2 - x1)
                x2 = a
                c2 = 0
    p[0], p[1], p[2], p[3] = x1, y1, x2, y2
    return (c1 | c2) == 0


@helper
def _put(flat: np.ndarray, h: int, w: int, x: int, y: int) -> None:
    """Pixel ``(x, y)`` of the (h, w) image ``flat`` set to 1 when inside it."""
    if 0 <= x < w and 0 <= y < h:
        flat[y * w + x] = 1


@helper
def _line2(flat: np.ndarray, h: int, w: int, p: np.ndarray) -> None:
    """``Line2``: a fixed-point (16 bits) line from ``p[0:2]`` to ``p[2:4]``, 8-connected,
    value 1, on the (h, w) image ``flat``."""
    if not _clip_line(w << _XY_SHIFT, h << _XY_SHIFT, p):
        return
    x1, y1, x2, y2 = p[0], p[1], p[2], p[3]
    dx, dy = x2 - x1, y2 - y1
    x_step = y_step = 0
    j = -1 if dx < 0 else 0
    ax = (dx ^ j) - j
    i = -1 if dy < 0 else 0
    ay = (dy ^ i) - i
    if ax > ay:
        dy = (dy ^ j) - j
        x1 ^= x2 & j
        x2 ^= x1 & j
        x1 ^= x2 & j
        y1 ^= y2 & j
        y2 ^= y1 & j
        y1 ^= y2 & j
        y_step = _cdiv(dy << _XY_SHIFT, ax | 1)
        ecount = (x2 - x1) >> _XY_SHIFT
    else:
        dx = (dx ^ i) - i
        x1 ^= x2 & i
        x2 ^= x1 & i
        x1 ^= x2 & i
        y1 ^= y2 & i
        y2 ^= y1 & i
        y1 ^= y2 & i
        x_step = _cdiv(dx << _XY_SHIFT, ay | 1)
        ecount = (y2 - y1) >> _XY_SHIFT
    x1 += _XY_ONE >> 1
    y1 += _XY_ONE >> 1
    _put(flat, h, w, (x2 + (_XY_ONE >> 1)) >> _XY_SHIFT, (y2 + (_XY_ONE >> 1)) >> _XY_SHIFT)
    # the pixels set in the loops themselves (no call with the image per pixel)
    if ax > ay:
        x1 >>= _XY_SHIFT
        while ecount >= 0:
            y = y1 >> _XY_SHIFT
            if 0 <= x1 < w and 0 <= y < h:
                flat[y * w + x1] = 1
            x1 += 1
            y1 += y_step
            ecount -= 1
    else:
        y1 >>= _XY_SHIFT
        while ecount >= 0:
            x = x1 >> _XY_SHIFT
            if 0 <= x < w and 0 <= y1 < h:
                flat[y1 * w + x] = 1
            x1 += x_step
            y1 += 1
            ecount -= 1


@helper
def _next_edge(
    pts: np.ndarray,
    order: np.ndarray,
    npts: int,
    shift: int,
    y: int,
    k: int,
    edge: np.ndarray,
    edges: int,
) -> int:
    """``FillConvexPoly``'s step to side ``k``'s next edge that reaches below row ``y``
    (``edge[k]``: index, direction, x, dx, end row); the edges left (below 0: none)."""
    delta = 1 << shift >> 1
    up = _XY_SHIFT - shift
    idx0, di = edge[k, 0], edge[k, 1]
    idx = idx0 + di
    if idx >= npts:
        idx -= npts
    while True:
        edges -= 1
        if edges < 0:
            return edges
        ty = (np.int64(pts[order[idx], 1]) + delta) >> shift
        if ty > y:
            xs = np.int64(pts[order[idx0], 0]) << up
            xe = np.int64(pts[order[idx], 0]) << up
            edge[k, 4] = ty
            edge[k, 3] = _cdiv((xe - xs) * 2 + (ty - y), 2 * (ty - y))
            edge[k, 2] = xs
            edge[k, 0] = idx
            return edges
        idx0 = idx
        idx += di
        if idx >= npts:
            idx -= npts


@kernel("void(uint8[:, ::1], int32[:, ::1], int32[::1], int64, int64)")
def fill_convex(img: np.ndarray, pts: np.ndarray, order: np.ndarray, npts: int, shift: int) -> None:
    """``cv2.fillConvexPoly(img, pts[order[:npts]], 1, cv2.LINE_8, shift)`` (value 1;
    ``0 < shift <= 16``)."""
    h, w = img.shape
    flat = img.ravel()
    delta = 1 << shift >> 1
    up = _XY_SHIFT - shift
    half = _XY_ONE >> 1
    seg = np.empty(4, np.int64)
    last = order[npts - 1]
    p0x, p0y = np.int64(pts[last, 0]) << up, np.int64(pts[last, 1]) << up
    xmin = xmax = np.int64(pts[order[0], 0])
    ymin = ymax = np.int64(pts[order[0], 1])
    imin = 0
    for i in range(npts):  # the outline
        vx, vy = np.int64(pts[order[i], 0]), np.int64(pts[order[i], 1])
        if vy < ymin:
            ymin = vy
            imin = i
        ymax = max(ymax, vy)
        xmax = max(xmax, vx)
        xmin = min(xmin, vx)
        seg[0], seg[1], seg[2], seg[3] = p0x, p0y, vx << up, vy << up
        _line2(flat, h, w, seg)
        p0x, p0y = vx << up, vy << up
    xmin, xmax = (xmin + delta) >> shift, (xmax + delta) >> shift
    ymin, ymax = (ymin + delta) >> shift, (ymax + delta) >> shift
    if npts < 3 or xmax < 0 or ymax < 0 or xmin >= w or ymin >= h:
        return
    ymax = min(ymax, h - 1)
    edge = np.empty((2, 5), np.int64)  # per side: index, direction, x, dx, end row
    y = ymin
    edge[0, 0], edge[0, 1], edge[0, 2], edge[0, 3], edge[0, 4] = imin, 1, -_XY_ONE, 0, y
    edge[1, 0], edge[1, 1], edge[1, 2], edge[1, 3], edge[1, 4] = imin, npts - 1, -_XY_ONE, 0, y
    edges = npts
    while True:  # the scanlines
        for k in range(2):
            if y >= edge[k, 4]:
                edges = _next_edge(pts, order, npts, shift, y, k, edge, edges)
        if edges < 0:
            break
        if y >= 0:
            lx, rx = min(edge[0, 2], edge[1, 2]), max(edge[0, 2], edge[1, 2])
            xx1 = max((lx + half) >> _XY_SHIFT, 0)
            xx2 = min((rx + half) >> _XY_SHIFT, w - 1)
            if (rx + half) >> _XY_SHIFT >= 0 and (lx + half) >> _XY_SHIFT < w:
                # unsigned indices: no wrap-around check, the loop becomes a memset
                for x in range(np.uint64(y * w + xx1), np.uint64(y * w + xx2 + 1)):
                    flat[x] = 1
        edge[0, 2] += edge[0, 3]
        edge[1, 2] += edge[1, 3]
        y += 1
        if y > ymax:
            break
