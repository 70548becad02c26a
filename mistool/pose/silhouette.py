"""Sub-pixel boundary points of a part's mask and robust straight-line (limb) fitting.

Boundary points are the mid-points between 4-neighbour pixel pairs whose labels differ
(one inside the part, one outside). For a mask sampled at pixel centres this is an
unbiased estimate of where the true edge crosses the pair, with a uniform +-0.5 px error
that averages out along a line. Pairs that leave the image produce no point, so the image
border never counts as an edge. Only the part's outer outline is examined, so holes
inside the part (specular highlights) never produce points.

The points are gathered and the lines fitted by compiled kernels
(:func:`mistool.kernels.pose.shaft_boundary`, :func:`mistool.kernels.pose.fit_line`),
imported at the first call.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from types import ModuleType

import cv2
import numpy as np

__all__ = [
    "BG",
    "FIT_MAX_POINTS",
    "FIT_THRESH_PX",
    "OTHER",
    "SHAFT",
    "Boundary",
    "Canvas",
    "as_mask",
    "fit_line_robust",
    "kernels",
    "make_canvas",
    "outline_points",
    "paste",
    "regular_subsample",
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


def paste(
    dst: np.ndarray, x0: int, y0: int, mask: np.ndarray, ox: int, oy: int, value: int
) -> None:
    """``dst[mask] = value`` where a mask crop at ``(ox, oy)`` overlaps the label crop
    ``dst`` at ``(x0, y0)`` (full-image px), in place."""
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
        paste(lab, x0, y0, m.astype(bool, copy=False), px, py, OTHER)
    paste(lab, x0, y0, part_mask.astype(bool, copy=False), ox, oy, SHAFT)
    return Canvas(lab, x0, y0)


_KERNELS: list[ModuleType] = []


def kernels() -> ModuleType:
    """:mod:`mistool.kernels.pose`, imported at the first call (numba, with scipy, loads
    then, not when mistool is imported: the viewer starts without it), then kept."""
    if not _KERNELS:
        import mistool.kernels.pose

        _KERNELS.append(mistool.kernels.pose)
    return _KERNELS[0]


def as_mask(mask: np.ndarray) -> np.ndarray:
    """A part mask as a C-contiguous bool array (the kernels' input; no copy when it is
    one already)."""
    if mask.dtype == np.bool_ and mask.flags.c_contiguous:
        return mask
    return np.ascontiguousarray(mask != 0)


_NO_MASK = np.zeros((0, 0), dtype=bool)


def outline_points(
    part_mask: np.ndarray,
    offset: tuple[int, int],
    contours: Sequence[np.ndarray],
    others: list[tuple[np.ndarray, tuple[int, int]]],
    image_shape: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray, Boundary, np.ndarray]:
    """A part's outline pixels, border flags, boundary points and region moments.

    Args:
        part_mask: (h, w) bool crop of the part.
        offset: (x0, y0) of the crop in the full image (px).
        contours: the part's outer contours (``cv2.findContours`` of the crop,
            ``RETR_EXTERNAL``, ``CHAIN_APPROX_NONE``), at least one.
        others: (mask, offset) crops of the same instrument's other parts (their pixels
            are the OTHER label, the part's own pixels take precedence).
        image_shape: (H, W) of the full image.

    Returns:
        ``(pix, border, boundary, moments)``: (N, 2) float64 outline pixels (full-image
        px, the contours one after the other), (N,) bool on the image border, the
        :class:`Boundary` points (for each of the four neighbours, right, left, down,
        up, in turn along the outline), and (6,) the region moments ``m00, m10, m01,
        m20, m11, m02`` of the contours (crop px, as ``cv2.moments`` of each contour,
        summed).
    """
    if len(contours) == 1:
        outline = contours[0].reshape(-1, 2)
        starts = np.array([0, len(outline)], np.int64)
    else:
        outline = np.concatenate([c.reshape(-1, 2) for c in contours])
        starts = np.cumsum([0] + [len(c) for c in contours], dtype=np.int64)
    masks = [(as_mask(m), int(ox), int(oy)) for m, (ox, oy) in others]
    if len(masks) > 2:  # the kernel takes two: all others in one label crop
        canvas = make_canvas(part_mask, offset, others, image_shape)
        masks = [(canvas.labels == OTHER, canvas.x0, canvas.y0)]
    masks += [(_NO_MASK, 0, 0)] * (2 - len(masks))
    (m1, x1, y1), (m2, x2, y2) = masks
    H, W = image_shape
    pix, border, bg, other, moments = kernels().shaft_boundary(
        outline if outline.dtype == np.int32 else outline.astype(np.int32),
        starts,
        as_mask(part_mask),
        int(offset[0]),
        int(offset[1]),
        m1,
        x1,
        y1,
        m2,
        x2,
        y2,
        int(H),
        int(W),
    )
    return pix, border, Boundary(bg, other), moments


#: :func:`fit_line_robust` fits at most this many points (a regular subsample).
FIT_MAX_POINTS = 192
#: The limb-line fit's inlier threshold (px).
FIT_THRESH_PX = 1.5


@functools.lru_cache(maxsize=1024)
def regular_subsample(n: int, m: int) -> np.ndarray:
    """Indices of a regular subsample of ``m`` of ``n`` points (read-only, cached)."""
    keep = np.arange(m) * (n - 1) // (m - 1)
    keep.flags.writeable = False
    return keep


def fit_line_robust(
    pts: np.ndarray,
    along: np.ndarray,
    thresh_px: float = FIT_THRESH_PX,
    iters: int = 12,
    max_points: int = FIT_MAX_POINTS,
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Robust sub-pixel line: RANSAC on long baselines, then Tukey-weighted TLS
    (:func:`mistool.kernels.pose.fit_line`).

    The RANSAC pairs come from a fixed table of draws (deterministic and thread-safe):
    one point in each half of the points ordered along the line. The best line by MSAC
    (residuals capped at ``thresh_px``) is refitted by total least squares on its
    inliers, then twice with Tukey's biweight at 2.5 robust scales (the scale from the
    median residual of the points within it, between 0.3 px and ``thresh_px``).

    Args:
        pts: (N, 2) candidate points (px).
        along: (N,) coordinate of each point along the expected line direction (px), used
            to draw well-separated pairs.
        thresh_px: inlier threshold (px).
        iters: RANSAC hypotheses (at most 64).
        max_points: larger inputs are regularly subsampled to this many points.

    Returns:
        ``(line, inliers, sigma_px)``: (3,) line with unit normal, indices of the
        inlier points (among all the points), residual RMS of the inliers (px); or None
        with fewer than 8 points (or 6 RANSAC inliers).
    """
    if not 0 < iters <= 64:
        raise ValueError(f"fit_line_robust: iters={iters!r}, expected 1 to 64")
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    along = np.asarray(along, dtype=np.float64)
    keep = None
    if len(pts) > max_points:  # a regular subsample: the fit's precision is already ~0.03 px
        keep = regular_subsample(len(pts), max_points)
        pts, along = pts[keep], along[keep]
    line = np.empty(4)
    inliers = np.empty(len(pts), np.int64)
    x, y = np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1])
    n_in = kernels().fit_line(
        x, y, np.ascontiguousarray(along), float(thresh_px), int(iters), line, inliers
    )
    if n_in < 0:
        return None
    inl = inliers[:n_in]
    return line[:3].copy(), (inl if keep is None else keep[inl]), float(line[3])
