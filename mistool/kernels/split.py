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

from mistool.kernels import kernel

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


@kernel("float64(float64, float64, float64, float64)")
def dot2(a0: float, a1: float, b0: float, b1: float) -> float:
    """``np.array([a0, a1]) @ np.array([b0, b1])`` (contiguous ``ddot``)."""
    return fma(a1, b1, fma(a0, b0, 0.0))


@kernel("float64(float64, float64, float64, float64, boolean)")
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


@kernel("float64(float64[::1], int64, int64)")
def _pairwise(a: np.ndarray, lo: int, n: int) -> float:
    if n < 8:
        res = -0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    if n <= 128:
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
    n2 = n // 2
    n2 -= n2 % 8
    return _pairwise(a, lo, n2) + _pairwise(a, lo + n2, n - n2)


@kernel("float64(float64[::1], int64)")
def pairwise_sum(a: np.ndarray, n: int) -> float:
    """``np.add.reduce(a[:n])`` of a contiguous float64 array (numpy's pairwise
    summation, from 0)."""
    return 0.0 + _pairwise(a, 0, n)


# the split -------------------------------------------------------------------------------

_SEGMENTS = (
    "float64[:, ::1], float64[:, ::1], float64[::1], float64[::1]"  # ends, dirs, back, radius
)


@kernel(f"float64(float64, float64, {_SEGMENTS}, int64, boolean)")
def _d2(
    x: float,
    y: float,
    ends: np.ndarray,
    dirs: np.ndarray,
    back: np.ndarray,
    radius: np.ndarray,
    k: int,
    single: bool,
) -> float:
    """Point (x, y)'s squared distance to segment ``k`` (``split.segment_d2_rows``: the
    coordinates along and across by ``dgemm``, less the offsets summed in plain floats;
    ``single``: one point, ``dgemv``'s order)."""
    dx, dy = dirs[k, 0], dirs[k, 1]
    ex, ey = ends[k, 0], ends[k, 1]
    along = row_dot(dx, dy, x, y, single) - (ex * dx + ey * dy)
    perp = row_dot(-dy, dx, x, y, single) - (ex * -dy + ey * dx)
    excess = along if (along >= 0.0 or along != along) else 0.0  # np.maximum(along, 0.0)
    b = back[k]
    if math.isfinite(b):
        behind = -along - b
        excess += behind if (behind >= 0.0 or behind != behind) else 0.0
    d2 = perp * perp
    d2 += excess * excess
    r = radius[k]
    d2 *= 1.0 / (r * r)
    return d2


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
    for k in range(ends.shape[0]):
        for i in range(n):
            out[k, i] = _d2(p[i, 0], p[i, 1], ends, dirs, back, radius, k, single)


@kernel(f"int64(float64, float64, {_SEGMENTS}, float64, boolean, boolean)")
def _label(
    x: float,
    y: float,
    ends: np.ndarray,
    dirs: np.ndarray,
    back: np.ndarray,
    radius: np.ndarray,
    keep_d2: float,
    keep: bool,
    single: bool,
) -> int:
    """The nearest segment's index (``split._Axes.nearest``): for two segments without
    ``keep``, 1 where the second is strictly nearer; else ``argmin`` (the first of equal
    minima, the first NaN); with ``keep``, K where the least distance (NaN if any) is
    above ``keep_d2``."""
    kk = ends.shape[0]
    d0 = _d2(x, y, ends, dirs, back, radius, 0, single)
    if kk == 2 and not keep:
        return 1 if _d2(x, y, ends, dirs, back, radius, 1, single) < d0 else 0
    lab = 0
    best = d0
    least = d0  # np.minimum.reduce: NaN spreads
    nan_at = 0 if d0 != d0 else -1
    for k in range(1, kk):
        d = _d2(x, y, ends, dirs, back, radius, k, single)
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
    n = p.shape[0]
    single = n == 1
    for i in range(n):
        out[i] = _label(p[i, 0], p[i, 1], ends, dirs, back, radius, keep_d2, keep, single)


@kernel(
    "boolean(float64[:, ::1], int64[::1], int64, float64[:, ::1], float64[::1],"
    " float64[:, ::1], float64[:, ::1], float64[::1], float64[:, ::1], float64[:, ::1],"
    " float64[::1], int64, int64, boolean, float64, float64)"
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
) -> bool:
    """Axis ``j`` refitted to the points labelled ``j`` (one round of
    :func:`refit_axes`; ``q``, ``proj``: work space); False when they are too few."""
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


@kernel(
    f"boolean(float64[:, ::1], {_SEGMENTS}, float64[:, ::1], float64[:, ::1], float64[::1],"
    " float64, boolean, int64, int64, boolean, int64, float64, float64)"
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
) -> bool:
    """``split._refit``: rounds of nearest axis, then each axis refitted to its points
    (direction: the 2x2 principal axis, unless it turns past ``turn_cos`` from
    ``start_dirs``; distal end: the points' reach, at most ``limit_end + margin``; when
    ``contiguous``, up to the first gap of ``gap_radii`` radii along the axis), until no
    point changes axis; ``ends`` and ``dirs`` updated in place. False when an axis keeps
    fewer than 3 points or ``weight`` x its points < ``min_area``. At most
    :data:`DOT_SERIAL_MAX` points."""
    n = pts.shape[0]
    single = n == 1
    lab = np.empty(n, np.int64)
    prev = np.empty(n, np.int64)
    q = np.empty((n, 2), np.float64)
    proj = np.empty(n, np.float64)
    for rnd in range(rounds):
        same = rnd > 0
        for i in range(n):
            lab[i] = _label(pts[i, 0], pts[i, 1], ends, dirs, back, radius, keep_d2, keep, single)
            same = same and lab[i] == prev[i]
        if same:
            break  # the same points give the same axes: converged
        for i in range(n):
            prev[i] = lab[i]
        for j in range(ends.shape[0]):
            if not _refit_axis(
                pts, lab, j, q, proj, ends, dirs, radius, limit_end, start_dirs, margin,
                weight, min_area, contiguous, turn_cos, gap_radii,
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


@kernel("int64(float64[:, ::1], int64, float64, boolean)")
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
    for i in range(n):
        lab[i] = _argmin_column(d2, i, keep_d2, keep)
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
