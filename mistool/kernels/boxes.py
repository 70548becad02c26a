"""Algorithm 1 per part, compiled (:mod:`mistool.geometry`'s ``fit_part`` and
``grow_to_pixel_edges``): a part's pixels as row runs, its 8-connected specks dropped, its
kept pixels' crop, their external contours traced as OpenCV traces them, and the box grown
to the pixel edges.

Each kernel gives the bits of the OpenCV and numpy steps it replaces (tests compare them):

- the contours are Suzuki's border following as ``cv2.findContours(mask, RETR_CCOMP,
  CHAIN_APPROX_SIMPLE)`` does it (OpenCV 4.10+ / 5.0, ``contours_new.cpp``): each
  8-connected component's outer border from its first pixel in raster order, a point
  wherever the chain direction changes; the components in *reverse* raster order, as
  OpenCV returns them. The order matters: ``cv2.minAreaRect`` starts its hull at the hull
  point that comes first in its input, which decides between equal-area rectangles.
- the projections onto the box axes are those of numpy's ``(N, 2) @ (2,)`` on this
  machine (OpenBLAS's ``dgemv``: ``fma(x, e0, y * e1)``, or ``fma(y, e1, x * e0)`` for a
  single point): which of several points on one box side rounds farthest out decides
  the side's last bit.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from llvmlite import ir  # type: ignore[import-untyped]
from numba import types
from numba.core.extending import intrinsic

from mistool.kernels import helper, kernel


def _fma_typed(typingctx: object, a: object, b: object, c: object) -> tuple[object, object]:
    """``a * b + c`` rounded once (LLVM's ``llvm.fma.f64``: the FMA instruction, or a
    correctly rounded library call)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context: Any, builder: ir.IRBuilder, signature: Any, args: list) -> object:
        d = ir.DoubleType()
        fn = builder.module.declare_intrinsic("llvm.fma", [d], ir.FunctionType(d, [d, d, d]))
        return builder.call(fn, args)

    return sig, codegen


_fma: Any = intrinsic(_fma_typed)


#: Columns (or rows) walked per box side by :func:`lattice_gap` (``geometry._GAP_WALK``).
GAP_WALK = 64
#: Lattice points this close to a side are on it (``minAreaRect``'s float32 angle).
GAP_EPS = 1e-4


@kernel("float64(float64, float64, float64, float64, float64)")
def lattice_gap(nx: float, ny: float, h: float, t_lo: float, t_hi: float) -> float:
    """Distance from the box side ``n . p = h`` (unit outward normal ``n``, between
    tangent positions ``t_lo`` and ``t_hi``) to the next row of pixel centres beyond it
    (see ``geometry._lattice_gaps``; the same operations in the same order)."""
    if abs(ny) >= abs(nx):  # walk the columns; a: the walked coordinate's coefficient
        a, b, tangent = nx, abs(ny), -ny
    else:
        a, b, tangent = ny, abs(nx), nx
    w0 = h * a + t_lo * tangent
    w1 = h * a + t_hi * tangent
    start = np.ceil(min(w0, w1) - GAP_EPS)
    full = max(np.floor(max(w0, w1) + GAP_EPS) - start + 1.0, 1.0)
    count = min(full, float(GAP_WALK))
    skipped = full - count  # a long side: its first and last GAP_WALK / 2 columns
    he = h + GAP_EPS
    best = -1.0
    for k in range(GAP_WALK):
        if k >= count:
            break
        p = (start + k) + (skipped if k >= GAP_WALK // 2 else 0.0)
        r = (he - a * p) / b
        frac = r - np.floor(r)
        if frac > best:
            best = frac
    return b * (1.0 - best) + GAP_EPS


#: Angles this close to 180 deg (after reduction) are reported as 0 deg
#: (``geometry._ANGLE_SNAP_DEG``).
ANGLE_SNAP_DEG = 1e-6

_GROWN = "UniTuple(float64, 5)"


@kernel(
    _GROWN + "(int32[:, ::1], float64, float64, float64, float64[:, ::1])",
    _GROWN + "(float32[:, ::1], float64, float64, float64, float64[:, ::1])",
)
def grow_box(
    points: np.ndarray, c: float, s: float, angle: float, corners: np.ndarray
) -> tuple[float, float, float, float, float]:
    """The minimum-area box of ``points`` ((N, 2) pixel centres, N >= 1) whose first side
    points along ``(c, s)`` (``minAreaRect``'s ``angle``, degrees), each side moved out by
    half its :func:`lattice_gap`: ``corners`` gets (4, 2) ``cv2.boxPoints``' corners of
    it (``geometry.box_points``' formula); returns its canonical (cx, cy, length, width,
    angle_deg) (``geometry._canonical``'s)."""
    n = points.shape[0]
    a_lo = a_hi = b_lo = b_hi = 0.0
    for i in range(n):
        x = float(points[i, 0])
        y = float(points[i, 1])
        if n >= 2:
            p1 = _fma(x, c, y * s)
            p2 = _fma(x, -s, y * c)
        else:
            p1 = _fma(y, s, x * c)
            p2 = _fma(y, c, x * -s)
        if i == 0:
            a_lo = a_hi = p1
            b_lo = b_hi = p2
            continue
        if p1 < a_lo:
            a_lo = p1
        if p1 > a_hi:
            a_hi = p1
        if p2 < b_lo:
            b_lo = p2
        if p2 > b_hi:
            b_hi = p2
    # sides with outward normals +e2, -e2, +e1, -e1 (e1 = (c, s), e2 = (-s, c))
    g0 = lattice_gap(-s, c, b_hi, -a_hi, -a_lo) / 2.0
    g1 = lattice_gap(s, -c, -b_lo, a_lo, a_hi) / 2.0
    g2 = lattice_gap(c, s, a_hi, b_lo, b_hi) / 2.0
    g3 = lattice_gap(-c, -s, -a_lo, -b_hi, -b_lo) / 2.0
    b_hi, b_lo, a_hi, a_lo = b_hi + g0, b_lo - g1, a_hi + g2, a_lo - g3
    ca = (a_lo + a_hi) / 2.0
    cb = (b_lo + b_hi) / 2.0
    cx = ca * c - cb * s
    cy = ca * s + cb * c
    w = a_hi - a_lo
    h = b_hi - b_lo
    hb = c * 0.5
    ha = s * 0.5
    corners[0, 0] = cx - ha * h - hb * w
    corners[0, 1] = cy + hb * h - ha * w
    corners[1, 0] = cx + ha * h - hb * w
    corners[1, 1] = cy - hb * h - ha * w
    corners[2, 0] = 2 * cx - corners[0, 0]
    corners[2, 1] = 2 * cy - corners[0, 1]
    corners[3, 0] = 2 * cx - corners[1, 0]
    corners[3, 1] = 2 * cy - corners[1, 1]
    # canonical: the long side's direction in [0, 180); a zero-length box at 0 deg
    if w >= h:
        length, width, direction = w, h, angle
    else:
        length, width, direction = h, w, angle + 90.0
    direction %= 180.0
    if direction >= 180.0 - ANGLE_SNAP_DEG or length == 0.0:
        direction = 0.0
    return cx, cy, length, width, direction


# --- cv2.minAreaRect of integer points ----------------------------------------------------
#
# OpenCV 5.0's ``minAreaRect``, step for step, so that its float32 results come out bit for
# bit: the convex hull as ``convexHull(points, clockwise=False)`` gives it (Sklansky's scan
# of the points sorted by x, then y, then input order; its vertices in OpenCV's order and
# from its start point, which decide between rectangles of equal area), then the rotating
# calipers in float32 (an edge chosen by the sign of a dot product), then the rectangle's
# angle brought into [-90, 0) in double (a side along 0 deg is reported at -90 deg).


@helper
def _hull_chain(
    xs: np.ndarray,
    ys: np.ndarray,
    start: int,
    end: int,
    stack: np.ndarray,
    nsign: int,
    sign2: int,
) -> int:
    """One chain of the hull from sorted point ``start`` to ``end`` (either direction) as
    OpenCV's ``Sklansky_`` scans it: ``stack`` gets the chain's sorted indices; returns
    their number. Points whose step in y has the sign ``nsign`` are passed over; a turn
    whose cross product does not have the sign ``sign2`` (or from a repeated point) pops
    the middle point."""
    incr = 1 if end > start else -1
    if start == end or (xs[start] == xs[end] and ys[start] == ys[end]):
        stack[0] = start
        return 1
    pprev = start
    pcur = start + incr
    pnext = pcur + incr
    size = 3
    stack[0], stack[1], stack[2] = pprev, pcur, pnext
    stop = end + incr
    while pnext != stop:
        by = ys[pnext] - ys[pcur]
        if (1 if by > 0 else (-1 if by < 0 else 0)) != nsign:
            ax = xs[pcur] - xs[pprev]
            ay = ys[pcur] - ys[pprev]
            bx = xs[pnext] - xs[pcur]
            turn = ay * bx - ax * by  # (int64: no overflow)
            if (1 if turn > 0 else (-1 if turn < 0 else 0)) == sign2 and (ax != 0 or ay != 0):
                pprev = pcur
                pcur = pnext
                pnext += incr
                stack[size] = pnext
                size += 1
            elif pprev == start:
                pcur = pnext
                stack[1] = pcur
                pnext += incr
                stack[2] = pnext
            else:
                stack[size - 2] = pnext
                pcur = pprev
                pprev = stack[size - 4]
                size -= 1
        else:
            pnext += incr
            stack[size - 1] = pnext
    return size - 1


@helper
def _monotone_shift(out: np.ndarray, m: int) -> None:
    """OpenCV's last step of the hull: a cyclic shift of the ``m >= 3`` indices ``out``
    that makes them ascending or descending, when there is one (else they stay)."""
    imin = imax = 0
    ups = 0
    for i in range(1, m):
        if out[i - 1] < out[i]:
            ups += 1
        if ups > 1 and ups <= i - 2:
            break
        if out[i] < out[imin]:
            imin = i
        if out[i] > out[imax]:
            imax = i
    gap = abs(imax - imin)
    if (gap == 1 or gap == m - 1) and (ups <= 1 or ups >= m - 2):
        ascending = (imax + 1) % m == imin
        j0 = imin if ascending else imax
        if j0 == 0:
            return
        j = j0
        for _ in range(m - 1):  # monotone all the way round from j0?
            nj = j + 1 if j + 1 < m else 0
            if ascending != (out[j] < out[nj]):
                return
            j = nj
        _reverse(out, 0, j0)  # rotate left by j0 in place: three reversals
        _reverse(out, j0, m)
        _reverse(out, 0, m)


@helper
def _reverse(a: np.ndarray, lo: int, hi: int) -> None:
    """Reverse ``a[lo:hi]`` in place."""
    hi -= 1
    while lo < hi:
        a[lo], a[hi] = a[hi], a[lo]
        lo += 1
        hi -= 1


@helper
def _sort_points(points: np.ndarray, order: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> None:
    """``order``: the indices of (N, 2) ``points`` sorted by x, then y, equal points in
    input order (OpenCV's ``CHullCmpPoints``); ``xs``, ``ys``: their coordinates so."""
    n = points.shape[0]
    if n <= 48:  # insertion sort by x, then y; equal points keep their input order
        for i in range(n):
            x, y = points[i, 0], points[i, 1]
            j = i
            while j > 0 and (xs[j - 1] > x or (xs[j - 1] == x and ys[j - 1] > y)):
                xs[j], ys[j], order[j] = xs[j - 1], ys[j - 1], order[j - 1]
                j -= 1
            xs[j], ys[j], order[j] = x, y, i
    else:
        key = np.empty(n, np.int64)
        for i in range(n):  # x, then y (offset: any int32 y keeps the order)
            key[i] = np.int64(points[i, 0]) * (1 << 32) + (np.int64(points[i, 1]) + (1 << 31))
        sorted_ = np.argsort(key, kind="mergesort")  # stable: equal points in input order
        for i in range(n):
            order[i] = sorted_[i]
            xs[i] = points[sorted_[i], 0]
            ys[i] = points[sorted_[i], 1]


@helper
def hull_ccw(points: np.ndarray, out: np.ndarray, work: np.ndarray) -> int:
    """``cv2.convexHull(points, clockwise=False, returnPoints=True)`` of (N, 2) integer
    points, N >= 1, as indices into ``points`` (``out``, (N,) at least; ``work``: (5N +
    4,) int64 scratch): the hull's vertices in OpenCV's order and from its start;
    returns their number."""
    n = points.shape[0]
    order = work[:n]
    xs = work[n : 2 * n]
    ys = work[2 * n : 3 * n]
    left = work[3 * n : 4 * n + 2]
    right = work[4 * n + 2 : 5 * n + 4]
    _sort_points(points, order, xs, ys)
    lo = hi = 0  # the first sorted point of the smallest / largest y
    for i in range(1, n):
        if ys[lo] > ys[i]:
            lo = i
        if ys[hi] < ys[i]:
            hi = i
    if xs[0] == xs[n - 1] and ys[0] == ys[n - 1]:  # one point, maybe repeated
        out[0] = 0
        return 1
    # upper half (counter-clockwise: the chain from the right end first)
    nl = _hull_chain(xs, ys, 0, hi, left, -1, 1)
    nr = _hull_chain(xs, ys, n - 1, hi, right, -1, -1)
    m = 0
    for i in range(nr - 1):
        out[m] = order[right[i]]
        m += 1
    for i in range(nl - 1, 0, -1):
        out[m] = order[left[i]]
        m += 1
    stop = left[1] if nl > 2 else (right[nr - 2] if nr > 2 else -1)
    # lower half
    nl = _hull_chain(xs, ys, 0, lo, left, 1, -1)
    nr = _hull_chain(xs, ys, n - 1, lo, right, 1, 1)
    if stop >= 0:
        check = left[1] if nl > 2 else (right[2 - nl] if nl + nr > 2 else -1)
        if check == stop or (check >= 0 and xs[check] == xs[stop] and ys[check] == ys[stop]):
            nl = min(nl, 2)  # all on one line: the lower half mirrors the upper
            nr = min(nr, 2)
    for i in range(nl - 1):
        out[m] = order[left[i]]
        m += 1
    for i in range(nr - 1, 0, -1):
        out[m] = order[right[i]]
        m += 1
    if m >= 3:
        _monotone_shift(out, m)
    return m


_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_FHALF = np.float32(0.5)
_FLT_MAX = np.float32(3.4028234663852886e38)


@helper
def _edges(
    hx: np.ndarray, hy: np.ndarray, n: int, vx: np.ndarray, vy: np.ndarray, inv: np.ndarray
) -> tuple[int, int, int, int]:
    """The calipers' start: each hull edge's vector (``vx``, ``vy``, float32) and its
    inverse length (``inv``: float32 of the double), and the first vertices of least y,
    largest x, largest y and least x."""
    left = bottom = right = top = 0
    x0, y0 = hx[0], hy[0]
    left_x = right_x = x0
    top_y = bottom_y = y0
    for i in range(n):
        if x0 < left_x:
            left_x, left = x0, i
        if x0 > right_x:
            right_x, right = x0, i
        if y0 > top_y:
            top_y, top = y0, i
        if y0 < bottom_y:
            bottom_y, bottom = y0, i
        j = i + 1 if i + 1 < n else 0
        dx = np.float64(hx[j] - x0)
        dy = np.float64(hy[j] - y0)
        vx[i] = np.float32(dx)
        vy[i] = np.float32(dy)
        inv[i] = np.float32(1.0 / np.sqrt(dx * dx + dy * dy))
        x0, y0 = hx[j], hy[j]
    return bottom, right, top, left


@helper
def _calipers(
    hx: np.ndarray, hy: np.ndarray, n: int, work: np.ndarray
) -> tuple[float, float, float, float, float, float]:
    """OpenCV's ``rotatingCalipers`` (minimum-area mode) over ``n > 2`` hull vertices
    (float32 coordinates; ``work``: (3n,) float32 scratch): the rectangle's corner and
    its two side vectors, float32."""
    vx = work[:n]
    vy = work[n : 2 * n]
    inv = work[2 * n : 3 * n]
    bottom, right, top, left = _edges(hx, hy, n, vx, vy, inv)
    orientation = _F0
    ax, ay = np.float64(vx[n - 1]), np.float64(vy[n - 1])
    for i in range(n):
        bx, by = np.float64(vx[i]), np.float64(vy[i])
        turn = ax * by - ay * bx
        if turn != 0.0:
            orientation = _F1 if turn > 0.0 else -_F1
            break
        ax, ay = bx, by
    base_a = orientation
    base_b = _F0
    s0, s1, s2, s3 = bottom, right, top, left  # the four calipers' vertices
    min_area = _FLT_MAX
    best_left = best_bottom = 0
    best_a = best_b = best_w = best_h = _F0
    for _ in range(n):
        # each caliper's edge turned into the first caliper's frame; the edge at the
        # smallest angle (right of the others: a dot product's sign) leads
        lead, p, ux, uy = 0, s0, vx[s0], vy[s0]
        wx, wy = vy[s1], -vx[s1]
        if wy * ux + -wx * uy < _F0:
            lead, p, ux, uy = 1, s1, wx, wy
        wx, wy = -vx[s2], -vy[s2]
        if wy * ux + -wx * uy < _F0:
            lead, p, ux, uy = 2, s2, wx, wy
        wx, wy = -vy[s3], vx[s3]
        if wy * ux + -wx * uy < _F0:
            lead, p, ux, uy = 3, s3, wx, wy
        lx = vx[p] * inv[p]
        ly = vy[p] * inv[p]
        nxt = p + 1 if p + 1 < n else 0
        if lead == 0:
            base_a, base_b, s0 = lx, ly, nxt
        elif lead == 1:
            base_a, base_b, s1 = ly, -lx, nxt
        elif lead == 2:
            base_a, base_b, s2 = -lx, -ly, nxt
        else:
            base_a, base_b, s3 = -ly, lx, nxt
        dx = hx[s1] - hx[s3]
        dy = hy[s1] - hy[s3]
        width = dx * base_a + dy * base_b
        dx = hx[s2] - hx[s0]
        dy = hy[s2] - hy[s0]
        height = -dx * base_b + dy * base_a
        area = width * height
        if area <= min_area:
            min_area = area
            best_left, best_bottom = s3, s0
            best_a, best_b, best_w, best_h = base_a, base_b, width, height
    a1, b1 = best_a, best_b
    a2, b2 = -best_b, best_a
    c1 = a1 * hx[best_left] + hy[best_left] * b1
    c2 = a2 * hx[best_bottom] + hy[best_bottom] * b2
    idet = _F1 / (a1 * b2 - a2 * b1)
    px = (c1 * b2 - c2 * b1) * idet
    py = (a1 * c2 - a2 * c1) * idet
    return px, py, a1 * best_w, b1 * best_w, a2 * best_h, b2 * best_h


@helper
def _min_area_rect(points: np.ndarray) -> tuple[float, float, float, float, float]:
    """``cv2.minAreaRect`` of (N, 2) int32 points: ``(cx, cy, w, h, angle)``, each the
    float32 value OpenCV gives (``angle`` in [-90, 0) degrees)."""
    n = points.shape[0]
    idx = np.empty(6 * n + 4, np.int64)  # the hull's indices, then the hull's scratch
    m = hull_ccw(points, idx, idx[n:]) if n > 0 else 0
    work = np.empty(5 * max(m, 1), np.float32)  # the hull's points, the calipers' scratch
    hx = work[:m]
    hy = work[m : 2 * m]
    for i in range(m):
        hx[i] = np.float32(points[idx[i], 0])
        hy[i] = np.float32(points[idx[i], 1])
    cx = cy = w = h = _F0
    angle = 0.0
    if m > 2:
        px, py, ux, uy, vx, vy = _calipers(hx, hy, m, work[2 * m :])
        cx = px + (ux + vx) * _FHALF
        cy = py + (uy + vy) * _FHALF
        w = np.float32(np.sqrt(np.float64(ux) * ux + np.float64(uy) * uy))
        h = np.float32(np.sqrt(np.float64(vx) * vx + np.float64(vy) * vy))
        angle = np.arctan2(np.float64(uy), np.float64(ux)) * 180.0 / np.pi
    elif m == 2:
        cx = (hx[0] + hx[1]) * _FHALF
        cy = (hy[0] + hy[1]) * _FHALF
        dx = np.float64(hx[1] - hx[0])
        dy = np.float64(hy[1] - hy[0])
        w = np.float32(np.sqrt(dx * dx + dy * dy))
        angle = np.arctan2(dy, dx) * 180.0 / np.pi
    elif m == 1:
        cx, cy = hx[0], hy[0]
    while angle >= 0.0:  # into [-90, 0): a quarter turn swaps the sides
        angle -= 90.0
        w, h = h, w
    while angle < -90.0:
        angle += 90.0
        w, h = h, w
    return (
        np.float64(cx),
        np.float64(cy),
        np.float64(w),
        np.float64(h),
        np.float64(np.float32(angle)),
    )


@helper
def _hull_angle(hx: np.ndarray, hy: np.ndarray, m: int, work: np.ndarray) -> float:
    """:func:`_min_area_rect`'s angle of a hull already in ``convexHull``'s order and
    from its start (``m > 2`` float32 vertices; ``work``: (3m,) float32 scratch)."""
    _, _, ux, uy, _, _ = _calipers(hx, hy, m, work)
    angle = np.arctan2(np.float64(uy), np.float64(ux)) * 180.0 / np.pi
    while angle >= 0.0:
        angle -= 90.0
    while angle < -90.0:
        angle += 90.0
    return np.float64(np.float32(angle))


@kernel("int64[::1](int32[:, ::1])")
def convex_hull_ccw(points: np.ndarray) -> np.ndarray:
    """The indices into (N, 2) int32 ``points`` (N >= 1) of ``cv2.convexHull(points,
    clockwise=False)``'s vertices, in its order (:func:`hull_ccw`)."""
    n = points.shape[0]
    out = np.empty(n, np.int64)
    return out[: hull_ccw(points, out, np.empty(5 * n + 4, np.int64))]


@kernel("UniTuple(float64, 5)(int32[:, ::1])")
def min_area_rect(points: np.ndarray) -> tuple[float, float, float, float, float]:
    """``cv2.minAreaRect`` of (N, 2) int32 points, bit for bit: ``(cx, cy, w, h,
    angle)``, each OpenCV's float32 value (see the section's comment)."""
    return _min_area_rect(points)


@kernel(
    _GROWN + "(int32[:, ::1], int32[:, ::1], float64[:, ::1])",
)
def grown_box_of(
    points: np.ndarray, hull: np.ndarray, corners: np.ndarray
) -> tuple[float, float, float, float, float]:
    """:func:`grow_box` of ``points`` with the angle of ``cv2.minAreaRect(hull)``
    (``hull``: those of them that may lie on their hull, N >= 1), the angle turned into
    radians as ``math.radians`` does: ``geometry.grown_box`` in one call."""
    angle = _min_area_rect(hull)[4]
    t = angle * (np.pi / 180.0)
    return grow_box(points, np.cos(t), np.sin(t), angle, corners)


# --- a part's pixels: runs, specks, crop, contours --------------------------------------


def _load8_typed(typingctx: object, arr: types.Array, i: types.Integer) -> tuple[object, object]:
    """The 8 bytes of a C-contiguous uint8 array from flat index ``i``, as one
    little-endian uint64 (an unaligned load; the caller keeps ``i + 8`` within it)."""
    sig = types.uint64(arr, types.int64)

    def codegen(context: Any, builder: ir.IRBuilder, signature: Any, args: list) -> object:
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        ptr = builder.bitcast(builder.gep(ary.data, [args[1]]), ir.IntType(64).as_pointer())
        return builder.load(ptr, align=1)

    return sig, codegen


load8: Any = intrinsic(_load8_typed)


def _load8_bytes_typed(
    typingctx: object, arr: types.Array, i: types.Integer
) -> tuple[object, object]:
    """The 8 bytes of a C-contiguous array (any dtype) from byte offset ``i``."""
    sig = types.uint64(arr, types.int64)

    def codegen(context: Any, builder: ir.IRBuilder, signature: Any, args: list) -> object:
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        base = builder.bitcast(ary.data, ir.IntType(8).as_pointer())
        ptr = builder.bitcast(builder.gep(base, [args[1]]), ir.IntType(64).as_pointer())
        return builder.load(ptr, align=1)

    return sig, codegen


load8_bytes: Any = intrinsic(_load8_bytes_typed)


def _count_zeros_typed(name: str, llvm_name: str, doc: str) -> Any:
    """The typing function of a uint64 intrinsic calling ``llvm_name`` (``llvm.cttz`` or
    ``llvm.ctlz``) with its "zero is poison" flag set: defined for non-zero ``x`` only."""

    def typed(typingctx: object, x: types.Integer) -> tuple[object, object]:
        sig = types.uint64(types.uint64)

        def codegen(context: Any, builder: ir.IRBuilder, signature: Any, args: list) -> object:
            t = ir.IntType(64)
            fnty = ir.FunctionType(t, [t, ir.IntType(1)])
            fn = builder.module.declare_intrinsic(llvm_name, [t], fnty)
            return builder.call(fn, [args[0], ir.Constant(ir.IntType(1), 1)])

        return sig, codegen

    typed.__name__ = typed.__qualname__ = name
    typed.__doc__ = doc
    return typed


_ctz_typed = _count_zeros_typed(
    "_ctz_typed", "llvm.cttz", "Trailing zero bits of a non-zero uint64."
)
ctz: Any = intrinsic(_ctz_typed)


_LOW7 = np.uint64(0x7F7F7F7F7F7F7F7F)
_HIGH = np.uint64(0x8080808080808080)
_ONES = np.uint64(0xFFFFFFFFFFFFFFFF)

_RUNS = "Tuple((int32[::1], int32[::1], int32[::1], int64))"


@kernel("int64(uint8[:, ::1], int32[::1], int32[::1], int32[::1])")
def _mask_runs_into(mask: np.ndarray, ry: np.ndarray, rx0: np.ndarray, rx1: np.ndarray) -> int:
    """:func:`mask_runs` into arrays of a given size; -1 when they are too short."""
    h, w = mask.shape
    cap = ry.shape[0]
    n = 0
    for y in range(h):
        base = y * w
        inside = False
        x = 0
        while x < w:
            if x + 32 <= w:  # 32 pixels passed over at once where none changes
                if inside:
                    a = load8(mask, base + x)
                    b = load8(mask, base + x + 8)
                    c = load8(mask, base + x + 16)
                    d = load8(mask, base + x + 24)
                    if (
                        (((a & _LOW7) + _LOW7) | a)
                        & (((b & _LOW7) + _LOW7) | b)
                        & (((c & _LOW7) + _LOW7) | c)
                        & (((d & _LOW7) + _LOW7) | d)
                        & _HIGH
                    ) == _HIGH:
                        x += 32
                        continue
                elif (
                    load8(mask, base + x)
                    | load8(mask, base + x + 8)
                    | load8(mask, base + x + 16)
                    | load8(mask, base + x + 24)
                ) == 0:
                    x += 32
                    continue
            if x + 8 <= w:
                word = load8(mask, base + x)
                set_ = (((word & _LOW7) + _LOW7) | word) & _HIGH  # bit 7: byte non-zero
                want = _HIGH if inside else np.uint64(0)
                if set_ == want:
                    x += 8
                    continue
                # the first byte that changes: one run starts or ends there
                x += np.int64(ctz(set_ ^ want) >> np.uint64(3))
            elif (mask[y, x] != 0) == inside:
                x += 1
                continue
            if inside:
                rx1[n] = x
                n += 1
            else:
                if n == cap:
                    return -1
                ry[n] = y
                rx0[n] = x
            inside = not inside
            x += 1
        if inside:
            rx1[n] = w
            n += 1
    return n


@kernel(_RUNS + "(uint8[:, ::1])")
def mask_runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The row runs of non-zero pixels in raster order, ``(ry, rx0, rx1, n)``: run ``i <
    n`` covers ``rx0[i] <= x < rx1[i]`` of row ``ry[i]``. Eight pixels at a time: a word
    whose bytes are all zero (outside a run) or all set (inside one) is passed over.
    (Arrays are never reassigned inside a loop here: numba would count references to
    them at every turn, ~30 ns each.)"""
    cap = 2 * mask.shape[0] + 16
    while True:
        ry = np.empty(cap, np.int32)
        rx0 = np.empty(cap, np.int32)
        rx1 = np.empty(cap, np.int32)
        n = _mask_runs_into(mask, ry, rx0, rx1)
        if n >= 0:
            return ry, rx0, rx1, n
        cap = 4 * cap


def _bswap_typed(typingctx: object, x: types.Integer) -> tuple[object, object]:
    """A uint64's bytes in reverse order (``llvm.bswap``)."""
    sig = types.uint64(types.uint64)

    def codegen(context: Any, builder: ir.IRBuilder, signature: Any, args: list) -> object:
        t = ir.IntType(64)
        fn = builder.module.declare_intrinsic("llvm.bswap", [t], ir.FunctionType(t, [t]))
        return builder.call(fn, [args[0]])

    return sig, codegen


bswap: Any = intrinsic(_bswap_typed)


_clz_typed = _count_zeros_typed(
    "_clz_typed", "llvm.ctlz", "Leading zero bits of a non-zero uint64."
)
clz: Any = intrinsic(_clz_typed)


@kernel("int64(uint8[::1], int64, int64, int64, int32[::1], int32[::1], int32[::1])")
def _bits_runs_into(
    bits: np.ndarray, at: int, h: int, w: int, ry: np.ndarray, rx0: np.ndarray, rx1: np.ndarray
) -> int:
    """:func:`bits_runs` into arrays of a given size; -1 when they are too short. Reads
    only the bytes of the mask's bits."""
    cap = ry.shape[0]
    n = 0
    for y in range(h):
        row = at + y * w
        inside = False
        x = 0
        while x < w:
            g = row + x
            if x + 64 <= w:  # 64 pixels passed over at once where none changes
                b = g >> 3
                s = np.uint64(g & 7)
                word = bswap(load8(bits, b))  # pixel g at the top bit
                if s:
                    word = (word << s) | (np.uint64(bits[b + 8]) >> (np.uint64(8) - s))
                diff = word ^ (_ONES if inside else np.uint64(0))
                if diff == 0:
                    x += 64
                    continue
                x += np.int64(clz(diff))  # the first pixel that changes
            else:  # the row's last < 64 pixels: their bytes only, the bits after them 0
                left = w - x
                b = g >> 3
                s = np.uint64(g & 7)
                last = (g + left - 1) >> 3
                word = np.uint64(0)
                for k in range(min(last - b + 1, 8)):
                    word |= np.uint64(bits[b + k]) << np.uint64(56 - 8 * k)
                if s:
                    word <<= s
                    if last == b + 8:
                        word |= np.uint64(bits[b + 8]) >> (np.uint64(8) - s)
                diff = (word ^ (_ONES if inside else np.uint64(0))) & (
                    _ONES << np.uint64(64 - left)
                )
                if diff == 0:
                    x = w
                    continue
                x += np.int64(clz(diff))
            if inside:
                rx1[n] = x
                n += 1
            else:
                if n == cap:
                    return -1
                ry[n] = y
                rx0[n] = x
            inside = not inside
            x += 1
        if inside:
            rx1[n] = w
            n += 1
    return n


@kernel(_RUNS + "(uint8[::1], int64, int64, int64)")
def bits_runs(
    bits: np.ndarray, at: int, h: int, w: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """:func:`mask_runs` of an (h, w) mask read from its packed bits: the ``h * w`` bits
    of ``bits`` from bit ``at`` on (``np.packbits`` of the raveled mask: a byte's most
    significant bit first), 64 pixels at a time, the same runs (a batch's masks as a
    worker sent them, :mod:`mistool.parallel`, read without unpacking them)."""
    cap = 2 * h + 16
    while True:
        ry = np.empty(cap, np.int32)
        rx0 = np.empty(cap, np.int32)
        rx1 = np.empty(cap, np.int32)
        n = _bits_runs_into(bits, at, h, w, ry, rx0, rx1)
        if n >= 0:
            return ry, rx0, rx1, n
        cap = 4 * cap


@kernel("int64(int32[::1], int32[::1], int32[::1], int32[::1], int64, int64)")
def join_runs(
    ry: np.ndarray, rx0: np.ndarray, rx1: np.ndarray, parent: np.ndarray, n: int, reach: int
) -> int:
    """Union-find of ``n`` runs in raster order: runs whose pixels lie within Chebyshev
    distance ``reach`` of each other (1: 8-connected; 3: 8-connected once dilated by a
    3x3 square) share a root, the component's first run (the smallest index).
    ``parent`` gets each run's root; returns the number of components."""
    for i in range(n):
        parent[i] = i
    first = 0  # the first run of the rows within reach above the current one
    for i in range(n):
        y = ry[i]
        while ry[first] < y - reach:
            first += 1
        lo, hi = rx0[i] - reach, rx1[i] - 1 + reach
        for j in range(first, i):  # (the row's own runs too: within reach when it is > 1)
            if rx0[j] <= hi and rx1[j] - 1 >= lo:
                a = i  # the two roots (path halving), the larger joining the smaller
                while parent[a] != a:
                    parent[a] = parent[parent[a]]
                    a = parent[a]
                b = j
                while parent[b] != b:
                    parent[b] = parent[parent[b]]
                    b = parent[b]
                if a < b:
                    parent[b] = a
                elif b < a:
                    parent[a] = b
    count = 0
    for i in range(n):  # every run's root (a root's index is below its members')
        parent[i] = parent[parent[i]]
        count += parent[i] == i
    return count


# chain codes E, NE, N, NW, W, SW, S, SE (OpenCV's), twice: s and s + 8 index the same step
_DX = np.array([1, 1, 0, -1, -1, -1, 0, 1], np.int64)
_DY = np.array([0, -1, -1, -1, 0, 1, 1, 1], np.int64)


def _next_table() -> np.ndarray:
    """``[code * 8 + s]``: the first chain code after ``s`` counter-clockwise (``s + 1``,
    ``s + 2``, ... ``s + 8``, modulo 8) whose bit is set in the neighbourhood ``code``
    (bit ``k``: the neighbour along chain code ``k`` is part of the component); 8 when
    none is."""
    table = np.full(256 * 8, 8, np.uint8)
    for code in range(256):
        for s in range(8):
            for k in range(1, 9):
                if code >> ((s + k) & 7) & 1:
                    table[code * 8 + s] = (s + k) & 7
                    break
    return table


_NEXT = _next_table()


@kernel("int64(boolean[::1], int64, int64, int64, int32[:, ::1], int64)")
def trace_outer(store: np.ndarray, w: int, x0: int, y0: int, points: np.ndarray, n: int) -> int:
    """The outer border of the 8-connected component whose first pixel in raster order
    is ``(x0, y0)``, as ``cv2.findContours(..., CHAIN_APPROX_SIMPLE)`` traces it, in the
    image ``store[1:-1].reshape(-1, w)[1:-1]`` (the rows above and below it and the
    first and last items of ``store`` are background; outside its columns is background
    too): the points where the chain direction changes appended to ``points`` from row
    ``n``; returns the new number of rows, or -1 when ``points`` is full.

    Each step looks up the next chain code in a table of (neighbourhood, code we came
    from): the same answer as OpenCV's search around the pixel, without its branches.
    A neighbourhood is read without bounds checks: the rows above and below are in
    ``store``, and the neighbours left of the first column and right of the last (the
    pixels the flat index wraps to, in ``store`` too) are masked out."""
    flat = store
    cap = points.shape[0]
    if n >= cap:
        return -1
    uw = np.uint64(w)
    one = np.uint64(1)
    step = np.empty(8, np.uint64)  # (unsigned flat indices, wrapping adds: no fix-up)
    for k in range(8):
        step[k] = np.uint64(_DX[k] + _DY[k] * w)
    x3, y3 = x0, y0
    i3 = np.uint64(y0 + 1) * uw + np.uint64(x0 + 1)
    i0 = i3
    i1 = i3  # the first neighbour clockwise from the west, set below
    s = 4
    prev = 0
    first = True
    while True:
        left = np.uint64(x3 > 0)
        right = np.uint64(x3 < w - 1)
        code = (
            (np.uint64(flat[i3 + one]) & right)
            | (np.uint64(flat[i3 + one - uw]) & right) << one
            | np.uint64(flat[i3 - uw]) << np.uint64(2)
            | (np.uint64(flat[i3 - one - uw]) & left) << np.uint64(3)
            | (np.uint64(flat[i3 - one]) & left) << np.uint64(4)
            | (np.uint64(flat[i3 - one + uw]) & left) << np.uint64(5)
            | np.uint64(flat[i3 + uw]) << np.uint64(6)
            | (np.uint64(flat[i3 + one + uw]) & right) << np.uint64(7)
        )
        if first:  # the start pixel (west of it: background)
            first = False
            s = 4
            while True:
                s = (s - 1) & 7
                if (code >> np.uint64(s)) & one or s == 4:
                    break
            if s == 4:  # a single pixel
                points[n, 0] = x0
                points[n, 1] = y0
                return n + 1
            i1 = i0 + step[s]
            prev = s ^ 4
        s = np.int64(_NEXT[code * np.uint64(8) + np.uint64(s)])
        # the point where the direction changes (written always, kept when it does:
        # no branch to mispredict); n < cap here
        points[n, 0] = x3
        points[n, 1] = y3
        n += s != prev
        if n == cap:
            return -1
        prev = s
        i4 = i3 + step[s]
        if i4 == i0 and i3 == i1:
            return n
        i3 = i4
        x3 += _DX[s]
        y3 += _DY[s]
        s = (s + 4) & 7


@kernel(
    "int64(boolean[::1], int64, int32[::1], int32[::1], int32[::1], int64[::1], int64, "
    "int64, int64, int64, int32[:, ::1])"
)
def _trace_kept(
    store: np.ndarray,
    w: int,
    rx0: np.ndarray,
    ry: np.ndarray,
    parent: np.ndarray,
    area: np.ndarray,
    min_area: int,
    n: int,
    x0: int,
    y0: int,
    points: np.ndarray,
) -> int:
    """The outer borders of the kept components (roots with an ``area`` of at least
    ``min_area``; :func:`trace_outer` in ``store``, ``w`` pixels a row, the runs'
    pixels at ``(x - x0, y - y0)``), in reverse raster order as OpenCV gives them, into
    ``points``: their number, or -1 when it is full."""
    m = 0
    for i in range(n - 1, -1, -1):
        if parent[i] == i and area[i] >= min_area:
            m = trace_outer(store, w, rx0[i] - x0, ry[i] - y0, points, m)
            if m < 0:
                return -1
    return m


@kernel("void(int64[::1], int64[::1], boolean[::1], boolean[::1])")
def hull_rows(lo: np.ndarray, hi: np.ndarray, on_lo: np.ndarray, on_hi: np.ndarray) -> None:
    """Which row extremes lie on the convex hull's boundary: ``lo[r]`` / ``hi[r]`` are
    the leftmost / rightmost x of row ``r`` (``lo > hi``: an empty row); ``on_lo`` /
    ``on_hi`` get True for those on the hull's left / right chain, collinear points
    included (a point is dropped only at a strict turn). (The first and last rows'
    other points on the boundary are not marked.)"""
    rows = lo.shape[0]
    stack = np.empty(rows, np.int64)
    for side in (1, -1):  # left chain: drop a point right of it; right chain: the mirror
        ext = lo if side == 1 else hi
        k = 0
        for r in range(rows):
            if lo[r] > hi[r]:
                continue
            while k >= 2:
                o, a = stack[k - 2], stack[k - 1]
                cross = (ext[a] - ext[o]) * (r - o) - (a - o) * (ext[r] - ext[o])
                if side * cross <= 0:
                    break
                k -= 1
            stack[k] = r
            k += 1
        on = on_lo if side == 1 else on_hi
        for t in range(k):
            on[stack[t]] = True


_FIT = "Tuple((UniTuple(int64, 5), boolean[:, ::1], int32[:, ::1], int32[:, ::1]))"


@helper
def _kept_crop(
    ry: np.ndarray, rx0: np.ndarray, rx1: np.ndarray, n: int, min_area: int
) -> tuple[Any, ...]:
    """:func:`fit_runs`' first steps: the runs' 8-connected components (``parent``, each
    root's ``area``), the kept ones' pixels painted in a crop with a background row above
    and below and a pixel before and after (``store``: for the trace; the crop itself is
    a contiguous view of it), their bounds, sums and each row's extremes. Returns
    ``(parent, area, kept, total, x0, y0, kh, kw, store, lo, hi, sx, sy)`` (``kept``:
    how many components are kept; ``total`` 0: none)."""
    parent = np.empty(max(n, 1), np.int32)
    join_runs(ry, rx0, rx1, parent, n, 1)
    area = np.zeros(max(n, 1), np.int64)  # per root
    for i in range(n):
        area[parent[i]] += rx1[i] - rx0[i]
    kept = 0
    total = 0
    x0 = y0 = 1 << 30
    x1 = y1 = -1
    for i in range(n):
        if area[parent[i]] >= min_area:
            kept += parent[i] == i
            total += rx1[i] - rx0[i]
            x0 = min(x0, rx0[i])
            x1 = max(x1, rx1[i])
            y0 = min(y0, ry[i])
            y1 = max(y1, ry[i] + 1)
    kh, kw = max(y1 - y0, 0), max(x1 - x0, 0)
    store = np.zeros((kh + 2) * kw + 2, np.bool_)
    paint = store
    lo = np.empty(kh, np.int64)  # each row's extremes
    hi = np.empty(kh, np.int64)
    for y in range(kh):
        lo[y], hi[y] = 1 << 30, -1
    sx = sy = 0
    for i in range(n):
        if area[parent[i]] >= min_area:
            y = ry[i] - y0
            a, b = rx0[i] - x0, rx1[i] - x0
            row = (y + 1) * kw + 1
            for x in range(np.uint64(row + a), np.uint64(row + b)):  # (unsigned: vectorised)
                paint[x] = True
            sx += (a + b - 1) * (b - a) // 2
            sy += y * (b - a)
            lo[y] = min(lo[y], a)
            hi[y] = max(hi[y], b - 1)
    return parent, area, kept, total, x0, y0, kh, kw, store, lo, hi, sx, sy


@helper
def _traced(
    store: np.ndarray,
    kw: int,
    kh: int,
    rx0: np.ndarray,
    ry: np.ndarray,
    parent: np.ndarray,
    area: np.ndarray,
    min_area: int,
    n: int,
    x0: int,
    y0: int,
    ox: int,
    oy: int,
    lo: np.ndarray,
    hi: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`fit_runs`' ``points`` and ``hull`` from :func:`_kept_crop`'s crop."""
    cap = 4 * n + 16
    m = -1
    while m < 0:  # (a new array per attempt, never inside the loop below: see mask_runs)
        points = np.empty((cap, 2), np.int32)
        m = _trace_kept(store, kw, rx0, ry, parent, area, min_area, n, x0, y0, points)
        cap *= 4
    on_lo = np.zeros(kh, np.bool_)
    on_hi = np.zeros(kh, np.bool_)
    hull_rows(lo, hi, on_lo, on_hi)
    count = 0
    for k in range(m):
        x, y = points[k, 0], points[k, 1]
        count += y == 0 or y == kh - 1 or (x == lo[y] and on_lo[y]) or (x == hi[y] and on_hi[y])
    hull = np.empty((count, 2), np.int32)
    j = 0
    for k in range(m):
        x, y = points[k, 0], points[k, 1]
        points[k, 0] = x + x0 + ox
        points[k, 1] = y + y0 + oy
        if y == 0 or y == kh - 1 or (x == lo[y] and on_lo[y]) or (x == hi[y] and on_hi[y]):
            hull[j, 0] = points[k, 0]
            hull[j, 1] = points[k, 1]
            j += 1
    return points[:m], hull


@kernel(_FIT + "(int32[::1], int32[::1], int32[::1], int64, int64, int64, int64)")
def fit_runs(
    ry: np.ndarray, rx0: np.ndarray, rx1: np.ndarray, n: int, min_area: int, ox: int, oy: int
) -> tuple[tuple[int, int, int, int, int], np.ndarray, np.ndarray, np.ndarray]:
    """A part's pixels given as ``n`` runs in raster order (see :func:`mask_runs`): its
    8-connected components of fewer than ``min_area`` pixels dropped, then

    - ``info``: (area, x0, y0, sum of x - x0, sum of y - y0) of the kept pixels, ``(x0,
      y0)`` the top-left of their bounds (all 0: nothing kept);
    - ``crop``: the kept pixels' (h, w) bool crop at ``(x0, y0)``;
    - ``points``: (N, 2) int32 external contour points of the kept components, in
      ``cv2.findContours``' order (see the module docstring), run coordinates plus
      ``(ox, oy)``;
    - ``hull``: those of ``points`` that may lie on their convex hull's boundary, every
      occurrence, in their order: ``cv2.minAreaRect(hull)`` is ``cv2.minAreaRect(points)``
      bit for bit (``convexHull`` keeps only hull vertices and starts them at the one
      that comes first in its input): the rows' extremes on the hull's boundary
      (:func:`hull_rows`; every hull point is one, since the contours' hull is the
      pixels'), and every point of the first and last rows.
    """
    parent, area, _, total, x0, y0, kh, kw, store, lo, hi, sx, sy = _kept_crop(
        ry, rx0, rx1, n, min_area
    )
    if total == 0:
        empty = np.zeros((0, 2), np.int32)
        return (0, 0, 0, 0, 0), np.zeros((0, 0), np.bool_), empty, empty
    crop = store[kw + 1 : (kh + 1) * kw + 1].reshape(kh, kw)
    points, hull = _traced(
        store, kw, kh, rx0, ry, parent, area, min_area, n, x0, y0, ox, oy, lo, hi
    )
    return (total, x0, y0, sx, sy), crop, points, hull


@kernel(_FIT + "(uint8[:, ::1], int64, int64, int64)")
def fit_mask(
    mask: np.ndarray, min_area: int, ox: int, oy: int
) -> tuple[tuple[int, int, int, int, int], np.ndarray, np.ndarray, np.ndarray]:
    """:func:`fit_runs` of a mask's non-zero pixels (mask coordinates)."""
    ry, rx0, rx1, n = mask_runs(mask)
    return fit_runs(ry, rx0, rx1, n, min_area, ox, oy)


_BOXED = "Tuple((UniTuple(int64, 5), boolean[:, ::1], UniTuple(float64, 5), float64[:, ::1]))"


@helper
def _ring_arcs(store: np.ndarray, kw: int, x: int, y: int) -> int:
    """The runs of part pixels among the 8 neighbours of crop pixel (x, y), walked round
    (:func:`_kept_crop`'s ``store``; outside the crop's columns is background)."""
    arcs = 0
    base = (y + 1) * kw + 1 + x
    last = False
    for k in range(9):  # (the ring from SE round to SE again: the first item's predecessor)
        d = (k + 7) & 7
        xx = x + _DX[d]
        on = 0 <= xx < kw and store[base + _DX[d] + _DY[d] * kw]
        if k > 0 and on and not last:
            arcs += 1
        last = on
    return arcs


@helper
def _row_chains(lo: np.ndarray, hi: np.ndarray, kh: int, hv: np.ndarray) -> int:
    """The strict convex hull of a crop's pixels (row ``y``'s extremes ``lo[y]``,
    ``hi[y]``; ``lo > hi``: an empty row; the first and last rows hold pixels), into
    ``hv`` ((2 kh + 2, 2) at least): its vertices in ``cv2.convexHull(clockwise=False)``'s
    order, the top row's first pixel last (the order in which ``minAreaRect`` sees the
    hull of a single component's contour, whose first point that pixel is: see
    :func:`fit_runs_box`); how many."""
    right = np.empty(kh, np.int64)  # the right chain's rows, top to bottom
    nr = 0
    for r in range(kh):  # pop while the turn is not strictly convex (collinear too)
        if lo[r] > hi[r]:  # (an empty row between components)
            continue
        while nr >= 2:
            o, a = right[nr - 2], right[nr - 1]
            if (hi[a] - hi[o]) * (r - o) - (a - o) * (hi[r] - hi[o]) > 0:
                break
            nr -= 1
        right[nr] = r
        nr += 1
    left = np.empty(kh, np.int64)
    nl = 0
    for r in range(kh):
        if lo[r] > hi[r]:
            continue
        while nl >= 2:
            o, a = left[nl - 2], left[nl - 1]
            if (lo[a] - lo[o]) * (r - o) - (a - o) * (lo[r] - lo[o]) < 0:
                break
            nl -= 1
        left[nl] = r
        nl += 1
    m = 0
    for t in range(0 if hi[0] != lo[0] else 1, nr):  # from the top row's last pixel down
        hv[m, 0], hv[m, 1] = hi[right[t]], right[t]
        m += 1
    bottom = kh - 1
    for t in range(nl - 1 if lo[bottom] != hi[bottom] else nl - 2, -1, -1):  # and up
        hv[m, 0], hv[m, 1] = lo[left[t]], left[t]
        m += 1
    return m


@helper
def _contour_order(
    hv: np.ndarray,
    m: int,
    ry: np.ndarray,
    rx0: np.ndarray,
    rx1: np.ndarray,
    parent: np.ndarray,
    area: np.ndarray,
    min_area: int,
    n: int,
    x0: int,
    y0: int,
    lo: np.ndarray,
    hi: np.ndarray,
) -> int:
    """:func:`_row_chains`' hull of several kept components (``m`` vertices in ``hv``,
    crop coordinates, each passed once by its component's contour) put in the order in
    which ``cv2.convexHull`` gives it for their traced contours (:func:`fit_runs`'
    points), in place; returns the number of vertices (``m``).

    That order depends on where each vertex comes in the contours' points: the
    components in reverse raster order of their first pixels, each contour from its
    first pixel round the component, the other way from ``hv``'s order. Each contour,
    as the hull, passes its vertices in the order of their outward normals, starting at
    its first pixel, where the normals point up (and a little left), as they do at the
    union's first pixel (``hv``'s last vertex). So a vertex's place in its contour is
    its place on the union's hull counted from the union's first pixel in the
    contour's direction, except for a component's own first pixel, always first in its
    contour (its normals on the union's hull may be any of its own: up and right of
    it, it comes last on that count). The vertices listed by (component, place) are in
    the contours' order, and ``convexHull`` (:func:`hull_ccw`) of that list starts and
    turns as it does for the contours (it looks only at the order of its points'
    indices)."""
    kh = lo.shape[0]
    root_lo = np.empty(kh, np.int64)  # the component of each row's first / last pixel
    root_hi = np.empty(kh, np.int64)
    for i in range(n):
        r = parent[i]
        if area[r] >= min_area:
            y = ry[i] - y0
            if rx0[i] - x0 == lo[y]:
                root_lo[y] = r
            if rx1[i] - 1 - x0 == hi[y]:
                root_hi[y] = r
    key = np.empty(m, np.int64)  # (reverse raster order of the root runs, then place)
    for k in range(m):
        x, y = hv[k, 0], hv[k, 1]
        r = root_lo[y] if x == lo[y] else root_hi[y]
        first = x == rx0[r] - x0 and y == ry[r] - y0  # its contour's first point
        key[k] = (n - r) * (m + 1) + (0 if first else m - k)
    pts = np.empty((m, 2), np.int32)  # the vertices in the contours' order
    for k in range(m):  # (insertion sort: the keys are distinct)
        kk = key[k]
        j = k
        while j > 0 and key[j - 1] > kk:
            key[j] = key[j - 1]
            pts[j, 0], pts[j, 1] = pts[j - 1, 0], pts[j - 1, 1]
            j -= 1
        key[j] = kk
        pts[j, 0], pts[j, 1] = hv[k, 0], hv[k, 1]
    idx = np.empty(6 * m + 4, np.int64)
    got = hull_ccw(pts, idx, idx[m:])
    for k in range(got):
        hv[k, 0], hv[k, 1] = pts[idx[k], 0], pts[idx[k], 1]
    return got


@kernel(_BOXED + "(int32[::1], int32[::1], int32[::1], int64, int64, int64, int64)")
def fit_runs_box(
    ry: np.ndarray, rx0: np.ndarray, rx1: np.ndarray, n: int, min_area: int, ox: int, oy: int
) -> tuple[tuple[int, int, int, int, int], np.ndarray, tuple[float, ...], np.ndarray]:
    """:func:`fit_runs` and the part's box in the same call: ``(info, crop, box,
    corners)``, ``box`` the canonical ``(cx, cy, length, width, angle_deg)`` and
    ``corners`` (4, 2) of ``geometry.grown_box(points, hull)`` (all 0: nothing kept).

    One kept component whose hull vertices each have one run of part pixels round them
    (so its outer contour passes each of them once, in the hull's order) needs no
    contour: ``convexHull`` of its contour is its pixels' strict hull starting after its
    first pixel (:func:`_row_chains`, from the rows' extremes); several such components
    need none either, their hull's vertices put in the contours' order
    (:func:`_contour_order`); and the box's sides are
    pushed to the same extremes over the hull's vertices as over the contour's points,
    except for a side at 45 deg (``minAreaRect``'s angle -45: there the rounded
    projections of a side's points tie within an ulp, and a point the contour leaves
    out can round farther): that box, and every other part, is fitted from the traced
    contour (tests/test_instances_speed.py compares both ways)."""
    parent, area, kept, total, x0, y0, kh, kw, store, lo, hi, sx, sy = _kept_crop(
        ry, rx0, rx1, n, min_area
    )
    corners = np.zeros((4, 2))
    if total == 0:
        empty = np.zeros((0, 0), np.bool_)
        return (0, 0, 0, 0, 0), empty, (0.0, 0.0, 0.0, 0.0, 0.0), corners
    info = (total, x0, y0, sx, sy)
    crop = store[kw + 1 : (kh + 1) * kw + 1].reshape(kh, kw)
    if kept >= 1:
        hv = np.empty((2 * kh + 2, 2), np.int32)
        m = _row_chains(lo, hi, kh, hv)
        safe = m >= 3
        for k in range(m):
            if safe and _ring_arcs(store, kw, hv[k, 0], hv[k, 1]) != 1:
                safe = False
        if safe and kept > 1:
            m = _contour_order(hv, m, ry, rx0, rx1, parent, area, min_area, n, x0, y0, lo, hi)
        if safe:
            work = np.empty(5 * m, np.float32)  # the hull's points, the calipers' scratch
            hx = work[:m]
            hy = work[m : 2 * m]
            for k in range(m):
                hv[k, 0] += x0 + ox
                hv[k, 1] += y0 + oy
                hx[k] = np.float32(hv[k, 0])
                hy[k] = np.float32(hv[k, 1])
            angle = _hull_angle(hx, hy, m, work[2 * m :])
            if angle != -45.0:
                t = angle * (np.pi / 180.0)
                box = grow_box(hv[:m], np.cos(t), np.sin(t), angle, corners)
                return info, crop, box, corners
    points, hull = _traced(
        store, kw, kh, rx0, ry, parent, area, min_area, n, x0, y0, ox, oy, lo, hi
    )
    return info, crop, grown_box_of(points, hull, corners), corners
