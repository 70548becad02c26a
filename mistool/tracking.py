"""Instruments in a frame (instances and their parts) and their identity across frames.

Two ways to tell instruments apart, chosen by the config:

- **Own label values** (``[[instrument]]`` tables): each instrument's parts come from its
  own value ranges; the instrument's name is its label. This is the paper's setting.
- **Merged masks** (no ``[[instrument]]`` tables, EndoVis'17 style: every instrument
  shares the part values): instances are the connected components of the *whole*
  instrument (shaft + wrist + clasper pixels together), bridged over gaps of up to
  :data:`MERGE_GAP_PX` pixels so a clasper one pixel away from its shaft stays one
  instrument. Components smaller than ``config.min_area_px`` are specks and are dropped.
  :class:`IdentityTracker` then keeps each instance's name across frames.

Every part's box is Algorithm 1 (:mod:`mistool.geometry`) over all of that part's
pixels in the instance, after dropping specks smaller than ``config.min_area_px``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from mistool.config import Config
from mistool.errors import MaskFormatError
from mistool.geometry import as_cv_labels, fit_part, range_mask
from mistool.model import PARTS, RotatedBox

#: Merged masks: pixels of one instrument separated by at most this many background
#: pixels are joined into one instance.
MERGE_GAP_PX = 1


@dataclass(frozen=True)
class PartObservation:
    """One part of one instrument in one frame."""

    part: str
    """Part name, one of :data:`~mistool.model.PARTS`."""
    box: RotatedBox
    """The part's rotated box (Algorithm 1), full-image px."""
    corners: np.ndarray
    """(4, 2) float64 box corners in ``cv2.boxPoints`` order, full-image px."""
    area_px: int
    """Number of the part's mask pixels (after speck removal)."""
    mask: np.ndarray
    """(h, w) bool crop of the part's pixels (after speck removal)."""
    offset: tuple[int, int]
    """(x0, y0): full-image px of the crop's top-left pixel."""


@dataclass(frozen=True)
class InstanceObservation:
    """One instrument in one frame."""

    label: str | None
    """The config instrument's name when instruments have their own label values;
    None in merged masks (the tracker names it)."""
    parts: dict[str, PartObservation]
    """Visible parts, proximal to distal."""
    centroid_px: tuple[float, float]
    """(x, y) mean of all the instrument's part pixels, px."""
    area_px: int
    """Number of the instrument's part pixels."""
    bbox_xywh: tuple[int, int, int, int]
    """Axis-aligned bounds of those pixels: (x0, y0, width, height), px."""


def _check_labels(labels: np.ndarray, config: Config) -> np.ndarray:
    arr = np.asarray(labels)
    if arr.ndim != 2:
        raise MaskFormatError(f"expected a single-channel (H, W) label image, got shape "
                              f"{arr.shape}")
    try:
        return as_cv_labels(arr)
    except ValueError as exc:
        raise MaskFormatError(f"label image: {exc}") from None


def _part_observation(part: str, mask: np.ndarray, x0: int, y0: int,
                      min_area_px: int) -> PartObservation | None:
    """Algorithm 1 for one part's uint8 mask (a crop at (x0, y0) of the full image)."""
    fit = fit_part(mask, min_area_px, (x0, y0))
    if fit is None:
        return None
    return PartObservation(part=part, box=fit.box, corners=fit.corners, area_px=fit.area_px,
                           mask=fit.mask.astype(bool), offset=fit.offset)


def _foreground(img: np.ndarray) -> tuple[int, int, int, int]:
    """(x, y, w, h) bounds of the non-zero pixels."""
    nz = img if img.dtype == np.uint8 else cv2.compare(img, 0, cv2.CMP_NE)
    return tuple(int(v) for v in cv2.boundingRect(nz))  # type: ignore[return-value]


def _instance(label: str | None, parts: dict[str, PartObservation]) -> InstanceObservation:
    area = sum(p.area_px for p in parts.values())
    sx = sy = 0.0
    x0 = y0 = math.inf
    x1 = y1 = -math.inf
    for p in parts.values():
        m = p.mask.view(np.uint8)
        cols = cv2.reduce(m, 0, cv2.REDUCE_SUM, dtype=cv2.CV_32S).ravel()  # pixels per column
        rows = cv2.reduce(m, 1, cv2.REDUCE_SUM, dtype=cv2.CV_32S).ravel()
        sx += float(cols @ np.arange(len(cols))) + p.offset[0] * p.area_px
        sy += float(rows @ np.arange(len(rows))) + p.offset[1] * p.area_px
        h, w = p.mask.shape
        x0, y0 = min(x0, p.offset[0]), min(y0, p.offset[1])
        x1, y1 = max(x1, p.offset[0] + w), max(y1, p.offset[1] + h)
    return InstanceObservation(
        label=label, parts=parts, centroid_px=(sx / area, sy / area), area_px=area,
        bbox_xywh=(int(x0), int(y0), int(x1 - x0), int(y1 - y0)))


def observe_frame(labels: np.ndarray, config: Config) -> list[InstanceObservation]:
    """Every instrument in one label image, with Algorithm 1's box for each visible part.

    Pure and thread-safe.

    Args:
        labels: (H, W) integer label image (uint8/uint16, or uint32 packed RGB when
            ``config.colour_masks``).
        config: part value ranges, instruments, ``min_area_px``.

    Returns:
        With ``config.instruments``: one observation per instrument that has a visible
        part, in config order, ``label`` set. Without: one per connected instance (see the
        module docstring), largest first, ``label`` None.

    Raises:
        MaskFormatError: if ``labels`` is not a 2-D integer image.
    """
    img = _check_labels(labels, config)
    min_area = config.min_area_px
    out: list[InstanceObservation] = []
    fx, fy, fw, fh = _foreground(img)
    if fw == 0 or fh == 0:
        return out
    crop = img[fy:fy + fh, fx:fx + fw]  # every part pixel is non-zero: work on its bounds
    if config.instruments:
        for spec in config.instruments:
            parts: dict[str, PartObservation] = {}
            for part in PARTS:
                if part in spec.parts and spec.parts[part][1] > 0:
                    obs = _part_observation(part, range_mask(crop, spec.parts[part]), fx, fy,
                                            min_area)
                    if obs is not None:
                        parts[part] = obs
            if parts:
                out.append(_instance(spec.name, parts))
        return out

    part_names = [p for p in PARTS if p in config.parts and config.parts[p][1] > 0]
    if not part_names:
        return out
    masks = {p: range_mask(crop, config.parts[p]) for p in part_names}
    union = masks[part_names[0]]
    for p in part_names[1:]:
        union = cv2.bitwise_or(union, masks[p])
    if MERGE_GAP_PX > 0:
        # pad so the bridging dilation sees the crop's border like the image's inside
        pad = MERGE_GAP_PX
        k = 2 * pad + 1
        padded = cv2.copyMakeBorder(union, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0)
        bridged = cv2.dilate(padded, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
        bridged = bridged[pad:-pad, pad:-pad]
    else:
        bridged = union
    contours, hierarchy = cv2.findContours(bridged, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    n_inst = int((hierarchy[0][:, 3] < 0).sum()) if contours else 0
    if n_inst == 0:
        return out
    if n_inst == 1:  # one bridged component: everything belongs to it
        parts = {}
        for p in part_names:
            obs = _part_observation(p, masks[p], fx, fy, min_area)
            if obs is not None:
                parts[p] = obs
        if parts and sum(o.area_px for o in parts.values()) >= max(min_area, 1):
            out.append(_instance(None, parts))
        return out
    n, cc, stats, _ = cv2.connectedComponentsWithStats(bridged, connectivity=8)
    counts = np.bincount(cc[union > 0], minlength=n)
    found = []
    for i in range(1, n):
        if counts[i] < max(min_area, 1):
            continue  # a speck of an instrument
        bx, by, bw, bh = (int(v) for v in stats[i, :4])
        inside = cc[by:by + bh, bx:bx + bw] == i
        parts = {}
        for p in part_names:
            pm = np.where(inside, masks[p][by:by + bh, bx:bx + bw], np.uint8(0))
            obs = _part_observation(p, pm, fx + bx, fy + by, min_area)
            if obs is not None:
                parts[p] = obs
        if parts:
            found.append(_instance(None, parts))
    found.sort(key=lambda inst: -inst.area_px)
    return found


def unknown_values(labels: np.ndarray, config: Config) -> np.ndarray:
    """Label values present that are neither 0 nor any configured part value.

    Args:
        labels: (H, W) integer label image.
        config: the part value ranges (the instruments' own when it has
            ``[[instrument]]`` tables, else the shared ones).

    Returns:
        Sorted 1-D array of the unknown values (int64); empty when all are known.
    """
    arr = np.asarray(labels)
    if arr.dtype == np.uint8 or arr.dtype == np.uint16:
        hist = np.bincount(arr.ravel(), minlength=1)
        values = np.flatnonzero(hist)
    else:
        values = np.unique(arr)
    values = values.astype(np.int64)
    known = values == 0
    if config.instruments:
        ranges = [r for spec in config.instruments for r in spec.parts.values()]
    else:
        ranges = list(config.parts.values())
    for lo, hi in ranges:
        known |= (values >= lo) & (values <= hi)
    return values[~known]
