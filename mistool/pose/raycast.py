"""Exact ray-cast label images of a simple instrument model (tests and benchmarks).

The model: a shaft, a capped cylinder of radius ``r`` from ``start`` to the joint ``J``,
and a clasper, a capped cylinder of radius ``r_clasper`` from ``J`` to the tip. A pixel
gets a part's label when its centre's ray hits that part first (z-buffer).
"""

from __future__ import annotations

import numpy as np

from mistool.pose.cylinder import pixel_rays

__all__ = ["capped_cylinder_depth", "render_instrument"]


def capped_cylinder_depth(
    rays: np.ndarray, p_a: np.ndarray, p_b: np.ndarray, radius_mm: float
) -> np.ndarray:
    """Distance along each ray (from the camera centre) to a closed cylinder.

    Args:
        rays: (N, 3) unit ray directions.
        p_a, p_b: (3,) end-cap centres (mm).
        radius_mm: radius (mm).

    Returns:
        (N,) distance to the first hit (mm), ``inf`` where the ray misses.
    """
    axis = p_b - p_a
    length = float(np.linalg.norm(axis))
    a = axis / length
    da = rays @ a
    dp = rays - da[:, None] * a
    w = -p_a
    wa = float(w @ a)
    wp = w - wa * a
    A = np.maximum(np.einsum("ij,ij->i", dp, dp), 1e-15)
    B = dp @ wp
    C = float(wp @ wp) - radius_mm**2
    disc = B * B - A * C
    sq = np.sqrt(np.maximum(disc, 0.0))
    best = np.full(len(rays), np.inf)
    for s in ((-B - sq) / A, (-B + sq) / A):
        t = s * da + wa
        ok = (disc >= 0) & (s > 0) & (t >= 0) & (t <= length)
        best = np.where(ok & (s < best), s, best)
    pa_a = float(p_a @ a)
    safe = np.where(np.abs(da) < 1e-15, 1e-15, da)
    for tc in (0.0, length):
        s = (tc + pa_a) / safe
        x = s[:, None] * rays - (p_a + tc * a)
        ok = (s > 0) & (np.einsum("ij,ij->i", x, x) <= radius_mm**2) & (np.abs(da) > 1e-15)
        best = np.where(ok & (s < best), s, best)
    return best


def render_instrument(
    shape: tuple[int, int],
    K: np.ndarray,
    start: np.ndarray,
    joint: np.ndarray,
    tip: np.ndarray | None,
    radius_mm: float,
    clasper_radius_mm: float | None = None,
    shaft_value: int = 160,
    clasper_value: int = 70,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Render one instrument's label image by ray casting pixel centres.

    Args:
        shape: (H, W) of the image.
        K: (3, 3) intrinsics.
        start: (3,) proximal end of the shaft (mm), may be far outside the view.
        joint: (3,) the joint J (shaft's distal cap centre, clasper's base).
        tip: (3,) clasper tip, or None for no clasper.
        radius_mm: shaft radius.
        clasper_radius_mm: clasper radius (default ``0.6 * radius_mm``).
        shaft_value, clasper_value: label values.
        out: optional (H, W) uint8 image to draw into (z-buffer not shared).

    Returns:
        (H, W) uint8 label image.
    """
    h, w = shape
    vv, uu = np.mgrid[0:h, 0:w]
    rays = pixel_rays(np.stack([uu.ravel(), vv.ravel()], axis=1), K)
    depth = capped_cylinder_depth(
        rays, np.asarray(start, float), np.asarray(joint, float), radius_mm
    )
    labels = np.zeros(h * w, dtype=np.uint8) if out is None else out.ravel().copy()
    labels[np.isfinite(depth)] = shaft_value
    if tip is not None:
        rc = 0.6 * radius_mm if clasper_radius_mm is None else clasper_radius_mm
        dc = capped_cylinder_depth(rays, np.asarray(joint, float), np.asarray(tip, float), rc)
        labels[np.isfinite(dc) & (dc < depth)] = clasper_value
    return labels.reshape(h, w)
