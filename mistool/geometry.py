"""Algorithm 1 of the paper: a rotated bounding box per instrument part.

For each part the paper masks the label image by the part's inclusive value range, takes
the external contours of the mask, and fits ``cv2.minAreaRect`` to *all* of the part's
contour points at once ("takes into account all the pixels belonging to either the shaft
or the metallic clasper"), then reads the corners with ``cv2.boxPoints``. mistool does the
same, and also ignores connected specks smaller than ``min_area_px`` pixels.

Conventions (see :mod:`mistool.model`): pixel centres are at integer coordinates. The
paper's box is fitted to pixel *centres*, so it lies inside the drawn shape by up to a
pixel row on each side (a W-pixel-wide axis-aligned bar measures W - 1; one pixel gives a
0 x 0 box). mistool reports that box with each side moved half-way to the next row of
pixel centres beyond it (:func:`grow_to_pixel_edges`; same centre line and angle, within
half a row spacing, <= 0.5 px, of the drawn shape's sides; a single pixel is 1 x 1). The
paper's own box is ``pixel_edges=False``. The canonical box has ``length >= width`` and
``angle_deg`` in ``[0, 180)``, the direction of the long side from +x towards +y.

OpenCV's ``minAreaRect`` angle convention changed across versions (``[-90, 0)`` before
4.5.1, ``(0, 90]`` after; OpenCV 5.0 returns ``[-90, 0)`` again, measured). In every
version the rectangle's first side (``size[0]``, "width") points along ``angle`` and the
second along ``angle + 90``; :func:`min_area_box` relies only on that and is the one
place where OpenCV's convention is converted to mistool's.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from mistool.model import RotatedBox

#: Angles this close to 180 deg (after reduction) are reported as 0 deg.
_ANGLE_SNAP_DEG = 1e-6


def min_area_box(points: np.ndarray) -> tuple[RotatedBox, np.ndarray]:
    """Minimum-area rotated rectangle of a point set, in canonical form.

    Args:
        points: (N, 2) pixel coordinates (x, y), int or float, N >= 1.

    Returns:
        ``(box, corners)``: the canonical :class:`~mistool.model.RotatedBox` and the
        rectangle's corners, shape (4, 2), float64, in ``cv2.boxPoints`` order (the
        order the paper's Algorithm 2 consumes).

    Raises:
        ValueError: if ``points`` is empty or not (N, 2).
    """
    rect = cv2.minAreaRect(_as_cv_points(points))
    corners = box_points(rect)
    return _canonical(rect), corners


def box_points(rect: tuple) -> np.ndarray:
    """``cv2.boxPoints`` in float64: the corners of an OpenCV ``RotatedRect``.

    Same formula and corner order as OpenCV's ``RotatedRect::points`` (checked against
    ``cv2.boxPoints`` by the tests), without its float32 rounding.

    Args:
        rect: ``((cx, cy), (w, h), angle_deg)`` as ``cv2.minAreaRect`` returns.

    Returns:
        (4, 2) float64 corners.
    """
    (cx, cy), (w, h), angle = rect
    t = math.radians(float(angle))
    b, a = math.cos(t) * 0.5, math.sin(t) * 0.5
    p0 = (cx - a * h - b * w, cy + b * h - a * w)
    p1 = (cx + a * h - b * w, cy - b * h - a * w)
    return np.array(
        [p0, p1, (2 * cx - p0[0], 2 * cy - p0[1]), (2 * cx - p1[0], 2 * cy - p1[1])],
        dtype=np.float64,
    )


def _as_cv_points(points: np.ndarray) -> np.ndarray:
    pts = np.asarray(points)
    if pts.ndim == 3 and pts.shape[1] == 1:  # OpenCV contour layout (N, 1, 2)
        pts = pts[:, 0, :]
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) == 0:
        raise ValueError(f"expected (N, 2) points with N >= 1, got shape {pts.shape}")
    if pts.dtype != np.int32 and pts.dtype != np.float32:
        pts = pts.astype(np.float32) if pts.dtype.kind == "f" else pts.astype(np.int32)
    return pts


def _canonical(rect: tuple) -> RotatedBox:
    """Convert an OpenCV ``RotatedRect`` ((cx, cy), (w, h), angle) to a RotatedBox.

    The side of length ``w`` points along ``angle`` and the side of length ``h`` along
    ``angle + 90`` (all OpenCV versions); the long side's direction, reduced to
    ``[0, 180)``, is the canonical angle. A zero-length box gets angle 0.
    """
    (cx, cy), (w, h), angle = rect
    w, h, angle = float(w), float(h), float(angle)
    if w >= h:
        length, width, direction = w, h, angle
    else:
        length, width, direction = h, w, angle + 90.0
    direction %= 180.0
    if direction >= 180.0 - _ANGLE_SNAP_DEG or length == 0.0:
        direction = 0.0
    return RotatedBox(cx=float(cx), cy=float(cy), length=length, width=width, angle_deg=direction)


def as_cv_labels(labels: np.ndarray) -> np.ndarray:
    """A label image in a dtype OpenCV's ``inRange`` accepts, without copying when possible.

    Args:
        labels: (H, W) integer (or bool) label image.

    Returns:
        (H, W) uint8, uint16 or int32 array with the same values.

    Raises:
        ValueError: if the array is not 2-D integer or holds values outside int32.
    """
    if labels.ndim != 2:
        raise ValueError(f"expected a 2-D label image, got shape {labels.shape}")
    kind = labels.dtype.kind
    if labels.dtype == np.uint8 or labels.dtype == np.uint16 or labels.dtype == np.int32:
        return labels
    if labels.dtype == np.bool_:
        return labels.view(np.uint8)
    if labels.dtype == np.uint32:
        # packed RGB (< 2**24) keeps its values; larger ones turn negative and so can
        # match no part range (ranges are >= 0)
        return labels.view(np.int32)
    if kind not in "iu":
        raise ValueError(f"expected an integer label image, got dtype {labels.dtype}")
    if labels.size and (
        int(labels.min()) < np.iinfo(np.int32).min or int(labels.max()) > np.iinfo(np.int32).max
    ):
        raise ValueError("label values do not fit in int32")
    return labels.astype(np.int32)


def range_mask(labels: np.ndarray, value_range: tuple[int, int]) -> np.ndarray:
    """The paper's ``mask()``: pixels whose value lies in an inclusive range.

    Args:
        labels: (H, W) label image (see :func:`as_cv_labels`).
        value_range: inclusive ``(lo, hi)`` label values.

    Returns:
        (H, W) uint8 mask, 255 inside the range, 0 elsewhere.
    """
    lo, hi = value_range
    img = as_cv_labels(labels)
    info = np.iinfo(img.dtype)
    lo, hi = max(int(lo), info.min), min(int(hi), info.max)
    if lo > hi:  # the range lies outside what this dtype can hold
        return np.zeros(img.shape, np.uint8)
    return cv2.inRange(img, lo, hi)


def remove_specks(mask: np.ndarray, min_area_px: int) -> tuple[np.ndarray, int]:
    """Drop 8-connected components smaller than ``min_area_px`` pixels.

    Args:
        mask: (h, w) uint8 mask (non-zero = inside).
        min_area_px: components with fewer pixels are removed; 0 or 1 keeps all.

    Returns:
        ``(kept, area_px)``: uint8 mask (the input itself when nothing is removed) and
        its number of non-zero pixels.
    """
    kept, area, _ = _clean(mask, min_area_px)
    return kept, area


def _clean(mask: np.ndarray, min_area_px: int) -> tuple[np.ndarray, int, list[np.ndarray] | None]:
    """:func:`remove_specks`, also returning the kept components' external contours
    (None when they are not at hand).

    Components are found from their contours (fast): one whose bounding rectangle holds
    fewer than ``min_area_px`` pixels is a speck, one whose contour polygon (through
    pixel centres, which encloses fewer pixels than the component has, by Pick's theorem)
    has an area of at least ``min_area_px`` is kept. Anything else, or a component with a
    hole, is decided by exact pixel counts (``connectedComponents``, slower).
    """
    contours, hierarchy = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return mask, 0, []
    hier = hierarchy[0]
    top = [i for i in range(len(contours)) if hier[i, 3] < 0]
    outer = [contours[i] for i in top]
    if min_area_px <= 1:
        return mask, int(cv2.countNonZero(mask)), outer
    if len(top) == 1:
        area = int(cv2.countNonZero(mask))
        if area < min_area_px:
            return np.zeros_like(mask), 0, []
        return mask, area, outer
    specks: list[np.ndarray] = []
    keep: list[np.ndarray] = []
    exact = False
    for i in top:
        c = contours[i]
        _, _, w, h = cv2.boundingRect(c)
        if w * h < min_area_px:
            specks.append(c)
        elif hier[i, 2] < 0 and cv2.contourArea(c) >= min_area_px:
            keep.append(c)
        else:
            exact = True
            break
    if exact:
        # labels, then pixel counts: OpenCV 5's statistics pass costs ~20x its labelling
        n, cc = cv2.connectedComponents(mask, connectivity=8)
        areas = np.bincount(cc.ravel(), minlength=n)[1:]
        ok = areas >= min_area_px
        if ok.all():
            return mask, int(areas.sum()), outer
        lut = np.zeros(n, np.uint8)
        lut[1:][ok] = 255
        return lut[cc], int(areas[ok].sum()), None
    if not specks:
        return mask, int(cv2.countNonZero(mask)), outer
    kept = mask.copy()
    # a speck's filled contour covers only that speck: 8-separate components never touch
    cv2.drawContours(kept, specks, -1, 0, thickness=cv2.FILLED)
    return kept, int(cv2.countNonZero(kept)), keep


def mask_points(mask: np.ndarray) -> np.ndarray:
    """The paper's ``contour()`` step: all points of the external contours of a mask.

    External contours hold every extreme pixel of every component, so ``minAreaRect`` of
    their points equals ``minAreaRect`` of all the mask's pixels.

    Args:
        mask: (h, w) uint8 mask.

    Returns:
        (N, 2) int32 pixel coordinates in the mask's frame; N = 0 for an empty mask.
    """
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return np.empty((0, 2), np.int32)
    return np.concatenate(contours, axis=0).reshape(-1, 2)


@dataclass(frozen=True)
class PartFit:
    """Algorithm 1's result for one part mask."""

    box: RotatedBox
    """The part's rotated box, full-image px."""
    corners: np.ndarray
    """(4, 2) float64 corners in ``cv2.boxPoints`` order, full-image px."""
    area_px: int
    """Number of the part's pixels after speck removal."""
    kept: np.ndarray
    """(h, w) bool tight crop of the kept pixels."""
    offset: tuple[int, int]
    """(x0, y0) full-image px of ``kept``'s top-left pixel."""

    @property
    def mask(self) -> np.ndarray:
        """(h, w) uint8 tight crop of the kept pixels, 255 inside."""
        return self.kept.view(np.uint8) * np.uint8(255)


def fit_part(
    mask: np.ndarray,
    min_area_px: int = 0,
    offset: tuple[int, int] = (0, 0),
    *,
    pixel_edges: bool = True,
) -> PartFit | None:
    """Algorithm 1 for one part: drop specks, contours, one ``minAreaRect`` over all of
    the part's contour points, ``boxPoints``.

    Args:
        mask: (h, w) uint8 mask of the part (non-zero inside), any crop of the image.
        min_area_px: connected specks smaller than this are ignored.
        offset: (x0, y0) full-image px of ``mask``'s top-left pixel.
        pixel_edges: see :func:`mask_box`.

    Returns:
        The fit, or None when no pixel is left.
    """
    from mistool.kernels.boxes import fit_mask  # (numba: not at the viewer's start)

    m = np.ascontiguousarray(mask)
    found = fit_mask(m, int(min_area_px), int(offset[0]), int(offset[1]))
    return fit_of(found, offset, pixel_edges)


def fit_of(
    found: tuple[Any, np.ndarray, np.ndarray, np.ndarray],
    offset: tuple[int, int],
    pixel_edges: bool = True,
) -> PartFit | None:
    """The :class:`PartFit` of :func:`mistool.kernels.boxes.fit_runs`' outputs (``info,
    crop, points, hull``; the points in full-image px), the runs' coordinates being at
    ``offset``; None when no pixel was kept."""
    info, kept, pts, hull = found
    area = int(info[0])
    if area == 0:
        return None
    box, corners = grown_box(pts, hull) if pixel_edges else min_area_box(hull)
    origin = (int(offset[0] + info[1]), int(offset[1] + info[2]))
    return PartFit(box=box, corners=corners, area_px=area, kept=kept, offset=origin)


#: Columns (or rows) walked per side by :func:`_lattice_gaps`. A side whose lattice
#: pattern repeats within this many columns (slope denominator <= 64) gets its exact gap;
#: any other gets a gap of at most about 1/64 px, whose half is negligible.
_GAP_WALK = 64  # (mistool.kernels.boxes.GAP_WALK)


def _lattice_gaps(
    normals: np.ndarray | list[tuple[float, float]],
    h: np.ndarray | list[float],
    t_lo: np.ndarray | list[float],
    t_hi: np.ndarray | list[float],
) -> np.ndarray:
    """Distance from each box side to the next row of pixel centres beyond it.

    Side ``s`` is the line ``n_s . p = h_s`` (``n_s`` its unit outward normal) between
    positions ``t_lo_s`` and ``t_hi_s`` along its tangent ``t = (-n_y, n_x)``. Among the
    pixel centres ``q`` beside that segment with ``n_s . q > h_s`` (outside the part),
    returns the smallest ``n_s . q - h_s``: 1 for an axis-aligned side, 0.71 at 45 deg,
    close to 0 for a long side at a generic angle.

    Walk the integer columns (sides closer to horizontal) or rows (closer to vertical)
    the segment spans (at most :data:`_GAP_WALK`: the first and last halves); in column
    ``p`` the first lattice point beyond the line ``a p + b q = h`` (``|b| >= |a|``) lies
    ``|b| (1 - frac((h - a p) / |b|))`` beyond it.

    Args:
        normals: (S, 2) unit outward normals.
        h, t_lo, t_hi: (S,) side offsets and tangent extents, px.

    Returns:
        (S,) gaps, px.
    """
    from mistool.kernels.boxes import lattice_gap

    return np.array(
        [
            lattice_gap(nx, ny, hs, lo, hi)
            for (nx, ny), hs, lo, hi in zip(
                np.asarray(normals).tolist(),
                np.asarray(h).tolist(),
                np.asarray(t_lo).tolist(),
                np.asarray(t_hi).tolist(),
                strict=True,
            )
        ],
        np.float64,
    )


def grow_to_pixel_edges(
    points: np.ndarray, box: RotatedBox | None = None
) -> tuple[RotatedBox, np.ndarray]:
    """Minimum-area box of pixel centres, each side moved half-way to the next pixel row.

    A shape drawn on the pixel grid lights the pixels whose centres it covers; the box of
    those centres (the paper's box) lies inside the shape by up to one pixel row on each
    side (up to a full pixel for axis-aligned sides, almost nothing for long sides at a
    generic angle). The unbiased estimate of each side is half-way between the outermost
    covered centres and the next row of pixel centres beyond them, so each side moves out
    by half of :func:`_lattice_gaps` (the error left is at most half that gap, <= 0.5 px,
    per side). A single pixel becomes a 1 x 1 box, a one-pixel-wide line gets width 1.
    The angle is that of ``cv2.minAreaRect``, and the corners keep OpenCV's own
    ``boxPoints`` order for the grown rectangle.

    Args:
        points: (N, 2) integer pixel centres, N >= 1.
        box: unused (kept for symmetry with :func:`min_area_box`'s result).

    Returns:
        ``(box, corners)`` like :func:`min_area_box`.
    """
    pts = np.ascontiguousarray(_as_cv_points(points))
    return grown_box(pts, pts)


def grown_box(pts: np.ndarray, hull: np.ndarray) -> tuple[RotatedBox, np.ndarray]:
    """:func:`grow_to_pixel_edges` of contiguous (N, 2) points (int32 or float32) whose
    ``minAreaRect`` is that of ``hull`` (those of them that may lie on their hull, as
    :func:`mistool.kernels.boxes.fit_runs` gives them): ``(box, corners)``. Integer
    points take one compiled call (``cv2.minAreaRect``'s angle bit for bit,
    :func:`mistool.kernels.boxes.grown_box_of`)."""
    kernels: Any = _KERNELS.get("boxes")
    if kernels is None:  # (imported at the first fit: numba is not for the viewer's start)
        from mistool.kernels import boxes as kernels

        _KERNELS["boxes"] = kernels
    corners = np.empty((4, 2))
    if pts.dtype == np.int32 and hull.dtype == np.int32:
        cx, cy, length, width, direction = kernels.grown_box_of(pts, hull, corners)
    else:
        (_, _), (_, _), angle = cv2.minAreaRect(hull)
        t = math.radians(angle)
        # e1 = (c, s): OpenCV's first side ("width"); the kernel projects the points on
        # e1 and e2 = (-s, c) as numpy's ``points @ e`` does, moves each side out by half
        # its lattice gap (:func:`_lattice_gaps`), gives the corners and the canonical box
        cx, cy, length, width, direction = kernels.grow_box(
            pts, math.cos(t), math.sin(t), angle, corners
        )
    return RotatedBox(cx=cx, cy=cy, length=length, width=width, angle_deg=direction), corners


#: Kernels imported at their first use (``mistool.kernels`` imports numba, and numba
#: SciPy: not for a program that only imports mistool, such as the viewer at its start).
_KERNELS: dict[str, Any] = {}


def mask_box(
    mask: np.ndarray, offset: tuple[int, int] = (0, 0), *, pixel_edges: bool = True
) -> tuple[RotatedBox, np.ndarray] | None:
    """Rotated box of every pixel of a part mask (no speck removal).

    Args:
        mask: (h, w) uint8 mask of one part.
        offset: (x0, y0) full-image position of the mask's top-left pixel.
        pixel_edges: grow the paper's box (fitted to pixel centres) to the estimated
            pixel edges (:func:`grow_to_pixel_edges`); False gives the paper's box as is.

    Returns:
        ``(box, corners)`` in full-image pixels (see :func:`min_area_box`), or None for
        an empty mask.
    """
    fit = fit_part(mask, 0, offset, pixel_edges=pixel_edges)
    return None if fit is None else (fit.box, fit.corners)


def bounding_boxes(
    labels: np.ndarray,
    parts: Mapping[str, tuple[int, int]],
    min_area_px: int = 0,
    *,
    pixel_edges: bool = True,
) -> dict[str, tuple[RotatedBox, np.ndarray]]:
    """Algorithm 1 on one label image: a box per part present.

    Args:
        labels: (H, W) integer label image.
        parts: part name -> inclusive label value range.
        min_area_px: connected specks smaller than this are ignored.
        pixel_edges: see :func:`mask_box`.

    Returns:
        part -> ``(box, corners)`` for every part with pixels left after speck removal.
    """
    out: dict[str, tuple[RotatedBox, np.ndarray]] = {}
    for part, rng in parts.items():
        fit = fit_part(range_mask(labels, rng), min_area_px, pixel_edges=pixel_edges)
        if fit is not None:
            out[part] = (fit.box, fit.corners)
    return out
