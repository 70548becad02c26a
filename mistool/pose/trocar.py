"""The trocar (fulcrum) point: robust least-squares intersection of 3D axis lines.

Laparoscopic instruments pivot about the incision point, so over a sequence the shaft's
3D axis lines all pass (nearly) through one point. Minimising the sum of squared
distances from a point ``T`` to lines ``(P_i, a_i)`` gives the linear system
``sum_i w_i (I - a_i a_i^T) T = sum_i w_i (I - a_i a_i^T) P_i``; iteratively reweighting
(Tukey biweight, scale from the median absolute residual) rejects frames whose axis is
wrong. The point is only defined when the lines are not all parallel: with too little
pivoting the system is ill-conditioned and no trocar is returned.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mistool.pose.filtering import median

__all__ = ["Trocar", "distances_to_lines", "intersect_lines"]


@dataclass(frozen=True)
class Trocar:
    """A sequence's trocar estimate."""

    point: np.ndarray
    """(3,) camera frame (mm)."""
    inliers: np.ndarray
    """(N,) bool: lines kept by the robust fit."""
    rms_mm: float
    """Root-mean-square distance of the inlier lines to the point (mm)."""
    spread_deg: float
    """Angular spread of the inlier lines' directions (degrees, RMS about their mean)."""
    cov: np.ndarray
    """(3, 3) covariance of ``point`` (mm^2): residual variance times the inverse normal
    matrix. Nearly parallel lines leave the point poorly known along their mean
    direction (large variance there) but well known across it."""

    def sigma_across(self, direction: np.ndarray) -> float:
        """1-sigma error of ``point`` perpendicular to a unit ``direction`` (mm, RMS of
        the two perpendicular components)."""
        p = np.eye(3) - np.outer(direction, direction)
        return float(np.sqrt(max(np.trace(p @ self.cov @ p), 0.0) / 2.0))


def distances_to_lines(point: np.ndarray, p: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Distances (N,) from a point (3,) to lines through ``p`` (N, 3) along unit ``a``."""
    d = point - p
    along = np.einsum("ij,ij->i", d, a)
    return _norms(d - along[:, None] * a)


def _norms(v: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(v, axis=1)`` of (N, 3) rows, bit for bit: numpy's sum of a row's
    squares runs left to right; written out on the columns, without its reduction's
    cost per row (~0.1 us: most of a trocar's time)."""
    s = v * v
    return np.sqrt(s[:, 0] + s[:, 1] + s[:, 2])


def _projectors(a: np.ndarray) -> np.ndarray:
    """(N, 3, 3): ``I - a_i a_i^T`` of each unit direction (N, 3)."""
    return np.eye(3)[None] - a[:, :, None] * a[:, None, :]


def _solve(p: np.ndarray, m: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The weighted least-squares point of the lines through ``p`` (N, 3) with
    projectors ``m`` (:func:`_projectors`), weights ``w`` (N,)."""
    wm = w[:, None, None] * m
    A = wm.sum(axis=0)
    b = np.einsum("nij,nj->i", wm, p)
    return np.linalg.solve(A + 1e-9 * np.eye(3), b)


#: Line pairs closer to parallel than 2 deg give no start point.
_PARALLEL_COS = np.cos(np.radians(2.0))


def _lmeds_start(p: np.ndarray, a: np.ndarray, pairs: int = 60) -> np.ndarray | None:
    """Least-median start: the closest point of random line pairs with the smallest
    median distance to all lines (robust to a large share of wrong lines).

    A candidate with fewer than half its distances below the best median so far is
    passed over without its median: that median is not below the best (the middle
    distance, or the lower of the two middle ones, is not), so it could not win."""
    rng = np.random.default_rng(0)
    n = len(p)
    half = (n + 1) // 2  # distances below a median that wins: at least this many
    i = rng.integers(0, n, pairs)
    j = rng.integers(0, n, pairs)
    best, best_med = None, np.inf
    for k in range(pairs):
        a1, a2 = a[i[k]], a[j[k]]
        c = float(a1 @ a2)
        if abs(c) > _PARALLEL_COS:
            continue
        d = p[j[k]] - p[i[k]]
        # closest points p1 + s a1, p2 + t a2
        da1, da2, sin2 = d @ a1, d @ a2, 1.0 - c * c
        s = (da1 - c * da2) / sin2
        t = (c * da1 - da2) / sin2
        x = 0.5 * (p[i[k]] + s * a1 + p[j[k]] + t * a2)
        r = distances_to_lines(x, p, a)
        if best is not None and np.count_nonzero(r < best_med) < half:
            continue
        med = median(r)
        if med < best_med:
            best, best_med = x, med
    return best


def intersect_lines(
    p: np.ndarray, a: np.ndarray, min_lines: int = 5, min_spread_deg: float = 2.0, iters: int = 10
) -> Trocar | None:
    """Robust least-squares intersection of 3D lines.

    Args:
        p: (N, 3) a point on each line (mm).
        a: (N, 3) unit directions.
        min_lines: fewest inlier lines for an estimate.
        min_spread_deg: minimum RMS angular spread of the directions; below it the
            lines are too close to parallel for a point to be defined.
        iters: reweighting iterations.

    Returns:
        The :class:`Trocar`, or None when undefined.
    """
    ok = np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(a), axis=1)
    p, a = p[ok], a[ok]
    if len(p) < min_lines:
        return None
    point = _lmeds_start(p, a)
    if point is None:
        return None
    scale = None
    m = _projectors(a)
    for _ in range(iters):
        r = distances_to_lines(point, p, a)
        mad = 1.4826 * median(r)
        scale = max(mad, 0.5) if scale is None else max(min(mad, scale), 0.5)
        u = r / (4.0 * scale)
        w = np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0)
        if np.count_nonzero(w) < min_lines:
            return None
        point = _solve(p, m, w)
    r = distances_to_lines(point, p, a)
    inl = w > 0
    mean_dir = a[inl].mean(axis=0)
    mean_dir /= np.linalg.norm(mean_dir)
    cosang = np.clip(a[inl] @ mean_dir, -1.0, 1.0)
    spread = float(np.degrees(np.sqrt(np.mean(np.arccos(cosang) ** 2))))
    if spread < min_spread_deg or int(inl.sum()) < min_lines:
        return None
    full = np.zeros(len(ok), dtype=bool)
    full[np.flatnonzero(ok)[inl]] = True
    A = m[inl].sum(axis=0)
    dof = max(int(inl.sum()) * 2 - 3, 1)
    var = float(np.sum(r[inl] ** 2)) / dof
    cov = var * np.linalg.inv(A + 1e-9 * np.eye(3))
    return Trocar(point, full, float(np.sqrt(np.mean(r[inl] ** 2))), spread, cov)
