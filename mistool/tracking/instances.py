"""Instruments in one frame: instances and their parts (``observe_frame``).

Two ways to tell instruments apart, chosen by the config:

- **Own label values** (``[[instrument]]`` tables): each instrument's parts come from its
  own value ranges; the instrument's name is its label. This is the paper's setting.
- **Merged masks** (no ``[[instrument]]`` tables, EndoVis'17 style: every instrument
  shares the part values): instances are the connected components of the *whole*
  instrument (shaft + wrist + clasper pixels together), bridged over gaps of up to
  :data:`MERGE_GAP_PX` pixels so a clasper one pixel away from its shaft stays one
  instrument. Components smaller than ``config.min_area_px`` are specks and are dropped.
  The other components are grouped into instruments by the rules of
  :data:`REACH_RULES` (one table: which kind of piece joins which kind of group, and how
  far it may reach), then pieces an occluder cut off join by shaft geometry
  (:func:`join_by_axis`: a shaft-only piece continuing another's shaft axis, a head on
  the distal extension of a shaft's axis).

Every part's box is Algorithm 1 (:mod:`mistool.geometry`) over all of that part's pixels
in the instance, after dropping specks smaller than ``config.min_area_px``. Everything
here is pure and per frame (it runs in worker processes).

The pixels are read once (:func:`scan_labels`: the foreground bounds, then the runs of
equal values in them); components, their labels, bounds and pixel counts, and each
part's Algorithm 1 come from those runs in compiled kernels
(:mod:`mistool.kernels.instances`, :mod:`mistool.kernels.boxes`) giving what OpenCV's
masks, ``connectedComponents`` and ``findContours`` gave, bit for bit
(``tests/test_instances_speed.py``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from mistool.config import Config
from mistool.errors import MaskFormatError
from mistool.geometry import as_cv_labels, fit_part
from mistool.model import PARTS, InstanceObservation, PartObservation, RotatedBox

__all__ = [
    "REACH_RULES",
    "ReachRule",
    "angle_diff_deg",
    "foreground_bounds",
    "make_instance",
    "observe_frame",
    "part_observation",
    "unit_vector",
]

#: Merged masks: pixels of one instrument separated by at most this many background
#: pixels are joined into one instance.
MERGE_GAP_PX = 1


@dataclass(frozen=True)
class ReachRule:
    """When a group of components (a *piece*) joins another group (a *target*).

    A *shaft* group holds at least ``min_area_px`` shaft pixels; a *head* group does not
    (jaws, a wrist). The piece joins when the gap between the two groups' pixels is at
    most ``max(base_px, frac * sqrt(area))`` px (``area``: the target's or the piece's
    group area, per ``scale_of``), capped at ``cap_px``.
    """

    name: str
    """What the rule is for (documentation)."""
    piece: str
    """``"shaft"``, ``"head"``, ``"inner head"`` (a head not touching the image border:
    its shaft cannot be beyond the border, so an occluder hides it) or ``"border head"``
    (a head touching the border: maybe a tool entering head first)."""
    target: str
    """``"shaft"`` or ``"head"``."""
    base_px: float
    """Smallest reach (px)."""
    frac: float = 0.0
    """Reach per sqrt(area) px."""
    scale_of: str = "target"
    """Whose area scales the reach: ``"target"`` or ``"piece"``."""
    cap_px: float = math.inf
    """Largest reach (px)."""
    max_area_ratio: float = math.inf
    """The piece's area must be less than this fraction of the target's."""

    def reach(self, piece_area: float, target_area: float) -> float:
        """The rule's reach (px) for groups of these areas (px)."""
        area = target_area if self.scale_of == "target" else piece_area
        return min(self.cap_px, max(self.base_px, self.frac * math.sqrt(area)))


#: Grouping fragments into instruments (merged masks), applied in this order; within a
#: rule the nearest piece-target pair joins first, and a group grows as pieces join it.
REACH_RULES: tuple[ReachRule, ...] = (
    # a small shaft piece next to a much larger one (a shaft cut by a hole or jitter)
    ReachRule("shaft fragment", "shaft", "shaft", base_px=30.0, max_area_ratio=0.25),
    # open jaws, a clasper cut in pieces: not new instruments
    ReachRule("head of a shaft", "inner head", "shaft", base_px=30.0, frac=0.8),
    # a head at the image border may be a tool entering head first (its shaft beyond
    # the border): it joins a shaft only from near
    ReachRule("head at the border", "border head", "shaft", base_px=30.0),
    # a head inside the view whose shaft an occluder hides (a speck reaches little)
    ReachRule("head cut off", "inner head", "shaft", 0.0, 2.5, "piece", cap_px=100.0),
    # the two jaws of an open clasper entering the view head first: larger heads first
    ReachRule("heads of one tool", "head", "head", base_px=60.0, frac=0.8, max_area_ratio=1.0),
)

#: Merged masks: a shaft-only piece whose axis continues another instance's shaft (angles
#: within this many degrees, centre within half a shaft width of that axis) is the same
#: instrument, cut in two by an occluder.
CUT_SHAFT_ANGLE_DEG = 6.0
#: Merged masks: a piece without a shaft whose centre lies on the distal extension of a
#: shaft's axis (within one shaft width of the axis, at most this many shaft widths past
#: its distal end) is that instrument's head, cut off by an occluder.
HEAD_AXIS_REACH = 3.0
#: ... unless the host already shows that head part at least this fraction of the
#: piece's size (its own head); a crumb of a head smaller than that joins.
HEAD_CRUMB_FRAC = 0.25


def unit_vector(angle_deg: float) -> np.ndarray:
    """(2,) unit vector of a direction in degrees (from +x towards +y)."""
    t = math.radians(angle_deg)
    return np.array([math.cos(t), math.sin(t)])


def angle_diff_deg(a: float, b: float) -> float:
    """Difference of two undirected directions (deg), in [0, 90]."""
    d = abs(a - b) % 180.0
    return min(d, 180.0 - d)


def _check_labels(labels: np.ndarray) -> np.ndarray:
    arr = np.asarray(labels)
    if arr.ndim != 2:
        raise MaskFormatError(
            f"expected a single-channel (H, W) label image, got shape {arr.shape}"
        )
    try:
        return as_cv_labels(arr)
    except ValueError as exc:
        raise MaskFormatError(f"label image: {exc}") from None


def part_observation(
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
        mask=fit.kept,
        offset=fit.offset,
    )


def _foreground(img: np.ndarray) -> tuple[int, int, int, int]:
    """(x, y, w, h) bounds of the non-zero pixels of a C-contiguous image."""
    from mistool.kernels.instances import foreground

    x, y, w, h = foreground(img)
    return int(x), int(y), int(w), int(h)


@dataclass(frozen=True)
class LabelRuns:
    """A label image's runs of equal non-zero values within its foreground bounds (what
    :func:`observe_frame` and :func:`mistool.parallel.unknown_values` read instead of the
    pixels)."""

    bounds: tuple[int, int, int, int]
    """``(x, y, w, h)`` of the non-zero pixels (:func:`foreground_bounds`)."""
    ry: np.ndarray
    """(>= n,) int32 run rows, relative to the bounds' top."""
    rx0: np.ndarray
    """(>= n,) int32 first column of each run, relative to the bounds' left."""
    rx1: np.ndarray
    """(>= n,) int32 column after each run's last."""
    rv: np.ndarray
    """(>= n,) int32 each run's value."""
    n: int
    """Number of runs (raster order)."""
    shape: tuple[int, int]
    """``(H, W)`` of the label image."""
    dtype: np.dtype
    """The label image's dtype as OpenCV saw it (:func:`mistool.geometry.as_cv_labels`)."""


def scan_labels(labels: np.ndarray, bounds: tuple[int, int, int, int] | None = None) -> LabelRuns:
    """The runs of a label image: one pass over it (rows of background passed over 64
    bytes at a time), or over its foreground ``bounds`` when given.

    Raises:
        MaskFormatError: if ``labels`` is not a 2-D integer image.
    """
    img = np.ascontiguousarray(_check_labels(labels))
    shape = (int(img.shape[0]), int(img.shape[1]))
    if bounds is not None and (bounds[2] == 0 or bounds[3] == 0):
        none = np.zeros(0, np.int32)
        return LabelRuns(bounds, none, none, none, none, 0, shape, img.dtype)
    box, ry, rx0, rx1, rv, n = _kernels().label_runs(img, bounds)
    return LabelRuns(box, ry, rx0, rx1, rv, int(n), shape, img.dtype)


def make_instance(
    label: str | None, parts: dict[str, PartObservation], shape: tuple[int, int] | None = None
) -> InstanceObservation:
    """An instance from its part observations (centroid, area and bounds of all pixels)."""
    area = sum(p.area_px for p in parts.values())
    sx = sy = 0.0
    x0 = y0 = math.inf
    x1 = y1 = -math.inf
    for p in parts.values():
        # the pixels' coordinate sums, exact integers (compiled: one pass over the mask)
        mx, my = _kernels().mask_sums(np.ascontiguousarray(p.mask).view(np.uint8))
        sx += float(mx) + p.offset[0] * p.area_px
        sy += float(my) + p.offset[1] * p.area_px
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


def foreground_bounds(labels: np.ndarray) -> tuple[int, int, int, int]:
    """``(x, y, w, h)`` bounds of the non-zero pixels of a label image (``w = h = 0``
    when there is none): every part pixel, and every label value but 0, is inside.

    Raises:
        MaskFormatError: if ``labels`` is not a 2-D integer image.
    """
    return _foreground(np.ascontiguousarray(_check_labels(labels)))


def observe_frame(
    labels: np.ndarray | None,
    config: Config,
    *,
    bounds: tuple[int, int, int, int] | None = None,
    runs: LabelRuns | None = None,
) -> list[InstanceObservation]:
    """Every instrument in one label image, with Algorithm 1's box for each visible part.

    Pure and thread-safe.

    Args:
        labels: (H, W) integer label image (uint8/uint16, or uint32 packed RGB when
            ``config.colour_masks``); None when ``runs`` are given (they are all that is
            read then).
        config: part value ranges, instruments, ``min_area_px``.
        bounds: :func:`foreground_bounds` of ``labels`` when the caller has them.
        runs: :func:`scan_labels` of ``labels`` when the caller has them.

    Returns:
        With ``config.instruments``: one observation per instrument that has a visible
        part, in config order, ``label`` set. Without: one per instrument found (see the
        module docstring), largest first, ``label`` None.

    Raises:
        MaskFormatError: if ``labels`` is not a 2-D integer image.
    """
    if runs is None:
        if labels is None:
            raise TypeError("observe_frame: give labels or runs")
        runs = scan_labels(labels, bounds)
    if runs.n == 0:  # (every part pixel is non-zero: the runs cover them all)
        return []
    if config.instruments:
        return _own_labels(runs, config)
    return _merged(runs, config)


def _value_range(rng: tuple[int, int], dtype: np.dtype) -> tuple[int, int]:
    """A part's inclusive value range as ``range_mask`` clips it to the image's dtype
    (empty: lo > hi)."""
    limits = _LIMITS.get(dtype)
    if limits is None:
        info = np.iinfo(dtype)
        limits = _LIMITS[dtype] = (int(info.min), int(info.max))
    return max(int(rng[0]), limits[0]), min(int(rng[1]), limits[1])


#: (min, max) of the label images' dtypes (``np.iinfo`` costs ~10 us).
_LIMITS: dict[np.dtype, tuple[int, int]] = {}


#: ``fit_parts``' members for runs all labelled 0: every run.
_ALL = np.ones(1, np.bool_)
#: ... and for runs labelled 0 or 1 (one component): every part pixel.
_BOTH = np.ones(2, np.bool_)


def _fit_instance(
    runs: LabelRuns,
    name: str | None,
    parts: list[str],
    ranges: np.ndarray,
    label: np.ndarray,
    members: np.ndarray,
    min_area: int,
) -> InstanceObservation | None:
    """Algorithm 1 of the pixels of ``runs`` with a ``label`` among ``members`` and a value
    in each part's range (``ranges``, (P, 2) for the P <= 3 names ``parts``), and the
    instance they make (:func:`make_instance`'s centroid and bounds), in one compiled
    call (:func:`mistool.kernels.instances.fit_parts`); None when no pixel is left."""
    fx, fy = runs.bounds[0], runs.bounds[1]
    info, boxes, corners, crops, centroid, (found, area, x, y, w, h), bits = _kernels().fit_parts(
        runs.ry, runs.rx0, runs.rx1, runs.rv, label, runs.n, ranges, members, min_area, fx, fy
    )
    if found == 0:
        return None
    # the frozen dataclasses made by filling their dicts: their __init__ sets each field
    # through object.__setattr__ (~5 us a frame of two instruments); the box's checks
    # are kept (RotatedBox raises as before). A part also keeps its mask's packed bits
    # (``_bits``: the mask and ``np.packbits`` of it, set by the kernel from the runs),
    # which a worker sends (``parallel.pack_frames``) instead of packing the mask again.
    fits = {}
    for k, ((size, px, py, _, _), box) in enumerate(
        zip(info.tolist(), boxes.tolist(), strict=True)
    ):
        if size:
            part = parts[k]
            cx, cy, length, width, angle = box
            if not (length >= width and 0.0 <= angle < 180.0):
                RotatedBox(*box)  # (raises)
            rbox = _new(RotatedBox)
            rbox.__dict__.update(cx=cx, cy=cy, length=length, width=width, angle_deg=angle)
            obs = _new(PartObservation)
            mask = crops[k]
            obs.__dict__.update(
                part=part, box=rbox, corners=corners[k], area_px=size, mask=mask,
                offset=(px, py), _bits=(mask, bits[k]),
            )  # fmt: skip
            fits[part] = obs
    inst = _new(InstanceObservation)
    inst.__dict__.update(
        label=name, parts=fits, centroid_px=centroid, area_px=area, bbox_xywh=(x, y, w, h),
        image_shape=runs.shape,
    )  # fmt: skip
    return inst


_new = object.__new__


def _kernels() -> Any:
    """:mod:`mistool.kernels.instances`, imported at the first frame (numba, and with it
    SciPy, is not for a program that only imports mistool, such as the viewer at its
    start)."""
    global _KERNELS
    if _KERNELS is None:
        from mistool.kernels import instances as kernels

        _KERNELS = kernels
    return _KERNELS


_KERNELS: Any = None


def _own_labels(runs: LabelRuns, config: Config) -> list[InstanceObservation]:
    """One instance per config instrument with a visible part (own label values)."""
    label = np.zeros(max(runs.n, 1), np.int32)
    out = []
    for spec in config.instruments:
        names = [p for p in PARTS if p in spec.parts and spec.parts[p][1] > 0]
        if not names:
            continue
        ranges = np.array([_value_range(spec.parts[p], runs.dtype) for p in names], np.int64)
        inst = _fit_instance(runs, spec.name, names, ranges, label, _ALL, config.min_area_px)
        if inst is not None:
            out.append(inst)
    return out


class _LazyLabels:
    """The component label image of the dilated union, painted when first sliced (only
    the pixel gap between two nearby groups needs it)."""

    def __init__(self, runs: LabelRuns, label: np.ndarray, stats: np.ndarray) -> None:
        self._runs = runs
        self._label = label
        self._stats = stats
        self._img: np.ndarray | None = None

    def chamfer_gap(
        self, a: list[int], b: list[int], box_a: list[int], box_b: list[int], reach: int
    ) -> float:
        """:func:`mistool.kernels.instances.chamfer_gap` of groups ``a`` and ``b`` in the
        window :func:`_pixel_gap` measures in."""
        r = self._runs
        _, _, w, h = r.bounds
        x0, y0, x1, y1 = _gap_window(box_a, box_b, reach)
        in_a = np.zeros(len(self._stats), np.bool_)
        in_a[a] = True
        in_b = np.zeros(len(self._stats), np.bool_)
        in_b[b] = True
        return float(
            _kernels().chamfer_gap(
                r.ry, r.rx0, r.rx1, self._label, r.n, in_a, in_b, x0, y0, x1, y1, w, h
            )
        )

    def __getitem__(self, key: Any) -> np.ndarray:
        if self._img is None:
            from mistool.kernels.instances import paint_components

            r = self._runs
            _, _, w, h = r.bounds
            self._img = paint_components(r.ry, r.rx0, r.rx1, self._label, r.n, w, h)
        return self._img[key]


def _merged_parts(config: Config, dtype: np.dtype) -> tuple[list[str], np.ndarray, int]:
    """The parts merged masks show (their names, their value ranges as
    :func:`_value_range` clips them to ``dtype``, (P, 2) int64; the shaft's index or -1),
    kept for the last config and dtype asked (a sequence's frames share them)."""
    global _MERGED_PARTS
    have = _MERGED_PARTS  # (one read: another thread may replace it)
    if have[0] is config and have[1] == dtype:
        return have[2]
    names = [p for p in PARTS if p in config.parts and config.parts[p][1] > 0]
    ranges = np.array([_value_range(config.parts[p], dtype) for p in names], np.int64)
    got = (names, ranges.reshape(-1, 2), names.index("shaft") if "shaft" in names else -1)
    _MERGED_PARTS = (config, dtype, got)
    return got


_MERGED_PARTS: tuple[Any, Any, Any] = (None, None, None)


def _merged(runs: LabelRuns, config: Config) -> list[InstanceObservation]:
    """Instances of merged masks (see the module docstring), largest first."""
    min_area = config.min_area_px
    part_names, ranges, shaft = _merged_parts(config, runs.dtype)
    if not part_names:
        return []
    fx, fy, fw, fh = runs.bounds
    shape = runs.shape
    n, label, table = _kernels().components(
        runs.ry,
        runs.rx0,
        runs.rx1,
        runs.rv,
        runs.n,
        ranges,
        shaft,
        fx,
        fy,
        fw,
        fh,
        shape[1],
        shape[0],
    )
    if n == 1:
        return []

    if n == 2:  # one (bridged) component: everything belongs to it
        inst = _fit_instance(runs, None, part_names, ranges, label, _BOTH, min_area)
        return [inst] if inst is not None and inst.area_px >= max(min_area, 1) else []
    k = _kernels()
    stats = table[:, : k.STAT_H + 1]
    counts, shaft_counts = table[:, k.STAT_COUNT], table[:, k.STAT_SHAFT]
    border = table[:, k.STAT_BORDER]
    memo: dict[tuple[int, ...], InstanceObservation | None] = {}

    def instance_of(group: list[int]) -> InstanceObservation | None:
        key = tuple(group)
        if key not in memo:
            members = np.zeros(n, np.bool_)
            members[group] = True
            memo[key] = _fit_instance(runs, None, part_names, ranges, label, members, min_area)
        return memo[key]

    def on_axis(piece: list[int], targets: list[list[int]]) -> int | None:
        """The target on whose shaft's distal extension the piece lies (index), among
        targets whose shaft is one straight shaft (a blob of crossing shafts is left
        out: its box says nothing of either axis)."""
        head = instance_of(piece)
        if head is None:
            return None
        ones: list[tuple[int, InstanceObservation]] = []
        for k, g in enumerate(targets):
            inst = instance_of(g)
            if inst is not None and _one_shaft(inst):
                ones.append((k, inst))
        host = _head_host(head, [head] + [inst for _, inst in ones], 0, shape) if ones else None
        return None if host is None else ones[host - 1][0]

    groups = group_components(
        counts,
        shaft_counts,
        stats,
        max(min_area, 1),
        _LazyLabels(runs, label, stats),
        border,
        prefer=on_axis,
    )
    found = [inst for inst in map(instance_of, groups) if inst is not None]
    found = join_by_axis(found, min_area, shape)
    found.sort(key=lambda inst: -inst.area_px)
    return found


def member_mask(labels: np.ndarray, members: list[int]) -> np.ndarray:
    """uint8 mask (255 / 0) of the pixels of ``labels`` (an int32 label image) whose label
    is one of ``members`` (a few labels: one comparison each, ~100x ``np.isin``)."""
    out = _compare(labels, members[0], cv2.CMP_EQ)
    for m in members[1:]:
        out = cv2.bitwise_or(out, _compare(labels, m, cv2.CMP_EQ))
    return out


#: ``cv2.compare`` (its stubs omit the scalar second operand it accepts).
_compare: Any = cv2.compare


class _Groups:
    """Components (labels of ``cc``) being grouped into instruments: union-find by root,
    each root's members, bounds (x0, y0, x1, y1 exclusive) and pixel area."""

    def __init__(self, labels: list[int], stats: np.ndarray, counts: np.ndarray) -> None:
        self.members: dict[int, list[int]] = {i: [i] for i in labels}
        self.box = {
            i: [
                int(stats[i, 0]),
                int(stats[i, 1]),
                int(stats[i, 0] + stats[i, 2]),
                int(stats[i, 1] + stats[i, 3]),
            ]
            for i in labels
        }
        self.area = {i: float(counts[i]) for i in labels}

    def join(self, i: int, j: int) -> None:
        """Root ``i`` and its members join root ``j``."""
        self.members[j] += self.members.pop(i)
        bi, bj = self.box[i], self.box[j]
        self.box[j] = [min(bi[0], bj[0]), min(bi[1], bj[1]), max(bi[2], bj[2]), max(bi[3], bj[3])]
        self.area[j] += self.area.pop(i)


#: An estimate of a pixel gap (:func:`mistool.kernels.instances.chamfer_gap`) lies within
#: this (px, plus this fraction of it) of what ``cv2.distanceTransform`` gives; measured:
#: within 4e-4 px up to ~300 px (tests/test_instances_speed.py), 25x less than this.
GAP_ESTIMATE_PX = 0.01
GAP_ESTIMATE_FRAC = 1e-4


class _Gap:
    """Pixel gap between two groups (bounds first; pixels only when the bounds are within
    the limit), memoised while neither group grows.

    With a component image painted on demand (:class:`_LazyLabels`), ``estimate`` gives
    bounds of the gap computed from the runs (:data:`GAP_ESTIMATE_PX`): the grouping
    measures the gap itself (``cv2.distanceTransform``, ~0.2 ms) only where those bounds
    do not decide."""

    def __init__(self, groups: _Groups, cc: np.ndarray | _LazyLabels) -> None:
        self._g = groups
        self._cc = cc
        self._memo: dict[tuple[int, int, int, int, int], float] = {}
        self._guess: dict[tuple[int, int, int, int, int], float] = {}

    def _box_gap(self, i: int, j: int) -> float:
        bi, bj = self._g.box[i], self._g.box[j]
        dx = max(bi[0] - bj[2] + 1, bj[0] - bi[2] + 1, 0)
        dy = max(bi[1] - bj[3] + 1, bj[1] - bi[3] + 1, 0)
        return math.hypot(dx, dy)

    def _key(self, i: int, j: int, limit: float) -> tuple[int, int, int, int, int]:
        return (i, j, len(self._g.members[i]), len(self._g.members[j]), int(math.ceil(limit)))

    def __call__(self, i: int, j: int, limit: float) -> float:
        g = self._box_gap(i, j)
        if g > limit:
            return g
        key = self._key(i, j, limit)
        if key not in self._memo:  # the groups have not grown since: same pixels, same gap
            mi, mj = self._g.members[i], self._g.members[j]
            self._memo[key] = _pixel_gap(self._cc, mi, mj, self._g.box[i], self._g.box[j], key[4])
        return self._memo[key]

    def estimate(self, i: int, j: int, limit: float) -> tuple[float, float]:
        """``(lo, hi)`` with ``lo <= self(i, j, limit) <= hi``."""
        g = self._box_gap(i, j)
        if g > limit:
            return g, g
        key = self._key(i, j, limit)
        if key in self._memo:
            return self._memo[key], self._memo[key]
        if not isinstance(self._cc, _LazyLabels):
            g = self(i, j, limit)
            return g, g
        if key not in self._guess:
            self._guess[key] = self._cc.chamfer_gap(
                self._g.members[i], self._g.members[j], self._g.box[i], self._g.box[j], key[4]
            )
        d = self._guess[key]
        if math.isinf(d):  # no pixel of j within reach: the gap is inf
            return d, d
        eps = GAP_ESTIMATE_PX + GAP_ESTIMATE_FRAC * d
        return d - eps, d + eps

    def within(self, i: int, j: int, limit: float) -> bool:
        """``self(i, j, limit) <= limit``."""
        lo, hi = self.estimate(i, j, limit)
        if lo > limit or hi <= limit:
            return hi <= limit
        return self(i, j, limit) <= limit


def group_components(
    counts: np.ndarray,
    shaft_counts: np.ndarray,
    stats: np.ndarray,
    min_area: int,
    cc: np.ndarray | _LazyLabels,
    border: np.ndarray,
    prefer: Callable[[list[int], list[list[int]]], int | None] | None = None,
) -> list[list[int]]:
    """Components (labels 1..n-1 of ``cc``) grouped into instruments by :data:`REACH_RULES`.

    A component smaller than ``min_area`` pixels is a speck and is dropped. Rules apply
    in order; within a rule, the nearest eligible (piece, target) pair within reach joins
    first, the target's bounds and area growing, until no pair is within reach. A head
    within reach of several shafts joins the one ``prefer`` names (given the piece's and
    the candidates' components: the index of a candidate, or None for the nearest).

    Args:
        counts: (n,) part pixels per component.
        shaft_counts: (n,) shaft pixels per component.
        stats: (n, >= 4) component bounds (x, y, w, h), the first columns of
            ``cv2.connectedComponentsWithStats``' stats.
        min_area: specks and shafts below this many pixels.
        cc: (H, W) component label image (or one painted when first sliced).
        border: (n,) True (non-zero) where a component touches the image border.
        prefer: see above (``observe_frame``: the shaft whose distal extension the head
            lies on, :func:`_head_host`).

    Returns:
        Groups of component labels, largest groups' components first.
    """
    labels = [i for i in range(1, len(counts)) if counts[i] >= min_area]
    labels.sort(key=lambda i: -counts[i])
    has_shaft = {i: bool(shaft_counts[i] >= min_area) for i in labels}
    if len(labels) < 2:
        return [[i] for i in labels]
    # a group's kind never changes (a piece joins a target, whose kind the group keeps):
    # a rule whose piece or target kind no group has joins nothing (two tools apart:
    # only shafts, so only the first rule is tried)
    kinds = set().union(*(_kind(i, has_shaft, border) for i in labels))
    groups = _Groups(labels, stats, counts)
    gap = _Gap(groups, cc)
    for rule in REACH_RULES:
        if rule.piece not in kinds or rule.target not in kinds:
            continue
        while True:
            best = _nearest_pair(rule, groups, gap, has_shaft, border)
            if best is None:
                break
            if prefer is not None and rule.target == "shaft" and not has_shaft[best[0]]:
                best = _preferred(rule, best, groups, gap, has_shaft, border, prefer)
            groups.join(*best)
    return list(groups.members.values())


def _preferred(
    rule: ReachRule,
    best: tuple[int, int],
    groups: _Groups,
    gap: _Gap,
    has_shaft: dict[int, bool],
    border: np.ndarray,
    prefer: Callable[[list[int], list[list[int]]], int | None],
) -> tuple[int, int]:
    """The (piece, target) to join: ``best`` (the nearest pair), or, when the head piece
    is within the rule's reach of several shafts, the one ``prefer`` chooses."""
    i = best[0]
    cands = [
        j
        for j in groups.members
        if j != i
        and rule.target in _kind(j, has_shaft, border)
        and groups.area[i] < rule.max_area_ratio * groups.area[j]
        and gap.within(i, j, rule.reach(groups.area[i], groups.area[j]))
    ]
    if len(cands) < 2:
        return best
    k = prefer(groups.members[i], [groups.members[j] for j in cands])
    return best if k is None else (i, cands[k])


def _kind(root: int, has_shaft: dict[int, bool], border: np.ndarray) -> set[str]:
    if has_shaft[root]:
        return {"shaft"}
    return {"head", "border head"} if border[root] else {"head", "inner head"}


def _nearest_pair(
    rule: ReachRule,
    groups: _Groups,
    gap: _Gap,
    has_shaft: dict[int, bool],
    border: np.ndarray,
) -> tuple[int, int] | None:
    """The nearest (piece, target) roots the rule joins, or None (the first of equally
    near pairs; a gap measured only when its estimate cannot decide)."""
    roots = list(groups.members)
    best: list[Any] | None = None  # [lo, hi, i, j, limit]: the nearest so far
    for i in roots:
        if rule.piece not in _kind(i, has_shaft, border):
            continue
        for j in roots:
            if j == i or rule.target not in _kind(j, has_shaft, border):
                continue
            if not groups.area[i] < rule.max_area_ratio * groups.area[j]:
                continue
            lim = rule.reach(groups.area[i], groups.area[j])
            lo, hi = gap.estimate(i, j, lim)
            if lo > lim:
                continue
            if hi > lim:  # within reach? measured
                lo = hi = gap(i, j, lim)
                if lo > lim:
                    continue
            if best is not None and lo < best[1] and hi >= best[0]:  # nearer? measured
                lo = hi = gap(i, j, lim)
                best[0] = best[1] = gap(best[2], best[3], best[4])
            if best is None or hi < best[0]:
                best = [lo, hi, i, j, lim]
    return None if best is None else (best[2], best[3])


def _pixel_gap(
    cc: np.ndarray | _LazyLabels,
    a: list[int],
    b: list[int],
    box_a: list[int],
    box_b: list[int],
    reach: int,
) -> float:
    """Smallest distance (px) from a pixel labelled in ``a`` to one labelled in ``b`` in the
    component label image ``cc``, looked for within ``reach`` px of ``a``'s bounds
    ``box_a`` (``box_b``: ``b``'s bounds; both x0, y0, x1, y1 exclusive); ``inf`` beyond."""
    x0, y0, x1, y1 = _gap_window(box_a, box_b, reach)
    win = cc[y0:y1, x0:x1]
    in_b = member_mask(win, b)
    if not cv2.countNonZero(in_b):
        return math.inf
    not_a = cv2.bitwise_not(member_mask(win, a))
    dist = cv2.distanceTransform(not_a, cv2.DIST_L2, cv2.DIST_MASK_3)  # ~2% off: a gate
    return float(cv2.minMaxLoc(dist, mask=in_b)[0])


def _gap_window(box_a: list[int], box_b: list[int], reach: int) -> tuple[int, int, int, int]:
    """Where :func:`_pixel_gap` looks (x0, y0, x1, y1 exclusive): all of a's bounds, and
    the part of b's within ``reach`` of them."""
    x0 = min(box_a[0], max(box_a[0] - reach, box_b[0]))
    y0 = min(box_a[1], max(box_a[1] - reach, box_b[1]))
    x1 = max(box_a[2], min(box_a[2] + reach, box_b[2]))
    y1 = max(box_a[3], min(box_a[3] + reach, box_b[3]))
    return x0, y0, x1, y1


# joining pieces an occluder cut off, by shaft geometry -------------------------------------


def _distal_sign(inst: InstanceObservation, shape: tuple[int, int]) -> float:
    """+1 if the instance's distal end is along +u of its shaft box, else -1: towards its
    other parts, or (shaft alone) away from the image border the shaft comes from."""
    a = inst.parts["shaft"].box
    u = unit_vector(a.angle_deg)
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


#: A shaft's pixels fill at least this share of its box when it is one straight shaft
#: (a rectangle, or a trapezoid in perspective); two crossing shafts fill much less.
ONE_SHAFT_FILL = 0.7


def _one_shaft(inst: InstanceObservation) -> bool:
    """Whether the instance's shaft pixels look like one straight shaft (its box's axis
    is that shaft's)."""
    shaft = inst.parts.get("shaft")
    if shaft is None:
        return False
    b = shaft.box
    return shaft.area_px >= ONE_SHAFT_FILL * b.length * b.width


def _shaft_host(piece: InstanceObservation, found: list[InstanceObservation], k: int) -> int | None:
    """The instance whose shaft axis a shaft-only piece continues (a shaft cut in two)."""
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
            and angle_diff_deg(a.angle_deg, b.angle_deg) > CUT_SHAFT_ANGLE_DEG
        ):
            continue
        u = unit_vector(ref.angle_deg)
        off = abs((q.cx - ref.cx) * u[1] - (q.cy - ref.cy) * u[0])  # to ref's axis
        if off <= 0.5 * max(ref.width, min(q.width, q.length)):
            return j
        if ref.length < 2.0 * ref.width and _end_to_end(ref, q):
            return j
    return None


#: Shaft stubs cut apart by a thin band (a specular streak, a thread, a segmentation gap)
#: are at most this far apart (px) along the shaft.
CUT_GAP_PX = 6.0


def _extent(box: RotatedBox, axis_deg: float) -> float:
    """The box's extent (px) along the direction ``axis_deg``."""
    t = math.radians(box.angle_deg - axis_deg)
    return abs(box.length * math.cos(t)) + abs(box.width * math.sin(t))


def _end_to_end(ref: RotatedBox, q: RotatedBox) -> bool:
    """Whether a stub ``ref`` (as wide as long: its box may lie across the shaft) and a
    piece ``q`` lie end to end along one of ``ref``'s box axes, at most
    :data:`CUT_GAP_PX` apart, with the same width across it (one shaft cut across)."""
    for axis in (ref.angle_deg, ref.angle_deg + 90.0):
        u = unit_vector(axis)
        along = abs((q.cx - ref.cx) * u[0] + (q.cy - ref.cy) * u[1])
        off = abs((q.cx - ref.cx) * u[1] - (q.cy - ref.cy) * u[0])
        across_ref, across_q = _extent(ref, axis + 90.0), _extent(q, axis + 90.0)
        if (
            off <= 0.25 * across_ref
            and abs(across_q - across_ref) <= 0.25 * across_ref
            and along <= 0.5 * (_extent(ref, axis) + _extent(q, axis)) + CUT_GAP_PX
        ):
            return True
    return False


def _head_host(
    piece: InstanceObservation, found: list[InstanceObservation], k: int, shape: tuple[int, int]
) -> int | None:
    """The instance on whose shaft's distal extension a head piece lies (nearest axis)."""
    best: tuple[float, int] | None = None
    hx, hy = piece.centroid_px
    for j, other in enumerate(found):
        if j == k or "shaft" not in other.parts:
            continue
        # the host must not already show a head part of this piece's size (its own
        # head): a crumb of a head joins, and so does a head larger than the stub of it
        # the host shows beside the occluder
        if any(
            p in other.parts
            and HEAD_CRUMB_FRAC * other.parts[p].area_px
            <= piece.parts[p].area_px
            <= other.parts[p].area_px
            for p in piece.parts
        ):
            continue
        a = other.parts["shaft"].box
        u = unit_vector(a.angle_deg) * _distal_sign(other, shape)
        along = (hx - a.cx) * u[0] + (hy - a.cy) * u[1] - a.length / 2
        off = abs((hx - a.cx) * u[1] - (hy - a.cy) * u[0])
        if off <= a.width and -a.length / 2 <= along <= HEAD_AXIS_REACH * a.width:
            if best is None or off < best[0]:
                best = (off, j)
    return None if best is None else best[1]


def _host_for(
    piece: InstanceObservation, found: list[InstanceObservation], k: int, shape: tuple[int, int]
) -> int | None:
    """The instance a piece belongs to by shaft geometry, or None."""
    if set(piece.parts) == {"shaft"}:
        return _shaft_host(piece, found, k)
    if "shaft" in piece.parts:
        return None
    return _head_host(piece, found, k, shape)


def join_by_axis(
    found: list[InstanceObservation], min_area: int, shape: tuple[int, int]
) -> list[InstanceObservation]:
    """Join pieces an occluder cut off to their instrument by shaft geometry.

    A shaft-only piece continuing another instance's shaft axis
    (:data:`CUT_SHAFT_ANGLE_DEG`), and a head on the distal extension of a shaft's axis
    (:data:`HEAD_AXIS_REACH`), join it; smallest pieces first, until nothing joins.
    """
    if len(found) < 2:
        return found
    found = sorted(found, key=lambda inst: inst.area_px)  # smallest pieces first
    k = 0
    while k < len(found):
        host = _host_for(found[k], found, k, shape)
        if host is None:
            k += 1
            continue
        joined = merge_instances(found[host], found[k], min_area)
        found = [inst for i, inst in enumerate(found) if i not in (k, host)] + [joined]
        found.sort(key=lambda inst: inst.area_px)
        k = 0
    return found


def merge_instances(
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
        joined = part_observation(name, m, x0, y0, min_area)
        if joined is not None:
            parts[name] = joined
    return make_instance(None, parts, a.image_shape)
