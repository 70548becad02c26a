"""Confidence without ground truth: re-render the estimated pose and compare with the mask.

Each part is modelled as a (possibly tapered) capped cylinder between two points; a
cylinder is convex, so its image is the convex hull of the projections of its two rim
circles. The hull is filled as OpenCV fills it (sub-pixel, 4 fractional bits; the hull and
the fill reproduced in a kernel, :mod:`mistool.kernels.polygon`) in a crop around the part
and compared with the part's mask: intersection over union, in [0, 1].

The shaft model is exact (a cylinder of the known diameter), so a correct pose scores
close to 1 (minus boundary corruption). The clasper's jaws are modelled by a cone from
``0.5 r`` at the joint to ``0.25 r`` at the tip, so even a correct clasper pose scores
lower (typically 0.5-0.8); compare clasper scores with each other, not with the shaft's.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from mistool.config import Camera
from mistool.lens import distort_points, ideal_bounds
from mistool.pose.silhouette import kernels

#: The image outline of a cylinder: its two rims, 24 points each.
_RIM_POINTS = 48

__all__ = [
    "Rims",
    "cylinder_iou",
    "hull_of_cylinder",
    "image_polygon",
    "iou_polygon_mask",
    "rims_iou",
]


class Rims:
    """A cylinder's image as the kernels write it (:func:`mistool.kernels.pose.cylinder_outline`,
    also filled by ``shaft_pose`` and ``tip_pose``): the rims' pixels, the same on the
    comparison canvas, the canvas and the result."""

    __slots__ = ("canvas", "pts", "shifted")

    def __init__(self) -> None:
        self.pts = np.empty((_RIM_POINTS, 2), np.float32)
        """(48, 2) float32 the two rims' pixels (24 points each)."""
        self.shifted = np.empty((_RIM_POINTS, 2), np.int32)
        """(48, 2) int32 the same on the canvas (x16 fixed point, canvas step)."""
        self.canvas = np.zeros(6, np.int64)
        """``x0, y0, step, rows, columns`` of the canvas, then the result: 0 no outline,
        1 no canvas (both give NaN), 2 both."""


def rims_iou(rims: Rims, mask: np.ndarray, offset: tuple[int, int]) -> float:
    """IoU of a cylinder's image (:class:`Rims`, undistorted camera) with a part's mask
    crop (bool, C-contiguous) at ``offset``: OpenCV's convex hull of the rims filled on the
    canvas, counted by :func:`mistool.kernels.pose.iou_count`; NaN without a canvas.

    The hull and the fill are OpenCV's reproduced in one kernel call
    (:func:`mistool.kernels.pose.rims_iou`); OpenCV itself where that hull would rest on
    float rounding (rims seen almost edge-on, equal points)."""
    iou = np.empty(1)
    if kernels().rims_iou(rims.pts, rims.shifted, rims.canvas, mask, offset[0], offset[1], iou):
        return float(iou[0])
    x0, y0, st, rows, cols, found = rims.canvas.tolist()
    if found < 2:
        return math.nan
    rend = np.zeros((rows, cols), np.uint8)
    hull = cv2.convexHull(rims.pts, returnPoints=False).reshape(-1)
    cv2.fillConvexPoly(rend, rims.shifted[hull], 1, lineType=cv2.LINE_8, shift=4)
    return float(kernels().iou_count(rend, mask, offset[0], offset[1], x0, y0, st))


def _rims(
    p_a: np.ndarray,
    p_b: np.ndarray,
    r_a: float,
    r_b: float,
    K: np.ndarray,
    min_z_mm: float,
    mask_box: tuple[int, int, int, int],
    image_shape: tuple[int, int],
    max_pixels: int,
) -> Rims:
    """:func:`mistool.kernels.pose.cylinder_outline` (``mask_box``: the mask crop's
    ``(x0, y0, h, w)``)."""
    rims = Rims()
    pts, shifted, canvas = rims.pts, rims.shifted, rims.canvas
    ox, oy, mh, mw = mask_box
    found = kernels().cylinder_outline(
        np.ascontiguousarray(p_a, dtype=np.float64),
        np.ascontiguousarray(p_b, dtype=np.float64),
        float(r_a),
        float(r_b),
        np.ascontiguousarray(K, dtype=np.float64),
        float(min_z_mm),
        int(ox),
        int(oy),
        int(mh),
        int(mw),
        int(image_shape[0]),
        int(image_shape[1]),
        int(max_pixels),
        pts,
        shifted,
        canvas,
    )
    canvas[5] = found
    return rims


def hull_of_cylinder(
    p_a: np.ndarray, p_b: np.ndarray, r_a: float, r_b: float, K: np.ndarray, min_z_mm: float = 1.0
) -> np.ndarray | None:
    """Image outline of a capped (tapered) cylinder: the convex hull of its two rims'
    projections (24 points each).

    Args:
        p_a, p_b: (3,) end centres (mm, camera frame).
        r_a, r_b: radii at ``p_a`` and ``p_b`` (mm).
        K: (3, 3) intrinsics.
        min_z_mm: rims closer to the camera plane than this give None.

    Returns:
        (M, 2) float32 convex polygon (px), or None.
    """
    rims = _rims(p_a, p_b, r_a, r_b, K, min_z_mm, (0, 0, 0, 0), (1, 1), 1)
    return cv2.convexHull(rims.pts).reshape(-1, 2) if rims.canvas[5] else None


def cylinder_iou(
    p_a: np.ndarray,
    p_b: np.ndarray,
    r_a: float,
    r_b: float,
    K: np.ndarray,
    mask: np.ndarray,
    offset: tuple[int, int],
    image_shape: tuple[int, int],
    camera: Camera | None = None,
    max_pixels: int = 40000,
) -> float:
    """``iou_polygon_mask(hull_of_cylinder(p_a, p_b, r_a, r_b, K), mask, offset,
    image_shape, camera, max_pixels)``, the same value, in two kernels around OpenCV's
    hull and fill for an undistorted camera (:func:`mistool.kernels.pose.iou_count`)."""
    if camera is not None and camera.distorted:
        poly = hull_of_cylinder(p_a, p_b, r_a, r_b, K)
        return iou_polygon_mask(poly, mask, offset, image_shape, camera, max_pixels)
    m = np.ascontiguousarray(mask, dtype=bool)
    box = (int(offset[0]), int(offset[1]), m.shape[0], m.shape[1])
    rims = _rims(p_a, p_b, r_a, r_b, K, 1.0, box, image_shape, max_pixels)
    return rims_iou(rims, m, (box[0], box[1]))


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


#: Edges of a polygon are split into pieces at most this long (px) before distortion, so
#: that their curved images are followed within a small fraction of a pixel.
_EDGE_STEP_PX = 4.0


def image_polygon(
    poly: np.ndarray, camera: Camera, image_shape: tuple[int, int]
) -> np.ndarray | None:
    """A convex polygon of the ideal pinhole image as seen in the camera's image: clipped
    to the part of the ideal image the camera sees (:func:`mistool.lens.ideal_bounds`),
    its edges subdivided, every point distorted. (M, 2) float32, or None when nothing is
    left (the result is not convex in general: fill it with ``cv2.fillPoly``)."""
    x0, y0, x1, y1 = ideal_bounds(camera, (int(image_shape[1]), int(image_shape[0])))
    box = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float32)
    area, clipped = cv2.intersectConvexConvex(np.asarray(poly, dtype=np.float32), box)
    if clipped is None or area <= 0:
        return None
    pts = clipped.reshape(-1, 2).astype(np.float64)
    nxt = np.roll(pts, -1, axis=0)
    pieces = []
    for p, q in zip(pts, nxt, strict=True):
        n = max(1, int(math.ceil(math.hypot(*(q - p)) / _EDGE_STEP_PX)))
        t = np.arange(n)[:, None] / n
        pieces.append(p + t * (q - p))
    return distort_points(np.concatenate(pieces), camera).astype(np.float32)
