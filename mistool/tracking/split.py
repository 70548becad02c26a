"""Splitting one blob that holds several instruments (pure functions).

Two instruments touching in merged masks form one instance. :func:`split_instance`
splits it between the instruments' shaft axes (from their expected part boxes), and
:func:`split_on_entries` between the shafts entering the view at the image border
(:func:`border_entries`). Both refine each shaft axis on the blob's
own pixels and refuse a split that is not shaft-like; head pixels (wrist, jaws) go to
the head beyond a shaft's distal end (:func:`head_distance2`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from mistool.kernels import split as kernels
from mistool.kernels.boxes import bits_runs, fit_runs_box, mask_runs
from mistool.kernels.split import DOT_SERIAL_MAX
from mistool.model import InstanceObservation, PartObservation, RotatedBox
from mistool.tracking.instances import unit_vector

__all__ = [
    "Axis",
    "border_entries",
    "border_runs",
    "BlobPixels",
    "SplitFit",
    "fit_split",
    "HeadAnchor",
    "head_distance2",
    "reference_boxes",
    "shaft_support",
    "split_instance",
    "split_on_entries",
    "split_pieces",
    "split_scored",
    "split_with_heads",
]

#: A split is kept only if each piece's pixels spread across its line by at most this
#: fraction of the shaft's width (RMS; a full rectangle of width w gives 0.29 w).
SPLIT_MAX_SPREAD = 0.45
#: ... and its lines differ in direction by at least this much (deg).
SPLIT_MIN_ANGLE_DEG = 8.0
#: A refitted axis turns at most this far (deg) from its expected direction in one frame.
SPLIT_MAX_TURN_DEG = 30.0
SPLIT_MAX_TURN_COS = math.cos(math.radians(SPLIT_MAX_TURN_DEG))
#: Rounds of "nearest axis, then refit each axis to its pixels".
SPLIT_REFIT_ROUNDS = 6
#: The refits use at most about this many shaft pixels (evenly subsampled).
SPLIT_FIT_POINTS = 1000
#: An axis's distal end may move past its expected end by this fraction of the
#: expected shaft length.
SPLIT_END_MARGIN = 0.1
#: Shafts from the border (``contiguous``): a shaft ends at the first gap of this many
#: half-widths between its pixels along its axis (beyond is another's).
SPLIT_CONTIGUOUS_GAP = 4.0
#: In a fit of at least this many axes, an axis's reach is cut back where another shaft
#: passes through its line (:data:`SPLIT_THROUGH_RADII`): a tool's expected shaft,
#: reaching across another's, took a wedge of it. Not in fits of two: every form tried
#: there renamed or lowered two-tool crossings (docs/tracking.md, tenth to thirteenth
#: passes). Fits of three got it in the fifteenth session (4 -> 3: the 108 crowded
#: sequences 95.55 -> 95.71%, 71 -> 74 at >= 95%; docs/tracking.md, "a sweep of the
#: identity step's constants").
SPLIT_THROUGH_AXES = 3
#: ... another shaft passes through an axis's line when its points lie on both sides of
#: it, farther than this many of the axis's half-widths (a shaft ending at the line, a V,
#: does not pass through) ...
SPLIT_THROUGH_RADII = 1.0
#: ... and the axis's points within that shaft's half-width, behind its distal end,
#: extend the axis's reach by at most this many of its half-widths beyond its other
#: points' reach.
SPLIT_THROUGH_CUT_RADII = 1.0

#: A shaft entering the view is seen on the image border over at least this many px.
ENTRY_MIN_PX = 6
#: Border runs of shaft pixels this close (px) are one shaft's entry (a hole, jitter).
ENTRY_MAX_GAP_PX = 8


@dataclass
class Axis:
    """A shaft's axis: a segment from ``end`` back along ``-direction`` for ``back`` px
    (``inf``: a half-line from the image border)."""

    end: np.ndarray
    """(2,) distal end, px."""
    direction: np.ndarray
    """(2,) unit direction, distal."""
    back: float
    """Length behind the end, px (``inf``: a half-line)."""


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


def distal_axis(boxes: dict[str, RotatedBox], shape: tuple[int, int] | None = None) -> Axis:
    """The shaft's axis from part boxes: the distal side is the one towards the other
    parts (a half-line from the border); without them, a segment whose distal end is
    the one farther inside the image of ``shape`` (H, W) (a shaft comes from the border)."""
    sb = boxes["shaft"]
    u = unit_vector(sb.angle_deg)
    c = np.array([sb.cx, sb.cy])
    others = [b for p, b in boxes.items() if p != "shaft"]
    if others:
        o = np.mean([[b.cx, b.cy] for b in others], axis=0)
        if (o - c) @ u < 0:
            u = -u
        back = math.inf
    else:
        back = sb.length
        if shape is not None:
            h, w = shape

            def inside(q: np.ndarray) -> float:  # distance to the nearest image border
                return float(min(q[0], w - 1 - q[0], q[1], h - 1 - q[1]))

            if inside(c - 0.5 * sb.length * u) > inside(c + 0.5 * sb.length * u):
                u = -u
    return Axis(c + 0.5 * sb.length * u, u, back)


def _pixels(part: PartObservation) -> np.ndarray:
    """(N, 2) float64 full-image (x, y) of a part's pixels, row by row."""
    xs, ys = _nonzero_xy(part.mask)
    return np.stack([xs + part.offset[0], ys + part.offset[1]], 1).astype(np.float64)


def _border_index_to_xy(i: int, ww: int, hh: int) -> tuple[float, float]:
    """Pixel (x, y) of index ``i`` along the image border walked as a loop: top, right,
    bottom, left."""
    i %= 2 * (ww - 1) + 2 * (hh - 1)
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


def border_runs(inst: InstanceObservation) -> list[tuple[np.ndarray, int]]:
    """Where the instance's shaft pixels lie on the image border: one run of border
    pixels per shaft entering the view (runs around a corner are one), as ``(ends,
    length)``: (3, 2) px of the run's first, middle and last pixel, and its length (px;
    at least :data:`ENTRY_MIN_PX`)."""
    shaft = inst.parts.get("shaft")
    if shaft is None or inst.image_shape is None:
        return []
    hh, ww = inst.image_shape
    x0, y0 = shaft.offset
    h, w = shaft.mask.shape
    if x0 > 0 and y0 > 0 and x0 + w < ww and y0 + h < hh:
        return []
    ends, lengths = kernels.border_runs(
        _mask_u8(shaft.mask), int(x0), int(y0), hh, ww, ENTRY_MIN_PX, ENTRY_MAX_GAP_PX
    )
    return list(zip(ends, lengths.tolist(), strict=True)) if len(lengths) else []


#: The direction of a shaft entering the view is fitted on at most about this many of
#: its pixels near the border (evenly subsampled).
ENTRY_FIT_POINTS = 4000


#: Directions tried for a shaft entering the view (every this many degrees).
ENTRY_STEP_DEG = 5.0
_ENTRY_DIRS = np.stack(
    [
        np.cos(np.radians(np.arange(0.0, 360.0, ENTRY_STEP_DEG))),
        np.sin(np.radians(np.arange(0.0, 360.0, ENTRY_STEP_DEG))),
    ]
)  # (2, K)


def _entry_lane(pts: np.ndarray, mid: np.ndarray, half: float) -> np.ndarray:
    """The points (N, 2) inside the straight lane from ``mid`` (a run's middle on the
    border), ``2 * half`` px wide, that holds the most of them (of the directions every
    :data:`ENTRY_STEP_DEG`): a shaft entering the view fills its own lane, while
    another tool's shaft passing near the entry only crosses it."""
    pts = _points(pts)
    inside = np.empty(len(pts), np.bool_)
    # (compiled: the float operations of numpy's (N, 2) @ (2, K) products, in one pass
    # per direction instead of (N, K) arrays)
    kernels.entry_lane(pts, float(mid[0]), float(mid[1]), half, _ENTRY_DIRS, inside)
    return pts[inside]


def border_entries(
    inst: InstanceObservation,
    runs: list[tuple[np.ndarray, int]] | None = None,
    *,
    lanes: bool = False,
) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """The shafts entering the view at the image border (:func:`border_runs`, or
    ``runs`` when already computed), as ``(point, inward direction, width)``, px: the
    direction is the principal axis of the shaft pixels near the run (``lanes``: of
    those in its fullest lane, :func:`_entry_lane`), the width the run's length across
    it. Empty unless there are two entries or more (one instrument
    per entry, unless two touch at the border)."""
    runs = border_runs(inst) if runs is None else runs
    if len(runs) < 2:
        return []
    shaft = inst.parts["shaft"]
    x0, y0 = shaft.offset
    h, w = shaft.mask.shape
    out = []
    for ends, length in runs:
        mid = ends[1]
        r = max(3.0 * length, 30.0)
        # the shaft pixels within r of the run: its window of the crop, then the disc
        xa, ya = max(int(mid[0] - r) - x0, 0), max(int(mid[1] - r) - y0, 0)
        xb, yb = min(int(mid[0] + r) + 1 - x0, w), min(int(mid[1] + r) + 1 - y0, h)
        xs, ys = _nonzero_xy(shaft.mask[ya:yb, xa:xb])
        step = max(1, len(ys) // ENTRY_FIT_POINTS)
        box = np.stack([xs[::step] + (xa + x0), ys[::step] + (ya + y0)], 1).astype(np.float64)
        rel = box - mid
        near = box[np.einsum("nd,nd->n", rel, rel) <= r * r]
        if len(near) < 3:
            continue
        if lanes:
            lane = _entry_lane(near, mid, 0.5 * length)
            near = lane if len(lane) >= 3 else near
        c, d = _principal_direction(near)
        if d @ (c - mid) < 0:
            d = -d
        tangent = ends[2] - ends[0]
        tn = float(np.hypot(*tangent))
        sin = abs(float(tangent[0] * d[1] - tangent[1] * d[0])) / tn if tn > 0 else 1.0
        out.append((mid, d, max(length * sin, 3.0)))
    return out if len(out) >= 2 else []


#: A shaft box is a stub seen at the image border (the shaft entering the view, its box
#: lying along the border) when its direction differs from the line from where it
#: enters to its head by more than this (deg) ...
STUB_ANGLE_DEG = 45.0


def reference_boxes(
    inst: InstanceObservation, runs: list[tuple[np.ndarray, int]]
) -> dict[str, RotatedBox]:
    """The instance's part boxes as a track's reference shape, with the shaft's box
    redrawn when the shaft is only a stub entering the view (``runs``: its
    :func:`border_runs`, one).

    A shaft that has just entered shows a sliver along the image border: its box lies
    along the border (:data:`STUB_ANGLE_DEG` off the line from the entry to the head),
    across the real shaft. The shaft's box is then the square of the entry's width on
    the line from the entry's middle towards the head's centre: a shaft as long as it is
    wide, entering where it does.
    """
    boxes = {p: o.box for p, o in inst.parts.items()}
    heads = [b for p, b in boxes.items() if p != "shaft"]
    if "shaft" not in boxes or len(runs) != 1 or not heads:
        return boxes
    ends, run_px = runs[0]
    (x0, y0), (mx, my), (x2, y2) = ends.tolist()
    # (plain floats: numpy's values; np.mean over the first axis sums from 0 in order;
    # np.hypot is the C library's, which math.hypot is not)
    sx = sy = 0.0
    for b in heads:
        sx += b.cx
        sy += b.cy
    dx, dy = sx / len(heads) - mx, sy / len(heads) - my
    norm = float(np.hypot(dx, dy))
    sb = boxes["shaft"]
    angle = math.degrees(math.atan2(dy, dx)) % 180.0
    diff = abs(sb.angle_deg - angle) % 180.0
    if norm <= 0 or min(diff, 180.0 - diff) <= STUB_ANGLE_DEG:
        return boxes
    dx, dy = dx / norm, dy / norm
    tx, ty = x2 - x0, y2 - y0
    tn = float(np.hypot(tx, ty))
    sin = abs(tx * dy - ty * dx) / tn if tn > 0 else 1.0
    width = max(float(run_px) * sin, sb.width, 1.0)
    half = 0.5 * width
    boxes["shaft"] = RotatedBox(mx + half * dx, my + half * dy, width, width, angle)
    return boxes


#: Where a shaft entering the view ends at its head (:func:`head_stop`): looked for
#: beyond this many shaft widths from the border ...
HEAD_STOP_FROM_WIDTHS = 1.0
#: ... in steps of a quarter width, over a window of one width along the half-line,
#: within half a width of it: the first window holding at least ``min_area_px`` head
#: pixels (wrist, jaws) and this many times as many as shaft pixels ...
HEAD_STOP_RATIO = 2.0
#: ... unless the shaft goes on beyond it (its lane at least half filled with shaft
#: pixels for this many widths, from within as many widths past the window: another
#: tool's head lying across it) ...
HEAD_STOP_ON_WIDTHS = 2.0
#: ... or on to another such window within this many widths, with at least half a
#: width of shaft between (the first head is another tool's, lying across this shaft
#: just short of its own).
HEAD_STOP_NEXT_WIDTHS = 3.0


def head_stop(
    heads: np.ndarray,
    shaft: np.ndarray,
    p: np.ndarray,
    d: np.ndarray,
    width: float,
    min_area_px: int,
) -> float | None:
    """How far (px) from ``p`` along ``d`` a shaft entering the view there, ``width`` px
    wide, ends at a head, or None: the first window of one width along the half-line
    where head pixels outnumber its shaft pixels (see :data:`HEAD_STOP_RATIO` and the
    constants after it).

    Args:
        heads: (N, 2) px, the blob's head pixels (every part but the shaft).
        shaft: (M, 2) px, the blob's shaft pixels.
        p: (2,) px, where the shaft enters the view.
        d: (2,) unit vector, its inward direction.
        width: its width, px.
        min_area_px: a head has at least this many pixels.
    """
    step = max(0.25 * width, 1.0)
    start = HEAD_STOP_FROM_WIDTHS * width
    least = max(min_area_px, 1)

    p0, p1, d0, d1 = float(p[0]), float(p[1]), float(d[0]), float(d[1])

    def lane_bins(q: np.ndarray) -> np.ndarray:  # (bin index along,) of q in the lane
        # (compiled: numpy's ``rel = q - p``, ``rel @ d``, ``(along - start) // step``)
        return kernels.lane_bins(_points(q), p0, p1, d0, d1, 0.5 * width, start, step)

    hi = lane_bins(heads)
    if len(hi) < least:
        return None
    si = lane_bins(shaft)
    n = int(max(hi.max(), si.max() if len(si) else 0)) + 5
    hb = np.bincount(hi, minlength=n)
    sb = np.bincount(si, minlength=n)
    window = np.ones(4, np.int64)  # four quarter-width bins: one width
    hw = np.convolve(hb, window)[3:]
    sw = np.convolve(sb, window)[3:]
    walls = np.flatnonzero((hw >= HEAD_STOP_RATIO * sw) & (hw >= least) & (hb > 0)).tolist()
    # how many bins in a row from each on are at least half filled with shaft pixels
    filled = sb >= 0.5 * step * width
    run = np.zeros(n + 1, np.int64)
    for j in range(n - 1, -1, -1):
        run[j] = run[j + 1] + 1 if filled[j] else 0
    on = int(round(4 * HEAD_STOP_ON_WIDTHS))
    for k, i in enumerate(walls):
        if (run[i + 1 : i + 1 + on] >= on).any():
            continue  # the shaft goes on beyond: another tool's head across it
        nxt = [j for j in walls[k + 1 :] if i + 4 < j <= i + 4 + 4 * HEAD_STOP_NEXT_WIDTHS]
        if nxt and (run[i + 1 : nxt[0]] >= 2).any():
            continue  # on to its own head, close beyond
        return start + i * step
    return None


def _head_pixels(inst: InstanceObservation) -> np.ndarray | None:
    """(N, 2) px of the instance's head pixels (every part but the shaft), or None."""
    parts = [o for name, o in inst.parts.items() if name != "shaft"]
    return np.concatenate([_pixels(o) for o in parts]) if parts else None


def split_on_entries(
    inst: InstanceObservation, entries: list[tuple[np.ndarray, np.ndarray, float]], min_area_px: int
) -> list[InstanceObservation] | None:
    """Split an instance between the shafts entering at ``entries`` (:func:`border_entries`):
    half-lines from the border. With two entries, each half-line ends where a head lies
    across it (:func:`head_stop`): a shaft ends at its head, and the pixels beyond (the
    other tool's shaft passing there) are not its."""
    x, y, w, h = inst.bbox_xywh
    reach = float(np.hypot(w, h))
    heads = _head_pixels(inst) if len(entries) == 2 else None
    shaft = _pixels(inst.parts["shaft"]) if heads is not None else None
    expected = []
    axes = []
    for p, d, width in entries:
        length = reach
        if heads is not None and shaft is not None:
            length = min(reach, head_stop(heads, shaft, p, d, width, min_area_px) or reach)
        c = p + 0.5 * length * d
        angle = math.degrees(math.atan2(d[1], d[0])) % 180.0
        expected.append({"shaft": RotatedBox(float(c[0]), float(c[1]), length, width, angle)})
        axes.append(Axis(p + length * d, d, math.inf))
    got = split_scored(inst, expected, min_area_px, axes, contiguous=True)
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
    :data:`SPLIT_MAX_SPREAD` x width) and no two axes are parallel side by side (two
    shafts on one line, pointing at each other, are fine). Wrist and clasper
    pixels go to the nearest head: the segment continuing a refitted shaft beyond its
    distal end (:func:`head_distance2`), or the expected box of that part moved with
    the shaft's distal end, whichever is nearer.

    Args:
        inst: the merged instance (parts with pixel crops).
        expected: per instrument, part -> expected box this frame (from its last frames
            apart from the others, moved by its velocity); each needs a ``"shaft"``.
        min_area_px: each instrument needs at least this many shaft pixels.

    Returns:
        One instance per instrument, same order, or None when the split is not
        trustworthy.
    """
    got = split_scored(inst, expected, min_area_px)
    return None if got is None else got[1]


@dataclass
class _Axes:
    """K shaft axes being refitted (arrays over the instruments)."""

    ends: np.ndarray  # (K, 2) distal ends, px
    dirs: np.ndarray  # (K, 2) unit directions, distal
    back: np.ndarray  # (K,) length behind the end, px (inf: half-line)
    radius: np.ndarray  # (K,) half-widths, px
    limit_end: np.ndarray  # (K, 2) expected distal ends (the end may pass it by a margin)
    start_dirs: np.ndarray  # (K, 2) the expected directions
    margin: np.ndarray  # (K,) that margin, px
    head_len: np.ndarray | None = None  # (K,) head lengths, px (None: HEAD_LENGTH_WIDTHS)
    keep_d2: float | None = None  # points farther (squared half-widths) from every axis:
    # another tool's (left out of the fit); None: every point is some axis's
    boxes: np.ndarray | None = None  # (K, 3, 5) the expected boxes (_initial_axes') ...
    others: list[list[str]] | None = None  # ... their other parts' names, in boxes[k, 1:]

    def nearest(self, pts: np.ndarray) -> np.ndarray:
        """(N,) index of each point's nearest axis; K for a point farther than
        ``keep_d2`` from all (when set)."""
        keep = self.keep_d2 is not None
        lab = np.empty(len(pts), np.intp)
        kernels.nearest_labels(
            _points(pts), _points(self.ends), _points(self.dirs), _values(self.back),
            _values(self.radius),
            self.keep_d2 if self.keep_d2 is not None else 0.0, keep, lab,
        )  # fmt: skip
        return lab

    def distance(self, pts: np.ndarray) -> np.ndarray:
        """(N, K) distances of points to the axes, in half-widths."""
        return _segment_distance(pts, self.ends, self.dirs, self.back, self.radius)


def _initial_axes(
    expected: list[dict[str, RotatedBox]],
    axes: list[Axis] | None,
    shape: tuple[int, int] | None = None,
) -> _Axes:
    """The instruments' axes before the refit: each shaft's :func:`distal_axis` (unless
    ``axes`` are given), its end moved past its expected one by its margin
    (:data:`SPLIT_END_MARGIN`), its half-width (at least 1 px) and head length
    (its other parts' extent along its axis x :data:`HEAD_SEEN_MARGIN`, between one
    shaft width and :data:`HEAD_LENGTH_WIDTHS` widths; the latter without them); one
    compiled pass
    (:func:`mistool.kernels.split.initial_axes`)."""
    k = len(expected)
    flat: list[float] = []  # (the (K, 3, 5) boxes made from one list: one conversion)
    counts = []
    others: list[list[str]] = []
    for e in expected:
        b = e["shaft"]
        flat += (b.cx, b.cy, b.length, b.width, b.angle_deg)
        names = []
        for p, b in e.items():
            if p != "shaft":
                flat += (b.cx, b.cy, b.length, b.width, b.angle_deg)
                names.append(p)
        n = len(names)
        flat += (0.0,) * (5 * (2 - n))
        counts.append(n)
        others.append(names)
    boxes = np.array(flat, np.float64).reshape(k, 3, 5)
    nother = np.array(counts, np.int64)
    ends0 = np.empty((k, 2))
    dirs = np.empty((k, 2))
    back = np.empty(k)
    if axes is not None:
        dirs[:] = [a.direction for a in axes]
        ends0[:] = [a.end for a in axes]
        back[:] = [a.back for a in axes]
    radius, margin, head_len = np.empty(k), np.empty(k), np.empty(k)
    hh, ww = shape if shape is not None else (-1, -1)
    kernels.initial_axes(
        boxes, nother, axes is not None, hh, ww, SPLIT_END_MARGIN, HEAD_LENGTH_WIDTHS,
        HEAD_SEEN_MARGIN, ends0, dirs, back, radius, margin, head_len,
    )  # fmt: skip
    return _Axes(
        ends=ends0 + margin[:, None] * dirs,
        dirs=dirs,
        back=back,
        radius=radius,
        limit_end=ends0,
        start_dirs=dirs.copy(),
        margin=margin,
        head_len=head_len,
        boxes=boxes,
        others=others,
    )


#: A head seen apart reaches at most this factor of its seen length beyond the shaft's
#: end in a split (its jaws may open, its wrist bend).
HEAD_SEEN_MARGIN = 1.25


def _principal_direction(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centroid (2,), unit direction of largest spread (2,)) of points (N, 2), in
    closed form (the 2x2 covariance's major axis)."""
    c, _, d = _centred_direction(q)
    return c, d


def _centred_direction(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_principal_direction` as ``(centroid, q - centroid, direction)``."""
    c = np.add.reduce(q, 0) / len(q)  # q.mean(0), without its Python-level overhead
    r = q - c
    sxx = float(r[:, 0] @ r[:, 0])
    syy = float(r[:, 1] @ r[:, 1])
    sxy = float(r[:, 0] @ r[:, 1])
    t = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
    return c, r, np.array([math.cos(t), math.sin(t)])


def _refit(ax: _Axes, pts: np.ndarray, weight: int, min_area_px: int, contiguous: bool) -> bool:
    """Rounds of nearest axis, then each axis refitted to its points, until no point
    changes axis; False when an axis keeps too few points (fewer than 3, or ``weight``
    times its points below ``min_area_px``).

    Each axis's direction is its points' principal axis (:func:`_centred_direction`),
    unless that turned more than :data:`SPLIT_MAX_TURN_DEG` from the expected axis (the
    spread of a stub entering the view, or of a shaft mostly under another, is across
    it); its distal end is the points' reach, never beyond the expected end plus its
    margin (``contiguous``: up to the first gap of :data:`SPLIT_CONTIGUOUS_GAP`
    half-widths along the axis, beyond is another's; with at least
    :data:`SPLIT_THROUGH_AXES` axes, not across another shaft passing through its line:
    :data:`SPLIT_THROUGH_RADII`). One compiled loop
    (:func:`mistool.kernels.split.refit_axes`), ``ax.ends`` and ``ax.dirs`` updated in
    place."""
    if len(pts) > DOT_SERIAL_MAX:  # (the fit's sample never is: SPLIT_FIT_POINTS)
        raise ValueError(f"_refit: {len(pts)} points, at most {DOT_SERIAL_MAX} (numpy's bits)")
    keep = ax.keep_d2 is not None
    through = SPLIT_THROUGH_RADII if len(ax.dirs) >= SPLIT_THROUGH_AXES else 0.0
    return bool(
        kernels.refit_axes(
            _points(pts), ax.ends, ax.dirs, ax.back, ax.radius, ax.limit_end,
            ax.start_dirs, ax.margin, ax.keep_d2 if ax.keep_d2 is not None else 0.0, keep,
            weight, min_area_px, contiguous, SPLIT_REFIT_ROUNDS, SPLIT_MAX_TURN_COS,
            SPLIT_CONTIGUOUS_GAP, through, SPLIT_THROUGH_CUT_RADII,
        )
    )  # fmt: skip


def _score(ax: _Axes, pts: np.ndarray) -> float | None:
    """The worst RMS distance of an axis's points to it (half-widths; a full rectangle
    gives 0.58), or None when a piece spreads more than :data:`SPLIT_MAX_SPREAD` widths
    (plus half a pixel) or two axes are near parallel side by side
    (one shaft cut in two strips, not two shafts on one line pointing at each other
    from opposite sides of the view: :func:`mistool.kernels.split.score_axes`)."""
    score = kernels.score_axes(
        _points(pts), ax.ends, ax.dirs, ax.back, ax.radius,
        ax.keep_d2 if ax.keep_d2 is not None else 0.0, ax.keep_d2 is not None,
        2.0 * SPLIT_MAX_SPREAD, SPLIT_MIN_ANGLE_DEG,
    )  # fmt: skip
    return None if score < 0.0 else float(score)


def _head_segments(
    name: str, ax: _Axes, expected: list[dict[str, RotatedBox]]
) -> tuple[list[np.ndarray], np.ndarray]:
    """The segments of each instrument's head for a head part ``name`` (its distances,
    in half-widths, are the least over its segments): its head segment
    (:func:`head_distance2`), and its expected box of that part moved with the shaft's
    distal end (its last shape seen apart: a bent wrist, open jaws). ``([ends, dirs,
    back, radius], row)``: (S, 2), (S, 2), (S,), (S,) segments and each one's
    instrument, head segments first, computed as the former numpy distances did."""
    # (plain floats: numpy's values, one operation at a time as its arrays did)
    radius = ax.radius.tolist()
    length = (
        [2.0 * HEAD_LENGTH_WIDTHS * r for r in radius]
        if ax.head_len is None
        else ax.head_len.tolist()
    )
    ends, dirs = ax.ends.tolist(), ax.dirs.tolist()
    s_ends = [
        (x + n * dx, y + n * dy) for (x, y), (dx, dy), n in zip(ends, dirs, length, strict=True)
    ]
    s_dirs, back, rad, rows = list(dirs), list(length), list(radius), list(range(len(dirs)))
    limit = ax.limit_end.tolist()
    for j, e in enumerate(expected):
        b = e.get(name)
        if b is None:
            continue
        t = math.radians(b.angle_deg)
        ux, uy = math.cos(t), math.sin(t)  # (unit_vector)
        h = 0.5 * b.length
        # the other parts move with their shaft's end
        cx = b.cx + (ends[j][0] - limit[j][0])
        cy = b.cy + (ends[j][1] - limit[j][1])
        s_ends.append((cx + h * ux, cy + h * uy))
        s_dirs.append((ux, uy))
        back.append(2 * h)
        rad.append(max(b.width / 2.0, 1.0))
        rows.append(j)
    seg = [np.array(s_ends), np.array(s_dirs), np.array(back), np.array(rad)]
    return seg, np.array(rows, np.int64)


#: A head (wrist and jaws) lies on its shaft's distal extension: from the shaft's end
#: forward for at most this many shaft widths (robotic: 2, laparoscopic: about 3.4).
HEAD_LENGTH_WIDTHS = 3.5


def head_distance2(p: np.ndarray, ax: _Axes) -> np.ndarray:
    """(N, K) squared distances of head pixels (N, 2) to each instrument's head segment
    (from its fitted shaft's distal end forward along its axis for
    :data:`HEAD_LENGTH_WIDTHS` shaft widths), in units of its shaft's half-width: a head
    is attached to the end of its own shaft, whatever shafts pass beside it."""
    return _head_d2_rows(p, ax).T


def _head_d2_rows(p: np.ndarray, ax: _Axes) -> np.ndarray:
    """:func:`head_distance2` as (K, N) rows."""
    length = 2.0 * HEAD_LENGTH_WIDTHS * ax.radius if ax.head_len is None else ax.head_len
    return segment_d2_rows(p, ax.ends + length[:, None] * ax.dirs, ax.dirs, length, ax.radius)


def segment_d2(
    p: np.ndarray, ends: np.ndarray, dirs: np.ndarray, back: np.ndarray, radius: np.ndarray
) -> np.ndarray:
    """(N, K) squared distances of points (N, 2) to K segments in units of each radius
    (the square of :func:`_segment_distance`): the transpose of :func:`segment_d2_rows`
    (a view; each segment's column is contiguous)."""
    return segment_d2_rows(p, ends, dirs, back, radius).T


def segment_d2_rows(
    p: np.ndarray, ends: np.ndarray, dirs: np.ndarray, back: np.ndarray, radius: np.ndarray
) -> np.ndarray:
    """(K, N) squared distances of points (N, 2) to K segments in units of each radius,
    one contiguous row per segment: the coordinates along and across each segment, the
    excess past its ends, no roots (:func:`mistool.kernels.split.segment_d2_rows`, the
    float operations of the former numpy product in their order)."""
    ends, dirs = _points(ends), _points(dirs)
    out = np.empty((len(ends), len(p)), np.float64)
    kernels.segment_d2_rows(_points(p), ends, dirs, _values(back), _values(radius), out)
    return out


def _points(p: np.ndarray) -> np.ndarray:
    """(N, 2) float64 C-contiguous (no copy when it is already)."""
    return np.ascontiguousarray(p, np.float64)


def _values(v: np.ndarray) -> np.ndarray:
    """(N,) float64 contiguous (no copy when it is already)."""
    return np.ascontiguousarray(v, np.float64)


def argmin_rows(d2: np.ndarray) -> np.ndarray:
    """(N,) ``d2.argmin(0)`` of (K, N) values (the first of equal minima, the first NaN),
    row by row: numpy's ``argmin`` over the first axis is ~20x slower for small K."""
    best = d2[0].copy()
    lab = np.zeros(d2.shape[1], np.intp)
    for j in range(1, len(d2)):
        nearer = d2[j] < best
        lab[nearer] = j
        np.minimum(best, d2[j], out=best)
    if np.isnan(best).any():  # (np.minimum keeps NaN; argmin takes the first NaN)
        return d2.argmin(0)
    return lab


def nearest_axis(
    p: np.ndarray, ends: np.ndarray, dirs: np.ndarray, back: np.ndarray, radius: np.ndarray
) -> np.ndarray:
    """(N,) index of the nearest of K segments (:func:`segment_d2`; ties to the lower
    index) for points (N, 2)."""
    lab = np.empty(len(p), np.intp)
    kernels.nearest_labels(
        _points(p), _points(ends), _points(dirs), _values(back), _values(radius), 0.0, False, lab
    )
    return lab


#: Shaft pixels are given to the nearest axis on a grid of cells this many px wide,
#: exactly (per pixel) only in cells next to a cell of another axis.
OWNER_CELL_PX = 8


def _owner_image(part: PartObservation, ax: _Axes) -> np.ndarray:
    """(h, w) index of the nearest axis (as :func:`nearest_axis`, K beyond ``keep_d2``) of
    every pixel of a part's crop, 255 off its mask: rasterised, the nearest axis of each
    :data:`OWNER_CELL_PX` cell's centre, refined per pixel only in the cells that border
    a cell of another axis (the regions are bounded by bisectors and parabolas, smooth on
    the scale of a cell). The split uses its runs (:func:`_shaft_pieces`); this paints
    them."""
    ry, rx0, rx1, n = _shaft_pieces(BlobPixels(_shaft_blob(part)), ax, len(ax.dirs) + 1)
    owner = np.full(part.mask.shape, 255, np.uint8)
    for j in range(len(n)):
        for y, a, b in zip(ry[j, : n[j]], rx0[j, : n[j]], rx1[j, : n[j]], strict=True):
            owner[y, a:b] = j
    return owner


def _shaft_blob(part: PartObservation) -> InstanceObservation:
    """An instance of one shaft part (for :func:`_owner_image`)."""
    return InstanceObservation(None, {"shaft": part}, (0.0, 0.0), part.area_px, (0, 0, 1, 1))


def _mask_u8(mask: np.ndarray) -> np.ndarray:
    """A bool or uint8 mask as C-contiguous uint8 (a view when it is already)."""
    m = np.ascontiguousarray(mask)
    return m.view(np.uint8) if m.dtype == np.bool_ else m.astype(np.uint8, copy=False)


def _nonzero_xy(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(xs, ys)`` int32 of a 2-D bool or uint8 mask's non-zero pixels, row by row:
    ``np.nonzero(mask)[::-1]`` by OpenCV's ``findNonZero``."""
    nz = cv2.findNonZero(mask.view(np.uint8))
    if nz is None:
        return np.empty(0, np.int32), np.empty(0, np.int32)
    xs, ys = nz.reshape(-1, 2).T
    return xs, ys


class BlobPixels:
    """A blob's part pixels, computed once and shared by every split hypothesis."""

    def __init__(self, inst: InstanceObservation) -> None:
        self.inst = inst
        self._cache: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._runs: tuple[np.ndarray, np.ndarray, np.ndarray, int] | None = None
        self._count = 0
        self._shape = (0, 0)
        self._samples: dict[int, np.ndarray] = {}  # shaft points by step (1: all)

    def shaft_runs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """The shaft crop's row runs, ``(ry, rx0, rx1, n)`` in raster order
        (:func:`mistool.kernels.boxes.mask_runs`: one pass over the mask, 8 px at a time
        where it does not change); the samples and the split's pieces come from them.
        A worker's part whose mask is still packed (``_packed``: the batch's bits, the
        mask's first bit there and its shape, :class:`mistool.parallel._SentPart`) gives
        them from its bits (:func:`mistool.kernels.boxes.bits_runs`), left packed."""
        if self._runs is None:
            part = self.inst.parts["shaft"]
            packed = part.__dict__.get("_packed")
            if packed is not None and packed[0].flags.writeable:
                bits, at, (h, w) = packed
                self._runs = bits_runs(bits, at, h, w)
                self._shape = (h, w)
            else:
                self._runs = mask_runs(_mask_u8(part.mask))
                self._shape = part.mask.shape
            ry, rx0, rx1, n = self._runs
            self._count = int((rx1[:n] - rx0[:n]).sum())
        return self._runs

    def shaft_shape(self) -> tuple[int, int]:
        """The shaft crop's (h, w) (a still-packed mask's without unpacking it)."""
        self.shaft_runs()
        return self._shape

    def _shaft_count(self) -> int:
        """How many shaft pixels the blob has."""
        self.shaft_runs()
        return self._count

    def shaft_points(self) -> np.ndarray:
        """(N, 2) float64 full-image (x, y) of the shaft's pixels, row by row."""
        return self._sample(1)

    def shaft_sample(self, max_points: int) -> tuple[np.ndarray, int]:
        """``(shaft_points()[::step], step)`` with ``step = len // max_points`` (at
        least 1): about ``max_points`` points, the others never converted (from the
        shaft's runs, :func:`mistool.kernels.split.run_points`)."""
        step = max(1, self._shaft_count() // max_points)
        return self._sample(step), step

    def _sample(self, step: int) -> np.ndarray:
        if step not in self._samples:
            part = self.inst.parts["shaft"]
            ry, rx0, rx1, n = self.shaft_runs()
            pts = np.empty((-(-self._count // step), 2), np.float64)
            x0, y0 = part.offset
            kernels.run_points(ry, rx0, rx1, n, int(x0), int(y0), step, pts)
            self._samples[step] = pts
        return self._samples[step]

    def get(self, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ys, xs) in the part's crop and (N, 2) float64 full-image (x, y) points, row
        by row (as ``np.nonzero``, ~10x slower on a 2-D mask than ``findNonZero``)."""
        if name not in self._cache:
            part = self.inst.parts[name]
            xs, ys = _nonzero_xy(part.mask)
            pts = np.stack([xs + part.offset[0], ys + part.offset[1]], 1).astype(np.float64)
            self._cache[name] = (ys, xs, pts)
        return self._cache[name]


@dataclass
class SplitFit:
    """A blob's shaft axes fitted for a split (:func:`fit_split`), before measuring."""

    score: float
    """The worst RMS distance of a shaft's pixels to its axis (half-widths); lower is
    better."""
    axes: _Axes
    expected: list[dict[str, RotatedBox]]


def fit_split(
    pixels: BlobPixels,
    expected: list[dict[str, RotatedBox]],
    min_area_px: int,
    axes: list[Axis] | None = None,
    contiguous: bool = False,
    min_tracks: int = 2,
    keep_d2: float | None = None,
) -> SplitFit | None:
    """Fit one shaft axis per instrument to a blob's shaft pixels; None when the split is
    not shaft-like (see :func:`split_instance`).

    Args:
        pixels: the blob's pixels (:class:`BlobPixels`).
        expected: per instrument, part -> expected box (each with a ``"shaft"``).
        min_area_px: each instrument needs at least this many shaft pixels.
        axes: the shafts' axes when not from ``expected`` (:func:`distal_axis`).
        contiguous: each shaft ends at the first gap of :data:`SPLIT_CONTIGUOUS_GAP`
            half-widths in its pixels along its axis (shafts entering from the border,
            their ends unknown).
        min_tracks: fewer instruments than this: None (one, when others in the blob
            take only head pixels, :func:`split_with_heads`).
        keep_d2: shaft pixels farther than this (squared half-widths) from every axis
            are left out of the fit (another tool's, with no axis here); None: none.
    """
    inst = pixels.inst
    if (
        "shaft" not in inst.parts
        or len(expected) < min_tracks
        or any("shaft" not in e for e in expected)
    ):
        return None
    # the fits need no more points than this
    fit_pts, step = pixels.shaft_sample(SPLIT_FIT_POINTS)
    ax = _initial_axes(expected, axes, inst.image_shape)
    ax.keep_d2 = keep_d2
    if not _refit(ax, fit_pts, step, min_area_px, contiguous):
        return None
    score = _score(ax, fit_pts)
    return None if score is None else SplitFit(score, ax, expected)


def split_pieces(
    pixels: BlobPixels, fit: SplitFit, min_area_px: int
) -> list[InstanceObservation] | None:
    """The blob's pixels given to the nearest fitted instrument, each piece measured
    (Algorithm 1); None when a piece has no shaft left."""
    got = split_with_heads(pixels, fit, min_area_px, [])
    return None if got is None else got[0]


@dataclass
class HeadAnchor:
    """An instrument in a blob with no shaft of its own there (its shaft out of view or
    never seen): it can take only head pixels, those nearest to where its head is
    expected."""

    boxes: dict[str, RotatedBox]
    """Its expected head part boxes (may be empty) ..."""
    centre: np.ndarray
    """... else (2,) px where it is expected ..."""
    radius: float
    """... and its size there (px)."""

    def distance2(self, name: str, p: np.ndarray) -> np.ndarray:
        """(N,) squared distances of part ``name``'s pixels (N, 2) to it, in units of
        the box's half-width (the least over :meth:`segments`; without boxes, to
        ``centre`` in units of ``radius``)."""
        seg = self.segments(name)
        if seg is None:
            d = p - self.centre
            return np.einsum("nd,nd->n", d, d) / (self.radius * self.radius)
        return np.minimum.reduce(segment_d2_rows(p, *seg))

    def segments(self, name: str) -> list[np.ndarray] | None:
        """The segments of part ``name``'s expected box, or of all its boxes when it
        has none of that part: ``[ends, dirs, back, radius]`` ((B, 2), (B, 2), (B,),
        (B,)); None without boxes."""
        boxes = [self.boxes[name]] if name in self.boxes else list(self.boxes.values())
        if not boxes:
            return None
        u = np.array([unit_vector(b.angle_deg) for b in boxes])
        h = np.array([0.5 * b.length for b in boxes])
        c = np.array([[b.cx, b.cy] for b in boxes])
        r = np.array([max(b.width / 2.0, 1.0) for b in boxes])
        return [c + h[:, None] * u, u, 2 * h, r]


def split_with_heads(
    pixels: BlobPixels, fit: SplitFit, min_area_px: int, anchors: list[HeadAnchor]
) -> tuple[list[InstanceObservation], list[InstanceObservation | None]] | None:
    """:func:`split_pieces`, some head pixels going to ``anchors`` (instruments without
    an expected shaft) when they lie nearer to them, and, with one anchor, the shaft
    pixels the fit left out (``fit.axes.keep_d2``) to it: ``(pieces, head pieces)``, one
    per anchor (None: no part of at least ``min_area_px`` pixels); None when a fitted
    instrument's piece has no shaft left.

    Each part's pixels get the index of their piece in a label image (the shaft's:
    :func:`_shaft_pieces`; a head part's: its nearest head, :func:`_head_labels`), whose
    row runs per index are measured (Algorithm 1, :func:`_measure_runs`)."""
    inst = pixels.inst
    k = len(fit.expected)
    n = k + len(anchors)
    got: dict[str, list[_Measured | None]] = {}
    if "shaft" in inst.parts:
        # (shaft pixels far from every axis, index k: a lone anchor's shaft)
        runs = _shaft_pieces(pixels, fit.axes, k + (len(anchors) == 1))
        got["shaft"] = _measure_runs("shaft", runs, inst.parts["shaft"].offset, min_area_px)
    if any(m is None for m in got.get("shaft", [None])[:k]):
        return None
    for name, part in inst.parts.items():
        if name == "shaft":
            continue
        got[name] = _measure_runs(
            name, _head_runs(part, fit.axes, fit.expected, anchors), part.offset, min_area_px
        )
    pieces: list[dict[str, _Measured]] = [{} for _ in range(n)]
    for name in inst.parts:  # (the blob's order of parts)
        for j, m in enumerate(got[name]):
            if m is not None:
                pieces[j][name] = m
    shape = inst.image_shape
    return (
        [_instance(parts, shape) for parts in pieces[:k]],
        [_instance(parts, shape) if parts else None for parts in pieces[k:]],
    )


def _head_runs(
    part: PartObservation,
    ax: _Axes,
    expected: list[dict[str, RotatedBox]],
    anchors: list[HeadAnchor],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The row runs of a head part's pixels nearest to each head (the instruments', then
    the anchors'; :func:`_head_labels`), ``(ry, rx0, rx1, count)`` per head, in one
    compiled call: :func:`mistool.kernels.split.head_part_runs` (its segments from
    :func:`_initial_axes`' boxes) without anchors, else
    :func:`mistool.kernels.split.head_cut_runs` of :func:`_head_labels`' segments."""
    ox, oy = int(part.offset[0]), int(part.offset[1])
    if anchors or ax.boxes is None or ax.others is None or ax.head_len is None:
        seg = _head_arguments(part, ax, expected, anchors)
        return kernels.head_cut_runs(_mask_u8(part.mask), ox, oy, *seg, len(seg[-1]))
    name = part.part
    which = np.array([o.index(name) + 1 if name in o else 0 for o in ax.others], np.int64)
    return kernels.head_part_runs(
        _mask_u8(part.mask), ox, oy, ax.boxes, which, _points(ax.ends), _points(ax.dirs),
        _values(ax.radius), _values(ax.head_len), _points(ax.limit_end),
    )  # fmt: skip


def _head_arguments(
    part: PartObservation,
    ax: _Axes,
    expected: list[dict[str, RotatedBox]],
    anchors: list[HeadAnchor],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`mistool.kernels.split.head_labels`' heads for a head part: ``(ends, dirs,
    back, radius, row, centres, is_centre)`` (see :func:`_head_labels`)."""
    segs, rows = _head_segments(part.part, ax, expected)
    parts = [segs]
    row = [rows]
    centres = np.zeros((len(ax.dirs) + len(anchors), 3))
    # (every instrument has its head segment: only an anchor without boxes is a centre)
    centre = [False] * len(ax.dirs)
    for a, anchor in enumerate(anchors, start=len(ax.dirs)):
        seg = anchor.segments(part.part)
        centre.append(seg is None)
        if seg is None:
            centres[a] = (anchor.centre[0], anchor.centre[1], anchor.radius * anchor.radius)
            continue
        parts.append(seg)
        row.append(np.full(len(seg[2]), a))
    if len(parts) == 1:  # (no anchor's boxes: the arrays as they are)
        ends, dirs, back, radius = segs
    else:
        ends, dirs, back, radius = (np.concatenate(c) for c in zip(*parts, strict=True))
    rows = np.concatenate(row).astype(np.int64) if len(row) > 1 else row[0]
    is_centre = np.array(centre, np.bool_)
    return (_points(ends), _points(dirs), _values(back), _values(radius), rows, centres, is_centre)


def _head_labels(
    part: PartObservation,
    ax: _Axes,
    expected: list[dict[str, RotatedBox]],
    anchors: list[HeadAnchor],
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray, int], np.ndarray]:
    """A head part's row runs (:func:`mistool.kernels.boxes.mask_runs`) and the index of
    the nearest head of each of its pixels, in the runs' order: the instruments'
    (:func:`_head_segments`), then the anchors' (their boxes' segments, or their
    centre), the first of equal distances (compiled:
    :func:`mistool.kernels.split.head_labels`)."""
    runs = mask_runs(_mask_u8(part.mask))
    px, py = kernels.run_pixels(*runs, int(part.offset[0]), int(part.offset[1]))
    lab = np.empty(len(px), np.int64)
    kernels.head_labels(px, py, *_head_arguments(part, ax, expected, anchors), lab)
    return runs, lab


#: A piece's part measured, with its pixels' full-image coordinate sums (its instance's
#: centroid): ``(obs, sum of x, sum of y)`` (a plain tuple: one per piece and part).
_Measured = tuple[PartObservation, int, int]


def _shaft_pieces(
    pixels: BlobPixels, ax: _Axes, nlab: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The row runs of each axis's shaft pixels (index ``j < nlab``; the pixels of
    :func:`_owner_image` labelled ``j``), from the shaft's runs
    (:meth:`BlobPixels.shaft_runs`) without an image
    (:func:`mistool.kernels.split.shaft_label_runs`)."""
    part = pixels.inst.parts["shaft"]
    ry, rx0, rx1, n = pixels.shaft_runs()
    h, w = pixels.shaft_shape()
    return kernels.shaft_label_runs(
        ry, rx0, rx1, n, h, w, int(part.offset[0]), int(part.offset[1]), _points(ax.ends),
        _points(ax.dirs), _values(ax.back), _values(ax.radius),
        ax.keep_d2 if ax.keep_d2 is not None else 0.0, ax.keep_d2 is not None, OWNER_CELL_PX,
        nlab,
    )  # fmt: skip


def _measure_runs(
    name: str,
    runs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    offset: tuple[int, int],
    min_area_px: int,
) -> list[_Measured | None]:
    """Part ``name`` of each piece from its row runs (``(ry, rx0, rx1, count)`` per
    piece, crop coordinates at ``offset``): Algorithm 1 of the runs
    (:func:`mistool.kernels.boxes.fit_runs_box`, as :func:`geometry.fit_part` of their
    mask), None when no pixel is kept."""
    ry, rx0, rx1, count = runs
    ox, oy = int(offset[0]), int(offset[1])
    out: list[_Measured | None] = []
    for j, n in enumerate(count.tolist()):
        if not n:
            out.append(None)
            continue
        # (geometry.fit_of's steps without its PartFit; the box from the rows' hull
        # without tracing the outline where that gives the traced box's bits)
        (area, x0, y0, sx, sy), kept, (cx, cy, length, width, angle), corners = fit_runs_box(
            ry[j], rx0[j], rx1[j], n, min_area_px, ox, oy
        )
        if area == 0:
            out.append(None)
            continue
        box = RotatedBox(cx=cx, cy=cy, length=length, width=width, angle_deg=angle)
        origin = (ox + x0, oy + y0)
        obs = PartObservation(name, box, corners, area, kept, origin)
        out.append((obs, sx + area * origin[0], sy + area * origin[1]))
    return out


def _instance(parts: dict[str, _Measured], shape: tuple[int, int] | None) -> InstanceObservation:
    """:func:`~mistool.tracking.instances.make_instance` of measured parts: the same
    values (its centroid's sums are exact integers in float64, so the parts' own sums
    give its bits)."""
    area = sx = sy = 0  # (exact integers: any order gives the same sums and bounds)
    x0 = y0 = 1 << 62
    x1 = y1 = -(1 << 62)
    obs = {}
    for name, (o, mx, my) in parts.items():
        obs[name] = o
        area += o.area_px
        sx += mx
        sy += my
        ox, oy = o.offset
        h, w = o.mask.shape
        x0, y0 = min(x0, ox), min(y0, oy)
        x1, y1 = max(x1, ox + w), max(y1, oy + h)
    return InstanceObservation(
        label=None,
        parts=obs,
        centroid_px=(float(sx) / area, float(sy) / area),
        area_px=area,
        bbox_xywh=(int(x0), int(y0), int(x1 - x0), int(y1 - y0)),
        image_shape=shape,
    )


def shaft_support(pixels: BlobPixels, box: RotatedBox) -> int:
    """How many of the blob's shaft pixels lie in ``box`` widened to twice its width and
    lengthened by its width (where an expected shaft would be seen); 0 for a blob with
    no shaft (tools' heads meeting while their shafts are hidden)."""
    if "shaft" not in pixels.inst.parts:
        return 0
    pts = pixels.shaft_points()
    u = unit_vector(box.angle_deg)
    rel = pts - (box.cx, box.cy)
    along = np.abs(rel @ u)
    across = np.abs(rel[:, 1] * u[0] - rel[:, 0] * u[1])
    return int(np.count_nonzero((along <= 0.5 * box.length + box.width) & (across <= box.width)))


def split_scored(
    inst: InstanceObservation,
    expected: list[dict[str, RotatedBox]],
    min_area_px: int,
    axes: list[Axis] | None = None,
    contiguous: bool = False,
) -> tuple[float, list[InstanceObservation]] | None:
    """:func:`split_instance` and its score (see :class:`SplitFit`); arguments as
    :func:`fit_split`."""
    pixels = BlobPixels(inst)
    fit = fit_split(pixels, expected, min_area_px, axes, contiguous)
    if fit is None:
        return None
    pieces = split_pieces(pixels, fit, min_area_px)
    return None if pieces is None else (fit.score, pieces)
