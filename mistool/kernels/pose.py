"""The per-frame metric pose's inner loops (:mod:`mistool.pose.measure`), compiled.

One instrument's pose used to be some 1,200 numpy calls of a few hundred elements each;
here it is a few compiled passes:

- :func:`shaft_boundary`: the shaft's outline pixels, its region moments and its sub-pixel
  boundary points (:mod:`mistool.pose.silhouette`: mid-points of 4-neighbour pairs between
  the shaft and background / the instrument's other parts), read from the part masks
  directly, without a label canvas.
- :func:`shaft_pose`: everything from the shaft's points to its row: the image frame
  (centroid, axis direction, distal sign), the limb-line candidates, one robust line per
  side (RANSAC on fixed draws, then Tukey-weighted total least squares), the axis in
  closed form (:mod:`mistool.pose.cylinder`), the joint on it, the refit of a short
  stretch, the propagated uncertainties, the proximal end and the quaternion.
- :func:`tip_pose` (:func:`jaw_ends` + :func:`tip_solve`): the clasper's jaw ends and the
  tip in 3D.
- :func:`shaft_from_masks`: the shaft from its masks to its row in one call (its outer
  contour traced as OpenCV traces it, :mod:`mistool.kernels.contours`, then the two
  kernels above).
- :func:`cylinder_outline`, :func:`rims_iou` and :func:`iou_count`: the quality IoU,
  OpenCV's convex hull and polygon fill reproduced (:mod:`mistool.kernels.polygon`).

Each is the former numpy code's steps in the same order, written as plain loops over
floats. Sums run left to right and 3-vector products as ``x0 * y0 + x1 * y1 + x2 * y2``
(no fused multiply-add): where numpy went through BLAS (matrix products, whose rounding
depends on the BLAS build and the CPU) or summed pairwise, the last bits differ; the
outputs are otherwise the former ones (``tests/test_pose_speed.py`` compares each kernel
with the numpy definition it replaces). The parameters of the pose (thresholds, priors)
stay documented in :mod:`mistool.pose.measure`, which passes them as one array
(:data:`PARAMS` names its entries).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, TypeVar, cast

import numpy as np

from mistool.kernels import helper, kernel
from mistool.kernels.boxes import load8 as _load8
from mistool.kernels.contours import _next_change, external_contours, outer_contour
from mistool.kernels.polygon import convex_hull, fill_convex

F = TypeVar("F", bound=Callable[..., Any])


def _inlined(signature: str) -> Callable[[F], F]:
    """:func:`~mistool.kernels.kernel` for a small function called per point: also
    compiled into each caller (numba's ``inline="always"``; a call from one cached kernel
    to another stays a call, with a reference count per array argument)."""

    def wrap(fn: F) -> F:
        from numba import njit

        compiled = njit([signature], cache=True, nogil=True, error_model="numpy", inline="always")
        return cast(F, compiled(fn))

    return wrap


__all__ = [
    "CLASPER_ASK_PYTHON",
    "CLASPER_EMPTY",
    "FIT_LEN",
    "GEO_OTHERS",
    "INSTANCE_ASK_PYTHON",
    "INSTANCE_MEASURED",
    "ONE_CALL_REASONS",
    "OUT",
    "PARAMS",
    "ROW_LEN",
    "SHAFT_ASK_PYTHON",
    "SHAFT_MEASURED",
    "SHAFT_MERGED",
    "SHAFT_NOT_VISIBLE",
    "TIP",
    "WHY",
    "clasper_from_mask",
    "cylinder_outline",
    "fit_line",
    "instance_from_masks",
    "iou_count",
    "jaw_ends",
    "rims_iou",
    "shaft_boundary",
    "shaft_from_masks",
    "shaft_pose",
    "tip_pose",
    "tip_solve",
]

#: Labels of a neighbour pixel (as :mod:`mistool.pose.silhouette`).
_BG, _SHAFT, _OTHER = 0, 1, 2

#: The entries of the parameter array :func:`shaft_pose` and :func:`tip_pose` read, in
#: order (the values and their meaning: :mod:`mistool.pose.measure`).
PARAMS: tuple[str, ...] = (
    "max_sigma_mm",
    "max_sigma_deg",
    "px_noise",
    "px_bias",
    "max_cap_spread_mm",
    "min_line_points",
    "min_line_span_px",
    "end_on_deg",
    "fit_max_points",
    "fit_thresh_px",
    "fit_iters",
    "tip_length_factor",
    "tip_length_sigma",
    "tip_bend_sigma_rad",
    "jaw_sep",
    "jaw_rad",
    "cut_angle_deg",
    "cut_offset_frac",
)
(
    _P_MAX_SIGMA_MM,
    _P_MAX_SIGMA_DEG,
    _P_PX_NOISE,
    _P_PX_BIAS,
    _P_CAP_SPREAD,
    _P_MIN_POINTS,
    _P_MIN_SPAN,
    _P_END_ON,
    _P_FIT_MAX,
    _P_FIT_THRESH,
    _P_FIT_ITERS,
    _P_TIP_FACTOR,
    _P_TIP_SIGMA,
    _P_TIP_BEND,
    _P_JAW_SEP,
    _P_JAW_RAD,
    _P_CUT_ANGLE,
    _P_CUT_OFFSET,
) = range(len(PARAMS))

#: Why :func:`shaft_pose` left cells empty (``OUT["why_all"]`` / ``OUT["why_shaft"]``);
#: :mod:`mistool.pose.measure` maps them to :mod:`mistool.pose.status` reasons.
WHY: tuple[str, ...] = (
    "",
    "no silhouette line",
    "one silhouette line",
    "rejected",
    "pointing at camera",
    "low quality",
    "uncertain axis",
    "joint out of view",
    "occluded",
)
_W_NO_LINE, _W_ONE_LINE, _W_REJECTED, _W_END_ON, _W_LOW, _W_AXIS, _W_OUT, _W_OCCLUDED = range(
    1, len(WHY)
)

#: Where :func:`shaft_pose` writes what (NaN: not known): name -> first index.
OUT: dict[str, int] = {
    "row": 0,  # 26 cells of the shaft's row, in measure._SHAFT_CELLS order
    "joint": 26,  # (3,) J, for the clasper (NaN: none)
    "a": 29,  # (3,) the axis' distal direction, for the clasper
    "quality_a": 32,  # (3,) the quality cylinder's proximal end (NaN: no quality)
    "quality_b": 35,  # (3,) its distal end
    "why_all": 38,  # WHY index for every part's row (0: none)
    "why_shaft": 39,  # WHY index for the shaft's row only (0: none)
    "clasper": 40,  # 1: go on to the clasper (the joint is known)
    "quality": 41,  # shaft_from_masks: the shaft's quality (NaN: none, or ask OpenCV)
    "quality_opencv": 42,  # shaft_from_masks: 1 when OpenCV must give the quality
    "size": 43,
}
_O_DISTAL, _O_L1, _O_L2, _O_UV, _O_SUV, _O_SIG, _O_END, _O_AXIS, _O_START, _O_QUAT = (
    0,
    1,
    4,
    7,
    9,
    11,
    13,
    16,
    19,
    22,
)
_O_JOINT, _O_A, _O_QA, _O_QB, _O_WHY_ALL, _O_WHY_SHAFT, _O_CLASPER = 26, 29, 32, 35, 38, 39, 40
_O_QUALITY, _O_QUALITY_OPENCV = 41, 42

#: :func:`tip_pose`'s output: name -> first index.
TIP: dict[str, int] = {"px": 0, "tip": 2, "axis": 5, "quat": 8, "size": 12}

#: A fitted line's record (:func:`_fit_limbs`): ``a, b, c`` (unit normal, interior
#: positive), the inliers' centre ``x, y``, their span along the axis, their count and
#: their residual RMS; NaN for no line.
FIT_LEN = 8

#: Fixed uniform draws for RANSAC (as ``silhouette._DRAWS`` was): deterministic and free.
_DRAWS = np.random.default_rng(12345).random((2, 64))
#: The tip's depth search grid over [0, 1] (numpy's own linspace values).
_UNIT_GRID = np.linspace(0.0, 1.0, 81)
#: The quality cylinder's rim: cos and sin of 24 angles (numpy's values).
_THETA = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)
_COS, _SIN = np.cos(_THETA), np.sin(_THETA)

# -- small helpers -----------------------------------------------------------------------


@kernel("float64(float64[::1], int64)")
def _select(v: np.ndarray, k: int) -> float:
    """The element of rank ``k`` of ``v`` (Hoare's quickselect, in place: afterwards no
    element left of ``k`` is larger, none right of it smaller)."""
    lo, hi = 0, len(v) - 1
    while lo < hi:
        p = v[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while v[i] < p:
                i += 1
            while v[j] > p:
                j -= 1
            if i <= j:
                v[i], v[j] = v[j], v[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return v[k]


@helper
def _kth(v: np.ndarray, n: int, k: int) -> float:
    """The element of rank ``k`` of ``v[:n]`` (no NaN; ``v``, of at least ``2 n``
    elements, is scratch): the value :func:`_select` gives, found without a branch per
    element. Each pass copies the range into the other half of ``v``, the elements below
    the pivot (a median of three) from its start and those above it from its end, every
    element written to both ends and kept at the end it belongs to; the elements equal
    to the pivot are left out (the gap between the two), so the range shrinks by at
    least one per pass. (Unsigned indices: no wrap-around checks.)"""
    one = np.uint64(1)
    lo, hi, kk = np.uint64(0), np.uint64(n), np.uint64(k)
    src, dst = np.uint64(0), np.uint64(n)
    while True:
        p0, p2 = v[src + lo], v[src + hi - one]
        p1 = v[src + lo + ((hi - lo) >> one)]
        p = max(min(p0, p1), min(max(p0, p1), p2))
        a, b = dst + lo, dst + hi - one
        for i in range(src + lo, src + hi):
            x = v[i]
            v[a] = x
            v[b] = x
            a += np.uint64(x < p)
            b -= np.uint64(x > p)
        a -= dst
        b -= dst
        if kk < a:
            hi = a
        elif kk > b:
            lo = b + one
        else:
            return p
        src, dst = dst, src


@kernel("int64[::1](float64[::1])")
def _argsort(v: np.ndarray) -> np.ndarray:
    """Indices that sort ``v`` (ascending, stable): :func:`_argsort_in` with its own
    scratch."""
    n = len(v)
    ints = np.empty(3 * n + 1, np.int64)
    return _argsort_in(v, ints, np.empty(2 * n))


@helper
def _argsort_in(v: np.ndarray, ints: np.ndarray, floats: np.ndarray) -> np.ndarray:
    """Indices that sort ``v`` (ascending, stable): a natural merge sort, so that the few
    monotone runs of one limb's boundary points (one per neighbour direction, in outline
    order) are merged in a pass or two instead of sorted from scratch. The keys move with
    their indices (one load per comparison). ``ints`` (``3 n + 1``) and ``floats``
    (``2 n``) are scratch; the answer is a view of ``ints``."""
    n = len(v)
    idx = ints[:n]
    tmp = ints[n : 2 * n]
    bounds = ints[2 * n : 3 * n + 1]
    key = floats[:n]
    tkey = floats[n : 2 * n]
    n_runs = 0
    i = 0
    while i < n:  # the runs: ascending as they are, strictly descending reversed
        j = i + 1
        if j < n and v[j] < v[i]:
            while j < n and v[j] < v[j - 1]:
                j += 1
            for k in range(j - i):
                idx[i + k] = j - 1 - k
                key[i + k] = v[j - 1 - k]
        else:
            while j < n and v[j] >= v[j - 1]:
                j += 1
            for k in range(i, j):
                idx[k] = k
                key[k] = v[k]
        bounds[n_runs] = i
        n_runs += 1
        i = j
    bounds[n_runs] = n
    while n_runs > 1:  # merge neighbouring runs pairwise
        m = 0
        for r in range(0, n_runs, 2):
            lo, mid = bounds[r], bounds[r + 1]
            hi = bounds[r + 2] if r + 2 <= n_runs else mid
            a, b, k = lo, mid, lo
            while a < mid and b < hi:
                if key[b] < key[a]:
                    tmp[k], tkey[k] = idx[b], key[b]
                    b += 1
                else:
                    tmp[k], tkey[k] = idx[a], key[a]
                    a += 1
                k += 1
            while a < mid:
                tmp[k], tkey[k] = idx[a], key[a]
                a += 1
                k += 1
            while b < hi:
                tmp[k], tkey[k] = idx[b], key[b]
                b += 1
                k += 1
            bounds[m] = lo
            m += 1
        bounds[m] = n
        n_runs = m
        idx, tmp = tmp, idx
        key, tkey = tkey, key
    return idx


@helper
def _vmax(a: np.ndarray) -> Any:
    """``a.max()`` of a 1-D float array, as numba's: the first NaN if any, else the
    first of the largest; a plain loop (numba's goes through a generic iterator)."""
    if len(a) == 0:
        raise ValueError("zero-size array to reduction operation maximum which has no identity")
    m = a[0]
    if math.isnan(m):
        return m
    for i in range(1, len(a)):
        v = a[i]
        if math.isnan(v):
            return v
        if v > m:
            m = v
    return m


@helper
def _vmin(a: np.ndarray) -> Any:
    """``a.min()`` as :func:`_vmax`."""
    if len(a) == 0:
        raise ValueError("zero-size array to reduction operation minimum which has no identity")
    m = a[0]
    if math.isnan(m):
        return m
    for i in range(1, len(a)):
        v = a[i]
        if math.isnan(v):
            return v
        if v < m:
            m = v
    return m


@kernel("float64(float64[::1])")
def _median(v: np.ndarray) -> float:
    """Median of a 1-D array (``np.median``; the same value), len >= 1; reorders ``v``."""
    n = len(v)
    k = n // 2
    upper = _select(v, k)
    if n % 2:
        return upper
    lower = v[0]
    for i in range(1, k):
        lower = max(lower, v[i])
    return 0.5 * (lower + upper)


@helper
def _median_in(v: np.ndarray, n: int, stride: int, scratch: np.ndarray) -> float:
    """:func:`_median` of ``v[0], v[stride], ... v[(n - 1) stride]`` (``n >= 1``; ``v``
    left as it is; ``scratch``: at least ``2 n`` elements): the same value, from
    :func:`_kth` (no branch per element) where that is sure to be it, i.e. where neither
    a NaN (the selections' orders differ) nor a negative zero (it equals 0.0: which of
    the two a selection returns depends on its order) is among the values; else from
    :func:`_median` itself. The middle pair's lower value of an even count is the
    largest value below the upper one, or the upper one when fewer than ``n / 2``
    values lie below it."""
    odd = False
    for i in range(n):
        x = v[i * stride]
        scratch[i] = x
        odd |= math.isnan(x) or (x == 0.0 and math.copysign(1.0, x) < 0.0)
    if odd:
        return _median(scratch[:n].copy())
    k = n // 2
    upper = _kth(scratch, n, k)
    if n % 2:
        return upper
    below = 0
    lower = -math.inf
    for i in range(n):
        x = v[i * stride]
        below += x < upper
        lower = max(lower, x) if x < upper else lower
    if below < k:
        lower = upper
    return 0.5 * (lower + upper)


@_inlined("UniTuple(float64, 3)(float64, float64, float64[:, ::1])")
def _ray(u: float, v: float, K: np.ndarray) -> tuple[float, float, float]:  # noqa: N803
    """Unit viewing ray of a pixel (``cylinder.pixel_rays``)."""
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    n = math.sqrt(x * x + y * y + 1.0)
    return x / n, y / n, 1.0 / n


@_inlined("float64(float64, float64, float64[:, ::1], float64[::1], float64[::1])")
def _closest1(u: float, v: float, K: np.ndarray, p0: np.ndarray, a: np.ndarray) -> float:  # noqa: N803
    """Axial coordinate of the axis point closest to a pixel's ray (``closest_on_axis``)."""
    dx, dy, dz = _ray(u, v, K)
    da = dx * a[0] + dy * a[1] + dz * a[2]
    dp = dx * p0[0] + dy * p0[1] + dz * p0[2]
    ap = a[0] * p0[0] + a[1] * p0[1] + a[2] * p0[2]
    return (da * dp - ap) / max(1.0 - da * da, 1e-12)


@_inlined("UniTuple(float64, 3)(float64, float64, float64, float64[:, ::1])")
def _plane_normal(a0: float, a1: float, a2: float, K: np.ndarray) -> tuple[float, float, float]:  # noqa: N803
    """Unit ``K^T line`` (``cylinder.plane_normal``)."""
    m0 = a0 * K[0, 0] + a1 * K[1, 0] + a2 * K[2, 0]
    m1 = a0 * K[0, 1] + a1 * K[1, 1] + a2 * K[2, 1]
    m2 = a0 * K[0, 2] + a1 * K[1, 2] + a2 * K[2, 2]
    mn = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
    return m0 / mn, m1 / mn, m2 / mn


@kernel(
    "boolean(float64, float64, float64, float64, float64, float64, float64[:, ::1], float64,"
    " float64[::1])"
)
def _axis_from_lines(
    la: float,
    lb: float,
    lc: float,
    ma: float,
    mb: float,
    mc: float,
    K: np.ndarray,  # noqa: N803
    radius: float,
    out: np.ndarray,
) -> bool:
    """``cylinder.axis_from_image_lines``: ``out[:3]`` the axis point, ``out[3:6]`` the
    unit direction; False when there is none."""
    p, q, r = _plane_normal(la, lb, lc, K)
    u, v, w = _plane_normal(ma, mb, mc, K)
    c = p * u + q * v + r * w
    if c <= -0.999999:
        return False
    cx, cy, cz = q * w - r * v, r * u - p * w, p * v - q * u
    sn = math.sqrt(cx * cx + cy * cy + cz * cz)
    if sn < 1e-9:
        return False
    f = radius / (1.0 + c)
    out[0], out[1], out[2] = f * (p + u), f * (q + v), f * (r + w)
    out[3], out[4], out[5] = cx / sn, cy / sn, cz / sn
    return True


@helper
def _quat_from_z(x: float, y: float, z: float, out: np.ndarray) -> None:
    """``cylinder.quat_from_z`` into ``out[:4]``."""
    if z < -1.0 + 1e-12:
        out[0], out[1], out[2], out[3] = 0.0, 1.0, 0.0, 0.0
        return
    w = 1.0 + z
    n = math.sqrt(w * w + y * y + x * x + 0.0 * 0.0)
    out[0], out[1], out[2], out[3] = w / n, -y / n, x / n, 0.0 / n


# -- boundary points ---------------------------------------------------------------------


@helper
def _contour_moments(outline: np.ndarray, start: int, stop: int, mom: np.ndarray) -> None:
    """Adds a closed contour's region moments ``m00, m10, m01, m20, m11, m02`` to ``mom``
    (``cv2.moments`` of the contour: Green's theorem over its polygon, in exact integer
    sums for image coordinates)."""
    a00 = a10 = a01 = a20 = a11 = a02 = 0.0
    xi_1 = float(outline[stop - 1, 0])
    yi_1 = float(outline[stop - 1, 1])
    for i in range(start, stop):
        xi = float(outline[i, 0])
        yi = float(outline[i, 1])
        xi2 = xi * xi
        yi2 = yi * yi
        dxy = xi_1 * yi - xi * yi_1
        xii_1 = xi_1 + xi
        yii_1 = yi_1 + yi
        a00 += dxy
        a10 += dxy * xii_1
        a01 += dxy * yii_1
        a20 += dxy * (xi_1 * xii_1 + xi2)
        a11 += dxy * (xi_1 * (yii_1 + yi_1) + xi * (yii_1 + yi))
        a02 += dxy * (yi_1 * yii_1 + yi2)
        xi_1 = xi
        yi_1 = yi
    if abs(a00) > 1.1920928955078125e-07:  # FLT_EPSILON, as OpenCV
        sign = 1.0 if a00 > 0 else -1.0
        mom[0] += a00 * (sign * 0.5)
        mom[1] += a10 * (sign * 0.16666666666666666666666666666667)
        mom[2] += a01 * (sign * 0.16666666666666666666666666666667)
        mom[3] += a20 * (sign * 0.083333333333333333333333333333333)
        mom[4] += a11 * (sign * 0.041666666666666666666666666666667)
        mom[5] += a02 * (sign * 0.083333333333333333333333333333333)


@helper
def _at(flat: np.ndarray, h: int, w: int, x: int, y: int) -> int:
    """1 when a crop (``flat``: its (h, w) bytes) holds its pixel ``(x, y)`` (any
    integers), else 0."""
    if x < 0 or y < 0 or x >= w or y >= h:
        return 0
    return flat[y * w + x]


@kernel(
    "void(int32[:, ::1], uint8[::1], int64, int64, int64, int64, uint8[::1], int64, int64,"
    " int64, int64, int64, int64, uint8[:, ::1])"
)
def _neighbour_labels(
    outline: np.ndarray,
    shaft: np.ndarray,
    sh: int,
    sw: int,
    sx: int,
    sy: int,
    other: np.ndarray,
    oh: int,
    ow: int,
    ox: int,
    oy: int,
    height: int,
    width: int,
    labels: np.ndarray,
) -> None:
    """The labels of each outline pixel's four neighbours (right, left, down, up):
    ``labels[d, i]`` SHAFT (the part, or outside the image: no point), OTHER (an other
    part's crop holds it) or BG. Masks as flat bytes; ``(sh, sw)``, ``(oh, ow)`` their
    shapes. Called first with an empty ``other`` (the part's own labels), then once per
    other part (BG labels it holds become OTHER).

    Written for speed: the branches taken depend on where the pixel is (long runs along
    the outline), not on the masks' values; no call with an array inside the loop."""
    n = len(outline)
    one, usw = np.uint64(1), np.uint64(sw)
    for i in range(n):
        px, py = outline[i, 0], outline[i, 1]  # crop px
        if oh:
            pass  # the part's own labels are set already
        elif 0 < px < sw - 1 and 0 < py < sh - 1:  # all four neighbours in the crop
            k = np.uint64(py * sw + px)  # unsigned: no wrap-around checks
            labels[0, i] |= shaft[k + one]
            labels[1, i] |= shaft[k - one]
            labels[2, i] |= shaft[k + usw]
            labels[3, i] |= shaft[k - usw]
        else:
            for d in range(4):
                cx = px + (1 if d == 0 else (-1 if d == 1 else 0))
                cy = py + (1 if d == 2 else (-1 if d == 3 else 0))
                x, y = cx + sx, cy + sy  # full-image px
                off_image = x < 0 or y < 0 or x >= width or y >= height
                labels[d, i] |= off_image or _at(shaft, sh, sw, cx, cy)
        a, b = px + sx - ox, py + sy - oy  # in the other part's crop
        if oh and -1 <= a <= ow and -1 <= b <= oh:
            for d in range(4):
                ca = a + (1 if d == 0 else (-1 if d == 1 else 0))
                cb = b + (1 if d == 2 else (-1 if d == 3 else 0))
                v = _at(other, oh, ow, ca, cb)
                labels[d, i] += (v & (labels[d, i] == _BG)) * _OTHER


_BOUNDARY_OUT = (
    "Tuple((float64[:, ::1], boolean[::1], float64[:, ::1], float64[:, ::1], float64[::1]))"
)


@kernel(
    _BOUNDARY_OUT + "(int32[:, ::1], int64[::1], boolean[:, ::1], int64, int64, boolean[:, ::1],"
    " int64, int64, boolean[:, ::1], int64, int64, int64, int64)"
)
def shaft_boundary(
    outline: np.ndarray,
    starts: np.ndarray,
    shaft: np.ndarray,
    sx: int,
    sy: int,
    o1: np.ndarray,
    x1: int,
    y1: int,
    o2: np.ndarray,
    x2: int,
    y2: int,
    height: int,
    width: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The shaft's outline pixels, their border flags, its boundary points and moments.

    Args:
        outline: (N, 2) the outline pixels of the shaft crop (crop px, ``cv2.findContours``,
            its contours one after the other).
        starts: (C + 1,) where each contour starts in ``outline``, then N.
        shaft: (h, w) the shaft crop; ``sx, sy`` its offset (px).
        o1, o2: the instrument's other parts' crops (``(0, 0)`` for none), offsets
            ``(x1, y1)``, ``(x2, y2)``: their pixels are the OTHER label.
        height, width: the image's size (px).

    Returns:
        ``(pix, border, bg, other, moments)``: (N, 2) the outline pixels (full-image px),
        (N,) on the image border, the boundary points (full-image px) next to background
        (M, 2) and next to other parts (L, 2) - for each of the four neighbours (right,
        left, down, up) in turn, along the outline (a pair leaving the image gives no
        point) - and the region moments ``m00, m10, m01, m20, m11, m02`` (crop px, summed
        over the contours).
    """
    n = outline.shape[0]
    labels = np.zeros((4, n), np.uint8)
    sh, sw = shaft.shape
    flat = shaft.view(np.uint8).ravel()
    _neighbour_labels(outline, flat, sh, sw, sx, sy, flat[:0], 0, 0, 0, 0, height, width, labels)
    for m, mx, my in ((o1, x1, y1), (o2, x2, y2)):
        oh, ow = m.shape
        if oh and ow:
            f = m.view(np.uint8).ravel()
            _neighbour_labels(
                outline, flat, sh, sw, sx, sy, f, oh, ow, mx, my, height, width, labels
            )
    pix = np.empty((n, 2))
    border = np.empty(n, np.bool_)
    for i in range(n):
        x = float(outline[i, 0] + sx)
        y = float(outline[i, 1] + sy)
        pix[i, 0], pix[i, 1] = x, y
        border[i] = x <= 0 or y <= 0 or x >= width - 1 or y >= height - 1
    bg, other = _boundary_points(pix, labels)
    mom = np.zeros(6)
    for c in range(len(starts) - 1):
        _contour_moments(outline, starts[c], starts[c + 1], mom)
    return pix, border, bg, other, mom


@helper
def _boundary_points(pix: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The boundary points of the outline pixels ``pix`` (full-image px) next to
    background and next to other parts, by their neighbours' ``labels``
    (:func:`_neighbour_labels`): :func:`shaft_boundary`'s ``bg, other``."""
    n = len(pix)
    # a background point is written, and kept (the count advanced) when it is one: no
    # branch on the label; points next to other parts are few (a rare branch)
    bg = np.empty((4 * n + 1, 2))
    other = np.empty((4 * n, 2))
    k_bg = k_other = 0
    for d in range(4):
        hx = 0.5 if d == 0 else (-0.5 if d == 1 else 0.0)
        hy = 0.5 if d == 2 else (-0.5 if d == 3 else 0.0)
        for i in range(n):
            lab = labels[d, i]
            fx, fy = pix[i, 0] + hx, pix[i, 1] + hy
            bg[k_bg, 0], bg[k_bg, 1] = fx, fy
            k_bg += lab == _BG
            if lab == _OTHER:
                other[k_other, 0], other[k_other, 1] = fx, fy
                k_other += 1
    return bg[:k_bg], other[:k_other]


@kernel("void(uint8[:, ::1], float64[::1])")
def raster_moments(canvas: np.ndarray, mom: np.ndarray) -> None:
    """The moments ``m00, m10, m01, m20, m11, m02`` of a 0/1 image's pixels into ``mom``
    (``cv2.moments(canvas, binaryImage=True)``: exact integer sums)."""
    h, w = canvas.shape
    m00 = m10 = m01 = m20 = m11 = m02 = 0
    for y in range(h):
        row = canvas[y]
        r0 = r1 = r2 = 0
        for x in range(w):
            v = np.int64(row[x] != 0)
            r0 += v
            r1 += v * x
            r2 += v * x * x
        m00 += r0
        m10 += r1
        m01 += r0 * y
        m20 += r2
        m11 += r1 * y
        m02 += r0 * y * y
    mom[0], mom[1], mom[2], mom[3], mom[4], mom[5] = m00, m10, m01, m20, m11, m02


@kernel("UniTuple(float64, 3)(float64[::1])")
def _central(mom: np.ndarray) -> tuple[float, float, float]:
    """``mu20, mu11, mu02`` from raw moments, as OpenCV computes them."""
    inv = 1.0 / mom[0] if abs(mom[0]) > 2.220446049250313e-16 else 0.0
    cx, cy = mom[1] * inv, mom[2] * inv
    return mom[3] - mom[1] * cx, mom[4] - mom[1] * cy, mom[5] - mom[2] * cy


@kernel("boolean(int32[:, ::1], int64[::1], uint8[:, ::1], int64, int64, float64, float64)")
def one_cut_shaft(
    outline: np.ndarray,
    starts: np.ndarray,
    union: np.ndarray,
    x0: int,
    y0: int,
    max_angle_deg: float,
    max_offset_frac: float,
) -> bool:
    """Whether shaft pieces are one shaft cut across (``measure._one_cut_shaft``): each
    piece's centroid on the pieces' common axis (within ``max_offset_frac`` of the piece's
    own width across it) and each elongated piece along it (``max_angle_deg``).

    Args:
        outline: (N, 2) the pieces' contours (image px), one after the other.
        starts: (C + 1,) where each starts in ``outline``, then N.
        union: the pieces filled (0/1), its pixel ``(0, 0)`` at the image's ``(x0, y0)``.
    """
    mom = np.zeros(6)
    raster_moments(union, mom)
    return _one_cut(outline, starts, mom, x0, y0, max_angle_deg, max_offset_frac)


@helper
def _one_cut(
    outline: np.ndarray,
    starts: np.ndarray,
    mom: np.ndarray,
    x0: int,
    y0: int,
    max_angle_deg: float,
    max_offset_frac: float,
) -> bool:
    """:func:`one_cut_shaft` from the filled pieces' moments ``mom`` (origin ``(x0, y0)``)."""
    if mom[0] <= 0:
        return False
    mu20, mu11, mu02 = _central(mom)
    theta = 0.5 * math.atan2(2.0 * mu11, mu20 - mu02)
    e0, e1 = math.cos(theta), math.sin(theta)
    n0, n1 = -e1, e0
    c0x, c0y = mom[1] / mom[0] + x0, mom[2] / mom[0] + y0
    mk = np.empty(6)
    for c in range(len(starts) - 1):
        lo_n = lo_e = math.inf
        hi_n = hi_e = -math.inf
        for i in range(starts[c], starts[c + 1]):
            x, y = float(outline[i, 0]), float(outline[i, 1])
            a, b = x * n0 + y * n1, x * e0 + y * e1
            lo_n, hi_n = min(lo_n, a), max(hi_n, a)
            lo_e, hi_e = min(lo_e, b), max(hi_e, b)
        across, along = hi_n - lo_n, hi_e - lo_e
        mk[:] = 0.0
        _contour_moments(outline, starts[c], starts[c + 1], mk)
        if mk[0] <= 0:
            return False
        ckx, cky = mk[1] / mk[0], mk[2] / mk[0]
        if abs((ckx - c0x) * n0 + (cky - c0y) * n1) > max_offset_frac * across:
            return False
        if along >= 1.5 * across:  # elongated: its own direction must agree
            k20, k11, k02 = _central(mk)
            tk = 0.5 * math.atan2(2.0 * k11, k20 - k02)
            if abs((math.degrees(tk - theta) + 90.0) % 180.0 - 90.0) > max_angle_deg:
                return False
    return True


# -- robust line fit ---------------------------------------------------------------------


@helper
def _tls(
    m00: float, m01: float, m02: float, m11: float, m12: float, sw: float, line: np.ndarray
) -> None:
    """Total-least-squares line from the weighted moments of centred points
    (``silhouette._tls_moments``) into ``line[:3]``."""
    mx, my = m02 / sw, m12 / sw
    sxx = m00 - sw * mx * mx
    sxy = m01 - sw * mx * my
    syy = m11 - sw * my * my
    phi = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
    nx, ny = -math.sin(phi), math.cos(phi)
    line[0], line[1], line[2] = nx, ny, -(nx * mx + ny * my)


@helper
def _irls_step(
    x: np.ndarray,
    y: np.ndarray,
    r: np.ndarray,
    line: np.ndarray,
    scale: float,
    thresh: float,
    core: np.ndarray,
) -> float:
    """One Tukey-weighted refit: ``line`` and the residuals ``r`` updated in place; the new
    scale, or -1 (nothing changed) when the weights sum below 6. ``core``: scratch of
    ``2 len(x)`` elements."""
    n = len(x)
    f = 1.0 / (2.5 * scale)
    m00 = m01 = m02 = m11 = m12 = sw = 0.0
    for t in range(n):
        u = r[t] * f
        w = max(1.0 - u * u, 0.0)
        w *= w
        xw = x[t] * w
        yw = y[t] * w
        m00 += xw * x[t]
        m01 += xw * y[t]
        m02 += xw
        m11 += yw * y[t]
        m12 += yw
        sw += w
    if sw < 6:
        return -1.0
    _tls(m00, m01, m02, m11, m12, sw, line)
    k = 0
    lim = 2.5 * scale
    for t in range(n):
        r[t] = line[0] * x[t] + line[1] * y[t] + line[2]
        ra = abs(r[t])
        if ra < lim:
            core[k] = ra
            k += 1
    if k:
        scale = min(max(1.4826 * _kth(core, k, k // 2), 0.3), thresh)
    return scale


@helper
def _sum8(v: np.ndarray) -> float:
    """Sum in eight interleaved running sums (numpy's order for up to 128 values:
    independent sums run in parallel; a NaN anywhere gives NaN)."""
    n = len(v)
    if n < 8:
        tot = 0.0
        for i in range(n):
            tot += v[i]
        return tot
    r0, r1, r2, r3, r4, r5, r6, r7 = v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7]
    m = n - n % 8
    for i in range(8, m, 8):
        r0 += v[i]
        r1 += v[i + 1]
        r2 += v[i + 2]
        r3 += v[i + 3]
        r4 += v[i + 4]
        r5 += v[i + 5]
        r6 += v[i + 6]
        r7 += v[i + 7]
    tot = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    for i in range(m, n):
        tot += v[i]
    return tot


@helper
def _ransac_in(
    x: np.ndarray,
    y: np.ndarray,
    along: np.ndarray,
    thresh: float,
    iters: int,
    h: np.ndarray,
    ints: np.ndarray,
    floats: np.ndarray,
) -> int:
    """MSAC over the lines through pairs of points from both halves along the line (the
    fixed draws): the best line into ``h[:3]``; its inlier count, or -1 for none.
    ``ints`` (``3 n + 1``) and ``floats`` (``3 n``) are scratch."""
    n = len(x)
    order = _argsort_in(along, ints, floats)
    half = n // 2
    best = math.inf
    res = floats[2 * n : 3 * n]
    found = False
    for k in range(iters):
        i = order[int(_DRAWS[0, k] * half)]
        j = order[n - half + int(_DRAWS[1, k] * half)]
        h0, h1 = y[i] - y[j], x[j] - x[i]
        ln = math.sqrt(h0 * h0 + h1 * h1)
        if not ln > 1e-9:  # NaN falls through: its residuals say no line
            if not math.isnan(ln):
                continue
        h0, h1 = h0 / ln, h1 / ln
        c = -(h0 * x[i] + h1 * y[i])
        for t in range(n):
            res[t] = min(abs(h0 * x[t] + h1 * y[t] + c), thresh)
        cost = _sum8(res)
        if math.isnan(cost):  # a NaN line or point: no line
            return -1
        if cost < best:
            best = cost
            h[0], h[1], h[2] = h0, h1, c
            found = True
    if not found:
        return -1
    count = 0
    for t in range(n):
        count += abs(h[0] * x[t] + h[1] * y[t] + h[2]) < thresh
    return count


@kernel("int64(float64[::1], float64[::1], float64[::1], float64, int64, float64[::1], int64[::1])")
def fit_line(
    px: np.ndarray,
    py: np.ndarray,
    along: np.ndarray,
    thresh: float,
    iters: int,
    line: np.ndarray,
    inliers: np.ndarray,
) -> int:
    """Robust sub-pixel line (``silhouette.fit_line_robust`` on at most its
    ``max_points``): RANSAC on long baselines, then two Tukey-weighted TLS refits.

    Args:
        px, py: (N,) the points (px); along: (N,) their coordinate along the line.
        thresh: inlier threshold (px); iters: RANSAC hypotheses (<= 64).
        line: (4,) receives ``a, b, c`` (unit normal) and the inliers' residual RMS.
        inliers: (N,) receives the inliers' indices.

    Returns:
        The inlier count, or -1 for no line (fewer than 8 points, fewer than 6 inliers).
    """
    n = len(px)
    floats = np.empty(_FIT_FLOATS * n + 3)
    ints = np.empty(_FIT_INTS * n + 1, np.int64)
    return _fit_line_in(px, py, along, thresh, iters, line, inliers, floats, ints)


#: Scratch of :func:`_fit_line_in` per point: ``_FIT_FLOATS n + 3`` floats, ``_FIT_INTS n
#: + 1`` integers.
_FIT_FLOATS, _FIT_INTS = 5, 3


@helper
def _fit_line_in(
    px: np.ndarray,
    py: np.ndarray,
    along: np.ndarray,
    thresh: float,
    iters: int,
    line: np.ndarray,
    inliers: np.ndarray,
    floats: np.ndarray,
    ints: np.ndarray,
) -> int:
    """:func:`fit_line` with its scratch given (``floats``: ``_FIT_FLOATS n + 3``,
    ``ints``: ``_FIT_INTS n + 1``): no allocation."""
    n = len(px)
    if n < 8:
        return -1
    sx = sy = 0.0
    for t in range(n):
        sx += px[t]
        sy += py[t]
    ox, oy = sx * (1.0 / n), sy * (1.0 / n)
    x = floats[:n]
    y = floats[n : 2 * n]
    for t in range(n):
        x[t] = px[t] - ox
        y[t] = py[t] - oy
    h = floats[_FIT_FLOATS * n : _FIT_FLOATS * n + 3]
    if _ransac_in(x, y, along, thresh, iters, h, ints, floats[2 * n : 5 * n]) < 6:
        return -1
    m00 = m01 = m02 = m11 = m12 = sw = 0.0
    for t in range(n):
        if abs(h[0] * x[t] + h[1] * y[t] + h[2]) < thresh:
            m00 += x[t] * x[t]
            m01 += x[t] * y[t]
            m02 += x[t]
            m11 += y[t] * y[t]
            m12 += y[t]
            sw += 1.0
    _tls(m00, m01, m02, m11, m12, sw, line)
    r = floats[2 * n : 3 * n]  # (the RANSAC's scratch is free again)
    for t in range(n):
        r[t] = line[0] * x[t] + line[1] * y[t] + line[2]
    scale = thresh
    core = floats[3 * n : 5 * n]
    for _ in range(2):
        step = _irls_step(x, y, r, line, scale, thresh, core)
        if step < 0:
            break
        scale = step
    lim = max(2.5 * scale, 0.75)
    k = 0
    ss = 0.0
    for t in range(n):
        if abs(r[t]) < lim:
            inliers[k] = t
            ss += r[t] * r[t]
            k += 1
    line[3] = math.sqrt(ss / k) if k else math.inf
    line[2] -= line[0] * ox + line[1] * oy
    return k


# -- the shaft's image frame and limb points ---------------------------------------------

#: The shaft's image frame (:func:`_frame`): entries of its array.
_F_E, _F_P, _F_SMIN, _F_SMAX, _F_DISTAL, _F_PROXB, _F_DISTB, _F_MED, _F_WIDTH = (
    0,
    2,
    4,
    5,
    6,
    7,
    8,
    9,
    11,
)
_F_LEN = 12


@kernel("UniTuple(float64, 2)(float64[:, ::1], boolean[::1])")
def _mean_rows(pts: np.ndarray, select: np.ndarray) -> tuple[float, float]:
    """Mean of the selected rows (running sums, as ``sum_rows``); NaN for none."""
    sx = sy = 0.0
    k = 0
    for i in range(len(select)):
        if select[i]:
            sx += pts[i, 0]
            sy += pts[i, 1]
            k += 1
    if not k:
        return math.nan, math.nan
    return sx / k, sy / k


@kernel(
    "void(float64[:, ::1], boolean[::1], float64[::1], float64[::1], float64[:, ::1], float64[::1])"
)
def _initial_direction(
    pix: np.ndarray,
    border: np.ndarray,
    centre: np.ndarray,
    mom: np.ndarray,
    other: np.ndarray,
    fr: np.ndarray,
) -> None:
    """``measure._initial_direction`` into ``fr[_F_E:_F_E + 2]`` (and the other parts'
    median point into ``fr[_F_MED:_F_MED + 2]``)."""
    m00 = mom[0]
    xm, ym = mom[1] / m00, mom[2] / m00
    mu20 = mom[3] / m00 - xm * xm
    mu02 = mom[5] / m00 - ym * ym
    mu11 = mom[4] / m00 - xm * ym
    cx, cy = centre[0], centre[1]
    fr[_F_MED] = fr[_F_MED + 1] = math.nan
    if len(other) >= 3:
        n_other = len(other)
        flat = other.reshape(2 * n_other)
        scratch = np.empty(2 * n_other)
        fr[_F_MED] = _median_in(flat, n_other, 2, scratch)
        fr[_F_MED + 1] = _median_in(flat[1:], n_other, 2, scratch)
    theta = 0.5 * math.atan2(2.0 * mu11, mu20 - mu02)
    e0, e1 = math.cos(theta), math.sin(theta)
    tr, det = mu20 + mu02, mu20 * mu02 - mu11 * mu11
    disc = math.sqrt(max(tr * tr / 4.0 - det, 0.0))
    d0x = d0y = math.nan
    if len(other) >= 3:
        d0x, d0y = fr[_F_MED] - cx, fr[_F_MED + 1] - cy
    elif tr / 2.0 + disc < 9.0 * max(tr / 2.0 - disc, 1e-9) and border.any():
        mx, my = _mean_rows(pix, border)
        d0x, d0y = cx - mx, cy - my
    if not math.isnan(d0x):
        nd0 = math.hypot(d0x, d0y)
        if nd0 > 2.0:
            e0, e1 = d0x / nd0, d0y / nd0
    fr[_F_E], fr[_F_E + 1] = e0, e1


@kernel(
    "void(float64[:, ::1], boolean[::1], float64[::1], float64[::1], float64[:, ::1],"
    " float64[::1], float64[::1])"
)
def _frame(
    pix: np.ndarray,
    border: np.ndarray,
    centre: np.ndarray,
    mom: np.ndarray,
    other: np.ndarray,
    fr: np.ndarray,
    s_pix: np.ndarray,
) -> None:
    """``measure._shaft_frame``: the frame into ``fr``, the outline pixels' coordinates
    along the (distal) axis into ``s_pix``."""
    _initial_direction(pix, border, centre, mom, other, fr)
    e0, e1 = fr[_F_E], fr[_F_E + 1]
    cx, cy = centre[0], centre[1]
    n = len(pix)
    for i in range(n):
        s_pix[i] = (pix[i, 0] - cx) * e0 + (pix[i, 1] - cy) * e1
    lo, hi = _vmin(s_pix), _vmax(s_pix)
    distal = 0
    if len(other) >= 3:
        tot = 0.0
        for i in range(len(other)):
            tot += (other[i, 0] - cx) * e0 + (other[i, 1] - cy) * e1
        distal = 1 if tot >= 0 else -1
    else:
        t_lo = t_hi = False
        for i in range(n):
            t_lo |= border[i] & (s_pix[i] <= lo + 2.0)
            t_hi |= border[i] & (s_pix[i] >= hi - 2.0)
        distal = 1 if (t_lo and not t_hi) else (-1 if (t_hi and not t_lo) else 0)
    if distal < 0:
        e0, e1 = -e0, -e1
        for i in range(n):
            s_pix[i] = -s_pix[i]
        lo, hi = -hi, -lo
    a_lo, a_hi = math.inf, -math.inf
    prox = dist = False
    for i in range(n):
        across = (pix[i, 0] - cx) * -e1 + (pix[i, 1] - cy) * e0
        a_lo, a_hi = min(a_lo, across), max(a_hi, across)
        prox |= border[i] & (s_pix[i] <= lo + 2.0)
        dist |= border[i] & (s_pix[i] >= hi - 2.0)
    fr[_F_E], fr[_F_E + 1], fr[_F_P], fr[_F_P + 1] = e0, e1, -e1, e0
    fr[_F_SMIN], fr[_F_SMAX] = lo, hi
    fr[_F_DISTAL] = distal
    fr[_F_PROXB], fr[_F_DISTB] = prox, dist
    fr[_F_WIDTH] = a_hi - a_lo


@_inlined("boolean(float64, float64, float64[:, ::1])")
def _near_other(x: float, y: float, other: np.ndarray) -> bool:
    """Within 2 px (strictly) of every other point of ``other`` (``measure._near``)."""
    for j in range(0, len(other), 2):
        dx = x - other[j, 0]
        dy = y - other[j, 1]
        if dx * dx + dy * dy < 4.0:
            return True
    return False


@kernel(
    "float64(float64[:, ::1], float64[:, ::1], float64[::1], float64[::1], float64[::1],"
    " float64[::1], boolean[::1], boolean[::1])"
)
def _limb_points(
    pts: np.ndarray,
    other: np.ndarray,
    centre: np.ndarray,
    fr: np.ndarray,
    s: np.ndarray,
    q: np.ndarray,
    keep_base: np.ndarray,
    keep: np.ndarray,
) -> float:
    """``measure._limb_points``: each background point's coordinates along / across the
    axis, kept away from the end zones and other parts; the end zones' length (px)."""
    s_min, s_max, width = fr[_F_SMIN], fr[_F_SMAX], fr[_F_WIDTH]
    zone = min(0.6 * width + 2.0, max(3.0, 0.15 * (s_max - s_min)))
    prox_free = not fr[_F_PROXB]
    lo_x = lo_y = hi_x = hi_y = 0.0
    if len(other):
        lo_x, lo_y = _vmin(other[:, 0]) - 2.0, _vmin(other[:, 1]) - 2.0
        hi_x, hi_y = _vmax(other[:, 0]) + 2.0, _vmax(other[:, 1]) + 2.0
    e0, e1, p0, p1 = fr[_F_E], fr[_F_E + 1], fr[_F_P], fr[_F_P + 1]
    cx, cy = centre[0], centre[1]
    for i in range(len(pts)):
        rx, ry = pts[i, 0] - cx, pts[i, 1] - cy
        s[i] = rx * e0 + ry * e1
        q[i] = rx * p0 + ry * p1
        keep_base[i] = (s[i] > s_min + zone) | (not prox_free)
    if len(other):  # points within 2 px of another part (a branch on where they are)
        for i in range(len(pts)):
            x, y = pts[i, 0], pts[i, 1]
            if lo_x <= x <= hi_x and lo_y <= y <= hi_y and keep_base[i]:
                keep_base[i] = not _near_other(x, y, other)
    for i in range(len(pts)):
        keep[i] = keep_base[i] & (s[i] < s_max - zone)
    return zone


@helper
def _fit_side(
    pts: np.ndarray,
    s: np.ndarray,
    par: np.ndarray,
    use: np.ndarray,
    cx: float,
    cy: float,
    fit: np.ndarray,
    line: np.ndarray,
    floats: np.ndarray,
    ints: np.ndarray,
) -> bool:
    """One side's limb line from the points ``use`` (already subsampled) into ``fit``
    (:data:`FIT_LEN` entries), or False. Scratch: ``floats`` of ``(3 + _FIT_FLOATS) n +
    3``, ``ints`` of ``(1 + _FIT_INTS) n + 1`` (no allocation)."""
    n = len(use)
    if n < par[_P_MIN_POINTS]:
        return False
    px, py, al = floats[:n], floats[n : 2 * n], floats[2 * n : 3 * n]
    for k in range(n):
        px[k], py[k], al[k] = pts[use[k], 0], pts[use[k], 1], s[use[k]]
    inl = ints[:n]
    thresh, iters = par[_P_FIT_THRESH], int(par[_P_FIT_ITERS])
    n_in = _fit_line_in(px, py, al, thresh, iters, line, inl, floats[3 * n :], ints[n:])
    if n_in < 0:
        return False
    lo = hi = 0.0
    sx = sy = 0.0
    for k in range(n_in):
        i = use[inl[k]]
        if k == 0 or s[i] < lo:
            lo = s[i]
        if k == 0 or s[i] > hi:
            hi = s[i]
        sx += pts[i, 0]
        sy += pts[i, 1]
    span = hi - lo if n_in else 0.0
    if n_in < par[_P_MIN_POINTS] or span < par[_P_MIN_SPAN]:
        return False
    sign = -1.0 if line[0] * cx + line[1] * cy + line[2] < 0 else 1.0
    fit[0], fit[1], fit[2] = sign * line[0], sign * line[1], sign * line[2]
    fit[3], fit[4] = sx / n_in, sy / n_in
    fit[5], fit[6], fit[7] = span, n_in, line[3]
    return True


@kernel(
    "void(float64[:, ::1], float64[::1], float64[::1], boolean[::1], float64[::1], float64[::1],"
    " float64[:, ::1])"
)
def _fit_limbs(
    pts: np.ndarray,
    s: np.ndarray,
    q: np.ndarray,
    keep: np.ndarray,
    centre: np.ndarray,
    par: np.ndarray,
    fits: np.ndarray,
) -> None:
    """``measure._fit_limbs``: one robust line per side of the axis (``fits[0]`` on the
    negative side, ``fits[1]`` the positive), interior (the centre) positive; a row of
    NaN for no line, and the worse of two lines on the same limb dropped."""
    cap = int(par[_P_FIT_MAX])
    line = np.empty(4)
    m = len(pts)
    sides = np.empty((2, m + 1), np.int64)
    most = min(m, cap)  # a side's points, at most
    floats = np.empty((3 + _FIT_FLOATS) * most + 3)  # _fit_side's scratch, both sides
    ints = np.empty((1 + _FIT_INTS) * most + 1, np.int64)
    n0 = n1 = 0
    for i in range(m):  # each index written to both lists, kept in its own: no branch
        sides[0, n0] = i
        sides[1, n1] = i
        n0 += keep[i] & (q[i] < 0)
        n1 += keep[i] & (q[i] > 0)
    for side in range(2):
        fits[side, :] = math.nan
        use = sides[side]
        n = n0 if side == 0 else n1
        if n > cap:  # a regular subsample (silhouette.regular_subsample)
            for k in range(cap):
                use[k] = use[k * (n - 1) // (cap - 1)]
            n = cap
        if not _fit_side(
            pts, s, par, use[:n], centre[0], centre[1], fits[side], line, floats, ints
        ):
            fits[side, :] = math.nan
    if not math.isnan(fits[0, 0]) and not math.isnan(fits[1, 0]):
        if fits[0, 0] * fits[1, 0] + fits[0, 1] * fits[1, 1] > 0:  # the same limb twice
            fits[0 if fits[0, 7] > fits[1, 7] else 1, :] = math.nan


# -- the axis and the joint --------------------------------------------------------------


@kernel(
    "boolean(float64[:, ::1], float64[:, ::1], float64, float64[::1], float64[::1], float64[::1])"
)
def _solve_axis(
    fits: np.ndarray,
    K: np.ndarray,  # noqa: N803
    radius: float,
    centre: np.ndarray,
    fr: np.ndarray,
    axis: np.ndarray,
) -> bool:
    """``measure._solve_axis``: ``axis[:3]`` a point ``p0``, ``axis[3:6]`` the distal
    direction ``a``, ``axis[6:9]`` the point seen at the centroid; False when the solution
    is behind the camera or its apparent width disagrees with the mask's."""
    if not _axis_from_lines(
        fits[0, 0], fits[0, 1], fits[0, 2], fits[1, 0], fits[1, 1], fits[1, 2], K, radius, axis
    ):
        return False
    p0, a = axis[0:3], axis[3:6]
    tc = _closest1(centre[0], centre[1], K, p0, a)
    x0, y0, z0 = p0[0] + tc * a[0], p0[1] + tc * a[1], p0[2] + tc * a[2]
    axis[6], axis[7], axis[8] = x0, y0, z0
    if z0 <= 0:
        return False
    ax, ay, az = a[0], a[1], a[2]
    z1 = z0 + az
    du = K[0, 0] * ((x0 + ax) / z1 - x0 / z0)
    dv = K[1, 1] * ((y0 + ay) / z1 - y0 / z0)
    if du * fr[_F_E] + dv * fr[_F_E + 1] < 0:
        a[0], a[1], a[2] = -ax, -ay, -az
    if fr[_F_DISTAL] == 0 and a[2] < 0:
        a[0], a[1], a[2] = -a[0], -a[1], -a[2]
    c0, c1 = centre[0], centre[1]
    wc = fits[0, 0] * c0 + fits[0, 1] * c1 + fits[0, 2] + (fits[1, 0] * c0 + fits[1, 1] * c1)
    wc += fits[1, 2]
    return 0.5 * fr[_F_WIDTH] <= wc <= 1.6 * fr[_F_WIDTH] + 2.0


@kernel(
    "UniTuple(float64, 2)(float64[:, ::1], int64, float64[::1], float64[::1], float64,"
    " float64[:, ::1])"
)
def _joint_t(
    pts: np.ndarray,
    n_other: int,
    p0: np.ndarray,
    a: np.ndarray,
    radius: float,
    K: np.ndarray,  # noqa: N803
) -> tuple[float, float]:
    """``measure._joint_t``: J's axial coordinate and the points' robust spread (mm) from
    the distal outline points ``pts`` (the first ``n_other`` next to other parts)."""
    n = len(pts)
    wx, wy, wz = -p0[0], -p0[1], -p0[2]
    wa = wx * a[0] + wy * a[1] + wz * a[2]
    px, py, pz = wx - wa * a[0], wy - wa * a[1], wz - wa * a[2]
    c = px * px + py * py + pz * pz - radius * radius
    t0 = -(p0[0] * a[0] + p0[1] * a[1] + p0[2] * a[2])
    use_bg = n - n_other >= 5
    v = np.empty(3 * n)  # the values, then _median_in's scratch
    k = 0
    for i in range(n):
        if use_bg and i < n_other:
            continue
        dx, dy, dz = _ray(pts[i, 0], pts[i, 1], K)
        da = dx * a[0] + dy * a[1] + dz * a[2]
        qx, qy, qz = dx - da * a[0], dy - da * a[1], dz - da * a[2]
        aa = max(qx * qx + qy * qy + qz * qz, 1e-12)
        b = qx * px + qy * py + qz * pz
        sq = math.sqrt(max(b * b - aa * c, 0.0))
        t_in = (-b - sq) / aa * da + t0
        t_out = (-b + sq) / aa * da + t0
        v[k] = t_in if i < n_other else min(t_in, t_out)
        k += 1
    scratch = v[k:]
    med = _median_in(v, k, 1, scratch)
    for i in range(k):
        v[i] = abs(v[i] - med)
    return med, 1.4826 * _median_in(v, k, 1, scratch)


@kernel("boolean(float64[::1], float64[::1], float64, float64)")
def _is_round_end(cap_q: np.ndarray, cap_s: np.ndarray, spread: float, max_spread: float) -> bool:
    """``measure._is_round_end``: the free distal end bulges distally at one axial
    coordinate (the shaft's round end), not an occluder's cut across the shaft."""
    n = len(cap_q)
    if n < 5 or spread > max_spread:
        return False
    mid = 0.5 * (_vmax(cap_q) + _vmin(cap_q))
    x2 = np.empty(n)
    m2 = ms = 0.0
    for i in range(n):
        x2[i] = (cap_q[i] - mid) * (cap_q[i] - mid)
        m2 += x2[i]
        ms += cap_s[i]
    m2 /= n
    ms /= n
    tot = 0.0
    for i in range(n):
        tot += (x2[i] - m2) * (cap_s[i] - ms)
    return tot < 0


@kernel(
    "int64(float64[::1], float64[:, ::1], float64[:, ::1], float64[:, ::1], float64[::1],"
    " float64[::1], float64[::1], float64, float64, float64[:, ::1], float64[::1], float64[::1])"
)
def _joint(
    axis: np.ndarray,
    fits: np.ndarray,
    pts: np.ndarray,
    other: np.ndarray,
    s: np.ndarray,
    q: np.ndarray,
    fr: np.ndarray,
    zone: float,
    radius: float,
    K: np.ndarray,  # noqa: N803
    par: np.ndarray,
    joint: np.ndarray,
) -> int:
    """``measure._joint``: J into ``joint`` on the axis ``axis[:6]``; 0, or the WHY index
    of no joint (distal end not seen, out of view, or not the shaft's own end)."""
    n_other = len(other)
    if fr[_F_DISTAL] == 0 or (fr[_F_DISTB] and n_other < 3):
        return _W_OUT
    tol = max(1.0, 2.5 * max(fits[0, 7], fits[1, 7]))
    cap = np.empty(len(pts), np.int64)
    n_cap = 0
    for i in range(len(pts)):
        if s[i] >= fr[_F_SMAX] - zone:
            d1 = abs(pts[i, 0] * fits[0, 0] + pts[i, 1] * fits[0, 1] + fits[0, 2])
            d2 = abs(pts[i, 0] * fits[1, 0] + pts[i, 1] * fits[1, 1] + fits[1, 2])
            if d1 > tol and d2 > tol:
                cap[n_cap] = i
                n_cap += 1
    if n_other + n_cap < 3:
        return _W_REJECTED
    end_pts = np.empty((n_other + n_cap, 2))
    end_pts[:n_other] = other
    cap_q, cap_s = np.empty(n_cap), np.empty(n_cap)
    for k in range(n_cap):
        end_pts[n_other + k, 0], end_pts[n_other + k, 1] = pts[cap[k], 0], pts[cap[k], 1]
        cap_q[k], cap_s[k] = q[cap[k]], s[cap[k]]
    p0, a = axis[0:3], axis[3:6]
    tj, spread = _joint_t(end_pts, n_other, p0, a, radius, K)
    if n_other < 3 and not _is_round_end(cap_q, cap_s, spread, par[_P_CAP_SPREAD]):
        return _W_OCCLUDED
    for i in range(3):
        joint[i] = p0[i] + tj * a[i]
    return 0 if joint[2] > 0 else _W_REJECTED


@kernel(
    "boolean(float64[:, ::1], float64[::1], float64[::1], float64[::1], boolean[::1],"
    " float64[:, ::1], float64[::1], float64[::1], float64[:, ::1], float64[::1])"
)
def _refit(
    pts: np.ndarray,
    s: np.ndarray,
    q: np.ndarray,
    centre: np.ndarray,
    keep_base: np.ndarray,
    K: np.ndarray,  # noqa: N803
    axis: np.ndarray,
    joint: np.ndarray,
    fits: np.ndarray,
    par: np.ndarray,
) -> bool:
    """The limb lines refitted with the points the first solution puts proximal of J
    (0.5 mm); False when a side has no line."""
    p0, a = axis[0:3], axis[3:6]
    tj = (joint[0] - p0[0]) * a[0] + (joint[1] - p0[1]) * a[1] + (joint[2] - p0[2]) * a[2]
    keep2 = np.empty(len(pts), np.bool_)
    for i in range(len(pts)):
        keep2[i] = keep_base[i] and _closest1(pts[i, 0], pts[i, 1], K, p0, a) < tj - 0.5
    _fit_limbs(pts, s, q, keep2, centre, par, fits)
    return not math.isnan(fits[0, 0]) and not math.isnan(fits[1, 0])


@kernel(
    "UniTuple(float64, 2)(float64[:, ::1], float64[:, ::1], float64, float64[::1], float64[::1],"
    " float64[::1])"
)
def _uncertainty(
    fits: np.ndarray,
    K: np.ndarray,  # noqa: N803
    radius: float,
    ref: np.ndarray,
    a: np.ndarray,
    par: np.ndarray,
) -> tuple[float, float]:
    """``measure._uncertainty``: 1-sigma error of the reference axis point (mm) and of the
    axis direction (deg), by finite differences of each line's offset and angle."""
    rx, ry, rz = ref[0], ref[1], ref[2]
    nr = math.sqrt(rx * rx + ry * ry + rz * rz)
    ux, uy, uz = rx / nr, ry / nr, rz / nr
    var_p = var_a = 0.0
    sol = np.empty(6)
    lines = np.empty((2, 3))
    for k in range(4):
        side = k // 2
        lines[0, :] = fits[0, :3]
        lines[1, :] = fits[1, :3]
        n_eff = max(2.0, min(fits[side, 6], fits[side, 5] / 2.0))
        sig = max(fits[side, 7], par[_P_PX_NOISE])
        la, lb, lc = fits[side, 0], fits[side, 1], fits[side, 2]
        if k % 2 == 0:  # the line's offset
            lines[side, 2] = lc - math.hypot(sig / math.sqrt(n_eff), par[_P_PX_BIAS])
        else:  # its angle, about its points' centre
            ang = sig * math.sqrt(12.0 / n_eff) / max(fits[side, 5], 1.0)
            co, si = math.cos(ang), math.sin(ang)
            na, nb = co * la - si * lb, si * la + co * lb
            lines[side, 0], lines[side, 1] = na, nb
            lines[side, 2] = -(na * fits[side, 3] + nb * fits[side, 4])
        l0, l1 = lines[0], lines[1]
        if not _axis_from_lines(l0[0], l0[1], l0[2], l1[0], l1[1], l1[2], K, radius, sol):
            return math.inf, math.inf
        px, py, pz, cx, cy, cz = sol[0], sol[1], sol[2], sol[3], sol[4], sol[5]
        da = cx * ux + cy * uy + cz * uz
        dp = px * ux + py * uy + pz * uz
        ap = cx * px + cy * py + cz * pz
        t = (da * dp - ap) / max(1.0 - da * da, 1e-12)
        ex, ey, ez = px + t * cx - rx, py + t * cy - ry, pz + t * cz - rz
        var_p += ex * ex + ey * ey + ez * ez
        deg = math.degrees(math.acos(min(1.0, abs(cx * a[0] + cy * a[1] + cz * a[2]))))
        var_a += deg * deg
    return math.sqrt(var_p), math.sqrt(var_a)


# -- quality -----------------------------------------------------------------------------


@kernel(
    "int64(float64[::1], float64[::1], float64, float64, float64[:, ::1], float64, int64, int64,"
    " int64, int64, int64, int64, int64, float32[:, ::1], int32[:, ::1], int64[::1])"
)
def cylinder_outline(
    p_a: np.ndarray,
    p_b: np.ndarray,
    r_a: float,
    r_b: float,
    K: np.ndarray,  # noqa: N803
    min_z: float,
    ox: int,
    oy: int,
    mh: int,
    mw: int,
    height: int,
    width: int,
    max_pixels: int,
    pts: np.ndarray,
    shifted: np.ndarray,
    canvas: np.ndarray,
) -> int:
    """The rim points of a capped (tapered) cylinder in the image and the canvas they are
    filled on to compare with a part's mask (``quality.hull_of_cylinder`` and
    ``iou_polygon_mask`` before the fill).

    Args:
        p_a, p_b: (3,) end centres (mm); r_a, r_b: their radii (mm).
        K: intrinsics; min_z: rims nearer the camera plane than this (mm) give False.
        ox, oy, mh, mw: the mask crop's offset and size; height, width: the image's.
        max_pixels: larger canvases sample every other pixel.
        pts: (48, 2) receives the rims' pixels (float32, as OpenCV's hull takes them).
        shifted: (48, 2) receives them on the canvas (x16 fixed point, canvas step).
        canvas: (6,) receives ``x0, y0, step, rows, columns`` (``canvas[5]`` is left).

    Returns:
        0: no outline (degenerate, or a rim behind ``min_z``); 1: the rim points only (the
        canvas would be empty); 2: both.
    """
    d0, d1, d2 = p_b[0] - p_a[0], p_b[1] - p_a[1], p_b[2] - p_a[2]
    nd = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    if not math.isfinite(nd) or nd < 1e-6:
        return 0
    ax, ay, az = d0 / nd, d1 / nd, d2 / nd
    if abs(ax) < 0.9:  # e1 = a x ref, ref = +x (or +y near +-x): cylinder's basis
        e0, e1, e2 = 0.0, az, -ay
    else:
        e0, e1, e2 = -az, 0.0, ax
    ne = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    e0, e1, e2 = e0 / ne, e1 / ne, e2 / ne
    f0, f1, f2 = ay * e2 - az * e1, az * e0 - ax * e2, ax * e1 - ay * e0
    n = len(_COS)
    xyz = np.empty((2 * n, 3))
    for k in range(2 * n):
        c, s = _COS[k % n], _SIN[k % n]
        r = r_a if k < n else r_b
        p = p_a if k < n else p_b
        xyz[k, 0] = r * (c * e0 + s * f0) + p[0]
        xyz[k, 1] = r * (c * e1 + s * f1) + p[1]
        xyz[k, 2] = r * (c * e2 + s * f2) + p[2]
    if _vmin(xyz[:, 2]) < min_z:
        return 0
    for k in range(2 * n):
        pts[k, 0] = np.float32(K[0, 0] * xyz[k, 0] / xyz[k, 2] + K[0, 2])
        pts[k, 1] = np.float32(K[1, 1] * xyz[k, 1] / xyz[k, 2] + K[1, 2])
    lx, ly = math.floor(_vmin(pts[:, 0])), math.floor(_vmin(pts[:, 1]))
    hx, hy = math.ceil(_vmax(pts[:, 0])), math.ceil(_vmax(pts[:, 1]))
    x0, y0 = int(max(0, min(ox, lx))), int(max(0, min(oy, ly)))
    x1, y1 = int(min(width, max(ox + mw, hx + 1))), int(min(height, max(oy + mh, hy + 1)))
    if x1 <= x0 or y1 <= y0:
        return 1
    st = 1 if (x1 - x0) * (y1 - y0) <= max_pixels else 2
    x0, y0 = x0 - x0 % st, y0 - y0 % st
    f = 16.0 / st
    for k in range(2 * n):
        shifted[k, 0] = np.int32(np.rint((float(pts[k, 0]) - x0) * f))
        shifted[k, 1] = np.int32(np.rint((float(pts[k, 1]) - y0) * f))
    canvas[0], canvas[1], canvas[2] = x0, y0, st
    canvas[3], canvas[4] = -(-(y1 - y0) // st), -(-(x1 - x0) // st)
    return 2


# -- the shaft's row -----------------------------------------------------------------------


@kernel(
    "boolean(float64[:, ::1], float64[::1], float64[::1], float64[:, ::1], float64[::1],"
    " float64[:, ::1], float64, float64[::1], float64[::1], float64[::1])"
)
def _shaft_row(
    pix: np.ndarray,
    s_pix: np.ndarray,
    fr: np.ndarray,
    fits: np.ndarray,
    axis: np.ndarray,
    K: np.ndarray,  # noqa: N803
    radius: float,
    joint: np.ndarray,
    par: np.ndarray,
    out: np.ndarray,
) -> bool:
    """``measure._shaft_row`` into ``out``: False when the joint's uncertainty is too large
    for any pose (the reason in ``out``)."""
    p0, a = axis[0:3], axis[3:6]
    has_joint = not math.isnan(joint[0])
    su, sv = _mean_rows(pix, s_pix <= fr[_F_SMIN] + 1.0)
    out[_O_SUV], out[_O_SUV + 1] = su, sv
    ref = joint if has_joint else axis[6:9]
    sig_p, sig_a = _uncertainty(fits, K, radius, ref, a, par)
    out[_O_SIG], out[_O_SIG + 1] = sig_p, sig_a
    if not sig_p <= par[_P_MAX_SIGMA_MM]:
        nr = math.sqrt(ref[0] * ref[0] + ref[1] * ref[1] + ref[2] * ref[2])
        cos_ray = abs((ref[0] / nr) * a[0] + (ref[1] / nr) * a[1] + (ref[2] / nr) * a[2])
        end_on = cos_ray > math.cos(math.radians(par[_P_END_ON]))
        out[_O_WHY_ALL] = _W_END_ON if end_on else _W_LOW
        return False
    out[_O_END : _O_END + 3] = joint
    if not sig_a <= par[_P_MAX_SIGMA_DEG]:
        out[_O_WHY_SHAFT] = _W_AXIS
        return True
    t_start = _closest1(su, sv, K, p0, a)
    start = np.empty(3)
    for i in range(3):
        start[i] = p0[i] + t_start * a[i]
    if has_joint:
        t_end = (joint[0] - p0[0]) * a[0] + (joint[1] - p0[1]) * a[1] + (joint[2] - p0[2]) * a[2]
    else:  # the distal end of the outline
        du, dv = _mean_rows(pix, s_pix >= fr[_F_SMAX] - 1.0)
        t_end = _closest1(du, dv, K, p0, a)
    out[_O_AXIS : _O_AXIS + 3] = a
    _quat_from_z(a[0], a[1], a[2], out[_O_QUAT : _O_QUAT + 4])
    if start[2] > 0 and t_end > t_start:
        out[_O_START : _O_START + 3] = start
        out[_O_QA : _O_QA + 3] = start
        for i in range(3):
            out[_O_QB + i] = p0[i] + t_end * a[i]
    return True


@kernel(
    "boolean(float64[:, ::1], float64[:, ::1], float64[:, ::1], float64[::1], float64[::1],"
    " float64[::1], float64[::1], float64[::1], boolean[::1], float64, float64[:, ::1], float64,"
    " float64[::1], float64[::1], float64[::1], float64[::1])"
)
def _solve_shaft(
    fits: np.ndarray,
    pts: np.ndarray,
    other: np.ndarray,
    centre: np.ndarray,
    fr: np.ndarray,
    s: np.ndarray,
    q: np.ndarray,
    s_pix: np.ndarray,
    keep_base: np.ndarray,
    zone: float,
    K: np.ndarray,  # noqa: N803
    radius: float,
    par: np.ndarray,
    axis: np.ndarray,
    joint: np.ndarray,
    out: np.ndarray,
) -> bool:
    """``measure._solve_shaft``: the axis and J from the limb lines ``fits``; on a short
    visible stretch once more with the lines refitted proximal of the first J (``fits``
    then holds the lines used). False: no axis (the reason in ``out``)."""
    if not _solve_axis(fits, K, radius, centre, fr, axis):
        out[_O_WHY_ALL] = _W_REJECTED
        return False
    joint[:] = math.nan
    why = _joint(axis, fits, pts, other, s, q, fr, zone, radius, K, par, joint)
    if why:
        joint[:] = math.nan
    out[_O_WHY_ALL] = why
    if why or fr[_F_SMAX] - fr[_F_SMIN] >= 2.5 * fr[_F_WIDTH]:
        return True
    fits2 = np.empty_like(fits)
    if not _refit(pts, s, q, centre, keep_base, K, axis, joint, fits2, par):
        return True
    axis2 = np.empty(9)
    if not _solve_axis(fits2, K, radius, centre, fr, axis2):
        return True
    joint2 = np.empty(3)
    if _joint(axis2, fits2, pts, other, s, q, fr, zone, radius, K, par, joint2):
        return True
    fits[:, :] = fits2
    axis[:] = axis2
    joint[:] = joint2
    return True


@kernel(
    "void(float64[:, ::1], boolean[::1], float64[::1], float64[::1], float64[:, ::1],"
    " float64[:, ::1], float64[:, ::1], float64, float64[::1], float64[::1], int64[::1],"
    " float32[:, ::1], int32[:, ::1], int64[::1])"
)
def shaft_pose(
    pix: np.ndarray,
    border: np.ndarray,
    centre: np.ndarray,
    mom: np.ndarray,
    bg: np.ndarray,
    other: np.ndarray,
    K: np.ndarray,  # noqa: N803
    radius: float,
    par: np.ndarray,
    out: np.ndarray,
    geo: np.ndarray,
    rims: np.ndarray,
    shifted: np.ndarray,
    canvas: np.ndarray,
) -> None:
    """The shaft's pose from its points (``measure_instance`` up to the clasper).

    Args:
        pix: (N, 2) outline pixels (ideal image, px); border: (N,) on the image border.
        centre: (2,) the region's centroid (ideal image); mom: its moments ``m00, m10,
            m01, m20, m11, m02`` (any origin).
        bg, other: (M, 2), (L, 2) boundary points next to background / other parts.
        K: (3, 3) intrinsics; radius: the shaft's radius (mm).
        par: the parameters, in :data:`PARAMS` order.
        out: (``OUT["size"]``,) receives the results (:data:`OUT`), NaN where unknown.
        geo: the shaft crop's ``x0, y0, h, w``, the image's ``H, W``, the quality
            canvas' ``max_pixels``.
        rims, shifted, canvas: receive the quality cylinder's image
            (:func:`cylinder_outline`; ``canvas[5]`` its result, 0 without a cylinder).
    """
    out[:] = math.nan
    out[_O_WHY_ALL] = out[_O_WHY_SHAFT] = out[_O_CLASPER] = out[_O_QUALITY_OPENCV] = 0.0
    canvas[5] = 0
    fr = np.empty(_F_LEN)
    s_pix = np.empty(len(pix))
    _frame(pix, border, centre, mom, other, fr, s_pix)
    out[_O_DISTAL] = 1.0 if fr[_F_DISTAL] != 0 else 0.0
    m = len(bg)
    s, q = np.empty(m), np.empty(m)
    keep_base, keep = np.empty(m, np.bool_), np.empty(m, np.bool_)
    zone = _limb_points(bg, other, centre, fr, s, q, keep_base, keep)
    fits = np.empty((2, FIT_LEN))
    _fit_limbs(bg, s, q, keep, centre, par, fits)
    out[_O_L1 : _O_L1 + 3] = fits[0, :3]
    out[_O_L2 : _O_L2 + 3] = fits[1, :3]
    if len(other) >= 3:
        out[_O_UV], out[_O_UV + 1] = fr[_F_MED], fr[_F_MED + 1]
    elif fr[_F_DISTAL] != 0 and not fr[_F_DISTB]:
        out[_O_UV], out[_O_UV + 1] = _mean_rows(pix, s_pix >= fr[_F_SMAX] - 1.0)
    n_lines = (not math.isnan(fits[0, 0])) + (not math.isnan(fits[1, 0]))
    if n_lines < 2:  # one limb line: refine_sequence may solve it with the trocar
        out[_O_WHY_ALL] = _W_NO_LINE if n_lines == 0 else _W_ONE_LINE
        return
    axis, joint = np.empty(9), np.empty(3)
    if not _solve_shaft(
        fits, bg, other, centre, fr, s, q, s_pix, keep_base, zone, K, radius, par, axis, joint, out
    ):
        return
    why = out[_O_WHY_ALL]
    out[_O_WHY_ALL] = 0.0
    out[_O_L1 : _O_L1 + 3] = fits[0, :3]
    out[_O_L2 : _O_L2 + 3] = fits[1, :3]
    if not _shaft_row(pix, s_pix, fr, fits, axis, K, radius, joint, par, out):
        return
    out[_O_WHY_ALL] = why
    out[_O_A : _O_A + 3] = axis[3:6]
    if not math.isnan(out[_O_QA]):
        qa, qb = out[_O_QA : _O_QA + 3], out[_O_QB : _O_QB + 3]
        canvas[5] = cylinder_outline(
            qa,
            qb,
            radius,
            radius,
            K,
            1.0,
            geo[0],
            geo[1],
            geo[2],
            geo[3],
            geo[4],
            geo[5],
            geo[6],
            rims,
            shifted,
            canvas,
        )
    if not why:
        out[_O_JOINT : _O_JOINT + 3] = joint
        out[_O_CLASPER] = 1.0


#: :func:`shaft_from_masks`' answers.
SHAFT_MEASURED, SHAFT_NOT_VISIBLE, SHAFT_ASK_PYTHON, SHAFT_MERGED = 0, 1, 2, 3
#: ``geo`` of :func:`shaft_from_masks`: the entries :func:`shaft_pose` reads, then the
#: number of the instrument's other parts.
GEO_OTHERS = 7
#: :func:`shaft_from_masks` answers for a shaft crop of at most this many pieces.
_MAX_PIECES = 64


@helper
def _contour_area(outline: np.ndarray, start: int, stop: int) -> float:
    """``cv2.contourArea`` of a contour (integer points: exact sums)."""
    if stop <= start:
        return 0.0
    a00 = 0.0
    px, py = float(outline[stop - 1, 0]), float(outline[stop - 1, 1])
    for i in range(start, stop):
        x, y = float(outline[i, 0]), float(outline[i, 1])
        a00 += px * y - py * x
        px, py = x, y
    return abs(a00 * 0.5)


@helper
def _squares_below(n: int) -> int:
    """``0^2 + 1^2 + ... + (n - 1)^2``."""
    return (n - 1) * n * (2 * n - 1) // 6


@helper
def _add_run(y: int, xa: int, xb: int, m: np.ndarray) -> None:
    """Adds the pixels ``xa <= x < xb`` of row ``y`` to the integer moments ``m``
    (``m00, m10, m01, m20, m11, m02``)."""
    n = xb - xa
    sx = (xa + xb - 1) * n // 2
    sxx = _squares_below(xb) - _squares_below(xa)
    m[0] += n
    m[1] += sx
    m[2] += n * y
    m[3] += sxx
    m[4] += sx * y
    m[5] += n * y * y


@helper
def _background_run(
    xa: int,
    xb: int,
    y: int,
    uh: int,
    uw: int,
    piece: int,
    r: int,
    prev_lo: int,
    prev_hi: int,
    bg: np.ndarray,
    parent: np.ndarray,
    edge: np.ndarray,
) -> None:
    """Records background run ``r`` (columns ``xa <= x < xb`` of canvas row ``y``, the
    piece ``piece`` on its left) for :func:`_filled_moments`, joined with the previous
    row's runs ``[prev_lo, prev_hi)`` that it touches (4-connected); ``edge``: its set
    reaches the canvas' edge."""
    bg[r, 0], bg[r, 1], bg[r, 2], bg[r, 3], parent[r] = xa, xb, y, piece, r
    edge[r] = y == 0 or y == uh - 1 or xa == 0 or xb == uw
    for j in range(prev_lo, prev_hi):
        if bg[j, 0] < xb and bg[j, 1] > xa:
            p = j
            while parent[p] != p:
                p = parent[p]
            q = r
            while parent[q] != q:
                q = parent[q]
            if p != q:
                keep, drop = min(p, q), max(p, q)
                parent[drop] = keep
                edge[keep] = edge[keep] or edge[drop]


@helper
def _filled_moments(
    runs: np.ndarray, large: np.ndarray, x0: int, y0: int, uh: int, uw: int, mom: np.ndarray
) -> None:
    """The moments of the large pieces filled (``cv2.drawContours(union, pieces, -1, 1,
    thickness=-1)`` of their outer contours, then :func:`raster_moments`), on the canvas
    of ``uh`` rows and ``uw`` columns at the crop's ``(x0, y0)``, into ``mom``, without
    drawing it: each piece with its holes (background runs not 4-connected to the
    canvas' edge; a hole's run belongs to the piece on its left, since no piece lies in
    another's hole, :func:`mistool.kernels.contours.external_contours`). The same exact
    integer sums as :func:`raster_moments` of the drawn canvas.

    Args:
        runs: the crop's row runs in raster order (row, first column, column after the
            last, piece label ``k + 1``: ``external_contours``).
        large: (C + 1,) 1 for the pieces to fill (by label).
    """
    m = np.zeros(6, np.int64)
    cap = len(runs) + uh + 1  # background runs: at most one more than the pieces' a row
    bg = np.empty((cap, 4), np.int64)  # first column, column after the last, row, piece
    parent = np.empty(cap, np.int64)
    edge = np.empty(cap, np.bool_)
    n = 0
    prev_lo = prev_hi = 0
    k = 0  # the next run
    n_fg = len(runs)
    x1 = x0 + uw
    for y in range(uh):
        while k < n_fg and runs[k, 0] < y0 + y:
            k += 1
        lo = n
        x = 0  # canvas column reached
        carry = 0
        while True:  # the gap before the next run (clipped to the canvas), then the run
            if k < n_fg and runs[k, 0] == y0 + y and runs[k, 1] < x1:
                fa, fb, lab = max(runs[k, 1], x0) - x0, min(runs[k, 2], x1) - x0, runs[k, 3]
                k += 1
                if fb <= 0:
                    continue
            else:
                fa = fb = uw
                lab = 0
            if fa > x:
                _background_run(x, fa, y, uh, uw, carry, n, prev_lo, prev_hi, bg, parent, edge)
                n += 1
            if fb >= uw and not lab:
                break
            if large[lab]:
                _add_run(y, fa, fb, m)
            carry = lab
            x = fb
            if x >= uw:
                break
        prev_lo, prev_hi = lo, n
    for r in range(n):
        p = r
        while parent[p] != p:
            p = parent[p]
        if not edge[p] and large[bg[r, 3]]:  # a hole of a large piece
            _add_run(bg[r, 2], bg[r, 0], bg[r, 1], m)
    for i in range(6):
        mom[i] = m[i]


@helper
def _largest_piece(
    outline: np.ndarray, starts: np.ndarray, n_pieces: int, runs: np.ndarray, par: np.ndarray
) -> int:
    """``measure._shaft_points``' choice among a crop's pieces: -1 to keep them all (one
    piece large, or the large ones one shaft cut across: ``measure._one_cut_shaft``),
    else the largest piece's contour (two shafts: it alone is measured)."""
    areas = np.empty(n_pieces)
    big = 0
    for c in range(n_pieces):
        areas[c] = _contour_area(outline, starts[c], starts[c + 1])
        if areas[c] > areas[big]:
            big = c
    floor = 0.25 * areas[big]
    large = np.zeros(n_pieces + 1, np.uint8)
    n_large = n_pts = 0
    for c in range(n_pieces):
        if areas[c] >= floor:
            large[c + 1] = 1
            n_large += 1
            n_pts += starts[c + 1] - starts[c]
    if n_large < 2:
        return -1
    pts = np.empty((n_pts, 2), np.int32)
    pstarts = np.empty(n_large + 1, np.int64)
    k = j = 0
    x0 = y0 = np.int64(2**62)
    x1 = y1 = -x0
    for c in range(n_pieces):
        if large[c + 1]:
            pstarts[j] = k
            j += 1
            for i in range(starts[c], starts[c + 1]):
                x, y = np.int64(outline[i, 0]), np.int64(outline[i, 1])
                pts[k, 0], pts[k, 1] = x, y
                k += 1
                x0, y0, x1, y1 = min(x0, x), min(y0, y), max(x1, x), max(y1, y)
    pstarts[n_large] = k
    mom = np.empty(6)
    _filled_moments(runs, large, x0, y0, y1 - y0 + 1, x1 - x0 + 1, mom)
    if _one_cut(pts, pstarts, mom, x0, y0, par[_P_CUT_ANGLE], par[_P_CUT_OFFSET]):
        return -1
    return big


@helper
def _others_before(lab: np.ndarray, pre: np.ndarray) -> None:
    """``pre[y, x]``: the OTHER pixels of ``lab``'s row ``y`` left of column ``x``
    (``pre``: ``lab``'s rows, one column more)."""
    hh, ww = lab.shape
    for y in range(hh):
        acc = 0
        pre[y, 0] = 0
        for x in range(ww):
            acc += lab[y, x] == _OTHER
            pre[y, x + 1] = acc


@helper
def _near_other_at(pre: np.ndarray, gap_rows: np.ndarray, x: int, y: int) -> bool:
    """``cv2.dilate(lab == OTHER, disk) > 0`` at ``lab``'s pixel ``(x, y)`` (inside it),
    from :func:`_others_before`'s ``pre`` (the disk: ``gap_rows[i]`` its half-width at
    row ``i - g``, ``2 g + 1`` rows; pixels outside ``lab`` count as not OTHER, as
    OpenCV's default border for a dilation)."""
    hh, ww = pre.shape[0], pre.shape[1] - 1
    g = (len(gap_rows) - 1) // 2
    for i in range(2 * g + 1):
        yy = y + i - g
        if 0 <= yy < hh:
            r = gap_rows[i]
            if pre[yy, min(x + r, ww - 1) + 1] > pre[yy, max(x - r, 0)]:
                return True
    return False


@helper
def _paste(
    lab: np.ndarray, lx: int, ly: int, mask: np.ndarray, mx: int, my: int, value: int
) -> None:
    """``silhouette.paste``: ``lab[mask] = value`` where the mask crop at ``(mx, my)``
    overlaps the label crop at ``(lx, ly)`` (full-image px)."""
    h, w = lab.shape
    mh, mw = mask.shape
    xa, ya = max(mx, lx), max(my, ly)
    xb, yb = min(mx + mw, lx + w), min(my + mh, ly + h)
    for y in range(ya, yb):
        for x in range(xa, xb):
            if mask[y - my, x - mx]:
                lab[y - ly, x - lx] = value


@helper
def _across_gap(
    outline: np.ndarray,
    shaft: np.ndarray,
    sx: int,
    sy: int,
    o1: np.ndarray,
    x1: int,
    y1: int,
    o2: np.ndarray,
    x2: int,
    y2: int,
    n_others: int,
    height: int,
    width: int,
    gap_rows: np.ndarray,
) -> tuple[bool, np.ndarray, np.ndarray]:
    """``measure._across_gap``: the boundary points (next to background, next to the
    other parts) with the other parts grown by the gap (the disk of ``gap_rows``), in the
    same window; ``(found, bg, other)``, ``found`` False where ``measure._across_gap``
    keeps the points it had."""
    g = (len(gap_rows) - 1) // 2
    h, w = shaft.shape
    cx0, cy0 = max(sx - 2 - g, 0), max(sy - 2 - g, 0)
    cx1, cy1 = min(sx + w + 2 + g, width), min(sy + h + 2 + g, height)
    wx0, wy0, wx1, wy1 = cx1, cy1, cx0, cy0  # the others' crops within the shaft's
    for k in range(n_others):
        m, mx, my = (o1, x1, y1) if k == 0 else (o2, x2, y2)
        mh, mw = m.shape
        wx0, wy0 = min(wx0, max(mx, cx0)), min(wy0, max(my, cy0))
        wx1, wy1 = max(wx1, min(mx + mw, cx1)), max(wy1, min(my + mh, cy1))
    wx0, wy0 = max(wx0 - g, cx0), max(wy0 - g, cy0)
    wx1, wy1 = min(wx1 + g, cx1), min(wy1 + g, cy1)
    empty = np.empty((0, 2))
    if wx0 >= wx1 or wy0 >= wy1:
        return False, empty, empty
    hh, ww = wy1 - wy0, wx1 - wx0
    lab = np.zeros((hh, ww), np.uint8)
    for k in range(n_others):
        m, mx, my = (o1, x1, y1) if k == 0 else (o2, x2, y2)
        _paste(lab, wx0, wy0, m, mx, my, _OTHER)
    _paste(lab, wx0, wy0, shaft, sx, sy, _SHAFT)
    pre = np.empty((hh, ww + 1), np.int64)
    _others_before(lab, pre)
    # the shaft's own labels (shaft_boundary's), then a background neighbour within the
    # window is OTHER where the grown other parts hold it: the dilation only where read
    n = len(outline)
    labels = np.zeros((4, n), np.uint8)
    sh, sw = shaft.shape
    flat = shaft.view(np.uint8).ravel()
    _neighbour_labels(outline, flat, sh, sw, sx, sy, flat[:0], 0, 0, 0, 0, height, width, labels)
    pix = np.empty((n, 2))
    for i in range(n):
        px, py = outline[i, 0], outline[i, 1]
        pix[i, 0], pix[i, 1] = float(px + sx), float(py + sy)
        a, b = px + sx - wx0, py + sy - wy0
        if -1 <= a <= ww and -1 <= b <= hh:
            for d in range(4):
                ca = a + (1 if d == 0 else (-1 if d == 1 else 0))
                cb = b + (1 if d == 2 else (-1 if d == 3 else 0))
                if (
                    labels[d, i] == _BG
                    and 0 <= ca < ww
                    and 0 <= cb < hh
                    and _near_other_at(pre, gap_rows, ca, cb)
                ):
                    labels[d, i] = _OTHER
    bg, other = _boundary_points(pix, labels)
    return len(other) >= 3, bg, other


@helper
def _piece_mask(runs: np.ndarray, label: int, h: int, w: int, kept: np.ndarray) -> np.ndarray:
    """The (h, w) mask of the runs labelled ``label``, in ``kept`` (or in a new array
    where ``kept`` is not of that shape)."""
    if kept.shape[0] != h or kept.shape[1] != w:
        kept = np.empty((h, w), np.bool_)
    flat = kept.reshape(h * w)  # a view (C-contiguous)
    for i in range(np.uint64(h * w)):
        flat[i] = False
    for r in range(len(runs)):
        if runs[r, 3] == label:
            row = runs[r, 0] * w
            for x in range(runs[r, 1], runs[r, 2]):
                flat[row + x] = True
    return kept


@kernel(
    "int64(boolean[:, ::1], boolean[:, ::1], int64, int64, boolean[:, ::1], int64, int64,"
    " float64[:, ::1], float64, float64[::1], float64[::1], int64[::1], float32[:, ::1],"
    " int32[:, ::1], int64[::1], boolean[:, ::1], int64[::1])"
)
def shaft_from_masks(
    shaft: np.ndarray,
    o1: np.ndarray,
    x1: int,
    y1: int,
    o2: np.ndarray,
    x2: int,
    y2: int,
    K: np.ndarray,  # noqa: N803
    radius: float,
    par: np.ndarray,
    out: np.ndarray,
    geo: np.ndarray,
    rims: np.ndarray,
    shifted: np.ndarray,
    canvas: np.ndarray,
    kept: np.ndarray,
    gap_rows: np.ndarray,
) -> int:
    """The shaft's pose from its masks, in one call, for an undistorted camera: the steps
    of ``measure._shaft_points`` (its outer contours traced as OpenCV traces them,
    :mod:`mistool.kernels.contours`; of several pieces, the larger of two shafts or all
    the pieces of one, ``measure._one_cut_shaft``; its boundary points and moments,
    :func:`shaft_boundary`, across a gap at the junction where it has one,
    ``measure._across_gap``; its centroid), then :func:`shaft_pose` and the quality
    (:func:`rims_iou`, into ``OUT["quality"]``, or ``OUT["quality_opencv"]`` set where
    OpenCV must answer).

    Args:
        shaft: the shaft crop; o1, o2: the other parts' crops (``(0, 0)`` for none) at
            ``(x1, y1)``, ``(x2, y2)``.
        K, radius, par, out, rims, shifted, canvas: as :func:`shaft_pose`.
        geo: as :func:`shaft_pose` (the shaft crop's ``x0, y0, h, w``, the image's
            ``H, W``, ``max_pixels``), then the number of other parts (at most 2).
        kept: the shaft crop's shape: receives the measured shaft (its larger piece) for
            :data:`SHAFT_MERGED` (of another shape: not asked for, a scratch then).
        gap_rows: the junction gap's disk (``measure._GAP_DISK``): its half-width at each
            row (``2 g + 1`` rows for a gap of ``g`` px).

    Returns:
        :data:`SHAFT_MEASURED` (``out`` and the rims filled); :data:`SHAFT_MERGED` (the
        same, for the larger of two shafts, in ``kept``); :data:`SHAFT_NOT_VISIBLE` (no
        pixel); :data:`SHAFT_ASK_PYTHON` where ``measure._shaft_points`` must answer (a
        piece that may lie in another's hole, an outline without area): nothing is
        written then.
    """
    h, w = shaft.shape
    sx, sy = geo[0], geo[1]
    starts = np.empty(_MAX_PIECES + 1, np.int64)
    buf = np.empty((8 * (h + w) + 64, 2), np.int32)
    n_pieces, runs = external_contours(shaft, buf, starts)
    if n_pieces == -2:  # a long border: the bound that always holds
        buf = np.empty((4 * h * w + 4, 2), np.int32)
        n_pieces, runs = external_contours(shaft, buf, starts)
    if n_pieces == 0:
        return SHAFT_NOT_VISIBLE
    if n_pieces < 0:
        return SHAFT_ASK_PYTHON
    measured = shaft
    merged = False
    outline = buf[: starts[n_pieces]]
    if n_pieces > 1:  # several pieces
        big = _largest_piece(buf, starts, n_pieces, runs, par)
        if big >= 0:  # two shafts: the larger alone
            merged = True
            measured = _piece_mask(runs, big + 1, h, w, kept)
            outline = buf[starts[big] : starts[big + 1]]
            starts[0], starts[1], n_pieces = 0, len(outline), 1
    starts = starts[: n_pieces + 1]
    pix, border, bg, other, mom = shaft_boundary(
        outline, starts, measured, sx, sy, o1, x1, y1, o2, x2, y2, geo[4], geo[5]
    )
    if mom[0] < 1.0:
        return SHAFT_ASK_PYTHON
    if len(other) < 3 and geo[GEO_OTHERS] > 0:  # a thin gap between the shaft and its head?
        found, gap_bg, gap_other = _across_gap(
            outline,
            measured,
            sx,
            sy,
            o1,
            x1,
            y1,
            o2,
            x2,
            y2,
            geo[GEO_OTHERS],
            geo[4],
            geo[5],
            gap_rows,
        )
        if found:
            bg, other = gap_bg, gap_other
    centre = np.empty(2)
    centre[0] = mom[1] / mom[0] + float(sx)
    centre[1] = mom[2] / mom[0] + float(sy)
    shaft_pose(pix, border, centre, mom, bg, other, K, radius, par, out, geo, rims, shifted, canvas)
    if not math.isnan(out[_O_QA]):  # the quality (quality.rims_iou)
        iou = np.empty(1)
        if rims_iou(rims, shifted, canvas, measured, sx, sy, iou):
            out[_O_QUALITY] = iou[0]
        else:
            out[_O_QUALITY_OPENCV] = 1.0
    return SHAFT_MERGED if merged else SHAFT_MEASURED


# -- the clasper's tip ---------------------------------------------------------------------


@helper
def _jaw_picks(
    ci: np.ndarray, ox: float, oy: float, ju: float, jv: float, width: float, picks: np.ndarray
) -> int:
    """The jaw ends' outline indices into ``picks`` (at most 2): the local maxima of the
    distance from J's pixel along the outline (windows of about one jaw width), at least
    half the farthest, more than ``width`` apart, farthest first; their count."""
    n = len(ci)
    if n < 2:
        return 0
    d = np.empty(n)
    for i in range(n):
        dx = (ci[i, 0] + ox) - ju
        dy = (ci[i, 1] + oy) - jv
        d[i] = math.sqrt(dx * dx + dy * dy)
    win = int(max(2, min(n // 4, np.rint(width))))
    dmax = _vmax(d)
    cand = np.empty(n, np.int64)
    k = 0
    for i in range(n):
        if d[i] < 0.5 * dmax:
            continue
        # d[i] is the maximum of its window (the outline is closed): its two neighbours
        # first (most points fail there), then the whole window
        if d[i - 1 if i > 0 else n - 1] > d[i] or d[i + 1 if i < n - 1 else 0] > d[i]:
            continue
        top = True
        for j in range(i - win, i + win + 1):
            jj = j + n if j < 0 else (j - n if j >= n else j)
            if d[jj] > d[i]:
                top = False
                break
        if top:
            cand[k] = i
            k += 1
    # farthest first, equal distances in outline order (a stable insertion sort: few)
    for a in range(1, k):
        c = cand[a]
        b = a
        while b > 0 and d[cand[b - 1]] < d[c]:
            cand[b] = cand[b - 1]
            b -= 1
        cand[b] = c
    n_picks = 0
    for o in range(k):
        i = cand[o]
        xi, yi = ci[i, 0] + ox, ci[i, 1] + oy
        far = True
        for p in range(n_picks):
            far &= math.hypot(xi - (ci[picks[p], 0] + ox), yi - (ci[picks[p], 1] + oy)) > width
        if far:
            picks[n_picks] = i
            n_picks += 1
            if n_picks == 2:
                break
    return n_picks


@helper
def _disc_runs(
    flat: np.ndarray,
    w: int,
    cx: int,
    cy: int,
    rad: float,
    x0: int,
    y0: int,
    x1: int,
    y1: int,
    runs: np.ndarray,
) -> tuple[int, int, int, int]:
    """The crop's (``flat``: its bytes, rows of ``w``) set pixels within ``rad`` of ``(cx,
    cy)`` and within ``[x0, x1) x [y0, y1)``: their row runs into ``runs`` (row, first
    column, column after the last; raster order; each row's span of the disc is ``|x -
    cx| <= dxm``, exactly), and the runs' number, the pixels' count and coordinate sums
    (exact integers)."""
    r2 = rad * rad
    n_runs = cnt = sx = sy = 0
    for y in range(y0, y1):
        rem = r2 - (y - cy) * (y - cy)
        if rem < 0:
            continue
        dxm = int(math.sqrt(rem))
        while dxm * dxm > rem:
            dxm -= 1
        while (dxm + 1) * (dxm + 1) <= rem:
            dxm += 1
        xa, xb = max(cx - dxm, x0), min(cx + dxm + 1, x1)
        base = y * w
        x = xa
        while x < xb:
            a = _next_change(flat, base + x, base + xb, False) - base
            if a >= xb:
                break
            x = _next_change(flat, base + a, base + xb, True) - base
            runs[n_runs, 0], runs[n_runs, 1], runs[n_runs, 2] = y, a, x
            n_runs += 1
            n = x - a
            cnt += n
            sx += (a + x - 1) * n // 2
            sy += y * n
    return n_runs, cnt, sx, sy


@helper
def _disc_extents(
    runs: np.ndarray,
    n_runs: int,
    ox: int,
    oy: int,
    mx: float,
    my: float,
    e0: float,
    e1: float,
) -> tuple[float, float, float]:
    """The largest coordinate along ``(e0, e1)`` and the extent across it (its least and
    largest) of the pixels of :func:`_disc_runs`' ``runs``, about ``(mx, my)``: within a
    row both are rounded linear functions of x, monotone, so a run's extremes are at its
    two ends (the values of the pixel-by-pixel maxima and minima; a zero's sign may
    differ, and does not reach :func:`_jaw_axis`'s end)."""
    along = -math.inf
    lo, hi = math.inf, -math.inf
    for r in range(n_runs):
        dy = float(runs[r, 0] + oy) - my
        for k in (runs[r, 1], runs[r, 2] - 1):
            dx = float(k + ox) - mx
            along = max(along, dx * e0 + dy * e1)
            across = dx * -e1 + dy * e0
            lo, hi = min(lo, across), max(hi, across)
    return along, lo, hi


@kernel(
    "boolean(boolean[:, ::1], int64, int64, int64, int64, float64, float64, float64, float64,"
    " float64[::1])"
)
def _jaw_axis(
    mask: np.ndarray,
    ox: int,
    oy: int,
    cx: int,
    cy: int,
    rad: float,
    ux: float,
    uy: float,
    width: float,
    end: np.ndarray,
) -> bool:
    """One jaw end moved onto its jaw's axis (``measure._jaw_tips``): from the crop pixels
    within ``rad`` of the outline pixel ``(cx, cy)`` (crop px), their principal direction
    (pointing along ``(ux, uy)``, away from J), the farthest extent along it: ``end[:2]``
    the end (px), ``end[2:4]`` the direction, ``end[4]`` the jaw's half-width (px, at
    most ``width``); False for fewer than 3 pixels. (The disc's row runs found once,
    :func:`_disc_runs`, then read twice.)"""
    h, w = mask.shape
    x0, y0 = max(int(math.floor(cx - rad)), 0), max(int(math.floor(cy - rad)), 0)
    x1, y1 = min(int(math.ceil(cx + rad)) + 1, w), min(int(math.ceil(cy + rad)) + 1, h)
    # a row of the disc holds at most one run per two columns
    runs = np.empty((max(y1 - y0, 0) * ((max(x1 - x0, 0) + 1) // 2), 3), np.int64)
    flat = mask.view(np.uint8).ravel()
    n_runs, cnt, sx, sy = _disc_runs(flat, w, cx, cy, rad, x0, y0, x1, y1, runs)
    if cnt < 3:
        return False
    mx, my = (sx + cnt * ox) / cnt, (sy + cnt * oy) / cnt
    c00 = c01 = c11 = 0.0
    for r in range(n_runs):  # the same pixels in the same order (row-major, np.nonzero's)
        dy = float(runs[r, 0] + oy) - my
        for k in range(runs[r, 1], runs[r, 2]):
            dx = float(k + ox) - mx
            c00 += dx * dx
            c01 += dx * dy
            c11 += dy * dy
    phi = 0.5 * math.atan2(2.0 * c01, c00 - c11)
    e0, e1 = math.cos(phi), math.sin(phi)
    if e0 * ux + e1 * uy < 0:
        e0, e1 = -e0, -e1
    along, lo, hi = _disc_extents(runs, n_runs, ox, oy, mx, my, e0, e1)
    end[0], end[1] = mx + (along + 0.5) * e0, my + (along + 0.5) * e1
    end[2], end[3] = e0, e1
    end[4] = min(0.5 * (hi - lo) + 0.5, width)
    return True


@kernel(
    "int64(int32[:, ::1], boolean[:, ::1], int64, int64, float64, float64, float64, boolean,"
    " int64, int64, float64[::1], float64[:, ::1])"
)
def jaw_ends(
    ci: np.ndarray,
    mask: np.ndarray,
    ox: int,
    oy: int,
    ju: float,
    jv: float,
    width: float,
    with_nears: bool,
    height: int,
    width_image: int,
    par: np.ndarray,
    ends: np.ndarray,
) -> int:
    """Far ends of the clasper's jaws in the image (``measure._jaw_tips``).

    Args:
        ci: (n, 2) the clasper's outline (its longest contour, crop px).
        mask: (h, w) the clasper crop; ``ox, oy`` its offset (px).
        ju, jv: J's pixel (the camera's image).
        width: the expected jaw width in the image (px, >= 2).
        with_nears: look at the outline near each end for the image border.
        height, width_image: the image's size (px).
        par: the parameters (:data:`PARAMS`).
        ends: (2, 5) receives each end's pixel (2), jaw direction (2), half-width.

    Returns:
        The number of ends (0-2), plus 4 when an end's outline touches the image border
        (the jaws are cut by it).
    """
    picks = np.empty(2, np.int64)
    n_picks = _jaw_picks(ci, float(ox), float(oy), ju, jv, width * par[_P_JAW_SEP], picks)
    rad = par[_P_JAW_RAD] * width
    if n_picks == 2:
        ax, ay = ci[picks[0], 0], ci[picks[0], 1]
        bx, by = ci[picks[1], 0], ci[picks[1], 1]
        rad = min(rad, 0.5 * math.hypot(float(ax + ox) - (bx + ox), float(ay + oy) - (by + oy)))
    n_ends = 0
    hidden = False
    for p in range(n_picks):
        k = picks[p]
        cx, cy = ci[k, 0], ci[k, 1]
        ux, uy = (cx + ox) - ju, (cy + oy) - jv
        if not _jaw_axis(mask, ox, oy, cx, cy, rad, ux, uy, width, ends[n_ends]):
            continue
        n_ends += 1
        if with_nears:
            for i in range(len(ci)):
                dx, dy = ci[i, 0] - cx, ci[i, 1] - cy
                if dx * dx + dy * dy <= rad * rad:
                    x, y = ci[i, 0] + ox, ci[i, 1] + oy
                    hidden |= x <= 0 or y <= 0 or x >= width_image - 1 or y >= height - 1
    return n_ends + (4 if hidden else 0)


@helper
def _tip_cost(
    lo: float,
    step: float,
    k: int,
    s_j: float,
    jj: float,
    ra: float,
    ja: float,
    l_nom: float,
    has_len: bool,
    par: np.ndarray,
) -> float:
    """:func:`_tip_depth`'s cost at grid point ``k``: the bend's, plus the length's."""
    s = lo + step * _UNIT_GRID[k]
    ln = math.sqrt(max((s - 2.0 * s_j) * s + jj, 0.0))
    cosb = min(max((s * ra - ja) / max(ln, 1e-9), -1.0), 1.0)
    c = math.acos(cosb) / par[_P_TIP_BEND]
    c = c * c
    if has_len:
        e = (ln - l_nom) / (par[_P_TIP_SIGMA] * l_nom)
        c += e * e
    return c


@kernel(
    "float64(float64, float64, float64, float64, float64, float64, float64, float64, float64,"
    " float64, boolean, float64[::1])"
)
def _tip_depth(
    rx: float,
    ry: float,
    rz: float,
    jx: float,
    jy: float,
    jz: float,
    ax: float,
    ay: float,
    az: float,
    l_nom: float,
    has_len: bool,
    par: np.ndarray,
) -> float:
    """The tip's depth along its ray (mm): the grid minimum of the length and bend costs,
    refined by a parabola.

    With a known length, the bend's arc cosine (the costly term) is taken only at the
    grid points whose length term alone is at most the cost at the length term's
    minimum (an upper bound of the least cost): elsewhere the cost, the length term plus
    a square, exceeds that bound, so the first grid point of least cost, and its
    neighbours' costs, are those of the whole grid (finite inputs; else the whole grid)."""
    s_j = rx * jx + ry * jy + rz * jz
    span = 3.0 * (l_nom if has_len else 16.0)
    lo = max(s_j - span, 1.0)
    step = s_j + span - lo
    jj = jx * jx + jy * jy + jz * jz
    ra = rx * ax + ry * ay + rz * az
    ja = jx * ax + jy * ay + jz * az
    n = len(_UNIT_GRID)
    cost = np.empty(n)
    lengths = np.empty(n)
    best = 0
    pruned = has_len and math.isfinite(
        rx + ry + rz + jx + jy + jz + ax + ay + az + l_nom + par[_P_TIP_BEND] + par[_P_TIP_SIGMA]
    )
    if pruned:  # the length terms first, and the cost where the length term is least
        for k in range(n):
            s = lo + step * _UNIT_GRID[k]
            ln = math.sqrt(max((s - 2.0 * s_j) * s + jj, 0.0))
            e = (ln - l_nom) / (par[_P_TIP_SIGMA] * l_nom)
            lengths[k] = e * e
            if lengths[k] < lengths[best]:
                best = k
        bound = _tip_cost(lo, step, best, s_j, jj, ra, ja, l_nom, has_len, par)
        if not math.isfinite(bound):
            pruned = False
        best = 0
    for k in range(n):
        if pruned and lengths[k] > bound:
            cost[k] = math.inf  # more than the least cost: never read
            continue
        c = _tip_cost(lo, step, k, s_j, jj, ra, ja, l_nom, has_len, par)
        cost[k] = c
        if c < cost[best]:
            best = k
    sk = lo + step * _UNIT_GRID[best]
    if 0 < best < n - 1:  # parabolic refinement
        for k in (best - 1, best + 1):
            if cost[k] == math.inf:
                cost[k] = _tip_cost(lo, step, k, s_j, jj, ra, ja, l_nom, has_len, par)
        c0, c1, c2 = cost[best - 1], cost[best], cost[best + 1]
        den = c0 - 2.0 * c1 + c2
        off = 0.5 * (c0 - c2) / den if den > 0 else 0.0
        sk += min(max(off, -1.0), 1.0) * ((lo + step * _UNIT_GRID[1]) - (lo + step * _UNIT_GRID[0]))
    return sk


@kernel(
    "int64(float64, float64, float64[::1], float64[::1], float64[:, ::1], float64, boolean,"
    " float64, float64, float64[::1], float64[::1])"
)
def tip_solve(
    tu: float,
    tv: float,
    joint: np.ndarray,
    a: np.ndarray,
    K: np.ndarray,  # noqa: N803
    length: float,
    hidden: bool,
    ju: float,
    jv: float,
    par: np.ndarray,
    out: np.ndarray,
) -> int:
    """The tip and the clasper axis from the tip's pixel (``measure._tip_solve``).

    Args:
        tu, tv: the tip's pixel (ideal image); ju, jv: J's pixel (ideal image).
        joint, a: (3,) J (mm) and the shaft's distal direction.
        K: intrinsics; length: the clasper's length (mm; NaN: unknown).
        hidden: the jaws are cut by the image border.
        par: the parameters (:data:`PARAMS`).
        out: (``TIP["size"]``,) receives the tip's pixel, the tip, the clasper axis, its
            quaternion (:data:`TIP`).

    Returns:
        0: nothing found; 1: only the tip's pixel; 2: everything.
    """
    out[:] = math.nan
    dist = math.hypot(tu - ju, tv - jv)
    if dist < 2.0:
        return 0
    out[0], out[1] = tu, tv
    uu, uv = (tu - ju) / dist, (tv - jv) / dist
    has_len = not math.isnan(length)
    l_nom = par[_P_TIP_FACTOR] * length
    rx, ry, rz = _ray(tu, tv, K)
    jx, jy, jz = joint[0], joint[1], joint[2]
    ax, ay, az = a[0], a[1], a[2]
    wx, wy, wz = (rx, ry, rz) if not hidden else _ray(ju + 10.0 * uu, jv + 10.0 * uv, K)
    nx, ny, nz = jy * wz - jz * wy, jz * wx - jx * wz, jx * wy - jy * wx
    nn = math.sqrt(nx * nx + ny * ny + nz * nz)
    if nn < 1e-9:
        return 1
    nx, ny, nz = nx / nn, ny / nn, nz / nn
    an = ax * nx + ay * ny + az * nz
    cx, cy, cz = ax - an * nx, ay - an * ny, az - an * nz
    ncl = math.sqrt(cx * cx + cy * cy + cz * cz)
    if ncl < 1e-6:
        return 1
    cx, cy, cz = cx / ncl, cy / ncl, cz / ncl
    du = K[0, 0] * ((jx + cx) / (jz + cz) - jx / jz)
    dv = K[1, 1] * ((jy + cy) / (jz + cz) - jy / jz)
    if du * uu + dv * uv < 0:
        cx, cy, cz = -cx, -cy, -cz
    if hidden:
        if not has_len:
            return 1
        out[2], out[3], out[4] = jx + l_nom * cx, jy + l_nom * cy, jz + l_nom * cz
        out[5], out[6], out[7] = cx, cy, cz
        _quat_from_z(cx, cy, cz, out[8:12])
        return 2
    sk = _tip_depth(rx, ry, rz, jx, jy, jz, ax, ay, az, l_nom, has_len, par)
    dx, dy, dz = sk * rx - jx, sk * ry - jy, sk * rz - jz
    nd = math.sqrt(dx * dx + dy * dy + dz * dz)
    if nd < 1e-6:
        return 1
    out[2], out[3], out[4] = sk * rx, sk * ry, sk * rz
    out[5], out[6], out[7] = dx / nd, dy / nd, dz / nd
    _quat_from_z(out[5], out[6], out[7], out[8:12])
    return 2


@kernel(
    "int64(int32[:, ::1], boolean[:, ::1], int64, int64, float64[::1], float64[::1],"
    " float64[:, ::1], float64, float64, boolean, int64, int64, float64, float64[::1],"
    " float64[::1])"
)
def _tip_pose(
    ci: np.ndarray,
    mask: np.ndarray,
    ox: int,
    oy: int,
    joint: np.ndarray,
    a: np.ndarray,
    K: np.ndarray,  # noqa: N803
    width: float,
    length: float,
    at_border: bool,
    height: int,
    width_image: int,
    cap: float,
    par: np.ndarray,
    out: np.ndarray,
) -> int:
    """:func:`tip_pose` before the quality cylinder."""
    jx, jy, jz = joint[0], joint[1], joint[2]
    ju, jv = K[0, 0] * jx / jz + K[0, 2], K[1, 1] * jy / jz + K[1, 2]
    ends = np.empty((2, 5))
    found = jaw_ends(ci, mask, ox, oy, ju, jv, width, at_border, height, width_image, par, ends)
    n, hidden = found & 3, found >= 4
    if n == 0:
        out[:] = math.nan
        return 0
    tu, tv = (
        (ends[0, 0], ends[0, 1])
        if n == 1
        else (0.5 * (ends[0, 0] + ends[1, 0]), 0.5 * (ends[0, 1] + ends[1, 1]))
    )
    got = tip_solve(tu, tv, joint, a, K, length, hidden, ju, jv, par, out)
    if got < 2 or hidden or not cap:
        return got
    tx, ty, tz = out[2], out[3], out[4]
    cos_v = abs(out[5] * tx + out[6] * ty + out[7] * tz) / math.sqrt(tx * tx + ty * ty + tz * tz)
    for k in range(n):
        f = cap * ends[k, 4] * cos_v
        ends[k, 0] -= f * ends[k, 2]
        ends[k, 1] -= f * ends[k, 3]
    tu, tv = (
        (ends[0, 0], ends[0, 1])
        if n == 1
        else (0.5 * (ends[0, 0] + ends[1, 0]), 0.5 * (ends[0, 1] + ends[1, 1]))
    )
    return tip_solve(tu, tv, joint, a, K, length, hidden, ju, jv, par, out)


@kernel(
    "int64(int32[:, ::1], boolean[:, ::1], int64, int64, float64[::1], float64[::1],"
    " float64[:, ::1], float64, float64, boolean, int64, int64, float64, float64[::1],"
    " float64[::1], float64, int64, float32[:, ::1], int32[:, ::1], int64[::1])"
)
def tip_pose(
    ci: np.ndarray,
    mask: np.ndarray,
    ox: int,
    oy: int,
    joint: np.ndarray,
    a: np.ndarray,
    K: np.ndarray,  # noqa: N803
    width: float,
    length: float,
    at_border: bool,
    height: int,
    width_image: int,
    cap: float,
    par: np.ndarray,
    out: np.ndarray,
    radius: float,
    max_pixels: int,
    rims: np.ndarray,
    shifted: np.ndarray,
    canvas: np.ndarray,
) -> int:
    """The tip of an undistorted camera's clasper (``measure._tip``): the jaw ends
    (:func:`jaw_ends`), the tip's pixel their mid-point, the tip (:func:`tip_solve`),
    then once more with each end pulled back by ``cap`` x its end cap's overshoot (unless
    the jaws are cut by the image border). ``width``: the jaw width (px, >= 2); ``length``
    NaN when unknown; returns and fills ``out`` as :func:`tip_solve`; with a tip, the
    quality cylinder's image (J to the tip, radii ``0.5 radius`` and ``0.25 radius``)
    into ``rims, shifted, canvas`` (:func:`cylinder_outline`, ``canvas[5]`` its result)."""
    canvas[5] = 0
    got = _tip_pose(
        ci, mask, ox, oy, joint, a, K, width, length, at_border, height, width_image, cap, par, out
    )
    if got == 2:
        canvas[5] = cylinder_outline(
            joint,
            out[2:5],
            0.5 * radius,
            0.25 * radius,
            K,
            1.0,
            ox,
            oy,
            mask.shape[0],
            mask.shape[1],
            height,
            width_image,
            max_pixels,
            rims,
            shifted,
            canvas,
        )
    return got


#: :func:`clasper_from_mask`'s answers besides :func:`tip_pose`'s (0, 1, 2).
CLASPER_EMPTY, CLASPER_ASK_PYTHON = -2, -1


@kernel(
    "int64(boolean[:, ::1], int64, int64, float64[::1], float64[::1], float64[:, ::1], float64,"
    " int64, int64, float64, float64[::1], float64[::1], float64, int64, float32[:, ::1],"
    " int32[:, ::1], int64[::1], float64[::1])"
)
def clasper_from_mask(
    mask: np.ndarray,
    ox: int,
    oy: int,
    joint: np.ndarray,
    a: np.ndarray,
    K: np.ndarray,  # noqa: N803
    length: float,
    height: int,
    width_image: int,
    cap: float,
    par: np.ndarray,
    out: np.ndarray,
    radius: float,
    max_pixels: int,
    rims: np.ndarray,
    shifted: np.ndarray,
    canvas: np.ndarray,
    quality: np.ndarray,
) -> int:
    """The clasper's tip from its mask, in one call, for an undistorted camera
    (``measure._clasper_rows``): its outer contour
    (:func:`mistool.kernels.contours.outer_contour`; of several pieces, OpenCV's first
    longest, :func:`mistool.kernels.contours.external_contours`), the jaw width in the image and
    whether the crop touches the image border, :func:`tip_pose`, then the quality
    (:func:`rims_iou`).

    Args:
        mask: the clasper crop at ``(ox, oy)``; joint, a: J and the shaft's distal axis.
        K, length, height, width_image, cap, par, out, radius, max_pixels, rims, shifted,
            canvas: as :func:`tip_pose` (``length`` NaN when unknown).
        quality: (2,) receives the quality (NaN without one) and 1.0 where OpenCV must
            give it (the hull rests on float rounding), else 0.0.

    Returns:
        :func:`tip_pose`'s answer; :data:`CLASPER_EMPTY` for a crop without pixels;
        :data:`CLASPER_ASK_PYTHON` (nothing written) for a crop of several pieces where
        one's bounding box holds another's (OpenCV answers).
    """
    h, w = mask.shape
    buf = np.empty((4 * (h + w) + 16, 2), np.int32)
    n = outer_contour(mask, buf)
    if n == -2:  # a long border: the bound that always holds
        buf = np.empty((4 * h * w + 4, 2), np.int32)
        n = outer_contour(mask, buf)
    if n == 0:
        return CLASPER_EMPTY
    lo = 0
    if n < 0:  # several pieces: OpenCV's first longest outline (measure._longest_outline)
        starts = np.empty(_MAX_PIECES + 1, np.int64)
        buf = np.empty((8 * (h + w) + 64, 2), np.int32)
        n_pieces, _ = external_contours(mask, buf, starts)
        if n_pieces == -2:
            buf = np.empty((4 * h * w + 4, 2), np.int32)
            n_pieces, _ = external_contours(mask, buf, starts)
        if n_pieces < 1:
            return CLASPER_ASK_PYTHON
        best = 0
        for k in range(1, n_pieces):
            if starts[k + 1] - starts[k] > starts[best + 1] - starts[best]:
                best = k
        lo, n = starts[best], starts[best + 1] - starts[best]
    width = max(K[0, 0] * 0.25 * (2.0 * radius) / max(joint[2], 1.0), 2.0)
    at_border = min(ox, oy) <= 0 or ox + w - 1 >= width_image - 1 or oy + h - 1 >= height - 1
    quality[0], quality[1] = math.nan, 0.0
    got = tip_pose(
        buf[lo : lo + n],
        mask,
        ox,
        oy,
        joint,
        a,
        K,
        width,
        length,
        at_border,
        height,
        width_image,
        cap,
        par,
        out,
        radius,
        max_pixels,
        rims,
        shifted,
        canvas,
    )
    if got == 2:
        iou = np.empty(1)
        if rims_iou(rims, shifted, canvas, mask, ox, oy, iou):
            quality[0] = iou[0]
        else:
            quality[1] = 1.0
    return got


#: A part's row as :func:`instance_from_masks` writes it (``measure.POSE_KEYS`` then
#: ``measure.AUX_KEYS``): end, axis, start, quaternion, quality; the two limb lines, the
#: joint's or tip's pixel, the proximal end's pixel, the two sigmas, the distal flag, the
#: status (a reason's code, NaN for none).
ROW_LEN = 28
_R_START, _R_QUAT, _R_QUALITY, _R_LINES, _R_UV, _R_DISTAL, _R_STATUS = 6, 9, 13, 14, 20, 26, 27
#: The reasons :func:`instance_from_masks` records, by their index in its ``reasons``
#: argument (which holds each one's status code): :data:`WHY`'s (the first unused), then
#: these.
ONE_CALL_REASONS: tuple[str, ...] = (*WHY, "merged", "no clasper", "tip not found", "not visible")
_RS_MERGED, _RS_NO_CLASPER, _RS_TIP_NOT_FOUND, _RS_NOT_VISIBLE = range(len(WHY), len(WHY) + 4)
#: :func:`instance_from_masks`' answers.
INSTANCE_MEASURED, INSTANCE_ASK_PYTHON = 0, 1


@helper
def _why_rows(rows: np.ndarray, first: int, stop: int, code: float) -> None:
    """A reason's code on rows ``first`` to ``stop - 1``, where none is recorded yet
    (``measure._why``)."""
    for i in range(first, stop):
        if not rows[i, _R_STATUS] >= 0:
            rows[i, _R_STATUS] = code


@helper
def _shaft_row_of(res: np.ndarray, rows: np.ndarray, reasons: np.ndarray) -> bool:
    """The shaft's row from :func:`shaft_pose`'s ``res`` (its quality included) and the
    reasons it gives (``measure._instance_in_steps``); whether to go on to the clasper."""
    rows[0, _R_DISTAL] = res[_O_DISTAL]
    for j in range(12):  # the limb lines to the sigmas
        rows[0, _R_LINES + j] = res[_O_L1 + j]
    for j in range(13):  # the pose without its quality
        rows[0, j] = res[_O_END + j]
    rows[0, _R_QUALITY] = res[_O_QUALITY]  # NaN without a quality cylinder
    why_shaft, why_all = int(res[_O_WHY_SHAFT]), int(res[_O_WHY_ALL])
    if why_shaft:
        _why_rows(rows, 0, 1, reasons[why_shaft])
    if why_all:
        _why_rows(rows, 0, 3, reasons[why_all])
        return False
    return res[_O_CLASPER] != 0


@helper
def _clasper_rows_of(
    found: int,
    tip: np.ndarray,
    joint: np.ndarray,
    quality: float,
    rows: np.ndarray,
    reasons: np.ndarray,
) -> None:
    """The clasper's and the wrist's rows from :func:`clasper_from_mask`'s answer
    (``measure._clasper_rows``)."""
    if found >= 0:  # a clasper with pixels
        if found:
            rows[1, _R_UV], rows[1, _R_UV + 1] = tip[0], tip[1]
        if found == 2:
            for j in range(6):  # end and axis
                rows[1, j] = tip[2 + j]
            for j in range(4):
                rows[1, _R_QUAT + j] = tip[8 + j]
            for j in range(3):
                rows[1, _R_START + j] = joint[j]
            rows[1, _R_QUALITY] = quality
        else:
            _why_rows(rows, 1, 3, reasons[_RS_TIP_NOT_FOUND])
    else:
        _why_rows(rows, 2, 3, reasons[_RS_NO_CLASPER])
    if not math.isnan(tip[5]):  # the wrist's axis
        for j in range(3):
            rows[2, 3 + j] = tip[5 + j]
        for j in range(4):
            rows[2, _R_QUAT + j] = tip[8 + j]
    for j in range(3):
        rows[2, _R_START + j] = joint[j]


@kernel(
    "int64(boolean[:, ::1], boolean[:, ::1], int64, int64, boolean[:, ::1], int64, int64,"
    " int64, int64, int64, int64, int64, int64, int64, float64[:, ::1], float64, float64,"
    " float64, float64[::1], int64[::1], float64[::1], float64[:, ::1])"
)
def instance_from_masks(
    shaft: np.ndarray,
    o1: np.ndarray,
    x1: int,
    y1: int,
    o2: np.ndarray,
    x2: int,
    y2: int,
    clasper: int,
    sx: int,
    sy: int,
    height: int,
    width: int,
    max_pixels: int,
    n_others: int,
    K: np.ndarray,  # noqa: N803
    radius: float,
    length: float,
    cap: float,
    par: np.ndarray,
    gap_rows: np.ndarray,
    reasons: np.ndarray,
    rows: np.ndarray,
) -> int:
    """One instrument's rows from its masks, in one call, for an undistorted camera
    (``measure.measure_instance``): :func:`shaft_from_masks`, then, where the shaft asks
    for it, :func:`clasper_from_mask`, each row written in its final order with the
    reasons of its empty cells.

    Args:
        shaft: the shaft crop at ``(sx, sy)``; o1, o2: the other parts' crops (``(0, 0)``
            for none) at ``(x1, y1)``, ``(x2, y2)``; clasper: which of them is the
            clasper (1 or 2; 0: none); n_others: how many there are (at most 2).
        height, width: the image's size (px); max_pixels: the quality canvas' bound.
        K, radius, par, gap_rows: as :func:`shaft_from_masks`; length, cap: as
            :func:`clasper_from_mask` (``length`` NaN when unknown).
        reasons: the status code of each of :data:`ONE_CALL_REASONS`.
        rows: (3, :data:`ROW_LEN`) receives the shaft's, the clasper's and the wrist's
            rows (``measure.POSE_KEYS + AUX_KEYS``; NaN where unknown).

    Returns:
        :data:`INSTANCE_MEASURED`, or :data:`INSTANCE_ASK_PYTHON` where Python or OpenCV
        must answer (a shaft or clasper crop whose pieces' boxes nest, an outline without
        area, a quality hull resting on float rounding): the rows are not to be read then.
    """
    h, w = shaft.shape
    geo = np.empty(8, np.int64)
    geo[0], geo[1], geo[2], geo[3] = sx, sy, h, w
    geo[4], geo[5], geo[6], geo[GEO_OTHERS] = height, width, max_pixels, n_others
    res = np.empty(_O_QUALITY_OPENCV + 1)
    pts = np.empty((48, 2), np.float32)
    shifted = np.empty((48, 2), np.int32)
    canvas = np.zeros(6, np.int64)
    kept = np.empty((0, 0), np.bool_)  # the merged shaft is not read here
    got = shaft_from_masks(
        shaft, o1, x1, y1, o2, x2, y2, K, radius, par, res, geo, pts, shifted, canvas, kept,
        gap_rows,
    )  # fmt: skip
    if got == SHAFT_ASK_PYTHON:
        return INSTANCE_ASK_PYTHON
    for i in range(3):
        for j in range(ROW_LEN):
            rows[i, j] = math.nan
    if got == SHAFT_NOT_VISIBLE:
        _why_rows(rows, 0, 3, reasons[_RS_NOT_VISIBLE])
        return INSTANCE_MEASURED
    if not math.isnan(res[_O_QA]) and res[_O_QUALITY_OPENCV]:
        return INSTANCE_ASK_PYTHON
    if not _shaft_row_of(res, rows, reasons):
        return INSTANCE_MEASURED
    if got == SHAFT_MERGED:
        _why_rows(rows, 0, 3, reasons[_RS_MERGED])
        return INSTANCE_MEASURED
    joint, a = res[_O_JOINT : _O_JOINT + 3], res[_O_A : _O_A + 3]
    tip = np.empty(12)
    for j in range(12):
        tip[j] = math.nan
    quality = np.empty(2)
    found = CLASPER_EMPTY
    if clasper:
        m, mx, my = (o1, x1, y1) if clasper == 1 else (o2, x2, y2)
        found = clasper_from_mask(
            m, mx, my, joint, a, K, length, height, width, cap, par, tip, radius, max_pixels,
            pts, shifted, canvas, quality,
        )  # fmt: skip
        if found == CLASPER_ASK_PYTHON or (found == 2 and quality[1]):
            return INSTANCE_ASK_PYTHON
    _clasper_rows_of(found, tip, joint, quality[0], rows, reasons)
    return INSTANCE_MEASURED


_BYTES_LOW = np.uint64(0x00FF00FF00FF00FF)
_LANES16 = np.uint64(0x0001000100010001)


@helper
def _ones_and(a: np.ndarray, i: int, b: np.ndarray, j: int, n: int) -> int:
    """The sum of ``a[i + t] & b[j + t]`` over ``t < n`` (0/1 bytes; ``a[i:i + n]``'s own
    sum with ``b, j = a, i``), eight at a time: up to 255 words summed into one word's
    byte lanes, then the lanes added (exact)."""
    tot = 0
    t = 0
    while n - t >= 8:
        m = min((n - t) // 8, 255)
        acc = np.uint64(0)
        for q in range(m):
            acc += _load8(a, i + t + 8 * q) & _load8(b, j + t + 8 * q)
        lanes = (acc & _BYTES_LOW) + ((acc >> np.uint64(8)) & _BYTES_LOW)
        tot += np.int64((lanes * _LANES16) >> np.uint64(48))
        t += 8 * m
    for q in range(t, n):
        tot += a[i + q] & b[j + q]
    return tot


@helper
def _ones_both(a: np.ndarray, i: int, b: np.ndarray, j: int, n: int) -> tuple[int, int]:
    """:func:`_ones_and` of ``a`` alone and of ``a & b`` in one pass:
    ``(sum a[i:i + n], sum a[i + t] & b[j + t])``."""
    tot = both = 0
    t = 0
    while n - t >= 8:
        m = min((n - t) // 8, 255)
        acc = acc_and = np.uint64(0)
        for q in range(m):
            word = _load8(a, i + t + 8 * q)
            acc += word
            acc_and += word & _load8(b, j + t + 8 * q)
        lanes = (acc & _BYTES_LOW) + ((acc >> np.uint64(8)) & _BYTES_LOW)
        tot += np.int64((lanes * _LANES16) >> np.uint64(48))
        lanes = (acc_and & _BYTES_LOW) + ((acc_and >> np.uint64(8)) & _BYTES_LOW)
        both += np.int64((lanes * _LANES16) >> np.uint64(48))
        t += 8 * m
    for q in range(t, n):
        tot += a[i + q]
        both += a[i + q] & b[j + q]
    return tot, both


_EVEN_BYTES = np.uint64(0x00FF00FF00FF00FF)
_PAIRS16 = np.uint64(0x0000FFFF0000FFFF)
_LOW32 = np.uint64(0x00000000FFFFFFFF)


@helper
def _spread4(x: np.uint64) -> np.uint64:
    """The low four bytes of ``x`` moved to the even bytes (byte ``k`` to byte ``2 k``;
    the high four dropped)."""
    x &= _LOW32
    x = (x | (x << np.uint64(16))) & _PAIRS16
    return (x | (x << np.uint64(8))) & _EVEN_BYTES


@helper
def _ones_both_step2(
    a: np.ndarray, i: np.uint64, b: np.ndarray, j: np.uint64, n: int
) -> tuple[int, int]:
    """:func:`_ones_both` of every other byte of ``a`` (0/1 bytes) against consecutive
    bytes of ``b``: ``(sum a[i + 2 t], sum a[i + 2 t] & b[j + t])`` over ``t < n``. Eight
    samples at a time: two words of ``a`` (their even bytes, 16-bit lanes), one of ``b``
    spread to the even bytes; the lanes' sums are exact (a row holds far fewer than 2**16
    samples). A word is loaded only where its eight bytes reach no further than the
    last sample of ``a`` and of ``b``."""
    acc = acc_and = np.uint64(0)
    t = 0
    while t + 9 <= n:  # a[i + 2 t + 15] <= a[i + 2 (n - 1)]; b[j + t + 7] < b[j + n]
        wb = _load8(b, np.int64(j) + t)
        wa0 = _load8(a, np.int64(i) + 2 * t) & _EVEN_BYTES
        wa1 = _load8(a, np.int64(i) + 2 * t + 8) & _EVEN_BYTES
        acc += wa0 + wa1
        acc_and += (wa0 & _spread4(wb)) + (wa1 & _spread4(wb >> np.uint64(32)))
        t += 8
    tot = np.int64((acc * _LANES16) >> np.uint64(48))
    both = np.int64((acc_and * _LANES16) >> np.uint64(48))
    for q in range(np.uint64(t), np.uint64(n)):
        v = a[i + np.uint64(2) * q]
        tot += v
        both += v & b[j + q]
    return tot, both


@kernel("float64(uint8[:, ::1], boolean[:, ::1], int64, int64, int64, int64, int64)")
def iou_count(
    rend: np.ndarray, mask: np.ndarray, ox: int, oy: int, x0: int, y0: int, st: int
) -> float:
    """IoU of a filled canvas (``rend``: 0 or 1, its pixel ``(i, j)`` at the image's
    ``(x0 + st j, y0 + st i)``) with a mask crop at ``(ox, oy)`` sampled on the same
    pixels; NaN when both are empty. (The byte counts eight bytes at a time,
    :func:`_ones_and`, :func:`_ones_both`; a canvas of step 2 samples every other mask
    byte, one at a time.)"""
    hc, wc = rend.shape
    mh, mw = mask.shape
    rflat = rend.ravel()
    n_rend = _ones_and(rflat, 0, rflat, 0, hc * wc)
    ia, ja = max(0, -(-(oy - y0) // st)), max(0, -(-(ox - x0) // st))
    ib, jb = min(hc, -(-(oy + mh - y0) // st)), min(wc, -(-(ox + mw - x0) // st))
    m8 = mask.view(np.uint8).ravel()
    inter = n_obs = 0
    for i in range(ia, ib):  # the mask's samples within the canvas
        m0 = np.uint64((y0 + st * i - oy) * mw + x0 + st * ja - ox)
        r0 = np.uint64(i * wc + ja)
        row_obs = row_inter = 0
        if st == 1:
            row_obs, row_inter = _ones_both(m8, np.int64(m0), rflat, np.int64(r0), jb - ja)
        else:
            row_obs, row_inter = _ones_both_step2(m8, m0, rflat, r0, jb - ja)
        n_obs += row_obs
        inter += row_inter
    union = n_rend + n_obs - inter
    return inter / union if union else math.nan


@kernel(
    "boolean(float32[:, ::1], int32[:, ::1], int64[::1], boolean[:, ::1], int64, int64,"
    " float64[::1])"
)
def rims_iou(
    pts: np.ndarray,
    shifted: np.ndarray,
    canvas: np.ndarray,
    mask: np.ndarray,
    ox: int,
    oy: int,
    iou: np.ndarray,
) -> bool:
    """The quality IoU of a cylinder's image (:func:`cylinder_outline`'s ``pts, shifted,
    canvas``) with a mask crop at ``(ox, oy)`` into ``iou[0]`` (NaN without a canvas):
    ``quality.rims_iou``'s OpenCV hull and fill (:mod:`mistool.kernels.polygon`), then
    :func:`iou_count`. False (nothing written) where the hull would rest on float
    rounding (:func:`mistool.kernels.polygon.convex_hull`): OpenCV answers then."""
    if canvas[5] < 2:
        iou[0] = math.nan
        return True
    hull = np.empty(len(pts), np.int32)
    k = convex_hull(pts, hull)
    if k < 0:
        return False
    rend = np.zeros((canvas[3], canvas[4]), np.uint8)
    fill_convex(rend, shifted, hull, k, 4)
    iou[0] = iou_count(rend, mask, ox, oy, canvas[0], canvas[1], canvas[2])
    return True
