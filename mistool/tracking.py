"""Instruments in a frame (instances and their parts) and their identity across frames.

Two ways to tell instruments apart, chosen by the config:

- **Own label values** (``[[instrument]]`` tables): each instrument's parts come from its
  own value ranges; the instrument's name is its label. This is the paper's setting.
- **Merged masks** (no ``[[instrument]]`` tables, EndoVis'17 style: every instrument
  shares the part values): instances are the connected components of the *whole*
  instrument (shaft + wrist + clasper pixels together), bridged over gaps of up to
  :data:`MERGE_GAP_PX` pixels so a clasper one pixel away from its shaft stays one
  instrument. Components smaller than ``config.min_area_px`` are specks and are dropped;
  a small component close to a much larger one (:data:`FRAGMENT_AREA_FRAC`,
  :data:`FRAGMENT_GAP_PX`) is a fragment of it (a jaw apart from its clasper at the image
  border, a piece cut off by an occluder).
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

#: Merged masks: a component with less than this fraction of a larger one's area, within
#: :data:`FRAGMENT_GAP_PX` of it, is a fragment of that instrument (see observe_frame).
FRAGMENT_AREA_FRAC = 0.25
FRAGMENT_GAP_PX = 30.0


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
    # one connected foreground (the common case) needs no bridging
    contours, hierarchy = cv2.findContours(union, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    n_inst = int((hierarchy[0][:, 3] < 0).sum()) if contours else 0
    bridged = union
    if n_inst > 1 and MERGE_GAP_PX > 0:
        # the crop holds every foreground pixel, so no padding is needed for the gaps
        k = 2 * MERGE_GAP_PX + 1
        bridged = cv2.dilate(union, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
        contours, hierarchy = cv2.findContours(bridged, cv2.RETR_CCOMP,
                                               cv2.CHAIN_APPROX_SIMPLE)
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
            out.append(_instance(None, parts))
        return out
    n, cc, stats, _ = cv2.connectedComponentsWithStats(bridged, connectivity=8)
    counts = np.bincount(cc[union > 0], minlength=n)
    found = []
    for group in _group_fragments(counts, stats, max(min_area, 1)):
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
            found.append(_instance(None, parts))
    found.sort(key=lambda inst: -inst.area_px)
    return found


def _group_fragments(counts: np.ndarray, stats: np.ndarray, min_area: int) -> list[list[int]]:
    """Components (labels 1..n-1) grouped into instruments.

    A component smaller than ``min_area`` pixels is a speck and is dropped. A *fragment*
    (less than :data:`FRAGMENT_AREA_FRAC` of a larger component's area, its bounding box
    at most :data:`FRAGMENT_GAP_PX` from that component's) joins the largest such
    neighbour: a jaw seen apart from its clasper at the image border, or a piece of an
    instrument cut off by an occluder, is not a new instrument.
    """
    labels = [i for i in range(1, len(counts)) if counts[i] >= min_area]
    labels.sort(key=lambda i: -counts[i])
    owner: dict[int, int] = {}
    for k, i in enumerate(labels):
        owner[i] = i
        for j in labels[:k]:  # larger components first
            if owner[j] != j or counts[i] >= FRAGMENT_AREA_FRAC * counts[j]:
                continue
            if _bbox_gap(stats[i], stats[j]) <= FRAGMENT_GAP_PX:
                owner[i] = j
                break
    groups: dict[int, list[int]] = {}
    for i in labels:
        groups.setdefault(owner[i], []).append(i)
    return list(groups.values())


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
    seen: int = 1


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
    - Leaving and coming back: an instrument unseen for up to ``max_gap_s`` seconds is
      remembered; a new instance near where it was last seen (and similar in direction)
      gets its old name back; after that gap it is forgotten and a newcomer gets a new
      name.

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
            One instrument name per instance, same order, all different.
        """
        if self._config.instruments and all(i.label is not None for i in instances):
            return [str(i.label) for i in instances]
        if self._last_frame is not None and frame_index <= self._last_frame:
            raise ValueError(f"IdentityTracker.assign: frame {frame_index} after frame "
                             f"{self._last_frame}; frames must come in increasing order")
        self._last_frame = frame_index
        live = [t for t in self._tracks if frame_index - t.last_frame <= self._max_gap]
        cost = np.full((len(live), len(instances)), np.inf)
        for a, t in enumerate(live):
            for b, inst in enumerate(instances):
                cost[a, b] = self._cost(t, inst, frame_index)
        pairs = _assignment(cost, self.MAX_COST)
        names: list[str | None] = [None] * len(instances)
        matched_tracks = set()
        for a, b in pairs:
            names[b] = live[a].name
            matched_tracks.add(a)
        # instruments hidden inside a matched instance (crossing): keep them coasting
        blob_of: dict[int, list[int]] = {}
        for a, t in enumerate(live):
            if a in matched_tracks or frame_index - t.last_frame > max(3, self._max_gap // 4):
                continue
            pred = self._predict(t, frame_index)
            for a2, b in pairs:
                # a blob that holds both: the prediction is inside it, and it is clearly
                # larger than the instrument it was matched to
                grown = instances[b].area_px > 1.3 * live[a2].area or live[a2].merged
                if grown and _inside(pred, instances[b].bbox_xywh, margin=0.15):
                    blob_of.setdefault(b, []).append(a)
                    break
        merged_blobs = set(blob_of)
        for a, b in pairs:
            self._update(live[a], instances[b], frame_index, merged=b in merged_blobs)
        for hidden in blob_of.values():
            for a in hidden:
                t = live[a]
                t.centroid = self._predict(t, frame_index)
                t.last_frame = frame_index
                t.merged = t.hidden = True
        for b, inst in enumerate(instances):
            if names[b] is None:
                track = self._new_track(inst, frame_index)
                names[b] = track.name
        return [str(n) for n in names]

    # internals ------------------------------------------------------------------------
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
        cost = float(np.hypot(*(c - pred))) / scale
        angle, elong = _appearance(inst)
        if angle is not None and t.angle is not None:
            w = min(elong, t.elongation)
            cost += self.ANGLE_WEIGHT * w * _angle_diff(angle, t.angle) / 90.0
        if not t.merged and gap <= 5:  # not a blob's area, nor an exit's partial one
            cost += self.AREA_WEIGHT * abs(math.log(max(inst.area_px, 1) / max(t.area, 1.0)))
        cost += self.GAP_WEIGHT * (gap - 1)
        if t.hidden:  # a shared blob keeps the name it had: no flapping during a crossing
            cost += self.HIDDEN_PENALTY
        return cost

    def _update(self, t: _Track, inst: InstanceObservation, frame: int, *,
                merged: bool) -> None:
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
            t.merged = False
        t.hidden = False
        t.last_frame = frame
        t.seen += 1

    def _new_track(self, inst: InstanceObservation, frame: int) -> _Track:
        angle, elong = _appearance(inst)
        t = _Track(name=str(self._next), last_frame=frame,
                   centroid=np.asarray(inst.centroid_px, dtype=np.float64),
                   velocity=np.zeros(2), area=float(inst.area_px), angle=angle,
                   elongation=elong, size=math.sqrt(inst.area_px))
        self._next += 1
        self._tracks.append(t)
        return t


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
