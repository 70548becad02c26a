"""The crossing split's inner loops (:mod:`mistool.tracking.split`): distances of points to
shaft segments, the nearest segment of each point, the refit of the shaft axes and its
score.

Segment ``k`` runs from ``ends[k]`` back along ``-dirs[k]`` for ``back[k]`` px (``inf``:
a half-line from the image border); distances are squared, in units of ``radius[k]``.

Each kernel gives the bits of the numpy code it replaces, so it adds and multiplies in
the order numpy and OpenBLAS do, and fuses a multiply-add where they do (``fma``: one
rounding). Measured on this project's numpy (2.4, OpenBLAS 0.3.31, x86-64 with FMA), each
against numpy on random inputs (``tests/test_split_speed.py``, with the kernels against
the former numpy definitions):

- ``a @ b`` of two contiguous float64 2-vectors (``ddot``, fewer than 16 elements): one
  multiply-add per element from 0, ``fma(a1, b1, fma(a0, b0, 0))`` (:func:`dot2`);
- ``a[:, 0] @ a[:, 1]`` (strided ``ddot``) of at most :data:`DOT_SERIAL_MAX` elements:
  blocks of four products summed ``t1 += m0 + m2; t2 += m1 + m3`` (no fusing), the tail
  fused into ``t1``, then ``t1 + t2`` (:func:`dot_strided`; longer ones OpenBLAS splits
  between its threads);
- ``(2K, 2) @ (2, N)`` (``dgemm``) with ``N >= 2``: ``fma(f1, y, f0 * x)``; with ``N == 1``
  and ``(N, 2) @ (2,)`` (``dgemv``): ``fma(f0, x, f1 * y)`` (:func:`row_dot`);
- ``np.add.reduce`` of a contiguous 1-D array (``sum``, ``mean``): pairwise summation
  (:func:`pairwise_sum`); over the first axis of an (N, 2) array: in order from 0.

A machine whose OpenBLAS picks other kernels (no FMA) gives other bits in numpy itself;
the tests say so there. (These helpers live in this one module: numba's disk cache of a
kernel is renewed when its own file changes, not when a module it calls into does.)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import cast

import numpy as np
from numba.core import types
from numba.extending import intrinsic

from mistool.kernels import helper, kernel
from mistool.kernels.boxes import ctz, load8, mask_runs

__all__ = [
    "DOT_SERIAL_MAX",
    "dot2",
    "dot_strided",
    "nearest_labels",
    "pairwise_sum",
    "refit_axes",
    "row_dot",
    "score_axes",
    "segment_d2_rows",
]

# numpy's and OpenBLAS's float operations -----------------------------------------------

#: OpenBLAS computes a dot product of at most this many elements in one thread (longer:
#: partial sums per thread, which :func:`dot_strided` does not reproduce).
DOT_SERIAL_MAX = 10_000


@intrinsic
def _fma(typingctx, a, b, c):  # type: ignore[no-untyped-def]  # (numba's intrinsic protocol)
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        return builder.fma(*args)  # llvm.fma.f64

    return sig, codegen


#: ``fma(a, b, c)``: ``a * b + c`` with one rounding, inside kernels.
fma = cast(Callable[[float, float, float], float], _fma)


@helper
def dot2(a0: float, a1: float, b0: float, b1: float) -> float:
    """``np.array([a0, a1]) @ np.array([b0, b1])`` (contiguous ``ddot``)."""
    return fma(a1, b1, fma(a0, b0, 0.0))


@helper
def row_dot(f0: float, f1: float, x: float, y: float, single: bool) -> float:
    """One element of ``frame @ p.T`` (frame row ``(f0, f1)``, point ``(x, y)``):
    ``dgemm``'s order, or ``dgemv``'s when ``single`` (one point, or ``(N, 2) @ (2,)``)."""
    if single:
        return fma(f0, x, f1 * y)
    return fma(f1, y, f0 * x)


@kernel("float64(float64[:], float64[:])")
def dot_strided(x: np.ndarray, y: np.ndarray) -> float:
    """``x @ y`` of two strided float64 vectors of one length, at most
    :data:`DOT_SERIAL_MAX` (OpenBLAS's strided ``ddot``)."""
    n = x.shape[0]
    t1 = 0.0
    t2 = 0.0
    n4 = n & -4
    i = 0
    while i < n4:
        m1 = y[i] * x[i]
        m2 = y[i + 1] * x[i + 1]
        m3 = y[i + 2] * x[i + 2]
        m4 = y[i + 3] * x[i + 3]
        t1 += m1 + m3
        t2 += m2 + m4
        i += 4
    while i < n:
        t1 = fma(y[i], x[i], t1)
        i += 1
    return t1 + t2


@helper
def _pairwise_block(a: np.ndarray, lo: int, n: int) -> float:
    """numpy's pairwise summation of ``a[lo : lo + n]`` for ``n <= 128`` (one block)."""
    if n < 8:
        res = -0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    stop = n - n % 8
    while i < stop:
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@helper
def _pairwise(a: np.ndarray, lo: int, n: int) -> float:
    """numpy's pairwise summation of ``a[lo : lo + n]``: blocks of at most 128 summed by
    :func:`_pairwise_block`, a longer range split at half its length (rounded down to a
    multiple of 8) and its halves' sums added. Written with an explicit stack, not as
    the recursion it is: numba cannot cache a function that calls itself (its machine
    code loaded from the cache then has an unresolved symbol: numba issue 6061, an
    "LLVM ERROR: Symbol not found" or a segmentation fault, depending on the order in
    which a process first compiled the kernels)."""
    if n <= 128:
        return _pairwise_block(a, lo, n)
    # each level halves the range: 64 levels hold any int64 length
    los = np.empty(64, np.int64)
    ns = np.empty(64, np.int64)
    stage = np.empty(64, np.int64)  # 0: left half next, 1: right half next, 2: both done
    left = np.empty(64, np.float64)  # the left half's sum, once known
    los[0], ns[0], stage[0] = lo, n, 0
    top = 0
    ret = 0.0  # the sum of the range just finished
    while True:
        m = ns[top]
        half = m // 2
        half -= half % 8
        if stage[top] == 0:
            stage[top] = 1
            child_lo, child_n = los[top], half
        elif stage[top] == 1:
            left[top] = ret
            stage[top] = 2
            child_lo, child_n = los[top] + half, m - half
        else:
            ret = left[top] + ret
            if top == 0:
                return ret
            top -= 1
            continue
        if child_n <= 128:
            ret = _pairwise_block(a, child_lo, child_n)
        else:
            top += 1
            los[top], ns[top], stage[top] = child_lo, child_n, 0


@kernel("float64(float64[::1], int64)")
def pairwise_sum(a: np.ndarray, n: int) -> float:
    """``np.add.reduce(a[:n])`` of a contiguous float64 array (numpy's pairwise
    summation, from 0)."""
    return 0.0 + _pairwise(a, 0, n)


# the split -------------------------------------------------------------------------------

_SEGMENTS = (
    "float64[:, ::1], float64[:, ::1], float64[::1], float64[::1]"  # ends, dirs, back, radius
)


@kernel(f"float64[:, ::1]({_SEGMENTS})")
def _frames(ends: np.ndarray, dirs: np.ndarray, back: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """(K, 6) per segment, what every point's distance uses: its direction ``(dx, dy)``,
    the offsets along and across it (``ends . (dx, dy)`` and ``ends . (-dy, dx)`` summed
    in plain floats, as ``split.segment_d2_rows`` did), ``back`` (NaN: none, not finite),
    ``1 / radius^2``."""
    kk = ends.shape[0]
    seg = np.empty((kk, 6), np.float64)
    for k in range(kk):
        dx, dy = dirs[k, 0], dirs[k, 1]
        ex, ey = ends[k, 0], ends[k, 1]
        seg[k, 0] = dx
        seg[k, 1] = dy
        seg[k, 2] = ex * dx + ey * dy
        seg[k, 3] = ex * -dy + ey * dx
        seg[k, 4] = back[k] if math.isfinite(back[k]) else math.nan
        r = radius[k]
        seg[k, 5] = 1.0 / (r * r)
    return seg


@helper
def _d2(x: float, y: float, seg: np.ndarray, k: int, single: bool) -> float:
    """Point (x, y)'s squared distance to segment ``k`` (``seg``: :func:`_frames`), as
    ``split.segment_d2_rows`` computed it: the coordinates along and across by ``dgemm``
    (``single``: one point, ``dgemv``'s order), less the offsets; the excess past the
    distal end and behind the proximal one (``np.maximum(v, 0.0)``: NaN kept)."""
    dx, dy = seg[k, 0], seg[k, 1]
    along = row_dot(dx, dy, x, y, single) - seg[k, 2]
    perp = row_dot(-dy, dx, x, y, single) - seg[k, 3]
    excess = along if (along >= 0.0 or along != along) else 0.0
    b = seg[k, 4]
    if b == b:
        behind = -along - b
        excess += behind if (behind >= 0.0 or behind != behind) else 0.0
    d2 = perp * perp
    d2 += excess * excess
    d2 *= seg[k, 5]
    return d2


@kernel("Tuple((float64[::1], float64[::1]))(float64[:, ::1])")
def _columns(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The x and y columns of points (N, 2), each contiguous: loops over them become
    vector code, over the interleaved pairs they do not (5x slower)."""
    n = p.shape[0]
    xs = np.empty(n, np.float64)
    ys = np.empty(n, np.float64)
    for i in range(n):
        xs[i] = p[i, 0]
        ys[i] = p[i, 1]
    return xs, ys


@kernel(f"void(float64[:, ::1], {_SEGMENTS}, float64[:, ::1])")
def segment_d2_rows(
    p: np.ndarray,
    ends: np.ndarray,
    dirs: np.ndarray,
    back: np.ndarray,
    radius: np.ndarray,
    out: np.ndarray,
) -> None:
    """``out`` (K, N): squared distances of points ``p`` (N, 2) to the K segments."""
    n = p.shape[0]
    single = n == 1
    seg = _frames(ends, dirs, back, radius)
    xs, ys = _columns(p)
    for k in range(ends.shape[0]):
        for i in range(n):
            out[k, i] = _d2(xs[i], ys[i], seg, k, single)


@helper
def _label(x: float, y: float, seg: np.ndarray, keep_d2: float, keep: bool, single: bool) -> int:
    """The nearest segment's index (``split._Axes.nearest``): for two segments without
    ``keep``, 1 where the second is strictly nearer; else ``argmin`` (the first of equal
    minima, the first NaN); with ``keep``, K where the least distance (NaN if any) is
    above ``keep_d2``."""
    kk = seg.shape[0]
    d0 = _d2(x, y, seg, 0, single)
    if kk == 2 and not keep:
        return 1 if _d2(x, y, seg, 1, single) < d0 else 0
    lab = 0
    best = d0
    least = d0  # np.minimum.reduce: NaN spreads
    nan_at = 0 if d0 != d0 else -1
    for k in range(1, kk):
        d = _d2(x, y, seg, k, single)
        if d != d and nan_at < 0:
            nan_at = k
        if d < best:
            best = d
            lab = k
        if not (least <= d or least != least):
            least = d
    if nan_at >= 0:
        lab = nan_at
    if keep and least > keep_d2:
        lab = kk
    return lab


@kernel(
    "void(float64[::1], float64[::1], float64[:, ::1], float64, boolean, boolean, int64[::1])",
    "void(float64[::1], float64[::1], float64[:, ::1], float64, boolean, boolean, uint8[::1])",
)
def _labels(
    xs: np.ndarray,
    ys: np.ndarray,
    seg: np.ndarray,
    keep_d2: float,
    keep: bool,
    single: bool,
    out: np.ndarray,
) -> None:
    """``out`` (N,): :func:`_label` of each point (``xs``, ``ys``); two segments without
    ``keep`` in one loop without branches (vector code). (uint8 ``out``: at most 255
    segments.)"""
    n = xs.shape[0]
    if seg.shape[0] == 2 and not keep:
        for i in range(n):
            out[i] = _d2(xs[i], ys[i], seg, 1, single) < _d2(xs[i], ys[i], seg, 0, single)
        return
    for i in range(n):
        out[i] = _label(xs[i], ys[i], seg, keep_d2, keep, single)


@kernel(f"void(float64[:, ::1], {_SEGMENTS}, float64, boolean, int64[::1])")
def nearest_labels(
    p: np.ndarray,
    ends: np.ndarray,
    dirs: np.ndarray,
    back: np.ndarray,
    radius: np.ndarray,
    keep_d2: float,
    keep: bool,
    out: np.ndarray,
) -> None:
    """``out`` (N,): each point's nearest segment (``split._Axes.nearest``; K beyond
    ``keep_d2`` from all, when ``keep``)."""
    xs, ys = _columns(p)
    _labels(xs, ys, _frames(ends, dirs, back, radius), keep_d2, keep, p.shape[0] == 1, out)


@helper
def _own_reach(lab: np.ndarray, j: int, shared: np.ndarray, proj: np.ndarray) -> float:
    """The largest ``proj`` (over the points labelled ``j``, in order) of a point not
    ``shared``; -inf when every one is."""
    own = -math.inf
    k = 0
    for i in range(lab.shape[0]):
        if lab[i] == j:
            if not shared[i] and proj[k] > own:
                own = proj[k]
            k += 1
    return own


@kernel(
    "boolean(float64[:, ::1], int64[::1], int64, float64[:, ::1], float64[::1],"
    " float64[:, ::1], float64[:, ::1], float64[::1], float64[:, ::1], float64[:, ::1],"
    " float64[::1], int64, int64, boolean, float64, float64, boolean[::1], float64)"
)
def _refit_axis(
    pts: np.ndarray,
    lab: np.ndarray,
    j: int,
    q: np.ndarray,
    proj: np.ndarray,
    ends: np.ndarray,
    dirs: np.ndarray,
    radius: np.ndarray,
    limit_end: np.ndarray,
    start_dirs: np.ndarray,
    margin: np.ndarray,
    weight: int,
    min_area: int,
    contiguous: bool,
    turn_cos: float,
    gap_radii: float,
    shared: np.ndarray,
    cut_radii: float,
) -> bool:
    """Axis ``j`` refitted to the points labelled ``j`` (one round of
    :func:`refit_axes`; ``q``, ``proj``: work space; ``shared`` (N,) or empty: points
    lying in another shaft's band, whose reach counts only within ``cut_radii`` radii of
    the others'); False when they are too few."""
    n = pts.shape[0]
    m = 0
    sx = 0.0
    sy = 0.0
    for i in range(n):  # q = pts[lab == j], c = np.add.reduce(q, 0) / len(q)
        if lab[i] == j:
            q[m, 0] = pts[i, 0]
            q[m, 1] = pts[i, 1]
            sx += pts[i, 0]
            sy += pts[i, 1]
            m += 1
    if m < 3 or m * weight < min_area:
        return False
    cx = sx / m
    cy = sy / m
    for i in range(m):  # r = q - c
        q[i, 0] -= cx
        q[i, 1] -= cy
    r = q[:m]
    sxx = dot_strided(r[:, 0], r[:, 0])
    syy = dot_strided(r[:, 1], r[:, 1])
    sxy = dot_strided(r[:, 0], r[:, 1])
    t = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
    d0, d1 = math.cos(t), math.sin(t)
    if abs(dot2(d0, d1, start_dirs[j, 0], start_dirs[j, 1])) >= turn_cos:
        if dot2(d0, d1, dirs[j, 0], dirs[j, 1]) >= 0:
            dirs[j, 0], dirs[j, 1] = d0, d1
        else:
            dirs[j, 0], dirs[j, 1] = -d0, -d1
    u0, u1 = dirs[j, 0], dirs[j, 1]
    mj = margin[j]
    limit = dot2(limit_end[j, 0] + mj * u0 - cx, limit_end[j, 1] + mj * u1 - cy, u0, u1)
    for i in range(m):
        proj[i] = row_dot(r[i, 0], r[i, 1], u0, u1, True)  # r @ u (dgemv)
    reach = proj[0]
    for i in range(1, m):  # proj.max(): NaN spreads
        pi = proj[i]
        if reach == reach and (pi > reach or pi != pi):
            reach = pi
    if shared.shape[0]:  # the reach of its points in no other shaft's band, if any
        own = _own_reach(lab, j, shared, proj)
        if own > -math.inf and reach - own > cut_radii * radius[j]:
            reach = own
    if contiguous:  # up to the first gap along the axis
        sp = np.sort(proj[:m])
        gap = gap_radii * radius[j]
        for i in range(m - 1):
            if sp[i + 1] - sp[i] > gap:
                reach = sp[i]
                break
    s = limit if limit < reach else reach  # min(reach, limit)
    ends[j, 0] = cx + s * u0
    ends[j, 1] = cy + s * u1
    return True


@helper
def _passes(
    xs: np.ndarray,
    ys: np.ndarray,
    seg: np.ndarray,
    lab: np.ndarray,
    single: bool,
    through_radii: float,
    radius: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    shared: np.ndarray,
) -> None:
    """``shared[i]``: point ``i``, labelled ``j``, lies within the radius of another axis
    ``k`` and behind its distal end, where ``k``'s shaft passes through ``j``'s line: the
    points labelled ``k`` reach farther than ``through_radii`` radii of ``j`` on both
    sides of it (``lo``, ``hi`` (K, K): work space, the extent of ``k``'s points across
    ``j``'s line). A shaft ending at another's line (a V) does not pass through it."""
    kk = seg.shape[0]
    n = xs.shape[0]
    for j in range(kk):
        for k in range(kk):
            lo[j, k] = 0.0
            hi[j, k] = 0.0
    for i in range(n):
        k = lab[i]
        if k < kk:
            for j in range(kk):
                if j != k:
                    perp = row_dot(-seg[j, 1], seg[j, 0], xs[i], ys[i], single) - seg[j, 3]
                    lo[j, k] = min(lo[j, k], perp)
                    hi[j, k] = max(hi[j, k], perp)
    for i in range(n):
        j = lab[i]
        s = False
        if j < kk:
            thr = through_radii * radius[j]
            for k in range(kk):
                if k != j and lo[j, k] < -thr and hi[j, k] > thr:
                    if _d2(xs[i], ys[i], seg, k, single) < 1.0:
                        along = row_dot(seg[k, 0], seg[k, 1], xs[i], ys[i], single) - seg[k, 2]
                        s = s or along < 0.0
        shared[i] = s


@kernel(
    f"boolean(float64[:, ::1], {_SEGMENTS}, float64[:, ::1], float64[:, ::1], float64[::1],"
    " float64, boolean, int64, int64, boolean, int64, float64, float64, float64, float64)"
)
def refit_axes(
    pts: np.ndarray,
    ends: np.ndarray,
    dirs: np.ndarray,
    back: np.ndarray,
    radius: np.ndarray,
    limit_end: np.ndarray,
    start_dirs: np.ndarray,
    margin: np.ndarray,
    keep_d2: float,
    keep: bool,
    weight: int,
    min_area: int,
    contiguous: bool,
    rounds: int,
    turn_cos: float,
    gap_radii: float,
    through_radii: float,
    cut_radii: float,
) -> bool:
    """``split._refit``: rounds of nearest axis, then each axis refitted to its points
    (direction: the 2x2 principal axis, unless it turns past ``turn_cos`` from
    ``start_dirs``; distal end: the points' reach, at most ``limit_end + margin``; when
    ``contiguous``, up to the first gap of ``gap_radii`` radii along the axis), until no
    point changes axis; ``ends`` and ``dirs`` updated in place. False when an axis keeps
    fewer than 3 points or ``weight`` x its points < ``min_area``. At most
    :data:`DOT_SERIAL_MAX` points.

    ``through_radii`` > 0: where another shaft passes through an axis's line (its points
    lie on both sides of the line, farther than ``through_radii`` of the axis's radii),
    the axis's points in that shaft's band (within its radius) behind its distal end
    extend the axis's reach by at most ``cut_radii`` of its radii (:func:`_passes`)."""
    n = pts.shape[0]
    single = n == 1
    lab = np.empty(n, np.int64)
    prev = np.empty(n, np.int64)
    q = np.empty((n, 2), np.float64)
    proj = np.empty(n, np.float64)
    xs, ys = _columns(pts)
    kk = ends.shape[0]
    through = through_radii > 0.0
    shared = np.zeros(n if through else 0, np.bool_)
    lo = np.empty((kk, kk) if through else (0, 0), np.float64)
    hi = np.empty_like(lo)
    for rnd in range(rounds):
        seg = _frames(ends, dirs, back, radius)
        _labels(xs, ys, seg, keep_d2, keep, single, lab)
        same = rnd > 0
        for i in range(n):
            same = same and lab[i] == prev[i]
        if same:
            break  # the same points give the same axes: converged
        for i in range(n):
            prev[i] = lab[i]
        if through:
            _passes(xs, ys, seg, lab, single, through_radii, radius, lo, hi, shared)
        for j in range(kk):
            if not _refit_axis(
                pts, lab, j, q, proj, ends, dirs, radius, limit_end, start_dirs, margin,
                weight, min_area, contiguous, turn_cos, gap_radii, shared, cut_radii,
            ):  # fmt: skip
                return False
    return True


@kernel("boolean(float64[:, ::1], float64[:, ::1], float64[::1], int64, int64, float64)")
def _side_by_side(
    ends: np.ndarray, dirs: np.ndarray, radius: np.ndarray, i: int, j: int, min_angle_deg: float
) -> bool:
    """``split._side_by_side``."""
    cos = dot2(dirs[i, 0], dirs[i, 1], dirs[j, 0], dirs[j, 1])
    a = abs(cos)
    if math.degrees(math.acos(a if a < 1.0 else 1.0)) >= min_angle_deg:
        return False
    if cos > 0:
        return True
    u0, u1 = dirs[i, 0], dirs[i, 1]
    hi_i = dot2(ends[i, 0], ends[i, 1], u0, u1)
    lo_j = dot2(ends[j, 0], ends[j, 1], u0, u1)
    return hi_i - lo_j > radius[i] + radius[j]


@helper
def _argmin_column(d2: np.ndarray, i: int, keep_d2: float, keep: bool) -> int:
    """``d2[:, i].argmin()`` (the first of equal minima, the first NaN; ``split.argmin_rows``);
    with ``keep``, K where the least (NaN if any) is above ``keep_d2``."""
    kk = d2.shape[0]
    best = d2[0, i]
    least = best
    lab = 0
    nan_at = 0 if best != best else -1
    for k in range(1, kk):
        d = d2[k, i]
        if d != d and nan_at < 0:
            nan_at = k
        if d < best:
            best = d
            lab = k
        if not (least <= d or least != least):  # np.minimum.reduce
            least = d
    if nan_at >= 0:
        lab = nan_at
    if keep and least > keep_d2:
        lab = kk
    return lab


@kernel("void(float64[:, ::1], float64, boolean, int64[::1])")
def _argmins(d2: np.ndarray, keep_d2: float, keep: bool, out: np.ndarray) -> None:
    """``out`` (N,): :func:`_argmin_column` of every column of ``d2`` (K, N); two rows
    without ``keep`` in one loop without branches (vector code)."""
    n = d2.shape[1]
    if d2.shape[0] == 2 and not keep:
        for i in range(n):
            d0 = d2[0, i]
            d1 = d2[1, i]
            out[i] = ((d1 < d0) or (d1 != d1)) and d0 == d0
        return
    for i in range(n):
        out[i] = _argmin_column(d2, i, keep_d2, keep)


@kernel(f"float64(float64[:, ::1], {_SEGMENTS}, float64, boolean, float64, float64)")
def score_axes(
    pts: np.ndarray,
    ends: np.ndarray,
    dirs: np.ndarray,
    back: np.ndarray,
    radius: np.ndarray,
    keep_d2: float,
    keep: bool,
    max_spread: float,
    min_angle_deg: float,
) -> float:
    """``split._score``: the worst RMS distance of an axis's points to it (radii), or -1
    when one is above ``max_spread + 0.5 / radius`` or two axes are near parallel
    (``min_angle_deg``) side by side."""
    n = pts.shape[0]
    kk = ends.shape[0]
    d2 = np.empty((kk, n), np.float64)
    segment_d2_rows(pts, ends, dirs, back, radius, d2)
    lab = np.empty(n, np.int64)
    _argmins(d2, keep_d2, keep, lab)
    score = 0.0
    mine = np.empty(n, np.float64)
    for j in range(kk):
        m = 0
        for i in range(n):
            if lab[i] == j:
                mine[m] = d2[j, i]
                m += 1
        rms = math.sqrt(pairwise_sum(mine, m) / m) if m else math.nan  # (mean of none)
        if rms > max_spread + 0.5 / radius[j]:
            return -1.0
        if rms > score:  # max(score, rms)
            score = rms
    for i in range(kk):
        for j in range(i + 1, kk):
            if _side_by_side(ends, dirs, radius, i, j, min_angle_deg):
                return -1.0
    return score


# the split's pixels ----------------------------------------------------------------------


@kernel("boolean[:, ::1](uint8[:, ::1])")
def _mixed_cells(coarse: np.ndarray) -> np.ndarray:
    """(ch, cw): whether each cell's 3 x 3 neighbourhood holds two labels (``cv2.dilate
    != cv2.erode`` of the cells' labels, the image border left out); separable: the
    least and greatest along rows, then along columns."""
    ch, cw = coarse.shape
    lo = np.empty((ch, cw), np.uint8)
    hi = np.empty((ch, cw), np.uint8)
    for ci in range(ch):
        for cj in range(cw):
            a = b = coarse[ci, cj]
            if cj > 0:
                a = min(a, coarse[ci, cj - 1])
                b = max(b, coarse[ci, cj - 1])
            if cj + 1 < cw:
                a = min(a, coarse[ci, cj + 1])
                b = max(b, coarse[ci, cj + 1])
            lo[ci, cj] = a
            hi[ci, cj] = b
    mixed = np.empty((ch, cw), np.bool_)
    for ci in range(ch):
        r0, r1 = max(ci - 1, 0), min(ci + 1, ch - 1)
        for cj in range(cw):
            a = min(lo[r0, cj], lo[ci, cj], lo[r1, cj])
            b = max(hi[r0, cj], hi[ci, cj], hi[r1, cj])
            mixed[ci, cj] = a != b
    return mixed


@helper
def _emit(
    j: int,
    y: int,
    a: int,
    b: int,
    out_y: np.ndarray,
    out_a: np.ndarray,
    out_b: np.ndarray,
    got: np.ndarray,
) -> bool:
    """Run ``a <= x < b`` of row ``y`` appended to label ``j``'s (none beyond ``nlab``);
    False when its arrays are full."""
    if j >= out_y.shape[0]:
        return True
    k = got[j]
    if k == out_y.shape[1]:
        return False
    out_y[j, k] = y
    out_a[j, k] = a
    out_b[j, k] = b
    got[j] = k + 1
    return True


@kernel(
    f"void(float64[::1], float64[::1], {_SEGMENTS}, int64[::1], float64[:, ::1], boolean[::1],"
    " int64[::1])"
)
def head_labels(
    px: np.ndarray,
    py: np.ndarray,
    ends: np.ndarray,
    dirs: np.ndarray,
    back: np.ndarray,
    radius: np.ndarray,
    row: np.ndarray,
    centres: np.ndarray,
    is_centre: np.ndarray,
    out: np.ndarray,
) -> None:
    """``out`` (N,): the nearest of R heads of each of a head part's N pixels (``px``,
    ``py``; all of them: one alone takes ``dgemv``'s one-point order), as
    ``split.split_with_heads`` computed it in numpy: head ``r``'s distance is the least
    (``np.minimum``, NaN spreading) over the segments ``s`` with ``row[s] == r``, in
    their order, or, where ``is_centre[r]``, ``|p - c|^2 / rr`` with ``(cx, cy, rr) =
    centres[r]`` (``np.einsum``: ``dx * dx + dy * dy``); the nearest is the first of
    equal least distances, the first NaN (``split.argmin_rows``). Each segment's
    distances over all the pixels in one loop (vector code)."""
    nrow = is_centre.shape[0]
    count = px.shape[0]
    single = count == 1
    seg = _frames(ends, dirs, back, radius)
    d2 = np.empty((nrow, count), np.float64)
    taken = np.zeros(nrow, np.bool_)
    for k in range(row.shape[0]):
        r = row[k]
        if not taken[r]:
            for i in range(count):
                d2[r, i] = _d2(px[i], py[i], seg, k, single)
            taken[r] = True
            continue
        for i in range(count):
            d = _d2(px[i], py[i], seg, k, single)
            v = d2[r, i]
            d2[r, i] = v if (v <= d or v != v) else d  # np.minimum(v, d)
    for r in range(nrow):
        if is_centre[r]:
            cx, cy, rr = centres[r, 0], centres[r, 1], centres[r, 2]
            for i in range(count):
                dx = px[i] - cx
                dy = py[i] - cy
                d2[r, i] = (dx * dx + dy * dy) / rr
    _argmins(d2, 0.0, False, out)


@kernel(
    "Tuple((float64[::1], float64[::1]))(int32[::1], int32[::1], int32[::1], int64, int64, int64)"
)
def run_pixels(
    ry: np.ndarray, rx0: np.ndarray, rx1: np.ndarray, n: int, x0: int, y0: int
) -> tuple[np.ndarray, np.ndarray]:
    """The full-image x and y of every pixel of ``n`` row runs (a crop at (x0, y0)), in
    the runs' order."""
    count = 0
    for i in range(n):
        count += rx1[i] - rx0[i]
    px = np.empty(count, np.float64)
    py = np.empty(count, np.float64)
    m = 0
    for i in range(n):
        y = ry[i] + y0
        for x in range(rx0[i], rx1[i]):
            px[m] = x + x0
            py[m] = y
            m += 1
    return px, py


@kernel(
    "boolean(int32[::1], int32[::1], int32[::1], int64, int64[::1], int32[:, ::1], int32[:, ::1],"
    " int32[:, ::1], int64[::1])"
)
def _cut_by_pixel(
    ry: np.ndarray,
    rx0: np.ndarray,
    rx1: np.ndarray,
    n: int,
    lab: np.ndarray,
    out_y: np.ndarray,
    out_a: np.ndarray,
    out_b: np.ndarray,
    got: np.ndarray,
) -> bool:
    """``n`` row runs cut where their pixels' labels (``lab``, in the runs' order)
    change; False when the outputs are too short."""
    m = 0
    for i in range(n):
        a, b = np.int64(rx0[i]), np.int64(rx1[i])
        start = a
        for x in range(a + 1, b + 1):
            if x == b or lab[m + x - a] != lab[m + start - a]:
                if not _emit(lab[m + start - a], ry[i], start, x, out_y, out_a, out_b, got):
                    return False
                start = x
        m += b - a
    return True


@kernel(
    "Tuple((int32[:, ::1], int32[:, ::1], int32[:, ::1], int64[::1]))(int32[::1], int32[::1],"
    " int32[::1], int64, int64[::1], int64)"
)
def cut_runs(
    ry: np.ndarray, rx0: np.ndarray, rx1: np.ndarray, n: int, lab: np.ndarray, nlab: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The row runs of each label ``j < nlab`` of ``n`` row runs whose pixels carry the
    labels ``lab`` (in the runs' order): maximal, in raster order (:func:`label_runs` of
    the label image they paint)."""
    cap = n + 1
    for i in range(lab.shape[0] - 1):
        cap += lab[i] != lab[i + 1]
    got = np.zeros(nlab, np.int64)
    out_y = np.empty((nlab, cap), np.int32)
    out_a = np.empty((nlab, cap), np.int32)
    out_b = np.empty((nlab, cap), np.int32)
    _cut_by_pixel(ry, rx0, rx1, n, lab, out_y, out_a, out_b, got)
    return out_y, out_a, out_b, got


_CUT = "Tuple((int32[:, ::1], int32[:, ::1], int32[:, ::1], int64[::1]))"


@kernel(
    f"{_CUT}(uint8[:, ::1], int64, int64, {_SEGMENTS}, int64[::1], float64[:, ::1], boolean[::1],"
    " int64)"
)
def head_cut_runs(
    mask: np.ndarray,
    x0: int,
    y0: int,
    ends: np.ndarray,
    dirs: np.ndarray,
    back: np.ndarray,
    radius: np.ndarray,
    row: np.ndarray,
    centres: np.ndarray,
    is_centre: np.ndarray,
    nlab: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A head part's pieces in one call: the row runs of each of its ``nlab`` nearest
    heads (:func:`cut_runs`) of its mask at (x0, y0) (``boxes.mask_runs``, the pixels
    of :func:`run_pixels`, their nearest heads by :func:`head_labels`, whose arguments
    the others are)."""
    ry, rx0, rx1, n = mask_runs(mask)
    px, py = run_pixels(ry, rx0, rx1, n, x0, y0)
    lab = np.empty(px.shape[0], np.int64)
    head_labels(px, py, ends, dirs, back, radius, row, centres, is_centre, lab)
    return cut_runs(ry, rx0, rx1, n, lab, nlab)


@kernel(
    "Tuple((float64[:, ::1], float64[:, ::1], float64[::1], float64[::1], int64[::1]))("
    "float64[:, :, ::1], int64[::1], float64[:, ::1], float64[:, ::1], float64[::1],"
    " float64[::1], float64[:, ::1])"
)
def head_segments(
    boxes: np.ndarray,
    which: np.ndarray,
    ends: np.ndarray,
    dirs: np.ndarray,
    radius: np.ndarray,
    head_len: np.ndarray,
    limit_end: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``split._head_segments`` of K fitted axes (``ends``, ``dirs``, ``radius``,
    ``head_len``, expected ends ``limit_end``) for one head part, whose expected box is
    ``boxes[k, which[k]]`` (``split._initial_axes``' boxes; ``which[k] == 0``: none):
    ``(ends, dirs, back, radius, row)``, each axis's head segment first, then the
    expected boxes moved with their shaft's end, in Python's float operations."""
    kk = ends.shape[0]
    s = kk
    for k in range(kk):
        s += which[k] != 0
    s_ends = np.empty((s, 2), np.float64)
    s_dirs = np.empty((s, 2), np.float64)
    s_back = np.empty(s, np.float64)
    s_rad = np.empty(s, np.float64)
    rows = np.empty(s, np.int64)
    for k in range(kk):
        n = head_len[k]
        dx, dy = dirs[k, 0], dirs[k, 1]
        s_ends[k, 0] = ends[k, 0] + n * dx
        s_ends[k, 1] = ends[k, 1] + n * dy
        s_dirs[k, 0], s_dirs[k, 1] = dx, dy
        s_back[k] = n
        s_rad[k] = radius[k]
        rows[k] = k
    i = kk
    for k in range(kk):
        if which[k] == 0:
            continue
        b = boxes[k, which[k]]
        t = math.radians(b[4])
        ux, uy = math.cos(t), math.sin(t)
        h = 0.5 * b[2]
        cx = b[0] + (ends[k, 0] - limit_end[k, 0])
        cy = b[1] + (ends[k, 1] - limit_end[k, 1])
        s_ends[i, 0] = cx + h * ux
        s_ends[i, 1] = cy + h * uy
        s_dirs[i, 0], s_dirs[i, 1] = ux, uy
        s_back[i] = 2 * h
        w2 = b[3] / 2.0
        s_rad[i] = 1.0 if 1.0 > w2 else w2  # max(width / 2, 1.0)
        rows[i] = k
        i += 1
    return s_ends, s_dirs, s_back, s_rad, rows


@kernel(
    f"{_CUT}(uint8[:, ::1], int64, int64, float64[:, :, ::1], int64[::1], float64[:, ::1],"
    " float64[:, ::1], float64[::1], float64[::1], float64[:, ::1])"
)
def head_part_runs(
    mask: np.ndarray,
    x0: int,
    y0: int,
    boxes: np.ndarray,
    which: np.ndarray,
    ends: np.ndarray,
    dirs: np.ndarray,
    radius: np.ndarray,
    head_len: np.ndarray,
    limit_end: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`head_cut_runs` of a head part between K fitted axes alone (no anchors):
    the segments of :func:`head_segments`, no centres."""
    kk = ends.shape[0]
    s_ends, s_dirs, s_back, s_rad, rows = head_segments(
        boxes, which, ends, dirs, radius, head_len, limit_end
    )
    centres = np.zeros((kk, 3), np.float64)
    is_centre = np.zeros(kk, np.bool_)
    return head_cut_runs(mask, x0, y0, s_ends, s_dirs, s_back, s_rad, rows, centres, is_centre, kk)


@kernel("boolean[::1](uint8[:, ::1], int64, int64, int64, int64)")
def _border_touch(mask: np.ndarray, x0: int, y0: int, hh: int, ww: int) -> np.ndarray:
    """(n,) over the image border walked as a loop (top, right, bottom, left; index 0
    the top left pixel): where a crop's pixels (``mask`` at (x0, y0), in an (hh, ww)
    image) touch it (``split._on_border``)."""
    h, w = mask.shape
    n = 2 * (ww - 1) + 2 * (hh - 1)
    on = np.zeros(n, np.bool_)
    if y0 == 0:
        for x in range(w):
            if mask[0, x] != 0:
                on[x0 + x] = True
    if x0 + w == ww:
        for y in range(h):
            if mask[y, w - 1] != 0:
                on[(ww - 1 + y0 + y) % n] = True
    if y0 + h == hh:
        for x in range(w):
            if mask[h - 1, x] != 0:
                on[(ww - 1) + (hh - 1) + (ww - 1 - (x0 + x))] = True
    if x0 == 0:
        for y in range(h):
            if mask[y, 0] != 0:
                on[(2 * (ww - 1) + (hh - 1) + (hh - 1 - (y0 + y))) % n] = True
    return on


@helper
def _border_xy(i: int, ww: int, hh: int, out: np.ndarray, j: int, k: int) -> None:
    """``out[j, k]``: pixel (x, y) of index ``i`` along the image border walked as a loop
    (top, right, bottom, left; ``split._border_index_to_xy``)."""
    i %= 2 * (ww - 1) + 2 * (hh - 1)
    if i < ww - 1:
        out[j, k, 0], out[j, k, 1] = i, 0
        return
    i -= ww - 1
    if i < hh - 1:
        out[j, k, 0], out[j, k, 1] = ww - 1, i
        return
    i -= hh - 1
    if i < ww - 1:
        out[j, k, 0], out[j, k, 1] = ww - 1 - i, hh - 1
        return
    i -= ww - 1
    out[j, k, 0], out[j, k, 1] = 0, hh - 1 - i


_BOOL_ONES = np.uint64(0x0101010101010101)


@helper
def _next_at(on: np.ndarray, lo: int, hi: int, want: bool) -> int:
    """The first index ``i`` in ``[lo, hi)`` with ``on[i] == want``, else ``hi``: eight
    items at a time (a bool is one byte, 0 or 1), the item from the word's trailing
    zeros."""
    skip = np.uint64(0) if want else _BOOL_ONES  # a word of eight items without `want`
    i = lo
    while i + 8 <= hi:
        word = load8(on, i) ^ skip
        if word != 0:
            return i + np.int64(ctz(word) >> np.uint64(3))
        i += 8
    while i < hi:
        if on[i] == want:
            return i
        i += 1
    return hi


@kernel(
    "Tuple((float64[:, :, ::1], int64[::1]))(uint8[:, ::1], int64, int64, int64, int64, int64,"
    " int64)"
)
def border_runs(
    mask: np.ndarray,
    x0: int,
    y0: int,
    hh: int,
    ww: int,
    min_px: int,
    max_gap: int,
) -> tuple[np.ndarray, np.ndarray]:
    """``split.border_runs``' runs of a shaft crop (``mask`` at (x0, y0)) in an (hh, ww)
    image: the image border walked as a loop (top, right, bottom, left; index 0 the top
    left pixel), where the shaft's pixels touch it; runs closer than ``max_gap`` px
    joined, those of at least ``min_px`` kept, walking from the first border pixel off
    the shaft. Returns ``(ends, lengths)``: (k, 3, 2) the (x, y) px of each run's first,
    middle and last pixel, (k,) its length; none when fewer than ``min_px`` border
    pixels are the shaft's or all are. The loop is walked a stretch at a time
    (:func:`_next_at`: mostly no pixel of the shaft), from its first pixel off the shaft
    to the end and then from index 0 to there (a run across index 0 is one run)."""
    on = _border_touch(mask, x0, y0, hh, ww)
    n = on.shape[0]
    start = _next_at(on, 0, n, False)
    cap = n // 2 + 1
    out = np.empty((cap, 2), np.int64)  # each run's first index (from start) and length
    m = 0
    total = 0
    for part in range(2):
        at, hi = (start, n) if part == 0 else (0, start)
        shift = -start if part == 0 else n - start  # to indices from start
        while True:
            a = _next_at(on, at, hi, True)
            if a == hi:
                break
            b = _next_at(on, a, hi, False)
            total += b - a
            a += shift
            if m > 0 and a - (out[m - 1, 0] + out[m - 1, 1]) <= max(max_gap, 0):
                out[m - 1, 1] = b + shift - out[m - 1, 0]
            else:
                out[m, 0] = a
                out[m, 1] = b + shift - a
                m += 1
            at = b
    if total < min_px or start == n:
        return np.empty((0, 3, 2)), np.empty(0, np.int64)
    k = 0
    for j in range(m):
        k += out[j, 1] >= min_px
    ends = np.empty((k, 3, 2))
    lengths = np.empty(k, np.int64)
    k = 0
    for j in range(m):
        if out[j, 1] >= min_px:
            first = out[j, 0] + start
            length = out[j, 1]
            lengths[k] = length
            _border_xy(first, ww, hh, ends, k, 0)
            _border_xy(first + length // 2, ww, hh, ends, k, 1)
            _border_xy(first + length - 1, ww, hh, ends, k, 2)
            k += 1
    return ends, lengths


# heads handed over (mistool.tracking.heads) --------------------------------------------


@helper
def _box_d(
    x: float,
    y: float,
    cx: float,
    cy: float,
    u0: float,
    u1: float,
    hl: float,
    hw: float,
    single: bool,
) -> float:
    """Point (x, y)'s distance to a box (centre, unit direction ``u``, half length and
    width) as ``heads.box_distance`` computes it: ``d = p - c``; ``|d @ u| - hl`` and
    ``|d @ (-u1, u0)| - hw`` by ``dgemv`` (``single``: one point, its order), each
    ``np.maximum(., 0)``, then ``hypot``."""
    d0 = x - cx
    d1 = y - cy
    if single:
        a = fma(d1, u1, d0 * u0)
        b = fma(d1, u0, d0 * -u1)
    else:
        a = fma(d0, u0, d1 * u1)
        b = fma(d0, -u1, d1 * u0)
    along = abs(a) - hl
    across = abs(b) - hw
    along = along if (along >= 0.0 or along != along) else 0.0
    across = across if (across >= 0.0 or across != across) else 0.0
    return math.hypot(along, across)


@kernel("void(float64[:, ::1], float64, float64, float64, float64, float64, float64, float64[::1])")
def box_distances(
    xy: np.ndarray,
    cx: float,
    cy: float,
    u0: float,
    u1: float,
    hl: float,
    hw: float,
    out: np.ndarray,
) -> None:
    """``out`` (N,): ``heads.box_distance`` of points ``xy`` (N, 2) to a box."""
    n = xy.shape[0]
    single = n == 1
    for i in range(n):
        out[i] = _box_d(xy[i, 0], xy[i, 1], cx, cy, u0, u1, hl, hw, single)


@helper
def _window(
    h: int,
    w: int,
    x0: int,
    y0: int,
    cx: float,
    cy: float,
    u0: float,
    u1: float,
    hl: float,
    hw: float,
    reach: float,
) -> tuple[int, int, int, int]:
    """``(ya, yb, xa, xb)``: the rows and columns of an (h, w) crop at (x0, y0) that may
    hold a pixel within ``reach`` px of a box (centre, unit direction, half length and
    width): the box's bounds grown by ``reach`` + 1 px (the others lie farther; a
    non-finite bound: the whole crop that way)."""
    ex = hl * abs(u0) + hw * abs(u1) + reach + 1.0
    ey = hl * abs(u1) + hw * abs(u0) + reach + 1.0
    ya, yb, xa, xb = 0, h, 0, w
    if math.isfinite(cx - ex) and math.isfinite(cx + ex):
        xa = min(max(int(math.floor(cx - ex)) - x0, 0), w)
        xb = max(min(int(math.ceil(cx + ex)) - x0 + 1, w), 0)
    if math.isfinite(cy - ey) and math.isfinite(cy + ey):
        ya = min(max(int(math.floor(cy - ey)) - y0, 0), h)
        yb = max(min(int(math.ceil(cy + ey)) - y0 + 1, h), 0)
    return ya, yb, xa, xb


@kernel(
    "boolean(uint8[:, ::1], int64, int64, float64, float64, float64, float64, float64, float64,"
    " float64, int64)"
)
def shown_near(
    mask: np.ndarray,
    x0: int,
    y0: int,
    cx: float,
    cy: float,
    u0: float,
    u1: float,
    hl: float,
    hw: float,
    reach: float,
    min_area: int,
) -> bool:
    """Whether at least ``min_area`` pixels of a part's crop (``mask`` at (x0, y0)) lie
    within ``reach`` px of a box (``heads.box_distance`` of every pixel, counted):
    only the pixels within the box's bounds grown by ``reach`` + 1 px are looked at (the
    others lie farther), and the count stops at ``min_area``."""
    h, w = mask.shape
    count = 0
    for y in range(h):  # one pixel alone: dgemv's one-point order
        for x in range(w):
            if mask[y, x] != 0:
                count += 1
                if count == 2:
                    break
        if count == 2:
            break
    single = count == 1
    ya, yb, xa, xb = _window(h, w, x0, y0, cx, cy, u0, u1, hl, hw, reach)
    near = 0
    for y in range(ya, yb):
        for x in range(xa, xb):
            if mask[y, x] != 0 and _box_d(x + x0, y + y0, cx, cy, u0, u1, hl, hw, single) <= reach:
                near += 1
                if near >= min_area:
                    return True
    return near >= min_area


@kernel(
    "int64(uint8[:, ::1], int64, int64, float64, float64, float64, float64, float64, float64,"
    " boolean, float64, float64, float64, float64, float64, float64, float64)"
)
def claimed(
    mask: np.ndarray,
    x0: int,
    y0: int,
    cx: float,
    cy: float,
    u0: float,
    u1: float,
    hl: float,
    hw: float,
    has_own: bool,
    ocx: float,
    ocy: float,
    ou0: float,
    ou1: float,
    ohl: float,
    ohw: float,
    reach: float,
) -> int:
    """How many pixels of a part's crop (``mask`` at (x0, y0)) lie within ``reach`` px
    of a box and nearer to it than to a second box (``has_own``; without it, every one
    within reach whose distance is below inf): ``heads.box_distance`` of every pixel to
    each (one pixel alone: ``dgemv``'s one-point order), counted as ``heads.
    hand_over_heads`` counted ``(to_me <= reach) & (to_me < to_own)``; only the pixels
    within the box's bounds grown by ``reach`` + 1 px are looked at (:func:`_window`:
    the others lie farther), the second distance only within reach."""
    h, w = mask.shape
    count = 0
    for y in range(h):
        for x in range(w):
            if mask[y, x] != 0:
                count += 1
                if count == 2:
                    break
        if count == 2:
            break
    single = count == 1
    ya, yb, xa, xb = _window(h, w, x0, y0, cx, cy, u0, u1, hl, hw, reach)
    moved = 0
    for y in range(ya, yb):
        for x in range(xa, xb):
            if mask[y, x] == 0:
                continue
            px = float(x + x0)
            py = float(y + y0)
            d = _box_d(px, py, cx, cy, u0, u1, hl, hw, single)
            if not d <= reach:
                continue
            own = _box_d(px, py, ocx, ocy, ou0, ou1, ohl, ohw, single) if has_own else math.inf
            if d < own:
                moved += 1
    return moved


@helper
def _count_upto(mask: np.ndarray, most: int) -> int:
    """The mask's non-zero pixels, counted up to ``most``."""
    n = 0
    for y in range(mask.shape[0]):
        for x in range(mask.shape[1]):
            if mask[y, x] != 0:
                n += 1
                if n == most:
                    return n
    return n


@helper
def _paint(canvas: np.ndarray, x: int, y: int, bounds: np.ndarray, k: int) -> None:
    """Pixel (x, y) set (255) on ``canvas`` (at ``bounds[0], bounds[1]`` of ``bounds``),
    counted in ``bounds[k]`` and its bounds ``bounds[k + 1 : k + 5]`` (x0, y0, x1, y1,
    exclusive ends) grown over it."""
    canvas[y - bounds[1], x - bounds[0]] = 255
    if bounds[k] == 0:
        bounds[k + 1] = x
        bounds[k + 2] = y
        bounds[k + 3] = x + 1
        bounds[k + 4] = y + 1
    else:
        bounds[k + 1] = min(bounds[k + 1], x)
        bounds[k + 2] = min(bounds[k + 2], y)
        bounds[k + 3] = max(bounds[k + 3], x + 1)
        bounds[k + 4] = max(bounds[k + 4], y + 1)
    bounds[k] += 1


@kernel(
    "int64(uint8[:, ::1], int64, int64, uint8[:, ::1], int64, int64, float64, float64,"
    " float64, float64, float64, float64, boolean, float64, float64, float64, float64,"
    " float64, float64, float64, uint8[:, ::1], uint8[:, ::1], int64[::1])"
)
def hand_over_pixels(
    mine: np.ndarray,
    mx0: int,
    my0: int,
    donor: np.ndarray,
    dx0: int,
    dy0: int,
    cx: float,
    cy: float,
    u0: float,
    u1: float,
    hl: float,
    hw: float,
    has_own: bool,
    ocx: float,
    ocy: float,
    ou0: float,
    ou1: float,
    ohl: float,
    ohw: float,
    reach: float,
    got: np.ndarray,
    left: np.ndarray,
    bounds: np.ndarray,
) -> int:
    """``heads.hand_over_heads``' hand-over of one part's pixels, painted: the donor's
    pixels (``donor`` at (dx0, dy0)) within ``reach`` of the box expected by the tool
    receiving the part (centre, unit direction, half length and width) and nearer to it
    than to the donor's own expected box (``has_own``; the :func:`claimed` pixels) move
    to the receiver, whose own pixels of the part (``mine`` at (mx0, my0); an empty
    array: none) within ``reach`` of the donor's box go the other way. ``got`` and
    ``left`` (zeros, at ``bounds[0], bounds[1]``, covering both crops) receive the
    receiver's and the donor's new pixels (255); ``bounds[2:7]`` and ``bounds[7:12]``:
    each one's pixel count (as the former pixel lists' lengths: kept + moved, left +
    back) and bounds (x0, y0, x1, y1; ends exclusive). Returns the count moved.
    Distances as ``heads.box_distance`` of each pixel list (one pixel alone: its
    one-point order), only for the pixels within a box's bounds grown by ``reach`` + 1
    px (:func:`_window`: the others lie farther), the donor's own box's only within
    reach of the receiver's."""
    for k in range(2, 12):
        bounds[k] = 0
    moved = 0
    single = _count_upto(donor, 2) == 1
    h, w = donor.shape
    ya, yb, xa, xb = _window(h, w, dx0, dy0, cx, cy, u0, u1, hl, hw, reach)
    for y in range(h):
        for x in range(w):
            if donor[y, x] == 0:
                continue
            px = x + dx0
            py = y + dy0
            mine_now = False
            if ya <= y < yb and xa <= x < xb:
                d = _box_d(float(px), float(py), cx, cy, u0, u1, hl, hw, single)
                if d <= reach:
                    own = math.inf
                    if has_own:
                        own = _box_d(float(px), float(py), ocx, ocy, ou0, ou1, ohl, ohw, single)
                    mine_now = d < own
            if mine_now:
                moved += 1
                _paint(got, px, py, bounds, 2)
            else:
                _paint(left, px, py, bounds, 7)
    single = _count_upto(mine, 2) == 1
    h, w = mine.shape
    ya, yb, xa, xb = _window(h, w, mx0, my0, ocx, ocy, ou0, ou1, ohl, ohw, reach)
    for y in range(h):
        for x in range(w):
            if mine[y, x] == 0:
                continue
            px = x + mx0
            py = y + my0
            back = (
                has_own
                and ya <= y < yb
                and xa <= x < xb
                and _box_d(float(px), float(py), ocx, ocy, ou0, ou1, ohl, ohw, single) <= reach
            )
            if back:
                _paint(left, px, py, bounds, 7)
            else:
                _paint(got, px, py, bounds, 2)
    return moved


# the split's initial axes (mistool.tracking.split._initial_axes) ------------------------


@helper
def _corners_along(box: np.ndarray, d0: float, d1: float, out: np.ndarray) -> None:
    """``out`` (4,): ``box.corners() @ d`` of a box ``(cx, cy, length, width, angle)``:
    ``RotatedBox.corners``' plain floats, then ``dgemv``'s fused multiply-adds."""
    cx, cy, length, width = box[0], box[1], box[2], box[3]
    t = math.radians(box[4])
    ux, uy = math.cos(t), math.sin(t)
    hl, hw = length / 2.0, width / 2.0
    ax, ay = hl * ux, hl * uy
    bx, by = hw * -uy, hw * ux
    out[0] = fma(cx - ax - bx, d0, (cy - ay - by) * d1)
    out[1] = fma(cx + ax - bx, d0, (cy + ay - by) * d1)
    out[2] = fma(cx + ax + bx, d0, (cy + ay + by) * d1)
    out[3] = fma(cx - ax + bx, d0, (cy - ay + by) * d1)


@helper
def _inside(x: float, y: float, hh: int, ww: int) -> float:
    """``split.distal_axis``' distance of (x, y) to the nearest image border: Python's
    ``min(x, w - 1 - x, y, h - 1 - y)`` (the first of equal ones)."""
    m = x
    for v in (ww - 1 - x, y, hh - 1 - y):
        if v < m:
            m = v
    return m


@kernel(
    "void(float64[:, :, ::1], int64[::1], boolean, int64, int64, float64, float64, float64,"
    " float64[:, ::1], float64[:, ::1], float64[::1], float64[::1], float64[::1], float64[::1])"
)
def initial_axes(
    boxes: np.ndarray,
    nother: np.ndarray,
    given: bool,
    hh: int,
    ww: int,
    margin_frac: float,
    head_widths: float,
    seen_margin: float,
    ends0: np.ndarray,
    dirs: np.ndarray,
    back: np.ndarray,
    radius: np.ndarray,
    margin: np.ndarray,
    head_len: np.ndarray,
) -> None:
    """``split._initial_axes`` of K instruments' expected boxes (``boxes`` (K, 3, 5):
    ``cx, cy, length, width, angle``, the shaft's first, then its ``nother[k]`` other
    parts' in their order): unless ``given`` (``ends0``, ``dirs``, ``back`` set), each
    shaft's distal axis (``split.distal_axis``: towards the other parts' mean, or
    without them away from the nearest border of an (hh, ww) image, ``hh`` < 0: none);
    ``radius`` (half the shaft's width, at least 1), ``margin`` (``margin_frac`` of its
    length) and ``head_len`` (``split._head_length``: its other parts' extent along the
    axis x ``seen_margin``, between one shaft width and ``head_widths`` widths), with
    the float operations of the numpy code they replace."""
    proj = np.empty(4, np.float64)
    for k in range(boxes.shape[0]):
        cx, cy, length, width = boxes[k, 0, 0], boxes[k, 0, 1], boxes[k, 0, 2], boxes[k, 0, 3]
        n = nother[k]
        if not given:
            t = math.radians(boxes[k, 0, 4])
            u0, u1 = math.cos(t), math.sin(t)
            half = 0.5 * length
            if n:
                ox = 0.0
                oy = 0.0
                for j in range(1, n + 1):  # np.mean(axis=0): from 0 in order, / n
                    ox += boxes[k, j, 0]
                    oy += boxes[k, j, 1]
                ox /= n
                oy /= n
                if dot2(ox - cx, oy - cy, u0, u1) < 0:
                    u0, u1 = -u0, -u1
                back[k] = math.inf
            else:
                back[k] = length
                if hh >= 0:
                    near = _inside(cx - half * u0, cy - half * u1, hh, ww)
                    far = _inside(cx + half * u0, cy + half * u1, hh, ww)
                    if near > far:
                        u0, u1 = -u0, -u1
            dirs[k, 0], dirs[k, 1] = u0, u1
            ends0[k, 0] = cx + half * u0
            ends0[k, 1] = cy + half * u1
        margin[k] = margin_frac * length
        w2 = width / 2.0
        r = 1.0 if 1.0 > w2 else w2  # max(width / 2, 1.0)
        radius[k] = r
        longest = 2.0 * head_widths * r
        if n == 0:
            head_len[k] = longest
            continue
        hi = -math.inf
        lo = math.inf
        nan = False
        for j in range(1, n + 1):
            _corners_along(boxes[k, j], dirs[k, 0], dirs[k, 1], proj)
            for v in proj:
                nan = nan or v != v
                hi = max(hi, v)
                lo = min(lo, v)
        reach = math.nan if nan else hi - lo
        grown = seen_margin * reach
        low = 2.0 * r
        top = grown if grown > low else low  # max(2r, grown)
        head_len[k] = top if top < longest else longest  # min(longest, top)


# the shaft from its row runs (mistool.kernels.boxes.mask_runs) --------------------------


@kernel("void(int32[::1], int32[::1], int32[::1], int64, int64, int64, int64, float64[:, ::1])")
def run_points(
    ry: np.ndarray,
    rx0: np.ndarray,
    rx1: np.ndarray,
    n: int,
    x0: int,
    y0: int,
    step: int,
    out: np.ndarray,
) -> None:
    """``out`` (M, 2): full-image (x, y) of every ``step``-th pixel of ``n`` row runs in
    raster order (run ``i``: ``rx0[i] <= x < rx1[i]`` of row ``ry[i]``, a crop at (x0,
    y0)), from the first (numpy's ``flatnonzero`` of their mask, sampled)."""
    m = 0
    k = 0  # index of the runs' next pixel
    for i in range(n):
        a, b = rx0[i], rx1[i]
        first = a + (-k) % step  # the run's first pixel whose index is a multiple of step
        for x in range(first, b, step):
            out[m, 0] = x + x0
            out[m, 1] = ry[i] + y0
            m += 1
        k += b - a


@kernel(
    "boolean(int32[::1], int32[::1], int32[::1], int64, int64, uint8[:, ::1], boolean[:, ::1],"
    " int64[:, ::1], uint8[::1], int32[:, ::1], int32[:, ::1], int32[:, ::1], int64[::1])"
)
def _cut_runs(
    ry: np.ndarray,
    rx0: np.ndarray,
    rx1: np.ndarray,
    n: int,
    s: int,
    coarse: np.ndarray,
    mixed: np.ndarray,
    nxt: np.ndarray,
    lab: np.ndarray,
    out_y: np.ndarray,
    out_a: np.ndarray,
    out_b: np.ndarray,
    got: np.ndarray,
) -> bool:
    """:func:`shaft_label_runs`' runs cut where the label changes (the mixed cells'
    pixels labelled ``lab``, in the runs' order; ``nxt``: :func:`_stretches`); False
    when the outputs are too short. Eight pixels of a mixed cell with the label of the
    pixel before them are passed over in one compare (the labels' 8 bytes)."""
    nlab, cap = out_y.shape
    total = lab.shape[0]
    ones = np.uint64(0x0101010101010101)
    m = 0
    for i in range(n):
        y = ry[i]
        ci = y // s
        cur = -1
        start = rx0[i]
        x = rx0[i]
        while x < rx1[i]:
            cj = x // s
            stop = min(rx1[i], nxt[ci, cj] * s)  # (a stretch of one label, or a mixed cell)
            if mixed[ci, cj]:
                if (
                    stop - x == 8
                    and cur >= 0
                    and m + 8 <= total
                    and load8(lab, m) == np.uint64(cur) * ones
                ):
                    m += 8
                    x = stop
                    continue
                for xx in range(x, stop):
                    v = np.int64(lab[m])
                    m += 1
                    if v != cur:
                        if cur >= 0 and not _emit(cur, y, start, xx, out_y, out_a, out_b, got):
                            return False
                        cur = v
                        start = xx
            else:
                v = np.int64(coarse[ci, cj])
                if v != cur:
                    if cur >= 0 and not _emit(cur, y, start, x, out_y, out_a, out_b, got):
                        return False
                    cur = v
                    start = x
            x = stop
        if cur >= 0 and not _emit(cur, y, start, rx1[i], out_y, out_a, out_b, got):
            return False
    return True


@kernel("int64[:, ::1](uint8[:, ::1], boolean[:, ::1])")
def _stretches(coarse: np.ndarray, mixed: np.ndarray) -> np.ndarray:
    """(ch, cw): for each cell, the first cell after it in its row that is mixed, or not
    mixed with another label (cw: none): a run crossing unmixed cells of one label is
    walked one stretch at a time, not cell by cell."""
    ch, cw = coarse.shape
    nxt = np.empty((ch, cw), np.int64)
    for ci in range(ch):
        nxt[ci, cw - 1] = cw
        for cj in range(cw - 2, -1, -1):
            same = not mixed[ci, cj] and not mixed[ci, cj + 1]
            nxt[ci, cj] = (
                nxt[ci, cj + 1] if same and coarse[ci, cj] == coarse[ci, cj + 1] else cj + 1
            )
        for cj in range(cw):
            if mixed[ci, cj]:
                nxt[ci, cj] = cj + 1
    return nxt


@kernel(
    f"Tuple((int32[:, ::1], int32[:, ::1], int32[:, ::1], int64[::1]))(int32[::1], int32[::1],"
    f" int32[::1], int64, int64, int64, int64, int64, {_SEGMENTS}, float64, boolean, int64,"
    " int64)"
)
def shaft_label_runs(
    ry: np.ndarray,
    rx0: np.ndarray,
    rx1: np.ndarray,
    n: int,
    h: int,
    w: int,
    x0: int,
    y0: int,
    ends: np.ndarray,
    dirs: np.ndarray,
    back: np.ndarray,
    radius: np.ndarray,
    keep_d2: float,
    keep: bool,
    s: int,
    nlab: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The nearest axis of each pixel of an (h, w) shaft crop at (x0, y0) given as its
    ``n`` row runs (:func:`mistool.kernels.boxes.mask_runs`), as row runs per axis: what
    :func:`label_runs` gave of the owner image ``split._owner_cells`` made, without the
    image. Each ``s`` x ``s`` cell's label (:func:`_label`) from its centre (one cell
    alone: ``dgemv``'s one-point order), per pixel in the cells whose 3 x 3
    neighbourhood holds two labels (gathered and labelled in one loop; one alone: the
    one-point order), each run cut where the label changes. ``(ry, rx0, rx1, count)``
    per label ``j < nlab``, in raster order, maximal (as ``mask_runs`` of
    ``owner == j``). (The mixed cells' pixels are gathered into arrays of at most
    their cells' size, their labels kept as bytes: fewer than 255 axes.)"""
    ch = (h + s - 1) // s
    cw = (w + s - 1) // s
    half = 0.5 * (s - 1)
    seg = _frames(ends, dirs, back, radius)
    cx = np.empty(ch * cw, np.float64)  # the cells' centres, row by row
    cy = np.empty(ch * cw, np.float64)
    for ci in range(ch):
        for cj in range(cw):
            cx[ci * cw + cj] = (x0 + cj * s) + half
            cy[ci * cw + cj] = (y0 + ci * s) + half
    cells = np.empty(ch * cw, np.int64)
    _labels(cx, cy, seg, keep_d2, keep, ch * cw == 1, cells)  # (one cell: dgemv's order)
    coarse = np.empty((ch, cw), np.uint8)
    for ci in range(ch):
        for cj in range(cw):
            coarse[ci, cj] = cells[ci * cw + cj]
    mixed = _mixed_cells(coarse)
    nxt = _stretches(coarse, mixed)
    most = 0  # at most every pixel of the runs, or of the mixed cells
    for i in range(n):
        most += rx1[i] - rx0[i]
    nmixed = 0
    for ci in range(ch):
        for cj in range(cw):
            nmixed += mixed[ci, cj]
    most = min(most, nmixed * s * s)
    xs = np.empty(most, np.float64)
    ys = np.empty(most, np.float64)
    count = 0  # pixels in mixed cells
    for i in range(n):
        ci = ry[i] // s
        cj, last = rx0[i] // s, (rx1[i] - 1) // s
        yy = np.float64(ry[i] + y0)
        while cj <= last:
            if mixed[ci, cj]:
                for x in range(max(rx0[i], cj * s), min(rx1[i], cj * s + s)):
                    xs[count] = x + x0
                    ys[count] = yy
                    count += 1
            cj = nxt[ci, cj]
    lab = np.empty(count, np.uint8)
    _labels(xs[:count], ys[:count], seg, keep_d2, keep, count == 1, lab)
    cap = n + count + 1
    while True:
        out_y = np.empty((nlab, cap), np.int32)
        out_a = np.empty((nlab, cap), np.int32)
        out_b = np.empty((nlab, cap), np.int32)
        got = np.zeros(nlab, np.int64)
        if _cut_runs(ry, rx0, rx1, n, s, coarse, mixed, nxt, lab, out_y, out_a, out_b, got):
            return out_y, out_a, out_b, got
        cap *= 4


# a shaft entering the view (mistool.tracking.split.border_entries) ----------------------


@kernel("void(float64[:, ::1], float64, float64, float64, float64[:, ::1], boolean[::1])")
def entry_lane(
    pts: np.ndarray, mx: float, my: float, half: float, dirs: np.ndarray, out: np.ndarray
) -> None:
    """``out`` (N,): which of the points ``pts`` (N, 2) lie in the straight lane from
    (mx, my), ``2 * half`` px wide, along the direction (a column of ``dirs`` (2, K))
    holding the most of them, the first of equal counts (``split._entry_lane``: ``rel =
    pts - m``, ``rel @ dirs`` and ``rel @ (-dirs[1], dirs[0])`` by ``dgemm``, one point:
    its one-point order)."""
    n = pts.shape[0]
    single = n == 1
    rx = np.empty(n, np.float64)
    ry = np.empty(n, np.float64)
    for i in range(n):
        rx[i] = pts[i, 0] - mx
        ry[i] = pts[i, 1] - my
    best = -1
    most = -1
    for k in range(dirs.shape[1]):
        d0, d1 = dirs[0, k], dirs[1, k]
        count = 0
        for i in range(n):
            along = row_dot(rx[i], ry[i], d0, d1, single)
            across = row_dot(rx[i], ry[i], -d1, d0, single)
            count += along >= 0.0 and abs(across) <= half
        if count > most:
            most = count
            best = k
    d0, d1 = dirs[0, best], dirs[1, best]
    for i in range(n):
        along = row_dot(rx[i], ry[i], d0, d1, single)
        across = row_dot(rx[i], ry[i], -d1, d0, single)
        out[i] = along >= 0.0 and abs(across) <= half


@helper
def floor_divide(a: float, b: float) -> float:
    """``a // b`` of two floats as numpy's ``floor_divide`` (and CPython) computes it:
    from ``fmod``, the quotient rounded to the nearest integer when ``floor`` lands
    more than half away (``npy_divmod``)."""
    mod = np.fmod(a, b)  # (C fmod: exact)
    if b == 0.0:
        return a / b
    div = (a - mod) / b
    if mod != 0.0:
        if (b < 0.0) != (mod < 0.0):
            div -= 1.0
    if div != 0.0:
        floordiv = np.floor(div)  # (a float: math.floor gives an int here)
        if div - floordiv > 0.5:
            floordiv += 1.0
        return floordiv
    return math.copysign(0.0, a / b)


@kernel(
    "int64[::1](float64[:, ::1], float64, float64, float64, float64, float64, float64, float64)"
)
def lane_bins(
    q: np.ndarray,
    px: float,
    py: float,
    d0: float,
    d1: float,
    half: float,
    start: float,
    step: float,
) -> np.ndarray:
    """The bin index along the lane of each point of ``q`` (N, 2) lying in it, in their
    order (``split.head_stop``'s lane: ``rel = q - p``, ``along = rel @ d`` by
    ``dgemv``, ``across = |rel_x d_y - rel_y d_x|``; the points with ``across <= half``
    and ``along > start``, binned as ``((along - start) // step).astype(int64)``)."""
    n = q.shape[0]
    got = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        r0 = q[i, 0] - px
        r1 = q[i, 1] - py
        along = row_dot(r0, r1, d0, d1, True)
        across = abs(r0 * d1 - r1 * d0)
        if across <= half and along > start:
            got[m] = np.int64(floor_divide(along - start, step))
            m += 1
    out = np.empty(m, np.int64)
    for i in range(m):
        out[i] = got[i]
    return out
