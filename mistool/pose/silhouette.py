"""Sub-pixel boundary points of a part's mask and robust straight-line (limb) fitting.

Boundary points are the mid-points between 4-neighbour pixel pairs whose labels differ
(one inside the part, one outside). For a mask sampled at pixel centres this is an
unbiased estimate of where the true edge crosses the pair, with a uniform +-0.5 px error
that averages out along a line. Pairs that leave the image produce no point, so the image
border never counts as an edge. Only the part's outer outline is examined, so holes
inside the part (specular highlights) never produce points.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = [
    "BG",
    "FIT_MAX_POINTS",
    "OTHER",
    "SHAFT",
    "Boundary",
    "Canvas",
    "add_rows",
    "boundary_points",
    "fit_line_robust",
    "make_canvas",
    "sub_rows",
    "regular_subsample",
    "sum_rows",
    "take_rows",
]

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
