"""Instruments in a frame (instances and their parts) and their identity across frames.

Two ways to tell instruments apart, chosen by the config:

- **Own label values** (``[[instrument]]`` tables): each instrument's parts come from its
  own value ranges; the instrument's name is its label. This is the paper's setting.
- **Merged masks** (no ``[[instrument]]`` tables, EndoVis'17 style: every instrument
  shares the part values): instances are the connected components of the *whole*
  instrument (shaft + wrist + clasper pixels together), bridged over gaps of up to
  :data:`MERGE_GAP_PX` pixels so a clasper one pixel away from its shaft stays one
  instrument. Components smaller than ``config.min_area_px`` are specks and are dropped;
  a component without shaft pixels (open jaws, a clasper cut by an occluder) joins the
  nearest group with a shaft within reach (:data:`HEAD_GAP_FRAC`; distances between the
  pixels, groups growing as heads join), or, if it does not touch the image border (no
  shaft can reach it but under an occluder), within :data:`HEAD_ORPHAN_FRAC`; a small
  shaft piece close to a much larger one joins it (:data:`FRAGMENT_AREA_FRAC`,
  :data:`FRAGMENT_GAP_PX`), and pieces an occluder cut off join by shaft geometry: a
  shaft-only piece continuing another's shaft axis (also a short stub's), a head on the
  distal extension of a shaft's axis (:data:`HEAD_AXIS_REACH`).
  :class:`IdentityTracker` then keeps each instance's name across frames, also through
  crossings (instruments touching form one instance: ``assign`` keeps one name for it and
  lets the other coast; ``resolve`` splits it between the instruments' shaft axes), when
  instruments already touch as they come into view (``resolve`` splits a blob on the
  shafts entering at the image border when it holds more of them than instruments known
  in it) and when one leaves the view and comes back (looked for near where it left).

Every part's box is Algorithm 1 (:mod:`mistool.geometry`) over all of that part's
pixels in the instance, after dropping specks smaller than ``config.min_area_px``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from mistool.config import Config
from mistool.errors import MaskFormatError
from mistool.geometry import as_cv_labels, fit_part, range_mask
from mistool.model import PARTS, RotatedBox

#: Merged masks: pixels of one instrument separated by at most this many background
#: pixels are joined into one instance.
MERGE_GAP_PX = 1

#: Merged masks: a component with less than this fraction of a larger one's area, within
#: :data:`FRAGMENT_GAP_PX` of it, is a fragment of that instrument (see observe_frame).
FRAGMENT_AREA_FRAC = 0.25
FRAGMENT_GAP_PX = 30.0
#: Merged masks: a component without shaft pixels joins a shaft component this many
#: sqrt(area) px away (see observe_frame).
HEAD_GAP_FRAC = 0.8
#: ... and components without shaft pixels join each other this many px apart (the two
#: jaws of an open clasper entering the view).
HEAD_HEAD_GAP_PX = 60.0
#: ... and a head that does not touch the image border (its shaft cannot be beyond it)
#: joins a shaft component up to this many sqrt(its area) px away, at most
#: :data:`HEAD_ORPHAN_GAP_PX` (an occluder hides what joins them; a speck reaches little).
HEAD_ORPHAN_FRAC = 2.5
HEAD_ORPHAN_GAP_PX = 100.0


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
    image_shape: tuple[int, int] | None = None
    """(H, W) of the label image (None if unknown): where the image border is."""


def _check_labels(labels: np.ndarray, config: Config) -> np.ndarray:
    arr = np.asarray(labels)
    if arr.ndim != 2:
        raise MaskFormatError(
            f"expected a single-channel (H, W) label image, got shape {arr.shape}"
        )
    try:
        return as_cv_labels(arr)
    except ValueError as exc:
        raise MaskFormatError(f"label image: {exc}") from None


def _part_observation(
    part: str, mask: np.ndarray, x0: int, y0: int, min_area_px: int
) -> PartObservation | None:
    """Algorithm 1 for one part's uint8 mask (a crop at (x0, y0) of the full image)."""
    fit = fit_part(mask, min_area_px, (x0, y0))
    if fit is None:
        return None
    return PartObservation(
        part=part,
        box=fit.box,
        corners=fit.corners,
        area_px=fit.area_px,
        mask=fit.mask.astype(bool),
        offset=fit.offset,
    )


def _foreground(img: np.ndarray) -> tuple[int, int, int, int]:
    """(x, y, w, h) bounds of the non-zero pixels."""
    nz = img if img.dtype == np.uint8 else cv2.compare(img, 0, cv2.CMP_NE)
    return tuple(int(v) for v in cv2.boundingRect(nz))  # type: ignore[return-value]


def _instance(
    label: str | None, parts: dict[str, PartObservation], shape: tuple[int, int] | None = None
) -> InstanceObservation:
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
        label=label,
        parts=parts,
        centroid_px=(sx / area, sy / area),
        area_px=area,
        bbox_xywh=(int(x0), int(y0), int(x1 - x0), int(y1 - y0)),
        image_shape=shape,
    )


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
    shape = (int(img.shape[0]), int(img.shape[1]))
    min_area = config.min_area_px
    out: list[InstanceObservation] = []
    fx, fy, fw, fh = _foreground(img)
    if fw == 0 or fh == 0:
        return out
    crop = img[fy : fy + fh, fx : fx + fw]  # every part pixel is non-zero: work on its bounds
    if config.instruments:
        for spec in config.instruments:
            parts: dict[str, PartObservation] = {}
            for part in PARTS:
                if part in spec.parts and spec.parts[part][1] > 0:
                    obs = _part_observation(
                        part, range_mask(crop, spec.parts[part]), fx, fy, min_area
                    )
                    if obs is not None:
                        parts[part] = obs
            if parts:
                out.append(_instance(spec.name, parts, shape))
        return out

    part_names = [p for p in PARTS if p in config.parts and config.parts[p][1] > 0]
    if not part_names:
        return out
    masks = {p: range_mask(crop, config.parts[p]) for p in part_names}
    union = masks[part_names[0]]
    for p in part_names[1:]:
        union = cv2.bitwise_or(union, masks[p])
    # one connected foreground (the common case) needs no bridging
    contours, hierarchy = cv2.findContours(union, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    n_inst = int((hierarchy[0][:, 3] < 0).sum()) if contours else 0
    bridged = union
    if n_inst > 1 and MERGE_GAP_PX > 0:
        # the crop holds every foreground pixel, so no padding is needed for the gaps
        k = 2 * MERGE_GAP_PX + 1
        bridged = cv2.dilate(union, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
        contours, hierarchy = cv2.findContours(bridged, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
        n_inst = int((hierarchy[0][:, 3] < 0).sum())
    if n_inst == 0:
        return out
    if n_inst == 1:  # one (bridged) component: everything belongs to it
        parts = {}
        for p in part_names:
            obs = _part_observation(p, masks[p], fx, fy, min_area)
            if obs is not None:
                parts[p] = obs
        if parts and sum(o.area_px for o in parts.values()) >= max(min_area, 1):
            out.append(_instance(None, parts, shape))
        return out
    n, cc, stats, _ = cv2.connectedComponentsWithStats(bridged, connectivity=8)
    counts = np.bincount(cc[union > 0], minlength=n)
    shaft_counts = (
        np.bincount(cc[masks["shaft"] > 0], minlength=n)
        if "shaft" in masks
        else np.zeros(n, np.int64)
    )
    found = []
    h_img, w_img = img.shape[:2]
    border = (
        (stats[:, 0] + fx <= 0)
        | (stats[:, 1] + fy <= 0)
        | (stats[:, 0] + stats[:, 2] + fx >= w_img)
        | (stats[:, 1] + stats[:, 3] + fy >= h_img)
    )
    for group in _group_fragments(counts, shaft_counts, stats, max(min_area, 1), cc, border):
        x0 = min(int(stats[i, 0]) for i in group)
        y0 = min(int(stats[i, 1]) for i in group)
        x1 = max(int(stats[i, 0] + stats[i, 2]) for i in group)
        y1 = max(int(stats[i, 1] + stats[i, 3]) for i in group)
        sub = cc[y0:y1, x0:x1]
        inside = sub == group[0] if len(group) == 1 else np.isin(sub, group)
        parts = {}
        for p in part_names:
            pm = np.where(inside, masks[p][y0:y1, x0:x1], np.uint8(0))
            obs = _part_observation(p, pm, fx + x0, fy + y0, min_area)
            if obs is not None:
                parts[p] = obs
        if parts:
            found.append(_instance(None, parts, shape))
    found = _join_cut_shafts(found, min_area, (img.shape[0], img.shape[1]))
    found.sort(key=lambda inst: -inst.area_px)
    return found


#: Merged masks: a shaft-only piece whose axis continues another instance's shaft (angles
#: within this many degrees, centre within half a shaft width of that axis) is the
#: same instrument, cut in two by an occluder.
CUT_SHAFT_ANGLE_DEG = 6.0
#: Merged masks: a piece without a shaft whose centre lies on the distal extension of a
#: shaft's axis (within one shaft width of the axis, at most this many shaft widths past
#: its distal end) is that instrument's head, cut off by an occluder.
HEAD_AXIS_REACH = 3.0


def _distal_sign(inst: InstanceObservation, shape: tuple[int, int]) -> float:
    """+1 if the instance's distal end is along +u of its shaft box, else -1: towards its
    other parts, or (shaft alone) away from the image border the shaft comes from."""
    a = inst.parts["shaft"].box
    u = _unit(a.angle_deg)
    others = [o.box for p, o in inst.parts.items() if p != "shaft"]
    if others:
        o = np.mean([[b.cx, b.cy] for b in others], axis=0)
        return 1.0 if (o[0] - a.cx) * u[0] + (o[1] - a.cy) * u[1] >= 0 else -1.0
    h, w = shape

    def inside(x: float, y: float) -> float:  # distance to the nearest border
        return min(x, w - 1 - x, y, h - 1 - y)

    plus = inside(a.cx + a.length / 2 * u[0], a.cy + a.length / 2 * u[1])
    minus = inside(a.cx - a.length / 2 * u[0], a.cy - a.length / 2 * u[1])
    return 1.0 if plus >= minus else -1.0


def _host_for(
    piece: InstanceObservation, found: list[InstanceObservation], k: int, shape: tuple[int, int]
) -> int | None:
    """The instance a piece belongs to by shaft geometry, or None."""
    if set(piece.parts) == {"shaft"}:  # a shaft cut in two
        b = piece.parts["shaft"].box
        for j, other in enumerate(found):
            if j == k or "shaft" not in other.parts:
                continue
            a = other.parts["shaft"].box
            # a short stub's box has no reliable direction: the longer piece's axis is the
            # reference, and directions must agree only when the other is long too (twice
            # the shaft's width)
            ref, q = (a, b) if a.length >= b.length else (b, a)
            if (
                q.length >= 2.0 * ref.width
                and _angle_diff(a.angle_deg, b.angle_deg) > CUT_SHAFT_ANGLE_DEG
            ):
                continue
            u = _unit(ref.angle_deg)
            off = abs((q.cx - ref.cx) * u[1] - (q.cy - ref.cy) * u[0])  # to ref's axis
            if off <= 0.5 * max(ref.width, min(q.width, q.length)):
                return j
        return None
    if "shaft" in piece.parts:
        return None
    best: tuple[float, int] | None = None  # a head cut off: on a shaft's distal extension
    hx, hy = piece.centroid_px
    for j, other in enumerate(found):
        if j == k or "shaft" not in other.parts:
            continue
        # the host must not already show a head part of this piece's size (its own
        # head): a crumb of a head (< FRAGMENT_AREA_FRAC of the host's) joins, and so
        # does a head larger than the stub of it the host shows beside the occluder
        if any(
            p in other.parts
            and FRAGMENT_AREA_FRAC * other.parts[p].area_px
            <= piece.parts[p].area_px
            <= other.parts[p].area_px
            for p in piece.parts
        ):
            continue
        a = other.parts["shaft"].box
        u = _unit(a.angle_deg) * _distal_sign(other, shape)
        along = (hx - a.cx) * u[0] + (hy - a.cy) * u[1] - a.length / 2
        off = abs((hx - a.cx) * u[1] - (hy - a.cy) * u[0])
        if off <= a.width and -a.length / 2 <= along <= HEAD_AXIS_REACH * a.width:
            if best is None or off < best[0]:
                best = (off, j)
    return None if best is None else best[1]


def _join_cut_shafts(
    found: list[InstanceObservation], min_area: int, shape: tuple[int, int]
) -> list[InstanceObservation]:
    """Join pieces cut off by an occluder to their instrument (:func:`_host_for`)."""
    if len(found) < 2:
        return found
    found = sorted(found, key=lambda inst: inst.area_px)  # smallest pieces first
    k = 0
    while k < len(found):
        host = _host_for(found[k], found, k, shape)
        if host is None:
            k += 1
            continue
        joined = _merge_instances(found[host], found[k], min_area)
        found = [inst for i, inst in enumerate(found) if i not in (k, host)] + [joined]
        found.sort(key=lambda inst: inst.area_px)
        k = 0
    return found


def _merge_instances(
    a: InstanceObservation, b: InstanceObservation, min_area: int
) -> InstanceObservation:
    """One instance from two: each part refitted on both instances' pixels."""
    parts: dict[str, PartObservation] = {}
    for name in PARTS:
        obs = [inst.parts[name] for inst in (a, b) if name in inst.parts]
        if not obs:
            continue
        if len(obs) == 1:
            parts[name] = obs[0]
            continue
        x0 = min(o.offset[0] for o in obs)
        y0 = min(o.offset[1] for o in obs)
        x1 = max(o.offset[0] + o.mask.shape[1] for o in obs)
        y1 = max(o.offset[1] + o.mask.shape[0] for o in obs)
        m = np.zeros((y1 - y0, x1 - x0), np.uint8)
        for o in obs:
            h, w = o.mask.shape
            ox, oy = o.offset[0] - x0, o.offset[1] - y0
            m[oy : oy + h, ox : ox + w][o.mask] = 255
        joined = _part_observation(name, m, x0, y0, min_area)
        if joined is not None:
            parts[name] = joined
    return _instance(None, parts, a.image_shape)


def _group_fragments(
    counts: np.ndarray,
    shaft_counts: np.ndarray,
    stats: np.ndarray,
    min_area: int,
    cc: np.ndarray | None = None,
    border: np.ndarray | None = None,
) -> list[list[int]]:
    """Components (labels 1..n-1) grouped into instruments.

    - A component smaller than ``min_area`` pixels is a speck and is dropped.
    - A *fragment* (a shaft piece with less than :data:`FRAGMENT_AREA_FRAC` of a larger
      component's area, at most :data:`FRAGMENT_GAP_PX` from its pixels) joins it.
    - A *head* (a component without shaft pixels: jaws, a wrist) joins the group with a
      shaft (a component and what joined it so far) nearest to it, if at most
      ``max(FRAGMENT_GAP_PX, HEAD_GAP_FRAC * sqrt(group area))`` px away: open jaws, or a
      clasper cut in pieces by an occluder, are not new instruments. Heads join one at a
      time, nearest first, each join growing its group's bounds and area. The gap is the
      groups' bounding boxes' gap, and, with ``cc`` (the component label image), the
      pixels' own gap (a head beside a long oblique shaft is far from its pixels, though
      inside its bounds). Heads with no such shaft near (an instrument entering the view
      head first) join each other by the same distance (at least
      :data:`HEAD_HEAD_GAP_PX`).
    - A head left alone that does not touch the image border (``border[i]`` False) has
      lost its shaft to an occluder: it joins the nearest group with a shaft within
      :data:`HEAD_ORPHAN_FRAC` x sqrt(its area), at most :data:`HEAD_ORPHAN_GAP_PX`.
    """
    labels = [i for i in range(1, len(counts)) if counts[i] >= min_area]
    labels.sort(key=lambda i: -counts[i])
    hosts = [i for i in labels if shaft_counts[i] >= min_area]
    heads = [i for i in labels if shaft_counts[i] < min_area]

    owner: dict[int, int] = {i: i for i in labels}
    members: dict[int, list[int]] = {i: [i] for i in labels}
    box = {
        i: [
            int(stats[i, 0]),
            int(stats[i, 1]),
            int(stats[i, 0] + stats[i, 2]),
            int(stats[i, 1] + stats[i, 3]),
        ]
        for i in labels
    }  # x0, y0, x1, y1 (excl.)
    area = {i: float(counts[i]) for i in labels}

    def join(i: int, j: int) -> None:  # group i (a root) into group j (a root)
        owner[i] = j
        members[j] += members.pop(i)
        bi, bj = box[i], box[j]
        box[j] = [min(bi[0], bj[0]), min(bi[1], bj[1]), max(bi[2], bj[2]), max(bi[3], bj[3])]
        area[j] += area[i]

    def reach(j: int) -> float:
        return max(FRAGMENT_GAP_PX, HEAD_GAP_FRAC * math.sqrt(area[j]))

    memo: dict[tuple[int, int, int, int, int], float] = {}

    def gap(i: int, j: int, limit: float) -> float:
        bi, bj = box[i], box[j]
        dx = max(bi[0] - bj[2] + 1, bj[0] - bi[2] + 1, 0)
        dy = max(bi[1] - bj[3] + 1, bj[1] - bi[3] + 1, 0)
        g = math.hypot(dx, dy)
        if g > limit or cc is None:
            return g
        key = (i, j, len(members[i]), len(members[j]), int(math.ceil(limit)))
        if key not in memo:  # the groups have not grown since: same pixels, same gap
            memo[key] = _pixel_gap(cc, members[i], members[j], bi, bj, key[4])
        return memo[key]

    for k, i in enumerate(hosts):  # small shaft pieces next to a much larger one
        for j in hosts[:k]:
            if (
                owner[j] == j
                and counts[i] < FRAGMENT_AREA_FRAC * counts[j]
                and gap(i, j, FRAGMENT_GAP_PX) <= FRAGMENT_GAP_PX
            ):
                join(i, j)
                break
    todo = list(heads)
    while todo:  # the nearest head joins first; its group grows
        best: tuple[float, int, int] | None = None
        for i in todo:
            for j in members:
                if j in todo or j not in hosts:
                    continue
                g = gap(i, j, reach(j))
                if g <= reach(j) and (best is None or g < best[0]):
                    best = (g, i, j)
        if best is None:
            break
        todo.remove(best[1])
        join(best[1], best[2])
    for i in list(todo):  # a head inside the view cut off from its shaft by an occluder
        if border is not None and border[i]:
            continue  # a head at the border: its shaft may be beyond it
        lim = min(HEAD_ORPHAN_GAP_PX, HEAD_ORPHAN_FRAC * math.sqrt(area[i]))
        near = [(gap(i, j, lim), j) for j in members if j in hosts]
        near = [(g, j) for g, j in near if g <= lim]
        if near:
            todo.remove(i)
            join(i, min(near)[1])
    for k, i in enumerate(todo):  # heads without a shaft near: larger heads first
        for j in todo[:k]:
            if owner[j] == j:
                lim = max(reach(j), HEAD_HEAD_GAP_PX)
                if gap(i, j, lim) <= lim:
                    join(i, j)
                    break
    return list(members.values())


def _pixel_gap(
    cc: np.ndarray, a: list[int], b: list[int], box_a: list[int], box_b: list[int], reach: int
) -> float:
    """Smallest distance (px) from a pixel labelled in ``a`` to one labelled in ``b`` in the
    component label image ``cc``, looked for within ``reach`` px of ``a``'s bounds
    ``box_a`` (``box_b``: ``b``'s bounds; both x0, y0, x1, y1 exclusive); ``inf`` beyond."""
    # all of a, and the part of b's bounds within reach of a's
    x0 = min(box_a[0], max(box_a[0] - reach, box_b[0]))
    y0 = min(box_a[1], max(box_a[1] - reach, box_b[1]))
    x1 = max(box_a[2], min(box_a[2] + reach, box_b[2]))
    y1 = max(box_a[3], min(box_a[3] + reach, box_b[3]))
    win = cc[y0:y1, x0:x1]
    in_b = win == b[0] if len(b) == 1 else np.isin(win, b)
    if not in_b.any():
        return math.inf
    not_a = (win != a[0] if len(a) == 1 else ~np.isin(win, a)).astype(np.uint8)
    dist = cv2.distanceTransform(not_a, cv2.DIST_L2, cv2.DIST_MASK_3)  # ~2% off: a gate
    return float(dist[in_b].min())


def _bbox_gap(a: np.ndarray, b: np.ndarray) -> float:
    """Distance between two (x, y, w, h, ...) boxes' pixel ranges (0 when they overlap)."""
    dx = max(int(a[0]) - int(b[0] + b[2]) + 1, int(b[0]) - int(a[0] + a[2]) + 1, 0)
    dy = max(int(a[1]) - int(b[1] + b[3]) + 1, int(b[1]) - int(a[1] + a[3]) + 1, 0)
    return math.hypot(dx, dy)


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


@dataclass
class _Track:
    """An instrument the tracker has seen (mutable state, internal)."""

    name: str
    last_frame: int
    centroid: np.ndarray  # (2,) px, where the instrument itself is believed to be
    velocity: np.ndarray  # (2,) px per frame
    area: float
    angle: float | None  # shaft (or largest part) direction, deg in [0, 180)
    elongation: float  # (length - width) / length of that box, 0..1
    merged: bool = False  # inside a blob shared with another instrument: coasting
    hidden: bool = False  # ... and that blob carries another instrument's name
    size: float = 0.0  # largest sqrt(area) seen, px: the instrument's scale
    boxes: dict[str, RotatedBox] | None = None  # last part boxes seen apart from others
    boxes_frame: int = 0  # ... and their frame
    seen: int = 1
    entry: np.ndarray | None = None  # (2,) px where its shaft last entered the view alone


def _appearance(inst: InstanceObservation) -> tuple[float | None, float]:
    part = inst.parts.get("shaft") or max(inst.parts.values(), key=lambda p: p.area_px)
    box = part.box
    if box.length <= 0:
        return None, 0.0
    return box.angle_deg, (box.length - box.width) / box.length


def _angle_diff(a: float, b: float) -> float:
    d = abs(a - b) % 180.0
    return min(d, 180.0 - d)


class IdentityTracker:
    """Names instruments consistently across frames.

    With ``config.instruments`` the name is the instance's label. In merged masks each
    instance is matched to the known instruments by a cost built from the distance to
    the instrument's predicted position (constant velocity), the difference in shaft
    direction and the ratio of areas; the assignment minimises the total cost
    (exhaustively for a few instruments, greedily beyond). Names are ``"1"``, ``"2"``,
    ... in order of first appearance.

    - Crossing: when two instruments touch they form one instance. The instance keeps the
      name of the best match; the other instrument, whose predicted position lies inside
      that instance, is kept alive, and both *coast* on their predicted motion (their
      state is not polluted by the merged blob's centroid) until they separate, when
      position and shaft direction tell them apart again.
    - Touching since they appeared (``resolve`` only): a blob whose shaft pixels enter
      the view at more places on the image border than instruments known in it is split
      on those shafts (half-lines from the border, refitted as for a crossing, refused
      when ambiguous); each known instrument takes the piece entering nearest to where
      its own shaft last entered, the others get new names.
    - Leaving and coming back: an instrument unseen for up to ``max_gap_s`` seconds is
      remembered; a new instance near where it was last seen (within
      :attr:`LOST_SCALE_FRAC` of the image diagonal, growing with time, and similar in
      shaft direction) gets its old name back; after that gap it is forgotten and a
      newcomer gets a new name.

    ``assign`` must be called in frame order (it keeps state); it is not thread-safe.
    """

    #: Gate: a match costs at most this much (the distance term is in units of the
    #: instrument's size, sqrt(area)).
    MAX_COST = 3.0
    #: Weights of the direction (per 90 deg) and log-area-ratio terms.
    ANGLE_WEIGHT = 1.5
    AREA_WEIGHT = 0.3
    #: Extra cost per frame unseen, so recently seen instruments are preferred.
    GAP_WEIGHT = 0.02
    #: Extra cost for an instrument hidden in another's blob to take that blob's name.
    HIDDEN_PENALTY = 0.5
    #: An instrument unseen for more than 5 frames is searched for within a distance
    #: that grows by this many of its sizes per second unseen.
    LOST_SEARCH_GROWTH = 0.25
    #: ... starting from at most this fraction of the image diagonal (an instrument comes
    #: back near where it left, through its trocar; a large one is no wider gate).
    LOST_SCALE_FRAC = 0.1
    #: Splitting a blob on its shafts' entries: an instrument known in it takes the piece
    #: entering the view nearest to where its own shaft last entered, at a cost of one per
    #: this fraction of the image diagonal.
    ENTRY_SCALE_FRAC = 0.1

    def __init__(self, config: Config, *, max_gap_s: float = 2.0) -> None:
        self._config = config
        self._max_gap = max(1, int(round(max_gap_s * config.fps)))
        self._tracks: list[_Track] = []
        self._next = 1
        self._last_frame: int | None = None

    @property
    def names(self) -> tuple[str, ...]:
        """Every name handed out so far, in order of first appearance."""
        return tuple(t.name for t in self._tracks)

    def assign(self, frame_index: int, instances: list[InstanceObservation]) -> list[str]:
        """Names for one frame's instances.

        Args:
            frame_index: the frame's 0-based index; increasing between calls.
            instances: :func:`observe_frame`'s result for that frame.

        Returns:
            One instrument name per instance, same order, all different. An instance that
            holds two crossing instruments gets one name (see :meth:`resolve`).
        """
        return self._step(frame_index, instances, split=False)[1]

    def resolve(
        self, frame_index: int, instances: list[InstanceObservation]
    ) -> tuple[list[InstanceObservation], list[str]]:
        """Like :meth:`assign`, but an instance holding several known instruments (two
        crossing or grasping each other in merged masks) is split between them.

        The split (:func:`split_instance`) assigns the blob's pixels to the instruments'
        expected part boxes (their last boxes seen apart, moved by their velocity), the
        shaft axes refined on the blob's own pixels; it is used only when it is well
        supported, else the blob keeps one name as in :meth:`assign`.

        Args:
            frame_index: the frame's 0-based index; increasing between calls.
            instances: :func:`observe_frame`'s result for that frame.

        Returns:
            ``(instances, names)``: the instances (split ones replaced by their pieces,
            which have ``label`` None and new part boxes) and one name per instance. When
            nothing was split, ``instances`` is the very list passed in (so a caller can
            test ``is`` and redo per-instance work only for split frames).
        """
        return self._step(frame_index, instances, split=True)

    def _step(
        self, frame_index: int, instances: list[InstanceObservation], *, split: bool
    ) -> tuple[list[InstanceObservation], list[str]]:
        if self._config.instruments and all(i.label is not None for i in instances):
            return instances, [str(i.label) for i in instances]
        if self._last_frame is not None and frame_index <= self._last_frame:
            raise ValueError(
                f"IdentityTracker: frame {frame_index} after frame "
                f"{self._last_frame}; frames must come in increasing order"
            )
        self._last_frame = frame_index
        live = [t for t in self._tracks if frame_index - t.last_frame <= self._max_gap]
        cost = np.full((len(live), len(instances)), np.inf)
        for a, t in enumerate(live):
            for b, inst in enumerate(instances):
                cost[a, b] = self._cost(t, inst, frame_index)
        pairs = _assignment(cost, self.MAX_COST)
        owner = {b: a for a, b in pairs}
        # instruments hidden inside a matched instance (crossing): blob -> hidden tracks
        blob_of: dict[int, list[int]] = {}
        for a, t in enumerate(live):
            if a in owner.values() or frame_index - t.last_frame > max(3, self._max_gap // 4):
                continue
            pred = self._predict(t, frame_index)
            for a2, b in pairs:
                # a blob that holds both: the prediction is inside it, and it is clearly
                # larger than the instrument it was matched to
                grown = instances[b].area_px > 1.3 * live[a2].area or live[a2].merged
                if grown and _inside(pred, instances[b].bbox_xywh, margin=0.15):
                    blob_of.setdefault(b, []).append(a)
                    break
        pieces: dict[int, list[InstanceObservation]] = {}
        if split:
            for b, hidden in blob_of.items():
                group = [live[owner[b]]] + [live[a] for a in hidden]
                best: tuple[float, list[InstanceObservation]] | None = None
                # two motion hypotheses: slowing to a stop when they met, or keeping on
                for steps in (5, None):
                    expected = [self._expected_boxes(t, frame_index, steps) for t in group]
                    if not all(e is not None for e in expected):
                        break
                    got = _split(
                        instances[b],
                        expected,  # type: ignore[arg-type]
                        max(self._config.min_area_px, 1),
                    )
                    if got is not None and (best is None or got[0] < best[0]):
                        best = got
                if best is not None:
                    pieces[b] = best[1]
        # a blob with more shafts entering from the border than instruments known in it
        # (instruments touching since they came into view): split on those shafts
        own: dict[int, list[_Track]] = {}
        if split:
            # tracks believed hidden in a blob that was not split may be found elsewhere
            used = set(owner.values()) | {
                a for b, hidden in blob_of.items() if b in pieces for a in hidden
            }
            spare = [a for a in range(len(live)) if a not in used]
            for b, inst in enumerate(instances):
                if b in pieces:
                    continue
                group = ([owner[b]] + blob_of.get(b, [])) if b in owner else []
                spare_b = [a for a in spare if a not in group]
                entries = _border_entries(inst)
                if len(entries) < max(2, len(group)):
                    continue
                if len(entries) == len(group) and b not in blob_of:
                    continue  # as many shafts as instruments known: nothing new
                got = _split_entries(inst, entries, max(self._config.min_area_px, 1))
                if got is None:
                    continue
                cands = group + spare_b
                cost = np.full((len(cands), len(got)), np.inf)
                diag = math.hypot(*inst.image_shape) if inst.image_shape else 1000.0
                for r, a in enumerate(cands):
                    t = live[a]
                    for c, piece in enumerate(got):
                        if r >= len(group):
                            cost[r, c] = self._cost(t, piece, frame_index)
                        elif t.entry is not None:  # where its shaft entered the view
                            cost[r, c] = float(np.hypot(*(t.entry - entries[c][0]))) / (
                                self.ENTRY_SCALE_FRAC * diag
                            )
                        else:  # the blob's own instruments: their state is the blob's
                            cost[r, c] = 0.5 * self._cost(t, piece, frame_index)
                pairs_b = _assignment(cost, self.MAX_COST)
                taken = {cands[r] for r, _ in pairs_b}
                spare = [a for a in spare if a not in taken and a not in group]
                for b2 in [b2 for b2 in blob_of if b2 != b]:
                    blob_of[b2] = [a for a in blob_of[b2] if a not in taken]
                    if not blob_of[b2]:
                        del blob_of[b2]
                by_piece = {c: live[cands[r]] for r, c in pairs_b}
                tracks = []
                for c, piece in enumerate(got):
                    t = by_piece.get(c)
                    if t is None:
                        t = self._new_track(piece, frame_index)
                    else:
                        self._update(t, piece, frame_index, merged=False)
                    tracks.append(t)
                for a in group:  # known instruments the split did not find: coast
                    if a not in taken:
                        t = live[a]
                        t.centroid = self._predict(t, frame_index)
                        t.last_frame = frame_index
                        t.merged = t.hidden = True
                pieces[b] = got
                own[b] = tracks
        out_instances: list[InstanceObservation] = []
        names: list[str] = []
        for b, inst in enumerate(instances):
            if b in own:
                out_instances.extend(pieces[b])
                names.extend(t.name for t in own[b])
            elif b in pieces:
                group = [live[owner[b]]] + [live[a] for a in blob_of[b]]
                for t, piece in zip(group, pieces[b], strict=True):
                    self._update(t, piece, frame_index, merged=False, apart=False)
                    out_instances.append(piece)
                    names.append(t.name)
            elif b in owner:
                t = live[owner[b]]
                self._update(t, inst, frame_index, merged=b in blob_of)
                out_instances.append(inst)
                names.append(t.name)
            else:
                out_instances.append(inst)
                names.append(self._new_track(inst, frame_index).name)
        for b, hidden in blob_of.items():
            if b in pieces:
                continue
            for a in hidden:  # keep them coasting on their predicted motion
                t = live[a]
                t.centroid = self._predict(t, frame_index)
                t.last_frame = frame_index
                t.merged = t.hidden = True
        if not pieces:
            return instances, names  # the caller's own list: nothing was split
        return out_instances, names

    # internals ------------------------------------------------------------------------
    def _expected_boxes(
        self, t: _Track, frame: int, steps: int | None
    ) -> dict[str, RotatedBox] | None:
        """The track's last part boxes seen apart from others, moved to ``frame`` by at
        most ``steps`` frames of its velocity (None: all the way); the shaft is lengthened
        by what the rest of the constant-velocity motion would add along it."""
        if t.boxes is None:
            return None
        gap = frame - t.boxes_frame
        move = gap if steps is None else min(gap, steps)
        dx, dy = t.velocity * move
        out = {p: replace(b, cx=b.cx + float(dx), cy=b.cy + float(dy)) for p, b in t.boxes.items()}
        s = out["shaft"]
        u = _unit(s.angle_deg)
        extra = 2.0 * abs(float(t.velocity @ u)) * (gap - move)
        out["shaft"] = replace(s, length=s.length + extra)
        return out

    def _predict(self, t: _Track, frame: int) -> np.ndarray:
        gap = frame - t.last_frame
        steps = gap if t.merged or gap <= 5 else 5  # lost: look near where it was last
        return t.centroid + t.velocity * steps

    def _cost(self, t: _Track, inst: InstanceObservation, frame: int) -> float:
        gap = frame - t.last_frame
        pred = self._predict(t, frame)
        c = np.asarray(inst.centroid_px)
        # scale: the instrument's full size, also when it was last seen only partly
        scale = max(t.size, math.sqrt(inst.area_px), 10.0)
        if gap > 5 and not t.merged:  # unseen: the search area grows with time
            if inst.image_shape is not None:  # from where it left, whatever its size
                scale = min(scale, self.LOST_SCALE_FRAC * math.hypot(*inst.image_shape))
            scale *= 1.0 + self.LOST_SEARCH_GROWTH * (gap - 5) / self._config.fps
        cost = float(np.hypot(*(c - pred))) / scale
        angle, elong = _appearance(inst)
        lost = gap > 5 and not t.merged
        # an instrument coming back shows its head first: its direction is no shaft's
        if angle is not None and t.angle is not None and not (lost and "shaft" not in inst.parts):
            w = min(elong, t.elongation)
            cost += self.ANGLE_WEIGHT * w * _angle_diff(angle, t.angle) / 90.0
        if not t.merged and gap <= 5:  # not a blob's area, nor an exit's partial one
            cost += self.AREA_WEIGHT * abs(math.log(max(inst.area_px, 1) / max(t.area, 1.0)))
        cost += self.GAP_WEIGHT * (gap - 1)
        if t.hidden:  # a shared blob keeps the name it had: no flapping during a crossing
            cost += self.HIDDEN_PENALTY
        return cost

    def _update(
        self, t: _Track, inst: InstanceObservation, frame: int, *, merged: bool, apart: bool = True
    ) -> None:
        gap = frame - t.last_frame
        c = np.asarray(inst.centroid_px, dtype=np.float64)
        if merged:  # the blob's centroid is not this instrument's: coast
            t.centroid = self._predict(t, frame)
            t.merged = True
        else:
            if gap <= 5 and not t.merged:
                v = (c - t.centroid) / gap
                t.velocity = v if t.seen == 1 else 0.5 * t.velocity + 0.5 * v
            elif gap > 5:
                t.velocity = np.zeros(2)
            t.centroid = c
            t.area = float(inst.area_px)
            t.size = max(t.size, math.sqrt(t.area))
            angle, elong = _appearance(inst)
            t.angle, t.elongation = angle, elong
            if apart and "shaft" in inst.parts:  # a split piece is no reference shape
                t.boxes = {p: o.box for p, o in inst.parts.items()}
                t.boxes_frame = frame
            self._set_entry(t, inst)
            t.merged = False
        t.hidden = False
        t.last_frame = frame
        t.seen += 1

    @staticmethod
    def _set_entry(t: _Track, inst: InstanceObservation) -> None:
        runs = _border_runs(inst)
        if len(runs) == 1:  # one shaft entering: this instrument's (not a blob's)
            t.entry = runs[0][0][1]

    def _new_track(self, inst: InstanceObservation, frame: int) -> _Track:
        angle, elong = _appearance(inst)
        t = _Track(
            name=str(self._next),
            last_frame=frame,
            centroid=np.asarray(inst.centroid_px, dtype=np.float64),
            velocity=np.zeros(2),
            area=float(inst.area_px),
            angle=angle,
            elongation=elong,
            size=math.sqrt(inst.area_px),
        )
        if "shaft" in inst.parts:
            t.boxes = {p: o.box for p, o in inst.parts.items()}
            t.boxes_frame = frame
        self._set_entry(t, inst)
        self._next += 1
        self._tracks.append(t)
        return t


#: A split is kept only if each piece's pixels spread across its line by at most this
#: fraction of the shaft's width (RMS; a full rectangle of width w gives 0.29 w).
SPLIT_MAX_SPREAD = 0.45
#: ... and its lines differ in direction by at least this much (deg).
SPLIT_MIN_ANGLE_DEG = 8.0


def _segment_distance(
    p: np.ndarray, ends: np.ndarray, dirs: np.ndarray, back: np.ndarray, radius: np.ndarray
) -> np.ndarray:
    """(N, K) distances from points (N, 2) to K segments, in units of each segment's
    ``radius`` (half the part's width). Segment k runs from ``ends[k]`` backwards along
    ``-dirs[k]`` for ``back[k]`` px (``inf``: a half-line, a shaft coming from the
    image border)."""
    rel = p[:, None, :] - ends[None]
    along = np.einsum("nkd,kd->nk", rel, dirs)  # <= 0 behind the end
    perp = rel[..., 1] * dirs[None, :, 0] - rel[..., 0] * dirs[None, :, 1]
    excess = np.maximum(along, 0.0) + np.maximum(-along - back[None], 0.0)
    return np.hypot(perp, excess) / radius[None]


def _unit(angle_deg: float) -> np.ndarray:
    t = math.radians(angle_deg)
    return np.array([math.cos(t), math.sin(t)])


def _distal_axis(boxes: dict[str, RotatedBox]) -> tuple[np.ndarray, np.ndarray, float]:
    """The shaft's (distal end, distal unit direction, back length) from part boxes: the
    distal side is the one towards the other parts (unknown without them: a segment)."""
    sb = boxes["shaft"]
    u = _unit(sb.angle_deg)
    c = np.array([sb.cx, sb.cy])
    others = [b for p, b in boxes.items() if p != "shaft"]
    if others:
        o = np.mean([[b.cx, b.cy] for b in others], axis=0)
        if (o - c) @ u < 0:
            u = -u
        back = math.inf
    else:
        back = sb.length
    return c + 0.5 * sb.length * u, u, back


#: A shaft entering the view is seen on the image border over at least this many px.
ENTRY_MIN_PX = 6
#: Border runs of shaft pixels this close (px) are one shaft's entry (a hole, jitter).
ENTRY_MAX_GAP_PX = 8


def _border_runs(inst: InstanceObservation) -> list[tuple[np.ndarray, int]]:
    """Where the instance's shaft pixels lie on the image border: one run of border
    pixels per shaft entering the view (runs around a corner are one), as ``(ends,
    length)``: (3, 2) px of the run's first, middle and last pixel, and its length (px;
    at least :data:`ENTRY_MIN_PX`)."""
    shaft = inst.parts.get("shaft")
    if shaft is None or inst.image_shape is None:
        return []
    hh, ww = inst.image_shape
    m = shaft.mask
    x0, y0 = shaft.offset
    h, w = m.shape
    if x0 > 0 and y0 > 0 and x0 + w < ww and y0 + h < hh:
        return []
    n = 2 * (ww - 1) + 2 * (hh - 1)  # the border as a loop: top, right, bottom, left
    on = np.zeros(n, bool)
    xs, ys = np.arange(x0, x0 + w), np.arange(y0, y0 + h)
    if y0 == 0:
        on[xs[m[0]]] = True
    if x0 + w == ww:
        on[(ww - 1 + ys[m[:, -1]]) % n] = True
    if y0 + h == hh:
        on[(ww - 1) + (hh - 1) + (ww - 1 - xs[m[-1]])] = True
    if x0 == 0:
        on[(2 * (ww - 1) + (hh - 1) + (hh - 1 - ys[m[:, 0]])) % n] = True
    if on.sum() < ENTRY_MIN_PX or on.all():
        return []
    start = int(np.argmin(on))  # a border pixel off the shaft: runs do not wrap from here
    roll = np.roll(on, -start).astype(np.int8)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], roll, [0]])))

    def xy(i: int) -> tuple[float, float]:
        i %= n
        if i < ww - 1:
            return float(i), 0.0
        i -= ww - 1
        if i < hh - 1:
            return float(ww - 1), float(i)
        i -= hh - 1
        if i < ww - 1:
            return float(ww - 1 - i), float(hh - 1)
        i -= ww - 1
        return 0.0, float(hh - 1 - i)

    # a gap of a few pixels in one shaft's contact (a specular hole, boundary jitter) is
    # not a second shaft: runs that close are one entry
    runs: list[list[int]] = []
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        if runs and int(a) - runs[-1][1] <= ENTRY_MAX_GAP_PX:
            runs[-1][1] = int(b)
        else:
            runs.append([int(a), int(b)])
    out = []
    for a, b in runs:
        length = b - a
        if length >= ENTRY_MIN_PX:
            first = int(a) + start
            ends = np.array([xy(first), xy(first + length // 2), xy(first + length - 1)])
            out.append((ends, length))
    return out


def _border_entries(inst: InstanceObservation) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """The shafts entering the view at the image border (:func:`_border_runs`), as
    ``(point, inward direction, width)``, px: the direction is the principal axis of the
    shaft pixels near the run, the width the run's length across it. Empty unless there
    are two entries or more (one instrument per entry, unless two touch at the border)."""
    runs = _border_runs(inst)
    if len(runs) < 2:
        return []
    shaft = inst.parts["shaft"]
    yy, xx = np.nonzero(shaft.mask)
    pts = np.stack([xx + shaft.offset[0], yy + shaft.offset[1]], 1).astype(np.float64)
    pts = pts[:: max(1, len(pts) // 20000)]
    out = []
    for ends, length in runs:
        mid = ends[1]
        r = max(3.0 * length, 30.0)
        near = pts[np.einsum("nd,nd->n", pts - mid, pts - mid) <= r * r]
        if len(near) < 3:
            continue
        c = near.mean(0)
        _, v = np.linalg.eigh(np.cov((near - c).T))
        d = v[:, 1]
        if d @ (c - mid) < 0:
            d = -d
        tangent = ends[2] - ends[0]
        tn = float(np.hypot(*tangent))
        sin = abs(float(tangent[0] * d[1] - tangent[1] * d[0])) / tn if tn > 0 else 1.0
        out.append((mid, d, max(length * sin, 3.0)))
    return out if len(out) >= 2 else []


def _split_entries(
    inst: InstanceObservation, entries: list[tuple[np.ndarray, np.ndarray, float]], min_area_px: int
) -> list[InstanceObservation] | None:
    """Split an instance between the shafts entering at ``entries`` (:func:`_split` with
    half-lines from the border, nothing known of the instruments' heads)."""
    x, y, w, h = inst.bbox_xywh
    reach = float(np.hypot(w, h))
    expected = []
    axes = []
    for p, d, width in entries:
        c = p + 0.5 * reach * d
        angle = math.degrees(math.atan2(d[1], d[0])) % 180.0
        expected.append({"shaft": RotatedBox(float(c[0]), float(c[1]), reach, width, angle)})
        axes.append((p + reach * d, d, math.inf))
    got = _split(inst, expected, min_area_px, axes, contiguous=True)
    return None if got is None else got[1]


def split_instance(
    inst: InstanceObservation, expected: list[dict[str, RotatedBox]], min_area_px: int = 1
) -> list[InstanceObservation] | None:
    """Split one instance holding several instruments between them.

    Each instrument's shaft is a half-line from the image border to its distal end (from
    its expected boxes); the blob's shaft pixels go to the nearest one (distances in
    units of each shaft's half-width), each line is refitted to its pixels (direction,
    distal end; a few rounds), and the split is kept only if every instrument's pixels
    hug its axis like a shaft of its width (RMS distance at most
    :data:`SPLIT_MAX_SPREAD` x width) and no two axes are parallel. Wrist and clasper
    pixels go to the nearest expected box of that part, moved with its shaft's refitted
    distal end.

    Args:
        inst: the merged instance (parts with pixel crops).
        expected: per instrument, part -> expected box this frame (from its last frames
            apart from the others, moved by its velocity); each needs a ``"shaft"``.
        min_area_px: each instrument needs at least this many shaft pixels.

    Returns:
        One instance per instrument, same order, or None when the split is not
        trustworthy.
    """
    got = _split(inst, expected, min_area_px)
    return None if got is None else got[1]


def _split(
    inst: InstanceObservation,
    expected: list[dict[str, RotatedBox]],
    min_area_px: int,
    axes: list[tuple[np.ndarray, np.ndarray, float]] | None = None,
    contiguous: bool = False,
) -> tuple[float, list[InstanceObservation]] | None:
    """:func:`split_instance` and its score (the worst RMS distance of a shaft's pixels
    to its axis, in half-widths; lower is better). ``axes``: the shafts' (distal end,
    distal direction, back length) when not from ``expected`` (:func:`_distal_axis`);
    ``contiguous``: each shaft ends at the first gap of two widths in its pixels along
    its axis (shafts entering from the border, their ends unknown)."""
    shaft = inst.parts.get("shaft")
    k = len(expected)
    if shaft is None or k < 2 or any("shaft" not in e for e in expected):
        return None
    ys, xs = np.nonzero(shaft.mask)
    pts = np.stack([xs + shaft.offset[0], ys + shaft.offset[1]], 1).astype(np.float64)
    step = max(1, len(pts) // 4000)  # the fits need no more points than this
    fit_pts = pts[::step]
    if axes is None:
        axes = [_distal_axis(e) for e in expected]
    ends = np.array([a[0] for a in axes])
    dirs = np.array([a[1] for a in axes])
    back = np.array([a[2] for a in axes])
    ends0 = ends.copy()
    margin = np.array([0.1 * e["shaft"].length for e in expected])
    ends = ends + margin[:, None] * dirs
    radius = np.array([max(e["shaft"].width / 2.0, 1.0) for e in expected])
    for _ in range(6):  # nearest axis, then refit each axis to its pixels
        lab = _segment_distance(fit_pts, ends, dirs, back, radius).argmin(1)
        for j in range(k):
            q = fit_pts[lab == j]
            if len(q) < 3 or len(q) * step < min_area_px:
                return None
            c = q.mean(0)
            _, v = np.linalg.eigh(np.cov((q - c).T))
            d = v[:, 1]  # largest spread: along the shaft
            dirs[j] = d if d @ dirs[j] >= 0 else -d
            # the distal end: the pixels' reach, never beyond the expected end + margin
            limit = float((ends0[j] + margin[j] * dirs[j] - c) @ dirs[j])
            proj = (q - c) @ dirs[j]
            reach = float(proj.max())
            if contiguous:  # up to the first gap along the axis: beyond is another's
                sp = np.sort(proj)
                gaps = np.flatnonzero(np.diff(sp) > 4.0 * radius[j])
                if len(gaps):
                    reach = float(sp[gaps[0]])
            ends[j] = c + min(reach, limit) * dirs[j]
    d = _segment_distance(fit_pts, ends, dirs, back, radius)
    lab = d.argmin(1)
    score = 0.0
    for j in range(k):  # in units of the half-width: a full rectangle gives 0.58
        rms = math.sqrt(float((d[lab == j, j] ** 2).mean()))
        if rms > 2.0 * SPLIT_MAX_SPREAD + 0.5 / radius[j]:
            return None
        score = max(score, rms)
    for i in range(k):
        for j in range(i + 1, k):
            cosang = min(1.0, abs(float(dirs[i] @ dirs[j])))
            if math.degrees(math.acos(cosang)) < SPLIT_MIN_ANGLE_DEG:
                return None
    shift = ends - ends0  # the other parts move with their shaft's distal end
    pieces: list[dict[str, PartObservation]] = [{} for _ in range(k)]
    for name, part in inst.parts.items():
        ys, xs = np.nonzero(part.mask)
        p = np.stack([xs + part.offset[0], ys + part.offset[1]], 1).astype(np.float64)
        if name == "shaft" or not all(name in e for e in expected):
            dist = _segment_distance(p, ends, dirs, back, radius)
        else:
            u = np.array([_unit(e[name].angle_deg) for e in expected])
            h = np.array([0.5 * e[name].length for e in expected])
            c = np.array([[e[name].cx, e[name].cy] for e in expected]) + shift
            r = np.array([max(e[name].width / 2.0, 1.0) for e in expected])
            dist = _segment_distance(p, c + h[:, None] * u, u, 2 * h, r)
        owner = dist.argmin(1)
        for j in range(k):
            sel = owner == j
            if not sel.any():
                continue
            m = np.zeros(part.mask.shape, np.uint8)
            m[ys[sel], xs[sel]] = 255
            obs = _part_observation(name, m, part.offset[0], part.offset[1], min_area_px)
            if obs is not None:
                pieces[j][name] = obs
    if any("shaft" not in parts for parts in pieces):
        return None
    return score, [_instance(None, parts, inst.image_shape) for parts in pieces]


def _inside(p: np.ndarray, bbox: tuple[int, int, int, int], margin: float) -> bool:
    x, y, w, h = bbox
    mx, my = margin * w, margin * h
    return bool(x - mx <= p[0] <= x + w + mx and y - my <= p[1] <= y + h + my)


def _assignment(cost: np.ndarray, max_cost: float) -> list[tuple[int, int]]:
    """Pairs (row, col) minimising the total cost; pairs above ``max_cost`` are not made
    (leaving a row or column unmatched costs ``max_cost``)."""
    n_r, n_c = cost.shape
    if n_r == 0 or n_c == 0:
        return []
    c = np.where(cost <= max_cost, cost, np.inf)
    if min(n_r, n_c) <= 6 and max(n_r, n_c) <= 8:
        return _exhaustive(c, max_cost)
    pairs = []  # greedy, cheapest first
    used_r: set[int] = set()
    used_c: set[int] = set()
    for flat in np.argsort(c, axis=None):
        r, k = divmod(int(flat), n_c)
        if not np.isfinite(c[r, k]):
            break
        if r not in used_r and k not in used_c:
            pairs.append((r, k))
            used_r.add(r)
            used_c.add(k)
    return pairs


def _exhaustive(c: np.ndarray, max_cost: float) -> list[tuple[int, int]]:
    n_r, n_c = c.shape
    best: tuple[float, list[tuple[int, int]]] = (math.inf, [])

    def rec(r: int, used: int, total: float, pairs: list[tuple[int, int]]) -> None:
        nonlocal best
        if total >= best[0]:
            return
        if r == n_r:
            total += max_cost * (n_c - len(pairs))  # unmatched columns
            if total < best[0]:
                best = (total, list(pairs))
            return
        rec(r + 1, used, total + max_cost, pairs)  # row r unmatched
        for k in range(n_c):
            if not used >> k & 1 and np.isfinite(c[r, k]):
                pairs.append((r, k))
                rec(r + 1, used | 1 << k, total + c[r, k], pairs)
                pairs.pop()

    rec(0, 0, 0.0, [])
    return best[1]
