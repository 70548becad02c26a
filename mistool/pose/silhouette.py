"""Sub-pixel boundary points of a part's mask and robust straight-line (limb) fitting.

Boundary points are the mid-points between 4-neighbour pixel pairs whose labels differ
(one inside the part, one outside). For a mask sampled at pixel centres this is an
unbiased estimate of where the true edge crosses the pair, with a uniform +-0.5 px error
that averages out along a line. Pairs that leave the image produce no point, so the image
border never counts as an edge; pairs against a hole (a background region enclosed by the
instrument: a specular highlight) are left out too.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["BG", "HOLE", "OTHER", "SHAFT", "Boundary", "Canvas", "boundary_points",
           "fit_line_robust", "make_canvas"]

BG, SHAFT, OTHER, HOLE = 0, 1, 2, 3


@dataclass(frozen=True)
class Canvas:
    """A crop of the image around one part, labelled BG / SHAFT (the part) / OTHER (the
    instrument's other parts) / HOLE."""

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
    """Label crop around a part: the part, the instrument's other parts, holes.

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
    # holes: background enclosed by the instrument (4-connected background components
    # that do not touch the canvas edge). Canvas edges on the image border count as
    # outside too, so a notch cut by the border is not a hole.
    bgm = (lab == BG).astype(np.uint8)
    if bgm.any():
        n, comp = cv2.connectedComponents(bgm, connectivity=4)
        if n > 2:
            edge = np.unique(np.concatenate([comp[0], comp[-1], comp[:, 0], comp[:, -1]]))
            inner = np.ones(n, dtype=bool)
            inner[edge] = False
            inner[0] = False
            if inner.any():
                lab[inner[comp]] = HOLE
    return Canvas(lab, x0, y0)


def boundary_points(canvas: Canvas) -> Boundary:
    """Sub-pixel boundary points of the canvas' part (see module docstring)."""
    lab = canvas.labels
    pts_bg: list[np.ndarray] = []
    pts_ot: list[np.ndarray] = []
    for axis in (1, 0):
        if axis == 1:
            a, b = lab[:, :-1], lab[:, 1:]
        else:
            a, b = lab[:-1, :], lab[1:, :]
        sa, sb = a == SHAFT, b == SHAFT
        for other_val, sink in ((BG, pts_bg), (OTHER, pts_ot)):
            m = (sa & (b == other_val)) | (sb & (a == other_val))
            r, c = np.nonzero(m)
            if len(r):
                if axis == 1:
                    p = np.stack([c + 0.5 + canvas.x0, r + float(canvas.y0)], axis=1)
                else:
                    p = np.stack([c + float(canvas.x0), r + 0.5 + canvas.y0], axis=1)
                sink.append(p)
    bg = np.concatenate(pts_bg) if pts_bg else np.empty((0, 2))
    ot = np.concatenate(pts_ot) if pts_ot else np.empty((0, 2))
    return Boundary(bg, ot)


def _tls(pts: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Weighted total-least-squares line ``(a, b, c)`` with ``hypot(a, b) = 1``."""
    if w is None:
        m = pts.mean(axis=0)
        d = pts - m
        cov = d.T @ d
    else:
        sw = w.sum()
        m = (w[:, None] * pts).sum(axis=0) / sw
        d = pts - m
        cov = (w[:, None] * d).T @ d
    evals, evecs = np.linalg.eigh(cov)
    n = evecs[:, 0]
    return np.array([n[0], n[1], -float(n @ m)])


def fit_line_robust(pts: np.ndarray, along: np.ndarray, rng: np.random.Generator,
                    thresh_px: float = 1.5, iters: int = 40
                    ) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Robust sub-pixel line: RANSAC on long baselines, then Tukey-weighted TLS.

    Args:
        pts: (N, 2) candidate points (px).
        along: (N,) coordinate of each point along the expected line direction (px), used
            to draw well-separated pairs.
        rng: random generator (seeded by the caller: deterministic, thread-safe).
        thresh_px: inlier threshold (px).
        iters: RANSAC hypotheses.

    Returns:
        ``(line, inliers, sigma_px)``: (3,) line with unit normal, (N,) bool inliers,
        robust residual scale (px); or None with fewer than 8 points.
    """
    n = len(pts)
    if n < 8:
        return None
    order = np.argsort(along)
    half = n // 2
    i = order[rng.integers(0, half, iters)]
    j = order[rng.integers(n - half, n, iters)]
    d = pts[j] - pts[i]
    nrm = np.stack([-d[:, 1], d[:, 0]], axis=1)
    ln = np.linalg.norm(nrm, axis=1)
    ok = ln > 1e-9
    if not ok.any():
        return None
    nrm = nrm[ok] / ln[ok, None]
    c = -np.einsum("ij,ij->i", nrm, pts[i[ok]])
    res = np.abs(nrm @ pts.T + c[:, None])  # (iters, N)
    score = np.minimum(res, thresh_px).sum(axis=1)  # MSAC
    best = int(np.argmin(score))
    inl = res[best] < thresh_px
    if inl.sum() < 6:
        return None
    line = _tls(pts[inl])
    scale = thresh_px
    for _ in range(3):
        r = pts @ line[:2] + line[2]
        u = r / (2.5 * scale)
        w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
        if w.sum() < 6:
            break
        line = _tls(pts, w)
        r = pts @ line[:2] + line[2]
        core = np.abs(r) < 2.5 * scale
        mad = np.median(np.abs(r[core])) * 1.4826 if core.any() else scale
        scale = float(np.clip(mad, 0.3, thresh_px))
    r = pts @ line[:2] + line[2]
    inl = np.abs(r) < max(2.5 * scale, 0.75)
    sigma = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("inf")
    return line, inl, sigma
