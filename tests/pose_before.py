"""The metric pose as it was before the compiled kernels (commit 3fc5814): numpy and
OpenCV only, kept to compare the kernels with (``tests/test_pose_kernels.py``).

``mistool/pose/silhouette.py``, the cylinder outline of ``mistool/pose/quality.py`` and
``mistool/pose/measure.py`` of that commit, in one module, unchanged but for the imports
(the functions that did not change are imported from mistool)."""

# ruff: noqa: C901, E501, N803, N806
from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from mistool.config import Camera
from mistool.lens import distort_points, undistort_points
from mistool.model import InstanceObservation, PartObservation
from mistool.pose.cylinder import (
    axis_from_image_lines,
    closest_on_axis,
    pixel_rays,
    project,
    quat_from_z,
    ray_cylinder,
)
from mistool.pose.quality import image_polygon
from mistool.pose.status import AUX_STATUS, reason_code

# -- mistool/pose/silhouette.py --

BG, SHAFT, OTHER = 0, 1, 2


@dataclass(frozen=True)
class Canvas:
    """A crop of the image around one part, labelled BG / SHAFT (the part) / OTHER (the
    instrument's other parts)."""

    labels: np.ndarray
    """(h, w) uint8 labels."""
    x0: int
    """Full-image x of column 0 (px)."""
    y0: int
    """Full-image y of row 0 (px)."""


@dataclass(frozen=True)
class Boundary:
    """Sub-pixel boundary points of the part (full-image px)."""

    bg: np.ndarray
    """(N, 2) points between the part and background."""
    other: np.ndarray
    """(M, 2) points between the part and the instrument's other parts."""


def _paste(
    dst: np.ndarray, x0: int, y0: int, mask: np.ndarray, ox: int, oy: int, value: int
) -> None:
    h, w = dst.shape
    mh, mw = mask.shape
    xa, ya = max(ox, x0), max(oy, y0)
    xb, yb = min(ox + mw, x0 + w), min(oy + mh, y0 + h)
    if xa >= xb or ya >= yb:
        return
    sub = mask[ya - oy : yb - oy, xa - ox : xb - ox]
    view = dst[ya - y0 : yb - y0, xa - x0 : xb - x0]
    # view[sub] = value, by OpenCV (several times faster), in place
    cv2.copyTo(np.full(view.shape, value, np.uint8), sub.view(np.uint8), view)


def make_canvas(
    part_mask: np.ndarray,
    offset: tuple[int, int],
    others: list[tuple[np.ndarray, tuple[int, int]]],
    image_shape: tuple[int, int],
    margin: int = 2,
) -> Canvas:
    """Label crop around a part: the part and the instrument's other parts.

    Args:
        part_mask: (h, w) bool crop of the part.
        offset: (x0, y0) of the crop in the full image (px).
        others: (mask, offset) crops of the same instrument's other parts.
        image_shape: (H, W) of the full image.
        margin: background margin added around the crop, clipped to the image (px).

    Returns:
        The :class:`Canvas`.
    """
    H, W = image_shape
    ox, oy = offset
    mh, mw = part_mask.shape
    x0, y0 = max(ox - margin, 0), max(oy - margin, 0)
    x1, y1 = min(ox + mw + margin, W), min(oy + mh + margin, H)
    lab = np.zeros((y1 - y0, x1 - x0), dtype=np.uint8)
    for m, (px, py) in others:
        _paste(lab, x0, y0, m.astype(bool, copy=False), px, py, OTHER)
    _paste(lab, x0, y0, part_mask.astype(bool, copy=False), ox, oy, SHAFT)
    return Canvas(lab, x0, y0)


def boundary_points(canvas: Canvas, outline: np.ndarray) -> Boundary:
    """Sub-pixel boundary points of the canvas' part (see module docstring).

    Args:
        canvas: the part's :class:`Canvas`.
        outline: (N, 2) the part's outer outline pixels (full-image px, integers), e.g.
            from ``cv2.findContours``; only their 4-neighbour pairs are examined.
    """
    lab = canvas.labels
    h, w = lab.shape
    # pad by one pixel of the part's own label: pairs leaving the canvas give no point
    pad = cv2.copyMakeBorder(lab, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=SHAFT)
    ij = np.asarray(outline, dtype=np.int64)
    x = ij[:, 0] - (canvas.x0 - 1)
    y = ij[:, 1] - (canvas.y0 - 1)
    at = y * (w + 2)
    at += x
    # (4, N) neighbours (right, left, down, up), direction-major as the pairs are examined
    nb = pad.ravel().take(at + np.array([[1], [-1], [w + 2], [-(w + 2)]])).reshape(-1)
    # the pairs' mid-points (full-image px), each a complex number so that a selection of
    # them is gathered as one column
    f = np.empty((4, len(x), 2))
    np.add(x, _HALF_DX + (canvas.x0 - 1), out=f[:, :, 0])
    np.add(y, _HALF_DY + (canvas.y0 - 1), out=f[:, :, 1])
    fc = f.view(np.complex128).reshape(-1)
    return Boundary(
        fc[np.flatnonzero(nb == BG)].view(np.float64).reshape(-1, 2),
        fc[np.flatnonzero(nb == OTHER)].view(np.float64).reshape(-1, 2),
    )


_HALF_DX = np.array([[0.5], [-0.5], [0.0], [0.0]])  # (4, 1) half steps to the neighbour
_HALF_DY = np.array([[0.0], [0.0], [0.5], [-0.5]])


def take_rows(points: np.ndarray, index: np.ndarray) -> np.ndarray:
    """``points[index]`` for (N, 2) float64 points and an integer or boolean (N,) index,
    several times faster: a C-contiguous (N, 2) float64 array is gathered as one complex
    column (the same bytes moved)."""
    if points.dtype != np.float64 or not points.flags.c_contiguous or points.shape[1:] != (2,):
        return points[index]
    return points.view(np.complex128).reshape(-1)[index].view(np.float64).reshape(-1, 2)


def _as_complex(points: np.ndarray) -> np.ndarray | None:
    """(N,) complex view of C-contiguous (N, 2) float64 points (x + iy), else None."""
    if points.dtype != np.float64 or not points.flags.c_contiguous or points.shape[1:] != (2,):
        return None
    return points.view(np.complex128).reshape(-1)


def sum_rows(points: np.ndarray) -> np.ndarray:
    """``points.sum(axis=0)`` of (N, 2) points, N >= 1, bit for bit (numpy adds the rows
    of an (N, 2) array one after the other: the running sum's last row), faster: the
    running sum of the points as complex numbers adds x and y as reals do."""
    z = _as_complex(points)
    if z is None:
        return np.add.accumulate(points, axis=0)[-1]
    total = np.add.accumulate(z)[-1]
    return np.array([total.real, total.imag])


def sub_rows(points: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``points - p`` for (N, 2) points and one point ``p`` (2,), bit for bit; for many
    points as one complex column (numpy broadcasts (N, 2) - (2,) row by row, ~3x slower
    at N = 1,000)."""
    z = _as_complex(points) if len(points) >= 256 else None
    if z is None:
        return points - p
    return (z - complex(float(p[0]), float(p[1]))).view(np.float64).reshape(-1, 2)


def add_rows(points: np.ndarray, offset: tuple[float, float]) -> None:
    """``points += offset`` in place for (N, 2) points, bit for bit (as :func:`sub_rows`)."""
    z = _as_complex(points) if len(points) >= 256 else None
    if z is None:
        points += offset
    else:
        z += complex(offset[0], offset[1])


def _tls_moments(m: np.ndarray) -> np.ndarray:
    """Weighted total-least-squares line from the (3, 3) moment matrix ``(X w) X^T`` of
    homogeneous points ``X = (x, y, 1)``: (3,) ``(a, b, c)`` with ``hypot(a, b) = 1``."""
    (m00, m01, m02), (_, m11, m12), (_, _, sw) = m.tolist()
    mx, my = m02 / sw, m12 / sw
    sxx = m00 - sw * mx * mx
    sxy = m01 - sw * mx * my
    syy = m11 - sw * my * my
    phi = 0.5 * math.atan2(2.0 * sxy, sxx - syy)  # direction of the line
    nx, ny = -math.sin(phi), math.cos(phi)
    return np.array([nx, ny, -(nx * mx + ny * my)])


def _median(v: np.ndarray) -> float:
    k = len(v) // 2
    return float(np.partition(v, k)[k])


#: Fixed uniform draws for RANSAC: deterministic, thread-safe and free at call time.
_DRAWS = np.random.default_rng(12345).random((2, 64))


#: :func:`fit_line_robust` fits at most this many points (a regular subsample).
FIT_MAX_POINTS = 192


@functools.lru_cache(maxsize=1024)
def regular_subsample(n: int, m: int) -> np.ndarray:
    """Indices of a regular subsample of ``m`` of ``n`` points (read-only, cached)."""
    keep = np.arange(m) * (n - 1) // (m - 1)
    keep.flags.writeable = False
    return keep


@functools.lru_cache(maxsize=1024)
def _draw_indices(n: int, iters: int) -> tuple[np.ndarray, np.ndarray]:
    """Ranks (along the line) of the RANSAC pairs from the fixed draws (cached)."""
    half = n // 2
    pick_i = (_DRAWS[0, :iters] * half).astype(np.int64)
    pick_j = n - half + (_DRAWS[1, :iters] * half).astype(np.int64)
    pick_i.flags.writeable = False
    pick_j.flags.writeable = False
    return pick_i, pick_j


def fit_line_robust(
    pts: np.ndarray,
    along: np.ndarray,
    rng: np.random.Generator | None = None,
    thresh_px: float = 1.5,
    iters: int = 12,
    max_points: int = FIT_MAX_POINTS,
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Robust sub-pixel line: RANSAC on long baselines, then Tukey-weighted TLS.

    Args:
        pts: (N, 2) candidate points (px).
        along: (N,) coordinate of each point along the expected line direction (px), used
            to draw well-separated pairs.
        rng: random generator for the hypotheses; None uses a fixed table of draws
            (deterministic and thread-safe).
        thresh_px: inlier threshold (px).
        iters: RANSAC hypotheses.
        max_points: larger inputs are regularly subsampled to this many points.

    Returns:
        ``(line, inliers, sigma_px)``: (3,) line with unit normal, indices of the
        inlier points (among the points used when subsampled), residual RMS of the
        inliers (px); or None with fewer than 8 points.
    """
    n = len(pts)
    if n < 8:
        return None
    keep = None
    if n > max_points:  # a regular subsample: the fit's precision is already ~0.03 px
        keep = regular_subsample(n, max_points)
        pts, along = take_rows(pts, keep), along[keep]
        n = max_points
    # homogeneous coordinates relative to the points' mean (well conditioned moments):
    # a line (a, b, c) has residuals (a, b, c) @ X
    ox, oy = (sum_rows(pts) * (1.0 / n)).tolist()
    X = np.empty((3, n))
    np.subtract(pts.T, np.array([[ox], [oy]]), out=X[:2])
    X[2] = 1.0
    order = np.argsort(along)
    half = n // 2
    if rng is None:
        pick_i, pick_j = _draw_indices(n, iters)
    else:
        u1, u2 = rng.random(iters), rng.random(iters)
        pick_i, pick_j = (u1 * half).astype(np.int64), n - half + (u2 * half).astype(np.int64)
    # each hypothesis: the line through a pair of points, normal (y_i - y_j, x_j - x_i)
    # normalised; in plain floats (a dozen pairs: numpy's per-call overhead dominates)
    (xi, yi), (xj, yj) = X[:2, order[pick_i]].tolist(), X[:2, order[pick_j]].tolist()
    rows = []
    for ax, ay, bx, by in zip(xi, yi, xj, yj, strict=True):
        h0, h1 = ay - by, bx - ax
        ln = math.sqrt(h0 * h0 + h1 * h1)
        if ln > 1e-9 or math.isnan(ln):  # NaN kept, as before
            h0, h1 = h0 / ln, h1 / ln
            rows.append((h0, h1, -(h0 * ax + h1 * ay)))
    if not rows:
        return None
    H = np.array(rows)
    res = np.abs(H @ X)  # (iters, n)
    best = int(np.argmin(np.minimum(res, thresh_px).sum(axis=1)))  # MSAC
    inl = res[best] < thresh_px
    if np.count_nonzero(inl) < 6:
        return None
    xi = X[:, inl]
    line = _tls_moments(xi @ xi.T)
    scale = thresh_px
    r = line @ X  # signed residuals of the current line
    for _ in range(2):
        u = r * (1.0 / (2.5 * scale))
        w = np.maximum(1.0 - u * u, 0.0)
        w *= w  # Tukey's biweight, zero beyond 2.5 scale
        if w.sum() < 6:
            break
        line = _tls_moments((X * w) @ X.T)
        r = line @ X
        ra = np.abs(r)
        core = ra[ra < 2.5 * scale]
        if len(core):
            scale = min(max(1.4826 * _median(core), 0.3), thresh_px)
    inl = np.flatnonzero(np.abs(r) < max(2.5 * scale, 0.75))
    ri = r[inl]
    sigma = math.sqrt(float(ri @ ri) / len(inl)) if len(inl) else float("inf")
    line[2] -= line[0] * ox + line[1] * oy  # back to image coordinates
    return line, (inl if keep is None else keep[inl]), sigma


# -- mistool/pose/quality.py --

_THETA = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)
_COS_COL, _SIN_COL = np.cos(_THETA)[:, None], np.sin(_THETA)[:, None]


def perpendicular_basis(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (3,) completing the unit vector ``a`` to an orthonormal basis."""
    ax, ay, az = a.tolist()
    # e1 = a x ref, ref = +x (or +y when a is near +-x); plain floats (3-vectors)
    e1 = np.array([0.0, az, -ay] if abs(ax) < 0.9 else [-az, 0.0, ax])
    e1 /= math.sqrt(float(e1 @ e1))
    x, y, z = e1.tolist()
    return e1, np.array([ay * z - az * y, az * x - ax * z, ax * y - ay * x])


def hull_of_cylinder(
    p_a: np.ndarray, p_b: np.ndarray, r_a: float, r_b: float, K: np.ndarray, min_z_mm: float = 1.0
) -> np.ndarray | None:
    """Image outline of a capped (tapered) cylinder.

    Args:
        p_a, p_b: (3,) end centres (mm, camera frame).
        r_a, r_b: radii at ``p_a`` and ``p_b`` (mm).
        K: (3, 3) intrinsics.
        min_z_mm: rims closer to the camera plane than this give None.

    Returns:
        (M, 2) float32 convex polygon (px), or None.
    """
    d = p_b - p_a
    nd = math.sqrt(float(d @ d))
    if not math.isfinite(nd) or nd < 1e-6:
        return None
    e1, e2 = perpendicular_basis(d / nd)
    ring = _COS_COL * e1
    ring += _SIN_COL * e2
    pts = np.empty((2 * len(ring), 3))
    np.multiply(r_a, ring, out=pts[: len(ring)])
    np.multiply(r_b, ring, out=pts[len(ring) :])
    pts[: len(ring)] += p_a
    pts[len(ring) :] += p_b
    if pts[:, 2].min() < min_z_mm:
        return None
    return cv2.convexHull(project(pts, K).astype(np.float32)).reshape(-1, 2)


def iou_polygon_mask(
    poly: np.ndarray | None,
    mask: np.ndarray,
    offset: tuple[int, int],
    image_shape: tuple[int, int],
    camera: Camera | None = None,
    max_pixels: int = 40000,
) -> float:
    """IoU of a filled polygon with a part's mask, inside the image.

    Args:
        poly: (M, 2) convex polygon (px, full image; in the ideal pinhole image when
            ``camera`` distorts, see :func:`image_polygon`) or None (-> NaN).
        mask: (h, w) bool crop of the part.
        offset: (x0, y0) of the crop (px).
        image_shape: (H, W).
        camera: the camera, whose lens distortion bends the polygon's edges; None:
            the polygon is in the image already.
        max_pixels: larger comparison regions are sampled every other pixel in x and y
            (the IoU of two large regions changes by far less than 0.01).

    Returns:
        IoU in [0, 1], NaN when ``poly`` is None or both are empty.
    """
    convex = camera is None or not camera.distorted
    if not convex and poly is not None:
        poly = image_polygon(poly, camera, image_shape)  # type: ignore[arg-type]
    if poly is None:
        return float("nan")
    H, W = image_shape
    ox, oy = offset
    mh, mw = mask.shape
    (lx, ly), (hx, hy) = np.floor(poly.min(axis=0)).tolist(), np.ceil(poly.max(axis=0)).tolist()
    x0 = int(max(0, min(ox, lx)))
    y0 = int(max(0, min(oy, ly)))
    x1 = int(min(W, max(ox + mw, hx + 1)))
    y1 = int(min(H, max(oy + mh, hy + 1)))
    if x1 <= x0 or y1 <= y0:
        return float("nan")
    st = 1 if (x1 - x0) * (y1 - y0) <= max_pixels else 2
    x0, y0 = x0 - x0 % st, y0 - y0 % st
    hc, wc = -(-(y1 - y0) // st), -(-(x1 - x0) // st)
    canvas = np.zeros((hc, wc), dtype=np.uint8)
    shifted = poly - np.array([x0, y0], dtype=np.float64)
    shifted *= 16.0 / st
    shifted = np.round(shifted, out=shifted).astype(np.int32)
    if convex:
        cv2.fillConvexPoly(canvas, shifted, 1, lineType=cv2.LINE_8, shift=4)
    else:
        cv2.fillPoly(canvas, [shifted], 1, lineType=cv2.LINE_8, shift=4)
    rend = canvas.view(bool)
    n_rend = int(np.count_nonzero(rend))
    ia, ja = max(0, -(-(oy - y0) // st)), max(0, -(-(ox - x0) // st))
    ib, jb = min(hc, -(-(oy + mh - y0) // st)), min(wc, -(-(ox + mw - x0) // st))
    inter = n_obs = 0
    if ia < ib and ja < jb:  # the mask's samples within the canvas
        sub = mask[y0 + st * ia - oy :: st, x0 + st * ja - ox :: st][: ib - ia, : jb - ja]
        # one contiguous copy of a subsampled mask: counting over strided views is slower
        sub = sub.astype(bool, copy=False) if st == 1 else np.ascontiguousarray(sub, dtype=bool)
        n_obs = int(np.count_nonzero(sub))
        inter = int(np.count_nonzero(rend[ia:ib, ja:jb] & sub))
    union = n_rend + n_obs - inter
    return inter / union if union else float("nan")


# -- mistool/pose/measure.py --

#: The metric columns :func:`measure_instance` fills for each part.
POSE_KEYS: tuple[str, ...] = (
    "end_x_mm",
    "end_y_mm",
    "end_z_mm",
    "axis_x",
    "axis_y",
    "axis_z",
    "start_x_mm",
    "start_y_mm",
    "start_z_mm",
    "qw",
    "qx",
    "qy",
    "qz",
    "quality",
)
#: Per-frame auxiliary values (extra columns) that :func:`refine_sequence` uses to
#: re-solve frames with the trocar constraint, then drops. Limb lines are image lines
#: ``a u + b v + c = 0`` (px, unit normal, shaft inside positive); ``aux_u_px, aux_v_px``
#: is the joint's pixel (shaft row) or the tip's pixel (clasper row); ``aux_sigma_mm``,
#: ``aux_sigma_deg`` the 1-sigma errors of J (mm) and of the axis direction (degrees)
#: propagated from the limb lines' fits; ``aux_distal`` 1 when the distal direction was
#: seen in this frame, else 0; ``aux_su_px, aux_sv_px`` the pixel where the shaft leaves
#: the view (its proximal end).
AUX_KEYS: tuple[str, ...] = (
    "aux_l1a",
    "aux_l1b",
    "aux_l1c",
    "aux_l2a",
    "aux_l2b",
    "aux_l2c",
    "aux_u_px",
    "aux_v_px",
    "aux_su_px",
    "aux_sv_px",
    "aux_sigma_mm",
    "aux_sigma_deg",
    "aux_distal",
    AUX_STATUS,
)

#: Above this 1-sigma joint error (mm) the shaft pose is left empty: the view is too close
#: to end-on, or the limb lines too short, to trust the depth.
MAX_SIGMA_MM = 4.0
#: Above this 1-sigma axis-direction error (degrees) the axis is left empty (J is kept).
MAX_SIGMA_DEG = 3.0
_PX_NOISE = 0.3
#: A free distal end (no clasper next to it) is taken as the joint only when its outline
#: is the shaft's round end: its points' axial coordinates agree within this (mm, robust
#: sigma); an occluder's cut across the shaft does not.
_MAX_CAP_SPREAD_MM = 1.0
_PX_BIAS = 0.1
_MIN_LINE_POINTS = 10
_MIN_LINE_SPAN_PX = 12.0
#: A shaft whose depth is too uncertain is reported as ``"pointing at camera"`` when its
#: axis is within this angle (degrees) of the viewing ray, else as ``"low quality"``.
_END_ON_DEG = 30.0


_NAN_ROW = {k: math.nan for k in POSE_KEYS + AUX_KEYS}


def _nan_row() -> dict[str, float]:
    return _NAN_ROW.copy()


def _as_u8(mask: np.ndarray) -> np.ndarray:
    m = np.ascontiguousarray(mask)
    return m.view(np.uint8) if m.dtype == np.bool_ else (m != 0).astype(np.uint8)


def _outline(
    mask_u8: np.ndarray,
    offset: tuple[int, int],
    contours: Sequence[np.ndarray] | None = None,
) -> tuple[np.ndarray, dict[str, float]]:
    """Outline pixels (N, 2) of a mask (full-image px) and its region moments.

    A region's extreme points in any direction are outline pixels, so the outline
    replaces the full pixel list wherever only extremes are needed (much faster).
    """
    if contours is None:
        contours, _ = cv2.findContours(mask_u8, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if len(contours) == 1:
        pts = contours[0].reshape(-1, 2).astype(np.float64)
    else:
        pts = np.concatenate([c.reshape(-1, 2) for c in contours]).astype(np.float64)
    mom = {"m00": 0.0, "m10": 0.0, "m01": 0.0, "m20": 0.0, "m11": 0.0, "m02": 0.0}
    for c in contours:
        m = cv2.moments(c)
        for k in mom:
            mom[k] += m[k]
    if mom["m00"] < 1.0:  # degenerate outlines (lines of pixels): count pixels instead
        m = cv2.moments(mask_u8, binaryImage=True)
        mom = {k: m[k] for k in mom}
    add_rows(pts, offset)
    return pts, mom


def _mean_rows(v: np.ndarray, select: np.ndarray) -> np.ndarray:
    """``v[select].mean(axis=0)`` of (N, 2) points, bit for bit, faster; NaN for no row."""
    rows = take_rows(v, select)
    if not len(rows):
        return rows.mean(axis=0)
    return sum_rows(rows) / len(rows)


def _median_rows(v: np.ndarray) -> np.ndarray:
    """Column-wise median (as ``np.median(v, axis=0)``) of an (N, 2) array, N >= 1."""
    n = len(v)
    k = n // 2
    if n % 2:
        return np.partition(v, k, axis=0)[k]
    part = np.partition(v, (k - 1, k), axis=0)
    return 0.5 * (part[k - 1] + part[k])


def _median1(v: np.ndarray) -> float:
    """Median of a 1-D array (as ``np.median``, without its overhead), len >= 1."""
    n = len(v)
    k = n // 2
    if n % 2:
        return float(np.partition(v, k)[k])
    part = np.partition(v, (k - 1, k))
    return 0.5 * float(part[k - 1] + part[k])


def _ray(px: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Unit viewing ray (3,) of one pixel (2,) (``pixel_rays`` for a single pixel)."""
    u, v = px.tolist()
    x = (u - K.item(0, 2)) / K.item(0, 0)
    y = (v - K.item(1, 2)) / K.item(1, 1)
    n = math.sqrt(x * x + y * y + 1.0)
    return np.array([x / n, y / n, 1.0 / n])


_UNIT_GRID = np.linspace(0.0, 1.0, 81)


def _closest1(px: np.ndarray, K: np.ndarray, p0: np.ndarray, a: np.ndarray) -> float:
    """``closest_on_axis`` for a single pixel's ray (mm)."""
    d = _ray(px, K)
    da, dp, ap = float(d @ a), float(d @ p0), float(a @ p0)
    return (da * dp - ap) / max(1.0 - da * da, 1e-12)


def _window_max(x: np.ndarray, size: int) -> np.ndarray:
    """Sliding maximum: ``out[i] = x[i:i + size].max()`` for every full window."""
    m, w = x, 1
    while 2 * w <= size:  # m[i] = max(x[i:i + w])
        m = np.maximum(m[:-w], m[w:])
        w *= 2
    n_out = len(x) - size + 1
    return np.maximum(m[:n_out], m[size - w : size - w + n_out])


def _on_border(
    px: np.ndarray,
    image_shape: tuple[int, int],
    bounds: tuple[int, int, int, int] | None = None,
) -> np.ndarray:
    """(N,) bool: the pixel (N, 2) is on the image border. ``bounds``: ``(x0, y0, x1, y1)``
    known to hold every pixel (inclusive), so that only the sides they reach are tested."""
    H, W = image_shape
    x0, y0, x1, y1 = bounds if bounds is not None else (0, 0, W - 1, H - 1)
    out = np.zeros(len(px), dtype=bool)
    if x0 <= 0:
        out |= px[:, 0] <= 0
    if y0 <= 0:
        out |= px[:, 1] <= 0
    if x1 >= W - 1:
        out |= px[:, 0] >= W - 1
    if y1 >= H - 1:
        out |= px[:, 1] >= H - 1
    return out


def _crop_bounds(mask: np.ndarray, offset: tuple[int, int]) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)``: the full-image pixels a crop covers (inclusive)."""
    h, w = mask.shape
    return offset[0], offset[1], offset[0] + w - 1, offset[1] + h - 1


def _why(out: dict[str, dict[str, float]], reason: str, parts: Iterable[str] | None = None) -> None:
    """Record why the pose is empty (:mod:`mistool.pose.status`) on the given parts' rows
    (default: all), keeping a reason already recorded."""
    code = reason_code(reason)
    for name in out if parts is None else parts:
        if name in out and not out[name][AUX_STATUS] >= 0:
            out[name][AUX_STATUS] = code


def ideal_outline(pix: np.ndarray, bnd: Boundary, camera: Camera) -> tuple[np.ndarray, Boundary]:
    """The one place where mask points enter the pose: outline pixels (N, 2) and boundary
    points in the camera's image -> the same points in its ideal pinhole image
    (:func:`mistool.lens.undistort_points`; unchanged for an undistorted lens)."""
    if not camera.distorted:
        return pix, bnd
    n, m = len(pix), len(bnd.bg)
    ideal = undistort_points(np.concatenate([pix, bnd.bg, bnd.other]), camera)
    return ideal[:n], Boundary(bg=ideal[n : n + m], other=ideal[n + m :])


def _ideal_px(px: np.ndarray, camera: Camera) -> np.ndarray:
    """One pixel (2,) of the camera's image in its ideal image (``undistort_points``; the
    pixel itself for an undistorted lens)."""
    return undistort_points(px[None], camera)[0] if camera.distorted else px


def _fill_pose(
    row: dict[str, float], end: np.ndarray | None, axis: np.ndarray | None, start: np.ndarray | None
) -> None:
    if end is not None:
        row["end_x_mm"], row["end_y_mm"], row["end_z_mm"] = end.tolist()
    if axis is not None:
        row["axis_x"], row["axis_y"], row["axis_z"] = axis.tolist()
        row["qw"], row["qx"], row["qy"], row["qz"] = quat_from_z(axis).tolist()
    if start is not None:
        row["start_x_mm"], row["start_y_mm"], row["start_z_mm"] = start.tolist()


def _joint_t(
    pts: np.ndarray,
    is_other: np.ndarray,
    p0: np.ndarray,
    a: np.ndarray,
    radius: float,
    K: np.ndarray,
) -> tuple[float, float]:
    """J's axial coordinate (mm) and the points' robust spread (mm) from the shaft's
    distal outline points.

    Next to background the outline is exactly where the ray's chord through the infinite
    cylinder first reaches J's axial coordinate (``min(t_in, t_out) == t_J``); next to the
    clasper it is where the ray enters the cylinder at ``t_J`` (exact for a clasper or
    wrist as wide as the shaft; a narrower clasper seen over the shaft's end face biases it
    distally), so background points are preferred when there are enough of them.
    """
    rays = pixel_rays(pts, K)
    t_in, t_out, _ = ray_cylinder(rays, p0, a, radius)
    bg = ~is_other
    if np.count_nonzero(bg) >= 5:
        v = np.minimum(t_in, t_out)[bg]
    else:
        v = np.where(is_other, t_in, np.minimum(t_in, t_out))
    med = _median1(v)
    return med, 1.4826 * _median1(np.abs(v - med))


class _LineStats:
    """A fitted limb line's support: centre (2,) px, span (px), inliers, RMS (px)."""

    __slots__ = ("centre", "n", "sigma", "span")

    def __init__(self, centre: np.ndarray, span: float, n: int, sigma: float) -> None:
        self.centre, self.span, self.n, self.sigma = centre, span, n, sigma


def _fit_limbs(
    pts: np.ndarray,
    s: np.ndarray,
    q: np.ndarray,
    keep: np.ndarray,
    centre: np.ndarray,
    rng: np.random.Generator | None,
) -> tuple[list[np.ndarray | None], list[_LineStats | None]]:
    """One robust line per side of the axis; interior (the centre) on the positive side."""
    lines: list[np.ndarray | None] = []
    stats: list[_LineStats | None] = []
    for side in (q < 0, q > 0):
        use = np.flatnonzero(keep & side)
        if len(use) > FIT_MAX_POINTS:  # the fit's own regular subsample, taken here
            use = use[regular_subsample(len(use), FIT_MAX_POINTS)]
        enough = len(use) >= _MIN_LINE_POINTS
        fit = fit_line_robust(take_rows(pts, use), s[use], rng) if enough else None
        if fit is not None:
            line, inl, sig = fit
            idx = use[inl]
            n_in = len(idx)
            s_in = s[idx]
            span = float(s_in.max() - s_in.min()) if n_in else 0.0
            if n_in >= _MIN_LINE_POINTS and span >= _MIN_LINE_SPAN_PX:
                if line[:2] @ centre + line[2] < 0:
                    line = -line
                lines.append(line)
                stats.append(_LineStats(sum_rows(take_rows(pts, idx)) / n_in, span, n_in, sig))
                continue
        lines.append(None)
        stats.append(None)
    s0, s1 = stats
    if (
        lines[0] is not None
        and lines[1] is not None
        and s0 is not None
        and s1 is not None
        and float(lines[0][:2] @ lines[1][:2]) > 0
    ):
        # both fits found the same limb (e.g. the other one is out of the view and the
        # visible part's centroid is off-axis): keep the better one
        worse = 0 if s0.sigma > s1.sigma else 1
        lines[worse] = None
        stats[worse] = None
    return lines, stats


def _uncertainty(
    lines: Sequence[np.ndarray],
    stats: Sequence[_LineStats],
    K: np.ndarray,
    radius: float,
    ref: np.ndarray,
    a: np.ndarray,
) -> tuple[float, float]:
    """1-sigma error of a reference axis point (mm) and of the axis direction (deg),
    propagated by finite differences from each line's offset and angle uncertainty.

    Each line's errors come from its fit: residual RMS (at least ``_PX_NOISE``, the
    quantisation floor) over ``n_eff`` independent points (boundary errors are correlated
    over a few pixels: ``n_eff <= span / 2``), plus ``_PX_BIAS`` of unknown systematic
    offset (e.g. segmentation bias).
    """
    # plain floats: four solves of 3-vectors are much cheaper without numpy's overhead
    k_rows = K.tolist()
    rx, ry, rz = ref.tolist()
    nr = math.sqrt(rx * rx + ry * ry + rz * rz)
    ux, uy, uz = rx / nr, ry / nr, rz / nr
    ax_, ay_, az_ = a.tolist()
    base = [lines[0].tolist(), lines[1].tolist()]
    variants = []
    for k in (0, 1):
        st = stats[k]
        n_eff = max(2.0, min(float(st.n), st.span / 2.0))
        sig = max(st.sigma, _PX_NOISE)
        la, lb, lc = base[k]
        shifted = [la, lb, lc - math.hypot(sig / math.sqrt(n_eff), _PX_BIAS)]  # offset
        ang = sig * math.sqrt(12.0 / n_eff) / max(st.span, 1.0)  # angle, about the centre
        co, si = math.cos(ang), math.sin(ang)
        na, nb = co * la - si * lb, si * la + co * lb
        cx_, cy_ = st.centre.tolist()
        turned = [na, nb, -(na * cx_ + nb * cy_)]
        for ln in (shifted, turned):
            variants.append((ln, base[1]) if k == 0 else (base[0], ln))
    var_p = var_a = 0.0
    for la, lb in variants:
        sol = axis_from_image_lines(la, lb, k_rows, radius)
        if sol is None:
            return math.inf, math.inf
        (px, py, pz), (cx, cy, cz) = sol
        # the axis point closest to the reference ray
        da = cx * ux + cy * uy + cz * uz
        dp = px * ux + py * uy + pz * uz
        ap = cx * px + cy * py + cz * pz
        t = (da * dp - ap) / max(1.0 - da * da, 1e-12)
        ex, ey, ez = px + t * cx - rx, py + t * cy - ry, pz + t * cz - rz
        var_p += ex * ex + ey * ey + ez * ez
        var_a += math.degrees(math.acos(min(1.0, abs(cx * ax_ + cy * ay_ + cz * az_)))) ** 2
    return math.sqrt(var_p), math.sqrt(var_a)


@dataclass(frozen=True)
class _ShaftPoints:
    """Every image point of the shaft that the pose uses (full-image px).

    Gathered in one place (:func:`_shaft_points`); the clasper's points enter separately,
    in :func:`_tip`. Points are in the camera's *ideal* pinhole image: with a distorted
    lens they are undistorted here (:func:`ideal_outline`); ``border`` and ``mask`` stay
    in the camera's image.
    """

    pix: np.ndarray
    """(N, 2) outline pixels of the measured shaft region (ideal image, see below)."""
    centre: np.ndarray
    """(2,) the region's centroid (ideal image)."""
    moments: dict[str, float]
    """Region moments of that region (crop coordinates, as ``cv2.moments``)."""
    offset: tuple[int, int]
    """(x0, y0) of the crop the moments refer to."""
    bnd: Boundary
    """Sub-pixel boundary points: ``bg`` next to background, ``other`` next to the
    instrument's other parts."""
    border: np.ndarray
    """(N,) bool: the outline pixel is on the image border."""
    mask: np.ndarray
    """The measured shaft region (bool crop at ``offset``), for the quality IoU."""
    merged: bool
    """Two shafts were found in the instance (only the larger is measured)."""


@dataclass(frozen=True)
class _ShaftFrame:
    """The shaft's image frame: centroid and axis direction (distal when known)."""

    centre: np.ndarray
    """(2,) region centroid (px)."""
    e: np.ndarray
    """(2,) unit image direction of the axis, distal when ``distal_seen``."""
    eperp: np.ndarray
    """(2,) ``e`` turned by +90 degrees."""
    s_pix: np.ndarray
    """(N,) the outline pixels' coordinate along ``e`` from the centre (px)."""
    s_min: float
    s_max: float
    distal_seen: bool
    """The distal direction was seen (other parts, or one end at the image border)."""
    prox_at_border: bool
    """The proximal end of the outline touches the image border."""
    dist_at_border: bool
    """The distal end of the outline touches the image border."""
    med_other: np.ndarray | None
    """(2,) median of the boundary points next to other parts (the joint's pixel), or None."""
    width: float
    """Widest apparent width across ``e`` (px)."""


@dataclass(frozen=True)
class _LimbPoints:
    """The background boundary points that may lie on the limb lines."""

    pts: np.ndarray
    """(M, 2) background boundary points (px)."""
    s: np.ndarray
    """(M,) their coordinate along the axis direction (px)."""
    q: np.ndarray
    """(M,) their coordinate across it (px; the side of the axis)."""
    keep_base: np.ndarray
    """(M,) bool: away from the proximal end zone and from other parts."""
    keep: np.ndarray
    """(M,) bool: ``keep_base`` and away from the distal end zone."""
    zone: float
    """Length (px) of the end zones left out."""


@dataclass(frozen=True)
class _ShaftSolution:
    """The shaft's axis (camera frame, mm) and joint, with the limb lines they came from."""

    lines: tuple[np.ndarray, np.ndarray]
    stats: tuple[_LineStats, _LineStats]
    p0: np.ndarray
    """(3,) a point of the axis (mm)."""
    a: np.ndarray
    """(3,) unit axis direction, distal."""
    xc: np.ndarray
    """(3,) the axis point seen at the region's centroid (mm)."""
    joint: np.ndarray | None
    """(3,) J (mm), or None."""
    joint_why: str
    """Why there is no joint (:mod:`mistool.pose.status`); empty when there is one."""


#: A shaft separated from its own wrist or clasper by a thin gap (a segmentation that
#: misses the junction) still meets them there: its outline points within this many px
#: of them are taken as next to them.
_JUNCTION_GAP_PX = 5
_GAP_DISK = cv2.getStructuringElement(
    cv2.MORPH_ELLIPSE, (2 * _JUNCTION_GAP_PX + 1, 2 * _JUNCTION_GAP_PX + 1)
)


def _across_gap(
    bnd: Boundary,
    shaft_mask: np.ndarray,
    offset: tuple[int, int],
    others: list[tuple[np.ndarray, tuple[int, int]]],
    image_shape: tuple[int, int],
    pix: np.ndarray,
) -> Boundary:
    """The boundary points with the instrument's other parts grown by
    :data:`_JUNCTION_GAP_PX` (a thin gap at the junction closed), when that finds the
    junction; else ``bnd`` unchanged."""
    g = _JUNCTION_GAP_PX
    canvas = make_canvas(shaft_mask, offset, others, image_shape, margin=2 + g)
    lab = canvas.labels
    near = cv2.dilate(cv2.compare(lab, OTHER, cv2.CMP_EQ), _GAP_DISK) > 0  # type: ignore[call-overload]
    grown = lab.copy()
    grown[(lab == BG) & near] = OTHER
    found = boundary_points(Canvas(grown, canvas.x0, canvas.y0), pix)
    return found if len(found.other) >= 3 else bnd


#: Shaft pieces are one shaft cut across when their directions agree within this (deg)
#: and each piece's centroid is within this fraction of the larger piece's width of
#: its axis line.
_CUT_ANGLE_DEG = 8.0
_CUT_OFFSET_FRAC = 0.35


def _one_cut_shaft(contours: Sequence[np.ndarray], areas: np.ndarray, big: int) -> bool:
    """Whether the large shaft pieces (area >= 25% of the largest) are one shaft cut
    across: each piece's centroid on the pieces' common axis (within
    :data:`_CUT_OFFSET_FRAC` of its own width across it) and each elongated piece along
    it (:data:`_CUT_ANGLE_DEG`); two tools side by side are half a width off it."""
    pieces = [c for c, a in zip(contours, areas, strict=True) if a >= 0.25 * areas[big]]
    pts = np.concatenate([c.reshape(-1, 2) for c in pieces])
    x0, y0 = pts.min(axis=0)
    union = np.zeros((int(pts[:, 1].max() - y0) + 1, int(pts[:, 0].max() - x0) + 1), np.uint8)
    cv2.drawContours(union, [c - np.array([x0, y0]) for c in pieces], -1, 1, thickness=-1)
    m = cv2.moments(union, binaryImage=True)
    if m["m00"] <= 0:
        return False
    theta = 0.5 * math.atan2(2.0 * m["mu11"], m["mu20"] - m["mu02"])
    e = np.array([math.cos(theta), math.sin(theta)])
    n = np.array([-e[1], e[0]])
    c0 = np.array([m["m10"] / m["m00"] + x0, m["m01"] / m["m00"] + y0])
    for c in pieces:
        p = c.reshape(-1, 2).astype(np.float64)
        across = float(np.ptp(p @ n))
        along = float(np.ptp(p @ e))
        mk = cv2.moments(c)
        if mk["m00"] <= 0:
            return False
        ck = np.array([mk["m10"], mk["m01"]]) / mk["m00"]
        if abs(float((ck - c0) @ n)) > _CUT_OFFSET_FRAC * across:
            return False
        if along >= 1.5 * across:  # elongated: its own direction must agree
            tk = 0.5 * math.atan2(2.0 * mk["mu11"], mk["mu20"] - mk["mu02"])
            if abs((math.degrees(tk - theta) + 90.0) % 180.0 - 90.0) > _CUT_ANGLE_DEG:
                return False
    return True


def _shaft_points(
    parts: Mapping[str, PartObservation], image_shape: tuple[int, int], camera: Camera
) -> _ShaftPoints | None:
    """Gather the shaft's image points (the pose's pixel input, in the ideal image of
    ``camera``), or None for no region.

    Two shafts in one instance (two tools touching in a merged mask): only the larger
    shaft is kept (and ``merged`` set: the clasper, whose jaws may be either tool's, is
    then left empty). Pieces of one shaft cut across (a specular streak, a thread, a
    segmentation gap: :func:`_one_cut_shaft`) are kept together: they share its limb lines.
    """
    shaft = parts["shaft"]
    smask = _as_u8(shaft.mask)
    shaft_mask = shaft.mask
    contours, _ = cv2.findContours(smask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    merged = False
    if len(contours) > 1:
        areas = np.array([cv2.contourArea(c) for c in contours])
        big = int(np.argmax(areas))
        if np.count_nonzero(areas >= 0.25 * areas[big]) > 1 and not _one_cut_shaft(
            contours, areas, big
        ):
            merged = True
            keep_u8 = np.zeros_like(smask)
            cv2.drawContours(keep_u8, contours, big, 1, thickness=-1)
            smask = np.ascontiguousarray(keep_u8 & smask)
            shaft_mask = smask.view(bool)
            contours = (contours[big],)
    others = [(p.mask, p.offset) for n, p in parts.items() if n != "shaft"]
    canvas = make_canvas(shaft_mask, shaft.offset, others, image_shape)
    pix, mom = _outline(smask, shaft.offset, contours)
    if mom["m00"] <= 0:
        return None
    border = _on_border(pix, image_shape, _crop_bounds(shaft_mask, shaft.offset))  # camera's
    bnd = boundary_points(canvas, pix)
    if len(bnd.other) < 3 and others:  # a thin gap between the shaft and its head?
        bnd = _across_gap(bnd, shaft_mask, shaft.offset, others, image_shape, pix)
    ideal_pix, bnd = ideal_outline(pix, bnd, camera)
    centre = (mom["m10"] / mom["m00"] + shaft.offset[0], mom["m01"] / mom["m00"] + shaft.offset[1])
    return _ShaftPoints(
        pix=ideal_pix,
        centre=_ideal_px(np.array(centre), camera),
        moments=mom,
        offset=shaft.offset,
        bnd=bnd,
        border=border,
        mask=shaft_mask,
        merged=merged,
    )


def _initial_direction(
    sp: _ShaftPoints, centre: np.ndarray, mu: tuple[float, ...], med_other: np.ndarray | None
) -> np.ndarray:
    """(2,) unit image direction of the axis (sign not yet distal).

    The principal axis of the region, except where it fails: on a short visible stretch (as
    wide as long, or wider) the joint is on the axis, so the direction toward the
    shaft-clasper boundary is the axis' direction whatever the shape; without a clasper, a
    short stretch uses the direction away from where the shaft leaves the view.
    ``med_other``: the median of the boundary points next to other parts (at least 3),
    or None.
    """
    mu20, mu02, mu11 = mu
    theta = 0.5 * math.atan2(2.0 * mu11, mu20 - mu02)
    e = np.array([math.cos(theta), math.sin(theta)])
    tr, det = mu20 + mu02, mu20 * mu02 - mu11 * mu11
    disc = math.sqrt(max(tr * tr / 4.0 - det, 0.0))
    d0: np.ndarray | None = None
    if med_other is not None:
        d0 = med_other - centre
    elif tr / 2.0 + disc < 9.0 * max(tr / 2.0 - disc, 1e-9):
        if sp.border.any():
            d0 = centre - _mean_rows(sp.pix, sp.border)
    nd0 = math.hypot(d0[0], d0[1]) if d0 is not None else 0.0
    if d0 is not None and nd0 > 2.0:
        e = d0 / nd0
    return e


def _distal_sign(sp: _ShaftPoints, centre: np.ndarray, e: np.ndarray, s_pix: np.ndarray) -> int:
    """+1 / -1 when ``e`` / ``-e`` is distal (toward the other parts, else away from the
    image border), 0 when nothing tells."""
    if len(sp.bnd.other) >= 3:
        return 1 if float(((sp.bnd.other - centre) @ e).sum()) >= 0 else -1
    lo, hi = s_pix.min(), s_pix.max()
    t_lo = bool(np.any(sp.border & (s_pix <= lo + 2.0)))
    t_hi = bool(np.any(sp.border & (s_pix >= hi - 2.0)))
    return 1 if (t_lo and not t_hi) else (-1 if (t_hi and not t_lo) else 0)


def _shaft_frame(sp: _ShaftPoints) -> _ShaftFrame:
    """The shaft's image frame from its region moments and outline."""
    mom = sp.moments
    xm, ym = mom["m10"] / mom["m00"], mom["m01"] / mom["m00"]
    mu20 = mom["m20"] / mom["m00"] - xm * xm
    mu02 = mom["m02"] / mom["m00"] - ym * ym
    mu11 = mom["m11"] / mom["m00"] - xm * ym
    centre = sp.centre
    med_other = _median_rows(sp.bnd.other) if len(sp.bnd.other) >= 3 else None
    e = _initial_direction(sp, centre, (mu20, mu02, mu11), med_other)
    rel = sub_rows(sp.pix, centre)
    s_pix = rel @ e
    distal = _distal_sign(sp, centre, e, s_pix)
    if distal < 0:
        e = -e
        s_pix = -s_pix
    s_min, s_max = float(s_pix.min()), float(s_pix.max())
    eperp = np.array([-e[1], e[0]])
    across = rel @ eperp
    at_border = sp.border.any()
    return _ShaftFrame(
        centre=centre,
        e=e,
        eperp=eperp,
        s_pix=s_pix,
        s_min=s_min,
        s_max=s_max,
        distal_seen=distal != 0,
        prox_at_border=bool(at_border and (sp.border & (s_pix <= s_min + 2.0)).any()),
        dist_at_border=bool(at_border and (sp.border & (s_pix >= s_max - 2.0)).any()),
        med_other=med_other,
        width=float(across.max() - across.min()),
    )


def _limb_points(sp: _ShaftPoints, fr: _ShaftFrame) -> _LimbPoints:
    """The limb-line candidates: background boundary points minus the end zones (the
    joint's cap; the proximal end when inside the image) and points next to other parts."""
    # the joint's end cap reaches at most about half the width along the axis; on short
    # visible stretches keep most of the stretch for the lines (the robust fit rejects
    # the cap's points that curve away)
    zone = min(0.6 * fr.width + 2.0, max(3.0, 0.15 * (fr.s_max - fr.s_min)))
    pts = sp.bnd.bg
    rel = sub_rows(pts, fr.centre)
    s = rel @ fr.e
    keep_base = np.ones(len(pts), dtype=bool)
    if not fr.prox_at_border:
        keep_base &= s > fr.s_min + zone
    other = sp.bnd.other
    if len(other):  # leave out points within 2 px of another part
        keep_base[_near(pts, other)] = False
    return _LimbPoints(
        pts=pts,
        s=s,
        q=rel @ fr.eperp,
        keep_base=keep_base,
        keep=keep_base & (s < fr.s_max - zone),
        zone=zone,
    )


def _near(pts: np.ndarray, other: np.ndarray) -> np.ndarray:
    """Indices of the points (N, 2) within 2 px (strictly) of one of every other point
    of ``other`` (M, 2), M >= 1."""
    x, y = pts[:, 0], pts[:, 1]
    ox, oy = other[:, 0], other[:, 1]
    lo_x, lo_y, hi_x, hi_y = ox.min() - 2.0, oy.min() - 2.0, ox.max() + 2.0, oy.max() + 2.0
    inside = x >= lo_x
    inside &= x <= hi_x
    inside &= y >= lo_y
    inside &= y <= hi_y
    box = np.flatnonzero(inside)
    if not len(box):
        return box
    dx = np.subtract.outer(x[box], ox[::2])
    dy = np.subtract.outer(y[box], oy[::2])
    dx *= dx
    dy *= dy
    dx += dy  # squared distances
    return box[dx.min(axis=1) < 4.0]


def _joint_pixel(sp: _ShaftPoints, fr: _ShaftFrame) -> np.ndarray | None:
    """(2,) the joint's pixel (for a later trocar-constrained solve), or None."""
    if fr.med_other is not None:
        return fr.med_other
    if fr.distal_seen and not fr.dist_at_border:
        return _mean_rows(sp.pix, fr.s_pix >= fr.s_max - 1.0)
    return None


def _solve_axis(
    lines: tuple[np.ndarray, np.ndarray], K: np.ndarray, radius: float, fr: _ShaftFrame
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The axis ``(p0, a distal, xc)`` (mm) from two limb lines, or None when the solution
    is behind the camera or its apparent width disagrees with the mask's."""
    sol = axis_from_image_lines(lines[0].tolist(), lines[1].tolist(), K.tolist(), radius)
    if sol is None:
        return None
    p0, a = np.array(sol[0]), np.array(sol[1])
    tc = _closest1(fr.centre, K, p0, a)
    xc = p0 + tc * a
    x0, y0, z0 = xc.tolist()
    if z0 <= 0:
        return None
    ax, ay, az = a.tolist()
    z1 = z0 + az  # the image direction of a at xc, by a 1 mm step
    du = K[0, 0] * ((x0 + ax) / z1 - x0 / z0)
    dv = K[1, 1] * ((y0 + ay) / z1 - y0 / z0)
    if du * fr.e[0] + dv * fr.e[1] < 0:
        a = -a
    if not fr.distal_seen and a[2] < 0:  # no distal cue: by convention, into the scene
        a = -a
    # sanity: apparent width at the centroid vs the mask's
    c = fr.centre
    wc = float(lines[0][:2] @ c + lines[0][2] + lines[1][:2] @ c + lines[1][2])
    if not 0.5 * fr.width <= wc <= 1.6 * fr.width + 2.0:
        return None
    return p0, a, xc


def _is_round_end(cap_q: np.ndarray, cap_s: np.ndarray, spread: float) -> bool:
    """A free distal end is the shaft's round end (its outline bulges distally and sits at
    one axial coordinate), not an occluder's cut across the shaft.

    Args:
        cap_q, cap_s: (n,) the end's outline points across / along the axis (px).
        spread: robust spread of their axial coordinates on the cylinder (mm).
    """
    if len(cap_q) < 5 or spread > _MAX_CAP_SPREAD_MM:
        return False
    x2 = (cap_q - 0.5 * (cap_q.max() + cap_q.min())) ** 2
    x2c = x2 - x2.mean()
    return float(x2c @ (cap_s - cap_s.mean())) < 0  # along-axis coordinate shrinks outward


def _joint(
    p0: np.ndarray,
    a: np.ndarray,
    lines: tuple[np.ndarray, np.ndarray],
    stats: tuple[_LineStats, _LineStats],
    sp: _ShaftPoints,
    fr: _ShaftFrame,
    lp: _LimbPoints,
    radius: float,
    K: np.ndarray,
) -> tuple[np.ndarray | None, str]:
    """J (3,) (mm) on the axis ``(p0, a)`` from the shaft's distal outline, or None when
    the distal end is not seen, out of view, or not the shaft's own end; with the reason
    (:mod:`mistool.pose.status`) when None."""
    other = sp.bnd.other
    if not fr.distal_seen or (fr.dist_at_border and len(other) < 3):
        return None, "joint out of view"
    near = np.flatnonzero(lp.s >= fr.s_max - lp.zone)
    pn = take_rows(lp.pts, near)
    d1 = np.abs(pn @ lines[0][:2] + lines[0][2])
    d2 = np.abs(pn @ lines[1][:2] + lines[1][2])
    tol = max(1.0, 2.5 * max(st.sigma for st in stats))
    cap = near[(d1 > tol) & (d2 > tol)]
    end_pts = np.concatenate([other, take_rows(lp.pts, cap)])
    is_other = np.zeros(len(end_pts), dtype=bool)
    is_other[: len(other)] = True
    if len(end_pts) < 3:
        return None, "rejected"
    tj, spread = _joint_t(end_pts, is_other, p0, a, radius, K)
    if len(other) < 3 and not _is_round_end(lp.q[cap], lp.s[cap], spread):
        return None, "occluded"
    joint = p0 + tj * a
    return (joint, "") if joint[2] > 0 else (None, "rejected")


def _both(
    lines: list[np.ndarray | None], stats: list[_LineStats | None]
) -> tuple[tuple[np.ndarray, np.ndarray], tuple[_LineStats, _LineStats]] | None:
    """The two limb lines and their stats, or None when a side has no line."""
    l1, l2 = lines
    s1, s2 = stats
    if l1 is None or l2 is None or s1 is None or s2 is None:
        return None
    return (l1, l2), (s1, s2)


def _solve_shaft(
    lines: tuple[np.ndarray, np.ndarray],
    stats: tuple[_LineStats, _LineStats],
    sp: _ShaftPoints,
    fr: _ShaftFrame,
    lp: _LimbPoints,
    radius: float,
    K: np.ndarray,
) -> _ShaftSolution | None:
    """Axis and joint from the limb lines; on a short visible stretch, once more with the
    lines refitted proximal of the first joint (see below)."""
    res = _solve_axis(lines, K, radius, fr)
    if res is None:
        return None
    p0, a, xc = res
    joint, why = _joint(p0, a, lines, stats, sp, fr, lp, radius, K)
    first = _ShaftSolution(lines, stats, p0, a, xc, joint, why)
    if joint is None or fr.s_max - fr.s_min >= 2.5 * fr.width:
        return first
    # short visible stretch: the end-zone cut was small, so the joint's cap may have leaked
    # into the lines; refit with the points the first solution puts proximal of J (the limb
    # lines exist only there) and solve again
    t_pts = closest_on_axis(pixel_rays(lp.pts, K), p0, a)
    keep2 = lp.keep_base & (t_pts < float((joint - p0) @ a) - 0.5)
    refit = _both(*_fit_limbs(lp.pts, lp.s, lp.q, keep2, fr.centre, None))
    if refit is None:
        return first
    res2 = _solve_axis(refit[0], K, radius, fr)
    if res2 is None:
        return first
    joint2, _ = _joint(res2[0], res2[1], refit[0], refit[1], sp, fr, lp, radius, K)
    if joint2 is None:
        return first
    return _ShaftSolution(refit[0], refit[1], res2[0], res2[1], res2[2], joint2, "")


_LINE_KEYS = (("aux_l1a", "aux_l1b", "aux_l1c"), ("aux_l2a", "aux_l2b", "aux_l2c"))


def _store_lines(row: dict[str, float], lines: Sequence[np.ndarray | None]) -> None:
    """The limb lines in the ``aux_l*`` cells."""
    for keys, line in zip(_LINE_KEYS, lines, strict=True):
        if line is not None:
            row[keys[0]], row[keys[1]], row[keys[2]] = line.tolist()


def _shaft_row(
    out: dict[str, dict[str, float]],
    sol: _ShaftSolution,
    sp: _ShaftPoints,
    fr: _ShaftFrame,
    K: np.ndarray,
    radius: float,
    image_shape: tuple[int, int],
    camera: Camera,
) -> bool:
    """Fill the shaft's row (J, axis, proximal end, quality, uncertainties); False when
    the joint's uncertainty is too large for any pose (the reason recorded on every row)."""
    row = out["shaft"]
    p0, a, joint = sol.p0, sol.a, sol.joint
    prox = _mean_rows(sp.pix, fr.s_pix <= fr.s_min + 1.0)
    row["aux_su_px"], row["aux_sv_px"] = float(prox[0]), float(prox[1])
    # uncertainty of the joint (or the centroid's axis point) and of the direction
    ref = joint if joint is not None else sol.xc
    sig_p, sig_a = _uncertainty(sol.lines, sol.stats, K, radius, ref, a)
    row["aux_sigma_mm"], row["aux_sigma_deg"] = sig_p, sig_a
    if not sig_p <= MAX_SIGMA_MM:
        ray = ref / math.sqrt(float(ref @ ref))
        end_on = abs(float(ray @ a)) > math.cos(math.radians(_END_ON_DEG))
        _why(out, "pointing at camera" if end_on else "low quality")
        return False
    if not sig_a <= MAX_SIGMA_DEG:
        # the position is known but not the direction: J only (refine_sequence restores
        # the direction from the trocar when it can); the clasper still uses the
        # measured direction as its (weak) bend prior
        _fill_pose(row, joint, None, None)
        _why(out, "uncertain axis", ("shaft",))
        return True
    # proximal end: where the shaft leaves the view (or its proximal end)
    t_start = _closest1(prox, K, p0, a)
    start = p0 + t_start * a
    if joint is not None:
        t_end = float((joint - p0) @ a)
    else:  # the distal end of the outline
        t_end = _closest1(_mean_rows(sp.pix, fr.s_pix >= fr.s_max - 1.0), K, p0, a)
    start_ok = start[2] > 0 and t_end > t_start
    _fill_pose(row, joint, a, start if start_ok else None)
    if start_ok:
        poly = hull_of_cylinder(start, p0 + t_end * a, radius, radius, K)
        row["quality"] = iou_polygon_mask(poly, sp.mask, sp.offset, image_shape, camera)
    return True


def _clasper_rows(
    out: dict[str, dict[str, float]],
    parts: Mapping[str, PartObservation],
    joint: np.ndarray,
    a: np.ndarray,
    K: np.ndarray,
    radius: float,
    image_shape: tuple[int, int],
    clasper_length_mm: float | None,
    camera: Camera,
) -> None:
    """Fill the clasper's row (tip, clasper axis, quality) and the wrist's (its axis)."""
    clasper = parts.get("clasper")
    c_axis = None
    if clasper is not None and clasper.mask.any():
        tip, c_axis, tip_px = _tip(
            clasper, joint, a, K, image_shape, clasper_length_mm, 2.0 * radius, camera
        )
        crow = out["clasper"]
        if tip_px is not None:
            crow["aux_u_px"], crow["aux_v_px"] = float(tip_px[0]), float(tip_px[1])
        if tip is not None:
            _fill_pose(crow, tip, c_axis, joint)
            poly = hull_of_cylinder(joint, tip, 0.5 * radius, 0.25 * radius, K)
            crow["quality"] = iou_polygon_mask(
                poly, clasper.mask, clasper.offset, image_shape, camera
            )
        else:
            _why(out, "tip not found", ("clasper", "wrist"))
    else:
        _why(out, "no clasper", ("wrist",))
    if "wrist" in parts:
        _fill_pose(out["wrist"], None, c_axis, joint)


def measure_instance(
    instance: InstanceObservation,
    image_shape: tuple[int, int],
    camera: Camera | None,
    shaft_diameter_mm: float | None,
    clasper_length_mm: float | None,
) -> dict[str, dict[str, float]]:
    """Metric pose of one instrument in one frame.

    Pure and thread-safe (no shared state; RANSAC uses a fixed table of draws). The steps
    (see the module docstring): gather the shaft's points (:func:`_shaft_points`), its image
    frame (:func:`_shaft_frame`), the limb-line candidates (:func:`_limb_points`) and
    lines (:func:`_fit_limbs`), the axis and joint (:func:`_solve_shaft`), then the rows
    (:func:`_shaft_row`, :func:`_clasper_rows`).

    Args:
        instance: an ``InstanceObservation`` (``.parts``: part name -> observation with
            ``.mask`` (h, w) bool crop, ``.offset`` (x0, y0) px, ``.box`` RotatedBox).
        image_shape: (H, W) of the frame (px).
        camera: the pinhole intrinsics, or None (then every value is NaN).
        shaft_diameter_mm: the shaft's diameter (mm), or None (then NaN).
        clasper_length_mm: joint-to-tip length (mm), or None (the tip is then placed on
            the shaft axis' extension, i.e. assuming no bend out of the image plane).

    Returns:
        Part name -> {column: value} for every part of ``instance``: the columns of
        :data:`POSE_KEYS` (camera frame, mm, unit axes, quaternion wxyz, quality in [0, 1])
        plus :data:`AUX_KEYS`; NaN where unknown or not trustworthy.
    """
    parts = instance.parts
    out = {name: _nan_row() for name in parts}
    shaft = parts.get("shaft")
    if (
        camera is None
        or shaft is None
        or shaft_diameter_mm is None
        or not shaft_diameter_mm > 0
        or not shaft.mask.any()
    ):
        if camera is None:
            _why(out, "no camera")
        elif shaft is None or not shaft.mask.any():
            _why(out, "not visible")
        else:
            _why(out, "no shaft diameter")
        return out
    K = np.asarray(camera.K, dtype=np.float64)
    radius = 0.5 * float(shaft_diameter_mm)
    row = out["shaft"]
    sp = _shaft_points(parts, image_shape, camera)
    if sp is None:
        _why(out, "rejected")
        return out
    fr = _shaft_frame(sp)
    row["aux_distal"] = 1.0 if fr.distal_seen else 0.0
    lp = _limb_points(sp, fr)
    fitted, fitted_stats = _fit_limbs(lp.pts, lp.s, lp.q, lp.keep, fr.centre, None)
    _store_lines(row, fitted)
    jpx = _joint_pixel(sp, fr)
    if jpx is not None:
        row["aux_u_px"], row["aux_v_px"] = float(jpx[0]), float(jpx[1])
    both = _both(fitted, fitted_stats)
    if both is None:  # one limb line: refine_sequence may solve it with the trocar
        none = fitted[0] is None and fitted[1] is None
        _why(out, "no silhouette line" if none else "one silhouette line")
        return out
    sol = _solve_shaft(both[0], both[1], sp, fr, lp, radius, K)
    if sol is None:
        _why(out, "rejected")
        return out
    _store_lines(row, sol.lines)
    if not _shaft_row(out, sol, sp, fr, K, radius, image_shape, camera):
        return out
    if sol.joint is None or sp.merged:
        _why(out, sol.joint_why if sol.joint is None else "merged")
        return out
    _clasper_rows(out, parts, sol.joint, sol.a, K, radius, image_shape, clasper_length_mm, camera)
    return out


#: Tip depth prior: the joint-to-tip distance is the configured clasper length when the
#: wrist is straight and the jaws closed; opening and bending shorten it by a few percent.
_TIP_LENGTH_FACTOR = 1.0
_TIP_LENGTH_SIGMA = 0.05  # relative
_TIP_BEND_SIGMA_RAD = math.radians(45.0)
#: Jaw-end search: two jaw ends are distinct when more than this many jaw widths apart;
#: an end's jaw axis is estimated from the clasper pixels within this many jaw widths.
_JAW_SEP = 1.0
_JAW_RAD = 2.5
#: Fraction of the end-cap overshoot (jaw image radius x |cos(jaw, ray)|) removed.
_TIP_CAP = 1.0


def _jaw_tips(
    mask_u8: np.ndarray,
    offset: tuple[int, int],
    jpx: np.ndarray,
    width_px: float,
    with_nears: bool = True,
) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray], list[float]]:
    """Far ends of the clasper's jaws in the image.

    The jaw ends are the local maxima of the distance from J's pixel along the clasper's
    outline (a window of about one jaw width), at least half as far as the farthest;
    the two farthest that are more than ``_JAW_SEP`` jaw widths apart are the two open
    jaws, a single one is closed jaws. Each end is moved onto its jaw's axis: the farthest
    extent, along the principal direction of the clasper pixels within ``_JAW_RAD`` jaw
    widths (at most half the ends' separation), of those pixels, through their centroid.

    Args:
        mask_u8: (h, w) uint8 clasper crop; offset: its (x0, y0).
        jpx: (2,) J's pixel.
        width_px: expected jaw width in the image (px).
        with_nears: False: the outline points near each end are not gathered (their
            list is empty).

    Returns:
        (jaw-end pixels (2,), the outline points near each end (M, 2), each end's jaw
        direction (2,) (unit, away from J), each jaw's half-width in the image (px)).
    """
    contours, _ = cv2.findContours(mask_u8, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return [], [], [], []
    ci = max(contours, key=len).reshape(-1, 2)  # outline pixels (crop px, integers)
    c = ci.astype(np.float64)
    add_rows(c, offset)
    dj = sub_rows(c, jpx)
    d = np.sqrt(np.einsum("ij,ij->i", dj, dj))
    n = len(c)
    win = int(max(2, min(n // 4, round(width_px))))
    padded = np.concatenate([d[-win:], d, d[:win]])
    local = _window_max(padded, 2 * win + 1)
    cand = np.flatnonzero((d >= local) & (d >= 0.5 * d.max()))
    cand = cand[np.argsort(-d[cand])]
    sep = _JAW_SEP * width_px
    picks: list[int] = []
    at: list[tuple[float, float]] = []
    for i, (xi, yi) in zip(cand.tolist(), take_rows(c, cand).tolist(), strict=True):
        if all(math.hypot(xi - xj, yi - yj) > sep for xj, yj in at):
            picks.append(i)
            at.append((xi, yi))
        if len(picks) == 2:
            break
    rad = _JAW_RAD * width_px
    if len(picks) == 2:
        (xa, ya), (xb, yb) = at
        rad = min(rad, 0.5 * math.hypot(xa - xb, ya - yb))
    ends: list[np.ndarray] = []
    nears: list[np.ndarray] = []
    dirs: list[np.ndarray] = []
    halfw: list[float] = []
    for k in picks:
        nb, sx, sy = _pixels_within(mask_u8, offset, (int(ci[k, 0]), int(ci[k, 1])), rad)
        cnt = len(nb)
        if cnt < 3:
            continue
        # the pixels' mean: their coordinates are integers, so their sums are exact
        m = np.array([sx / cnt, sy / cnt])
        dd = sub_rows(nb, m)
        cov = dd.T @ dd
        phi = 0.5 * math.atan2(2.0 * cov[0, 1], cov[0, 0] - cov[1, 1])
        e = np.array([math.cos(phi), math.sin(phi)])
        if e @ (c[k] - jpx) < 0:
            e = -e
        ends.append(m + (float((dd @ e).max()) + 0.5) * e)
        dirs.append(e)
        across = dd @ np.array([-e[1], e[0]])
        halfw.append(min(0.5 * float(across.max() - across.min()) + 0.5, width_px))
        if with_nears:
            dc = ci - ci[k]
            nears.append(take_rows(c, np.einsum("ij,ij->i", dc, dc) <= rad * rad))
    return ends, nears, dirs, halfw


def _pixels_within(
    mask_u8: np.ndarray, offset: tuple[int, int], centre: tuple[int, int], rad: float
) -> tuple[np.ndarray, int, int]:
    """The pixels of a mask crop at ``offset`` within ``rad`` px of the pixel ``centre``
    (crop px, integers): (M, 2) float full-image px in row-major order (as ``np.nonzero``
    over the whole crop, only the window around ``centre`` examined), and the sums of
    their x and of their y (exact integers)."""
    h, w = mask_u8.shape
    cx, cy = centre
    x0, y0 = max(int(math.floor(cx - rad)), 0), max(int(math.floor(cy - rad)), 0)
    x1, y1 = min(int(math.ceil(cx + rad)) + 1, w), min(int(math.ceil(cy + rad)) + 1, h)
    if x0 >= x1 or y0 >= y1:
        return np.zeros((0, 2)), 0, 0
    ys, xs = np.nonzero(mask_u8[y0:y1, x0:x1])
    dx, dy = xs - (cx - x0), ys - (cy - y0)
    dx *= dx
    dy *= dy
    dx += dy  # squared distances, exact in integers
    inside = dx <= rad * rad
    xs, ys = xs[inside], ys[inside]
    fx, fy = offset[0] + x0, offset[1] + y0
    out = np.empty((len(xs), 2))
    np.add(xs, float(fx), out=out[:, 0])
    np.add(ys, float(fy), out=out[:, 1])
    return out, int(xs.sum()) + len(xs) * fx, int(ys.sum()) + len(ys) * fy


def _tip(
    clasper: PartObservation,
    joint: np.ndarray,
    a: np.ndarray,
    K: np.ndarray,
    image_shape: tuple[int, int],
    length: float | None,
    diameter: float,
    camera: Camera,
) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """Tip (3,), clasper axis (3,) and the tip's pixel (2,) in the ideal image (or Nones).

    The jaw ends are found on the clasper's mask, in the camera's image, and undistorted
    (:mod:`mistool.lens`) before they meet the 3D geometry.

    The tip's pixel is the mid-point of the jaw ends (:func:`_jaw_tips`), each end
    pulled back by its end cap's overshoot (the truth's jaw end is the cap's centre, the
    image ends at the cap's rim: a jaw's image radius x |cos(jaw, viewing ray)|). Its depth along
    the pixel's ray minimises a two-term cost: the joint-to-tip distance near the
    clasper length (well conditioned when the clasper is foreshortened) and a small bend
    from the shaft axis (well conditioned when the clasper is seen side-on). When the
    tip is cut by the image border it is placed at the nominal length along the least
    bent direction that projects along the clasper's image direction.
    """
    mask_u8 = _as_u8(clasper.mask)
    jx, jy, jz = joint.tolist()
    jpx = np.array([K[0, 0] * jx / jz + K[0, 2], K[1, 1] * jy / jz + K[1, 2]])  # project()
    jpx_image = distort_points(jpx[None], camera)[0] if camera.distorted else jpx
    width_px = K[0, 0] * 0.25 * diameter / max(float(joint[2]), 1.0)
    box = _crop_bounds(mask_u8, clasper.offset)
    at_border = min(box[:2]) <= 0 or box[2] >= image_shape[1] - 1 or box[3] >= image_shape[0] - 1
    ends, nears, dirs, halfw = _jaw_tips(
        mask_u8, clasper.offset, jpx_image, max(width_px, 2.0), with_nears=at_border
    )
    if not ends:
        return None, None, None
    tip_px = ends[0] if len(ends) == 1 else 0.5 * (ends[0] + ends[1])
    hidden = any(bool(_on_border(nb, image_shape, box).any()) for nb in nears)
    tip_px = _ideal_px(tip_px, camera)
    tip, c_axis, tip_px = _tip_solve(tip_px, joint, a, K, length, hidden, jpx)
    if tip is None or hidden or not _TIP_CAP:
        return tip, c_axis, tip_px
    # a jaw's image ends at its end cap's rim, which reaches beyond the cap's centre (the
    # truth's jaw end) by the jaw's image radius x |cos(jaw, viewing ray)|: pull each end
    # back by that (the clasper axis stands in for each jaw's direction) and solve again
    cos_v = abs(float(c_axis @ tip)) / math.sqrt(float(tip @ tip))
    ends = [e - _TIP_CAP * hw * cos_v * dr for e, dr, hw in zip(ends, dirs, halfw, strict=True)]
    tip_px = ends[0] if len(ends) == 1 else 0.5 * (ends[0] + ends[1])
    tip_px = _ideal_px(tip_px, camera)
    return _tip_solve(tip_px, joint, a, K, length, hidden, jpx)


def _tip_solve(
    tip_px: np.ndarray,
    joint: np.ndarray,
    a: np.ndarray,
    K: np.ndarray,
    length: float | None,
    hidden: bool,
    jpx: np.ndarray,
) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """The tip (3,) and clasper axis (3,) from the tip's pixel (see :func:`_tip`)."""
    # plain floats for the 3-vectors (numpy's per-call overhead dominates at this size)
    tu, tv = tip_px.tolist()
    ju, jv = jpx.tolist()
    dist = math.hypot(tu - ju, tv - jv)
    if dist < 2.0:
        return None, None, None
    uu, uv = (tu - ju) / dist, (tv - jv) / dist
    l_nom = _TIP_LENGTH_FACTOR * length if length is not None else None
    # least-bent direction in the plane of the camera centre, J and the tip's ray
    ray = _ray(tip_px, K)
    jx, jy, jz = joint.tolist()
    ax, ay, az = a.tolist()
    wx, wy, wz = (
        ray if not hidden else _ray(np.array([ju + 10.0 * uu, jv + 10.0 * uv]), K)
    ).tolist()
    nx, ny, nz = jy * wz - jz * wy, jz * wx - jx * wz, jx * wy - jy * wx
    nn = math.sqrt(nx * nx + ny * ny + nz * nz)
    if nn < 1e-9:
        return None, None, tip_px
    nx, ny, nz = nx / nn, ny / nn, nz / nn
    an = ax * nx + ay * ny + az * nz
    cx, cy, cz = ax - an * nx, ay - an * ny, az - an * nz
    ncl = math.sqrt(cx * cx + cy * cy + cz * cz)
    if ncl < 1e-6:
        return None, None, tip_px
    cx, cy, cz = cx / ncl, cy / ncl, cz / ncl
    # image direction of c at the joint (jz > 0 here)
    du = K[0, 0] * ((jx + cx) / (jz + cz) - jx / jz)
    dv_ = K[1, 1] * ((jy + cy) / (jz + cz) - jy / jz)
    if du * uu + dv_ * uv < 0:
        cx, cy, cz = -cx, -cy, -cz
    if hidden:
        if l_nom is None:
            return None, None, tip_px
        c = np.array([cx, cy, cz])
        return joint + l_nom * c, c, tip_px
    rx, ry, rz = ray.tolist()
    s_j = rx * jx + ry * jy + rz * jz
    span = 3.0 * (l_nom if l_nom is not None else 16.0)
    lo = max(s_j - span, 1.0)
    s = lo + (s_j + span - lo) * _UNIT_GRID
    # X(s) = s ray: |X - J|^2 = s^2 - 2 s (ray . J) + |J|^2, (X - J) . a = s (ray . a) - J . a
    ln = np.sqrt(np.maximum((s - 2.0 * s_j) * s + (jx * jx + jy * jy + jz * jz), 0.0))
    da = s * (rx * ax + ry * ay + rz * az) - (jx * ax + jy * ay + jz * az)
    cosb = np.minimum(np.maximum(da / np.maximum(ln, 1e-9), -1.0), 1.0)
    cost = (np.arccos(cosb) / _TIP_BEND_SIGMA_RAD) ** 2
    if l_nom is not None:
        cost += ((ln - l_nom) / (_TIP_LENGTH_SIGMA * l_nom)) ** 2
    k = int(cost.argmin())
    sk = float(s[k])
    if 0 < k < len(s) - 1:  # parabolic refinement
        c0, c1, c2 = cost[k - 1 : k + 2].tolist()
        den = c0 - 2.0 * c1 + c2
        off = 0.5 * (c0 - c2) / den if den > 0 else 0.0
        sk += min(max(off, -1.0), 1.0) * float(s[1] - s[0])
    dx, dy, dz = sk * rx - jx, sk * ry - jy, sk * rz - jz
    nd = math.sqrt(dx * dx + dy * dy + dz * dz)
    if nd < 1e-6:
        return None, None, tip_px
    return sk * ray, np.array([dx / nd, dy / nd, dz / nd]), tip_px
