"""Sub-pixel boundary points of a part's mask and robust straight-line (limb) fitting.

Boundary points are the mid-points between 4-neighbour pixel pairs whose labels differ
(one inside the part, one outside). For a mask sampled at pixel centres this is an
unbiased estimate of where the true edge crosses the pair, with a uniform +-0.5 px error
that averages out along a line. Pairs that leave the image produce no point, so the image
border never counts as an edge. Only the part's outer outline is examined, so holes
inside the part (specular highlights) never produce points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["BG", "OTHER", "SHAFT", "Boundary", "Canvas", "boundary_points",
           "fit_line_robust", "make_canvas"]

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


def _paste(dst: np.ndarray, x0: int, y0: int, mask: np.ndarray, ox: int, oy: int,
           value: int) -> None:
    h, w = dst.shape
    mh, mw = mask.shape
    xa, ya = max(ox, x0), max(oy, y0)
    xb, yb = min(ox + mw, x0 + w), min(oy + mh, y0 + h)
    if xa >= xb or ya >= yb:
        return
    sub = mask[ya - oy:yb - oy, xa - ox:xb - ox]
    view = dst[ya - y0:yb - y0, xa - x0:xb - x0]
    view[sub] = value


def make_canvas(part_mask: np.ndarray, offset: tuple[int, int],
                others: list[tuple[np.ndarray, tuple[int, int]]],
                image_shape: tuple[int, int], margin: int = 2) -> Canvas:
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
    ij = np.asarray(outline, dtype=np.int64) - [canvas.x0, canvas.y0]
    x, y = ij[:, 0], ij[:, 1]
    pts_bg: list[np.ndarray] = []
    pts_ot: list[np.ndarray] = []
    for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        nx, ny = x + dx, y + dy
        inside = (nx >= 0) & (nx < w) & (ny >= 0) & (ny < h)
        nb = np.full(len(x), SHAFT, dtype=np.uint8)
        nb[inside] = lab[ny[inside], nx[inside]]
        for other_val, sink in ((BG, pts_bg), (OTHER, pts_ot)):
            m = nb == other_val
            if m.any():
                sink.append(np.stack([x[m] + (canvas.x0 + 0.5 * dx),
                                      y[m] + (canvas.y0 + 0.5 * dy)], axis=1))
    bg = np.concatenate(pts_bg) if pts_bg else np.empty((0, 2))
    ot = np.concatenate(pts_ot) if pts_ot else np.empty((0, 2))
    return Boundary(bg, ot)


def _tls(x: np.ndarray, y: np.ndarray, w: np.ndarray | None = None
         ) -> tuple[float, float, float]:
    """Weighted total-least-squares line ``(a, b, c)`` with ``hypot(a, b) = 1``."""
    if w is None:
        w = np.ones(len(x))
    sw = float(w.sum())
    mx, my = float(w @ x) / sw, float(w @ y) / sw
    dx, dy = x - mx, y - my
    wdx = w * dx
    sxx, sxy, syy = float(wdx @ dx), float(wdx @ dy), float((w * dy) @ dy)
    phi = 0.5 * math.atan2(2.0 * sxy, sxx - syy)  # direction of the line
    nx, ny = -math.sin(phi), math.cos(phi)
    return nx, ny, -(nx * mx + ny * my)


def _median(v: np.ndarray) -> float:
    k = len(v) // 2
    return float(np.partition(v, k)[k])


#: Fixed uniform draws for RANSAC: deterministic, thread-safe and free at call time.
_DRAWS = np.random.default_rng(12345).random((2, 64))


def fit_line_robust(pts: np.ndarray, along: np.ndarray, rng: np.random.Generator | None = None,
                    thresh_px: float = 1.5, iters: int = 12, max_points: int = 192
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
        keep = np.linspace(0, n - 1, max_points).astype(np.int64)
        pts, along = pts[keep], along[keep]
        n = max_points
    x, y = np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1])
    order = np.argsort(along)
    half = n // 2
    if rng is None:
        u1, u2 = _DRAWS[0, :iters], _DRAWS[1, :iters]
    else:
        u1, u2 = rng.random(iters), rng.random(iters)
    i = order[(u1 * half).astype(np.int64)]
    j = order[n - half + (u2 * half).astype(np.int64)]
    nx, ny = y[i] - y[j], x[j] - x[i]
    ln = np.hypot(nx, ny)
    ok = ln > 1e-9
    if not ok.any():
        return None
    nx, ny = nx[ok] / ln[ok], ny[ok] / ln[ok]
    c = -(nx * x[i[ok]] + ny * y[i[ok]])
    res = np.abs(np.outer(nx, x) + np.outer(ny, y) + c[:, None])  # (iters, n)
    best = int(np.argmin(np.minimum(res, thresh_px).sum(axis=1)))  # MSAC
    inl = res[best] < thresh_px
    if np.count_nonzero(inl) < 6:
        return None
    a, b, c0 = _tls(x[inl], y[inl], np.ones(np.count_nonzero(inl)))
    scale = thresh_px
    for _ in range(2):
        r = a * x + b * y + c0
        u = r / (2.5 * scale)
        w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
        if w.sum() < 6:
            break
        a, b, c0 = _tls(x, y, w)
        r = np.abs(a * x + b * y + c0)
        core = r[r < 2.5 * scale]
        scale = float(np.clip(1.4826 * _median(core), 0.3, thresh_px)) if len(core) else scale
    line = np.array([a, b, c0])
    r = a * x + b * y + c0
    inl = np.flatnonzero(np.abs(r) < max(2.5 * scale, 0.75))
    sigma = float(np.sqrt(np.mean(r[inl] ** 2))) if len(inl) else float("inf")
    return line, (inl if keep is None else keep[inl]), sigma
