"""One frame's instruments from the label image's runs (mistool.kernels.instances) equal
the OpenCV mask pipeline they replace, bit for bit (issue 13: the workers' per-frame
cost): foreground bounds, runs, components and their OpenCV labels, Algorithm 1 of a
selection of runs, and every instance observe_frame returns."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mistool.config import Config, InstrumentSpec
from mistool.geometry import fit_part, range_mask
from mistool.kernels.instances import (
    components,
    fit_parts,
    fit_selected,
    foreground,
    label_runs,
    paint_components,
    value_counts,
    values_present,
)
from mistool.model import InstanceObservation, PartObservation, RotatedBox
from mistool.tracking import instances
from mistool.tracking.instances import (
    MERGE_GAP_PX,
    _head_host,
    _one_shaft,
    group_components,
    join_by_axis,
    make_instance,
    member_mask,
    observe_frame,
    part_observation,
    scan_labels,
)

DTYPES = [np.uint8, np.uint16, np.int32]


def _label_image(rng: np.random.Generator, dtype: type, values: Sequence[int]) -> np.ndarray:
    """Tools drawn as thick lines of one value with heads of others, specks, gaps cut
    by thin background lines (occluders), sometimes noise; any size (widths not a
    multiple of 8 too)."""
    h, w = int(rng.integers(1, 140)), int(rng.integers(1, 140))
    img = np.zeros((h, w), np.int32)
    if rng.random() < 0.15:
        img[rng.random((h, w)) < rng.uniform(0, 0.5)] = int(rng.choice(values))
        return img.astype(dtype)
    for _ in range(int(rng.integers(0, 5))):
        a, b = rng.integers(-20, 160, 2), rng.integers(-20, 160, 2)
        value = int(rng.choice(values))
        cv2.line(
            img, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), value, int(rng.integers(1, 22))
        )
        head = int(rng.choice(values))
        cv2.circle(img, (int(b[0]), int(b[1])), int(rng.integers(1, 14)), head, -1)
    for _ in range(int(rng.integers(0, 3))):  # occluders: thin background lines
        a, b = rng.integers(-20, 160, 2), rng.integers(-20, 160, 2)
        cv2.line(img, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), 0, int(rng.integers(1, 4)))
    for _ in range(int(rng.integers(0, 12))):
        img[int(rng.integers(0, h)), int(rng.integers(0, w))] = int(rng.choice(values))
    return img.astype(dtype)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from(DTYPES))
def test_foreground_is_opencvs_bounding_rect(seed, dtype):
    rng = np.random.default_rng(seed)
    img = np.zeros((int(rng.integers(1, 90)), int(rng.integers(1, 90))), dtype)
    for _ in range(int(rng.integers(0, 5))):
        y, x = int(rng.integers(0, img.shape[0])), int(rng.integers(0, img.shape[1]))
        img[y, x] = int(rng.integers(1, 200)) * (
            1 if dtype != np.int32 or rng.random() < 0.5 else -1
        )
    want = cv2.boundingRect((img != 0).astype(np.uint8))
    assert foreground(img) == tuple(want)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from(DTYPES))
def test_label_runs_are_the_images_runs_of_equal_values(seed, dtype):
    rng = np.random.default_rng(seed)
    img = _label_image(rng, dtype, [1, 2, 3, 70, 160, 255])
    bounds = foreground(img)
    _, ry, rx0, rx1, rv, n = label_runs(img, bounds)
    x, y, w, h = bounds
    got = np.zeros((h, w), np.int64)
    for i in range(n):
        assert rx0[i] < rx1[i] and rv[i] != 0
        assert not got[ry[i], rx0[i] : rx1[i]].any()
        got[ry[i], rx0[i] : rx1[i]] = rv[i]
        if rx1[i] < w:  # maximal: the next pixel has another value
            assert img[y + ry[i], x + rx1[i]] != rv[i]
        if rx0[i] > 0:
            assert img[y + ry[i], x + rx0[i] - 1] != rv[i]
    assert np.array_equal(got, img[y : y + h, x : x + w].astype(np.int64))
    keys = ry[:n].astype(np.int64) * 10**6 + rx0[:n]
    assert np.all(np.diff(keys) > 0)  # raster order
    # the whole image scanned: the foreground's bounds and the same runs
    whole, *got_runs = label_runs(img)
    assert whole == bounds
    for a, b in zip(got_runs[:4], (ry, rx0, rx1, rv), strict=True):
        assert np.array_equal(a[:n], b[:n])
    assert got_runs[4] == n


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([1, 2, 5, 40]))
def test_values_present_are_the_counted_values_wanted(seed, least):
    """values_present (the frame's unknown values in one pass) is the former
    ``np.flatnonzero`` of value_counts at least ``least`` where wanted: values 1..255 in
    runs of 1-30 pixels (a few values, or many), any table of wanted values."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(0, 300))
    rv = rng.integers(1, int(rng.choice([4, 256])), max(n, 1)).astype(np.int32)
    rx0 = rng.integers(0, 600, max(n, 1)).astype(np.int32)
    rx1 = (rx0 + rng.integers(1, 31, max(n, 1))).astype(np.int32)
    wanted = rng.random(256) < rng.random()
    got = values_present(rv, rx0, rx1, n, wanted, least)
    want = np.flatnonzero((value_counts(rv, rx0, rx1, n) >= least) & wanted)
    assert got.dtype == np.int64 and got.tolist() == want.tolist()


def _components_before(crop: np.ndarray, ranges: np.ndarray) -> tuple:
    """The former definition: part masks by ``range_mask``, their union dilated by a 3x3
    square, ``cv2.connectedComponentsWithStats`` (labels, bounds), pixel counts by
    ``np.bincount``."""
    masks = [range_mask(crop, (int(lo), int(hi))) for lo, hi in ranges]
    union = masks[0]
    for m in masks[1:]:
        union = cv2.bitwise_or(union, m)
    k = 2 * MERGE_GAP_PX + 1
    bridged = cv2.dilate(union, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
    n, cc, stats, _ = cv2.connectedComponentsWithStats(bridged, connectivity=8)
    counts = np.bincount(cc[union > 0], minlength=n)
    shaft_counts = np.bincount(cc[masks[0] > 0], minlength=n)
    return n, cc, stats[:, :4], counts, shaft_counts, union


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from(DTYPES), st.integers(1, 2))
def test_components_equal_opencvs_labels_bounds_and_counts(seed, dtype, threads):
    """Labels in OpenCV's order (its block-based labelling's: single- or multi-threaded),
    bounds of the dilated components, part and shaft pixels per component, the border."""
    rng = np.random.default_rng(seed)
    img = _label_image(rng, dtype, [10, 20, 30, 99])  # 99: a value of no part
    ranges = np.array([[10, 10], [20, 20], [30, 30]], np.int64)
    bounds = foreground(img)
    x, y, w, h = bounds
    if w == 0:
        return
    _, ry, rx0, rx1, rv, n = label_runs(img, bounds)
    got_n, label, table = components(
        ry, rx0, rx1, rv, n, ranges, 0, x, y, w, h, img.shape[1], img.shape[0]
    )
    stats, counts, shaft_counts, border = table[:, :4], table[:, 4], table[:, 5], table[:, 6]
    assert table.shape == (got_n, 7) and set(np.unique(border)) <= {0, 1}
    crop = img[y : y + h, x : x + w]
    saved = cv2.getNumThreads()
    cv2.setNumThreads(threads)
    try:
        want_n, cc, want_stats, want_counts, want_shaft, union = _components_before(crop, ranges)
    finally:
        cv2.setNumThreads(saved)
    if not union.any():
        assert got_n == 1
        return
    assert got_n == want_n
    assert np.array_equal(stats[1:], want_stats[1:]) and not stats[0].any()
    assert np.array_equal(counts, want_counts) and np.array_equal(shaft_counts, want_shaft)
    touch = (
        (want_stats[:, 0] + x <= 0)
        | (want_stats[:, 1] + y <= 0)
        | (want_stats[:, 0] + want_stats[:, 2] + x >= img.shape[1])
        | (want_stats[:, 1] + want_stats[:, 3] + y >= img.shape[0])
    )
    assert np.array_equal(border[1:], touch[1:])
    for i in range(n):  # each run's label is OpenCV's at its pixels (0: not a part value)
        want = cc[ry[i], rx0[i]] if union[ry[i], rx0[i]] else 0
        assert label[i] == want
    assert np.array_equal(paint_components(ry, rx0, rx1, label, n, w, h), cc.astype(np.int32))


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0, 1, 20, 300]))
def test_fit_of_selected_runs_is_fit_part_of_their_pixels(seed, min_area):
    """Algorithm 1 of the runs of some labels and a value range, its box included, is
    fit_part of the mask of their pixels (fit_part itself is checked against OpenCV in
    test_geometry)."""
    rng = np.random.default_rng(seed)
    img = _label_image(rng, np.uint8, [10, 11, 20, 30])
    bounds = foreground(img)
    x, y, w, h = bounds
    if w == 0:
        return
    _, ry, rx0, rx1, rv, n = label_runs(img, bounds)
    label = rng.integers(0, 4, max(n, 1)).astype(np.int32)
    members = rng.random(4) < 0.6
    lo, hi = (
        (10, 11) if rng.random() < 0.5 else (int(rng.integers(0, 40)), int(rng.integers(0, 40)))
    )
    mask = np.zeros((h, w), np.uint8)
    for i in range(n):
        if lo <= rv[i] <= hi and members[label[i]]:
            mask[ry[i], rx0[i] : rx1[i]] = 255
    offset = (x, y)
    info, kept, box, corners = fit_selected(
        ry, rx0, rx1, rv, label, n, lo, hi, members, min_area, *offset
    )
    want = fit_part(mask, min_area, offset)
    if want is None:
        assert info[0] == 0
        return
    assert RotatedBox(*box) == want.box and np.array_equal(corners, want.corners)
    assert info[0] == want.area_px and (x + info[1], y + info[2]) == want.offset
    assert np.array_equal(kept, want.kept)
    ys, xs = np.nonzero(kept)
    assert (info[3], info[4]) == (xs.sum(), ys.sum())


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0, 1, 20, 300]), st.integers(1, 3))
def test_fit_parts_is_each_parts_fit_and_make_instance(seed, min_area, n_parts):
    """fit_parts (one call per instance): each part is fit_selected of its range, its
    packed bits are ``np.packbits`` of its crop (specks dropped within its bounds
    included: min_area 20, 300), and the instance's centroid, area and bounds are
    make_instance's of those parts, bit for bit."""
    rng = np.random.default_rng(seed)
    img = _label_image(rng, np.uint8, [10, 11, 20, 30])
    bounds = foreground(img)
    x, y, w, h = bounds
    if w == 0:
        return
    _, ry, rx0, rx1, rv, n = label_runs(img, bounds)
    label = rng.integers(0, 4, max(n, 1)).astype(np.int32)
    members = rng.random(4) < 0.6
    ranges = np.array([sorted(rng.integers(0, 40, 2).tolist()) for _ in range(n_parts)], np.int64)
    if rng.random() < 0.5:
        ranges[0] = (10, 11)
    info, boxes, corners, crops, centroid, got_bounds, bits = fit_parts(
        ry, rx0, rx1, rv, label, n, ranges, members, min_area, x, y
    )
    for k in range(3):
        assert bits[k].dtype == np.uint8
        assert np.array_equal(bits[k], np.packbits(crops[k].reshape(-1)))
    parts = {}
    for k, (lo, hi) in enumerate(ranges.tolist()):
        fit, kept, box, corner = fit_selected(
            ry, rx0, rx1, rv, label, n, lo, hi, members, min_area, x, y
        )
        assert info[k, 0] == fit[0]
        if fit[0] == 0:
            assert crops[k].size == 0
            continue
        assert (info[k, 1], info[k, 2]) == (x + fit[1], y + fit[2])
        assert (info[k, 3], info[k, 4]) == kept.shape and np.array_equal(crops[k], kept)
        assert tuple(boxes[k]) == box and np.array_equal(corners[k], corner)
        parts[f"p{k}"] = PartObservation(
            f"p{k}", RotatedBox(*box), corner, int(fit[0]), kept, (x + fit[1], y + fit[2])
        )
    if not parts:
        assert got_bounds[0] == 0
        return
    want = make_instance(None, parts)
    assert got_bounds == (len(parts), want.area_px, *want.bbox_xywh)
    assert centroid == want.centroid_px


# --- observe_frame against the former mask pipeline (commit 3307ee1) ------------------------


def _labelled_components_before(
    mask: np.ndarray, contours: Sequence[np.ndarray], hierarchy: np.ndarray | None
) -> tuple[int, np.ndarray, np.ndarray]:
    rows = hierarchy[0] if hierarchy is not None else np.zeros((0, 4), np.int32)
    n, cc = cv2.connectedComponents(mask, connectivity=8, ltype=cv2.CV_16U)
    outer = [c for c, h in zip(contours, rows, strict=True) if h[3] < 0]
    assert len(outer) == n - 1
    stats = np.zeros((n, 4), np.int32)
    for c in outer:
        x, y = c[0, 0]
        stats[cc[y, x]] = cv2.boundingRect(c)
    return n, cc, stats


def _merged_before(
    crop: np.ndarray, origin: tuple[int, int], shape: tuple[int, int], config: Config
) -> list[InstanceObservation]:
    """``instances._merged`` as it was: masks, contours, OpenCV's components."""
    min_area = config.min_area_px
    part_names = [p for p in ("shaft", "wrist", "clasper") if p in config.parts]
    masks = {p: range_mask(crop, config.parts[p]) for p in part_names}
    union = masks[part_names[0]]
    for p in part_names[1:]:
        union = cv2.bitwise_or(union, masks[p])
    contours, hierarchy = cv2.findContours(union, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    n_inst = int((hierarchy[0][:, 3] < 0).sum()) if contours else 0
    bridged = union
    if n_inst > 1:
        k = 2 * MERGE_GAP_PX + 1
        bridged = cv2.dilate(union, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
        contours, hierarchy = cv2.findContours(bridged, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
        n_inst = int((hierarchy[0][:, 3] < 0).sum())
    if n_inst == 0:
        return []

    def parts_in(window: dict[str, np.ndarray], x0: int, y0: int) -> dict[str, PartObservation]:
        parts = {}
        for p, m in window.items():
            obs = part_observation(p, m, x0, y0, min_area)
            if obs is not None:
                parts[p] = obs
        return parts

    if n_inst == 1:
        parts = parts_in(masks, *origin)
        if parts and sum(o.area_px for o in parts.values()) >= max(min_area, 1):
            return [make_instance(None, parts, shape)]
        return []
    n, cc, stats = _labelled_components_before(bridged, contours, hierarchy)
    counts = np.bincount(cc[union > 0], minlength=n)
    shaft_counts = np.bincount(cc[masks["shaft"] > 0], minlength=n)
    fx, fy = origin
    border = (
        (stats[:, 0] + fx <= 0)
        | (stats[:, 1] + fy <= 0)
        | (stats[:, 0] + stats[:, 2] + fx >= shape[1])
        | (stats[:, 1] + stats[:, 3] + fy >= shape[0])
    )

    def instance_of(group: list[int]) -> InstanceObservation | None:
        x0 = min(int(stats[i, 0]) for i in group)
        y0 = min(int(stats[i, 1]) for i in group)
        x1 = max(int(stats[i, 0] + stats[i, 2]) for i in group)
        y1 = max(int(stats[i, 1] + stats[i, 3]) for i in group)
        inside = member_mask(cc[y0:y1, x0:x1], group)
        window = {p: cv2.bitwise_and(m[y0:y1, x0:x1], inside) for p, m in masks.items()}
        parts = parts_in(window, fx + x0, fy + y0)
        return make_instance(None, parts, shape) if parts else None

    def on_axis(piece: list[int], targets: list[list[int]]) -> int | None:
        head = instance_of(piece)
        if head is None:
            return None
        ones = [(k, i) for k, g in enumerate(targets) if (i := instance_of(g)) and _one_shaft(i)]
        host = _head_host(head, [head] + [i for _, i in ones], 0, shape) if ones else None
        return None if host is None else ones[host - 1][0]

    groups = group_components(
        counts, shaft_counts, stats, max(min_area, 1), cc, border, prefer=on_axis
    )
    found = [inst for inst in map(instance_of, groups) if inst is not None]
    found = join_by_axis(found, min_area, shape)
    found.sort(key=lambda inst: -inst.area_px)
    return found


def _observe_before(labels: np.ndarray, config: Config) -> list[InstanceObservation]:
    img = instances._check_labels(labels)
    shape = (int(img.shape[0]), int(img.shape[1]))
    x, y, w, h = cv2.boundingRect(img if img.dtype == np.uint8 else (img != 0).view(np.uint8))
    if w == 0:
        return []
    crop = img[y : y + h, x : x + w]
    if not config.instruments:
        return _merged_before(crop, (x, y), shape, config)
    out = []
    for spec in config.instruments:
        parts = {}
        for part in ("shaft", "wrist", "clasper"):
            if part in spec.parts and spec.parts[part][1] > 0:
                obs = part_observation(
                    part, range_mask(crop, spec.parts[part]), x, y, config.min_area_px
                )
                if obs is not None:
                    parts[part] = obs
        if parts:
            out.append(make_instance(spec.name, parts, shape))
    return out


def _bits(values: object) -> list[int]:
    return np.asarray(values, np.float64).view(np.int64).tolist()


def _key(inst: InstanceObservation) -> tuple:
    parts = [
        (
            name,
            _bits(dataclasses.astuple(p.box)),
            _bits(p.corners),
            p.area_px,
            p.offset,
            p.mask.dtype.str,
            p.mask.shape,
            p.mask.tobytes(),
        )
        for name, p in inst.parts.items()
    ]
    return (
        inst.label,
        parts,
        _bits(inst.centroid_px),
        inst.area_px,
        inst.bbox_xywh,
        inst.image_shape,
    )


MERGED = Config(
    labels="endovis17", parts={"shaft": (10, 10), "wrist": (20, 20), "clasper": (30, 30)}
)
OWN = Config(
    parts={},
    instruments=(
        InstrumentSpec("a", {"shaft": (10, 11), "clasper": (30, 30)}),
        InstrumentSpec("b", {"shaft": (40, 40), "wrist": (20, 20), "clasper": (50, 60)}),
    ),
)


@settings(max_examples=250, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.sampled_from(DTYPES),
    st.sampled_from([0, 1, 20, 150]),
    st.booleans(),
)
def test_observe_frame_equals_the_former_mask_pipeline(seed, dtype, min_area, own):
    """Every instance (boxes and corners to the last bit, masks, offsets, centroids,
    order): tools, heads, specks, occluder cuts, values of no part; merged masks and
    instruments with their own values."""
    rng = np.random.default_rng(seed)
    if own:
        config = dataclasses.replace(OWN, min_area_px=min_area)
        values = [10, 11, 20, 30, 40, 50, 55, 60, 99]
    else:
        config = dataclasses.replace(MERGED, min_area_px=min_area)
        values = [10, 10, 10, 20, 30, 99]
    img = _label_image(rng, dtype, values)
    want = [_key(i) for i in _observe_before(img, config)]
    got = [_key(i) for i in observe_frame(img, config)]
    assert got == want
    runs = scan_labels(img)
    assert [_key(i) for i in observe_frame(img, config, runs=runs)] == want


def _observe_counting_paints(img: np.ndarray, config: Config) -> tuple[list, list[bool]]:
    """observe_frame's instances (keys) and, per slice of the component image, whether it
    was painted then."""
    painted: list[bool] = []
    original = instances._LazyLabels.__getitem__

    def spy(self, key):  # type: ignore[no-untyped-def]
        painted.append(self._img is None)
        return original(self, key)

    instances._LazyLabels.__getitem__ = spy  # type: ignore[method-assign]
    try:
        got = [_key(i) for i in observe_frame(img, config)]
    finally:
        instances._LazyLabels.__getitem__ = original  # type: ignore[method-assign]
    return got, painted


def test_a_pixel_gap_is_measured_only_when_its_estimate_does_not_decide():
    """A head near a shaft, another far: the estimates decide, nothing is measured; two
    heads at the same gap from a shaft: which is nearer is measured (the component image
    painted once, then read again)."""
    config = dataclasses.replace(MERGED, min_area_px=5)
    img = np.zeros((200, 300), np.uint8)
    cv2.line(img, (10, 100), (120, 100), 10, 9)
    cv2.circle(img, (150, 110), 4, 20, -1)  # within reach of the shaft
    cv2.circle(img, (280, 20), 5, 30, -1)  # far away: its own instance
    got, painted = _observe_counting_paints(img, config)
    assert got == [_key(i) for i in _observe_before(img, config)]
    assert not painted
    img = np.zeros((200, 300), np.uint8)
    cv2.line(img, (10, 100), (200, 100), 10, 9)
    cv2.circle(img, (100, 80), 4, 30, -1)  # two heads, mirrored about the shaft's axis
    cv2.circle(img, (100, 120), 4, 30, -1)
    got, painted = _observe_counting_paints(img, config)
    assert got == [_key(i) for i in _observe_before(img, config)]
    assert painted and painted[0] and not any(painted[1:])


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_the_gap_estimate_is_within_its_bound_of_the_measured_gap(seed):
    """chamfer_gap (real-number chamfer distance from the runs) against _pixel_gap
    (cv2.distanceTransform on the component image): within 1e-3 px, 10x under the bound
    the grouping assumes (GAP_ESTIMATE_PX); inf together."""
    from mistool.kernels.instances import chamfer_gap
    from mistool.tracking.instances import GAP_ESTIMATE_PX, _gap_window, _pixel_gap

    rng = np.random.default_rng(seed)
    img = _label_image(rng, np.uint8, [10, 20, 30])
    bounds = foreground(img)
    x, y, w, h = bounds
    if w == 0:
        return
    _, ry, rx0, rx1, rv, n = label_runs(img, bounds)
    ranges = np.array([[10, 10], [20, 20], [30, 30]], np.int64)
    count, label, stats = components(
        ry, rx0, rx1, rv, n, ranges, 0, x, y, w, h, img.shape[1], img.shape[0]
    )
    if count < 3:
        return
    cc = paint_components(ry, rx0, rx1, label, n, w, h)
    labels = list(range(1, count))
    rng.shuffle(labels)
    k = int(rng.integers(1, len(labels)))
    a, b = labels[:k], labels[k:]

    def box(group: list[int]) -> list[int]:
        return [
            min(int(stats[i, 0]) for i in group),
            min(int(stats[i, 1]) for i in group),
            max(int(stats[i, 0] + stats[i, 2]) for i in group),
            max(int(stats[i, 1] + stats[i, 3]) for i in group),
        ]

    reach = int(rng.integers(0, 200))
    want = _pixel_gap(cc, a, b, box(a), box(b), reach)
    in_a, in_b = np.zeros(count, np.bool_), np.zeros(count, np.bool_)
    in_a[a], in_b[b] = True, True
    got = chamfer_gap(ry, rx0, rx1, label, n, in_a, in_b, *_gap_window(box(a), box(b), reach), w, h)
    if math.isinf(want):
        assert math.isinf(got)
        return
    assert abs(got - want) <= 1e-3 < GAP_ESTIMATE_PX


# --- the frame results' transport (mistool.parallel.pack_frames) ----------------------------


def _result_key(r: object) -> tuple:
    return (
        [_key(i) for i in r.instances],  # type: ignore[attr-defined]
        _poses_key(r.metrics),  # type: ignore[attr-defined]
        r.unknown.dtype.str,  # type: ignore[attr-defined]
        r.unknown.tolist(),  # type: ignore[attr-defined]
        r.shape,  # type: ignore[attr-defined]
        r.corrupt,  # type: ignore[attr-defined]
        r.deferred,  # type: ignore[attr-defined]
        repr(r.runs),  # type: ignore[attr-defined]
    )


def _poses_key(poses: np.ndarray | None) -> tuple | None:
    """A frame's metric pose array as its dtype, shape and bits (NaN payloads included)."""
    if poses is None:
        return None
    return poses.dtype.str, poses.shape, poses.tobytes()


def _poses(rng: np.random.Generator, n: int) -> np.ndarray | None:
    """A frame's metric pose (``FrameResult.metrics``): None, or ``(n, 3, ROW_LEN)``
    numbers with NaN cells, some of them with a payload of their own."""
    from mistool.pose.measure import ROW_LEN

    if rng.integers(0, 4) == 0:
        return None
    out = rng.normal(0, 1e3, (n, 3, ROW_LEN))
    out[rng.random(out.shape) < 0.3] = np.nan
    bits = out.reshape(-1).view(np.uint64)
    odd = rng.random(bits.shape) < 0.05
    bits[odd] = np.uint64(0x7FF8000000000000) | rng.integers(1, 2**20, int(odd.sum())).astype(
        np.uint64
    )
    return out


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans(), st.integers(1, 4))
def test_a_batch_of_frame_results_unpickles_to_the_same_values(seed, own, frames):
    """What a worker sends (a batch's numbers in flat tables, its masks as bits, each
    part's from a byte boundary) unpickles to the same results, frame by frame: every
    instance, value, dtype, shape and mask (masks C-contiguous bool), the unknown
    values, border runs, flags; one result pickled alone too."""
    import pickle

    from mistool.parallel import (
        FrameResult,
        FrameResults,
        MeasureWork,
        observe_labels,
    )
    from mistool.pose.measure import ROW_LEN

    rng = np.random.default_rng(seed)
    config = OWN if own else MERGED
    values = [10, 11, 20, 30, 40, 50, 60, 99] if own else [10, 10, 20, 30, 99]
    results = FrameResults()
    for _ in range(frames):
        img = _label_image(rng, np.uint8, values)
        result = observe_labels(img, config, False)
        result.deferred = bool(rng.integers(0, 2))
        result.corrupt = bool(rng.integers(0, 2))
        if rng.integers(0, 2) == 0:
            result.metrics = _poses(rng, len(result.instances))
        results.append(result)
    if rng.integers(0, 3) == 0:
        poses = np.zeros((0, 3, ROW_LEN)) if rng.integers(0, 2) else None
        results.insert(
            int(rng.integers(0, frames)), FrameResult([], poses, np.zeros(0, np.int64), (5, 7))
        )
    got = pickle.loads(pickle.dumps(results, protocol=pickle.HIGHEST_PROTOCOL))
    assert type(got) is list and len(got) == len(results)
    for a, b in zip(got, results, strict=True):
        assert isinstance(a, FrameResult)
        assert _result_key(a) == _result_key(b)
        for inst in a.instances:
            for p in inst.parts.values():
                assert p.mask.dtype == np.bool_ and p.mask.flags.c_contiguous
                assert p.corners.dtype == np.float64 and p.corners.shape == (4, 2)
    one = pickle.loads(pickle.dumps(results[-1], protocol=pickle.HIGHEST_PROTOCOL))
    assert isinstance(one, FrameResult) and _result_key(one) == _result_key(results[-1])
    empty = FrameResult([], None, np.zeros(0, np.int64), (5, 7))
    assert _result_key(pickle.loads(pickle.dumps(empty))) == _result_key(empty)
    # the caller's measuring tasks (instances and shapes out, metric poses back) too
    work = MeasureWork((r.instances, r.shape) for r in results)
    back = pickle.loads(pickle.dumps(work, protocol=pickle.HIGHEST_PROTOCOL))
    assert type(back) is list and len(back) == len(work)
    for (got_i, got_s), (want_i, want_s) in zip(back, work, strict=True):
        assert got_s == want_s and [_key(i) for i in got_i] == [_key(i) for i in want_i]


def _make_instance_before(
    label: str | None, parts: dict[str, PartObservation], shape: tuple[int, int] | None
) -> InstanceObservation:
    """``instances.make_instance`` as it was (the sums from ``cv2.reduce``)."""
    area = sum(p.area_px for p in parts.values())
    sx = sy = 0.0
    x0 = y0 = math.inf
    x1 = y1 = -math.inf
    for p in parts.values():
        m = p.mask.view(np.uint8)
        cols = cv2.reduce(m, 0, cv2.REDUCE_SUM, dtype=cv2.CV_32S).ravel()
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


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 3), st.booleans())
def test_make_instance_sums_the_masks_as_before(seed, nparts, strided):
    """make_instance's centroid from exact pixel sums of each part's mask (compiled,
    kernels.instances.mask_sums) is the former one from cv2.reduce's row and column
    sums, bit for bit: masks of any shape (up to a large blob), offsets far from 0, a
    mask that is a strided view."""
    rng = np.random.default_rng(seed)
    parts = {}
    for name in ("shaft", "wrist", "clasper")[:nparts]:
        h, w = int(rng.integers(1, 700)), int(rng.integers(1, 700))
        mask = rng.random((h, w)) < rng.uniform(0.02, 1.0)
        mask[int(rng.integers(0, h)), int(rng.integers(0, w))] = True
        if strided:
            mask = np.repeat(mask, 2, axis=1)[:, ::2]
        off = (int(rng.integers(0, 5000)), int(rng.integers(0, 5000)))
        area = int(mask.sum())
        box = RotatedBox(1.0, 2.0, 3.0, 1.0, 0.0)
        parts[name] = PartObservation(name, box, np.zeros((4, 2)), area, mask, off)
    got = make_instance(None, parts, (9000, 9000))
    want = _make_instance_before(None, parts, (9000, 9000))
    assert got.centroid_px == want.centroid_px
    assert (got.area_px, got.bbox_xywh) == (want.area_px, want.bbox_xywh)


@settings(max_examples=400, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.sampled_from(["polygon", "ellipse", "rectangle", "line", "noise"]),
    st.sampled_from([0, 1, 5, 40]),
)
def test_a_part_box_without_its_contour_is_the_contours(seed, shape, min_area):
    """fit_runs_box's box of one kept component from its rows' hull (no contour traced)
    is the box of its traced contour (fit_runs + grown_box_of), bit for bit: convex
    polygons, ellipses, rectangles at 0, 45, 90, 135 deg or any angle (45 deg: the
    traced contour's box), with bites and specks, thin lines (one-pixel necks: traced),
    noise (several components: traced), at any offset."""
    from mistool.kernels.boxes import fit_runs, fit_runs_box, grown_box_of, mask_runs

    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(1, 90)), int(rng.integers(1, 90))
    mask = np.zeros((h, w), np.uint8)
    if shape == "polygon":
        pts = rng.integers(-5, max(h, w) + 5, (int(rng.integers(3, 9)), 2)).astype(np.int32)
        cv2.fillPoly(mask, [pts], 1)
    elif shape == "ellipse":
        axes = (int(rng.integers(0, 45)), int(rng.integers(0, 45)))
        centre = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        cv2.ellipse(mask, centre, axes, float(rng.integers(0, 180)), 0, 360, 1, -1)
    elif shape == "rectangle":
        angle = float(rng.choice([0, 45, 90, 135, float(rng.uniform(0, 180))]))
        size = (float(rng.integers(1, 60)), float(rng.integers(1, 60)))
        centre = (float(rng.uniform(0, w)), float(rng.uniform(0, h)))
        corners = np.round(cv2.boxPoints((centre, size, angle))).astype(np.int32)
        cv2.fillPoly(mask, [corners], 1)
    elif shape == "line":
        a, b = rng.integers(-5, max(h, w) + 5, 2), rng.integers(-5, max(h, w) + 5, 2)
        cv2.line(mask, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), 1, int(rng.integers(1, 5)))
    else:
        mask[:] = rng.random((h, w)) < rng.random()
    if rng.random() < 0.3:  # bites and specks
        mask[rng.random((h, w)) < 0.03] = 0
        mask[rng.random((h, w)) < 0.01] = 1
    ry, rx0, rx1, n = mask_runs(mask)
    ox, oy = int(rng.integers(0, 700)), int(rng.integers(0, 500))
    info, crop, box, corners = fit_runs_box(ry, rx0, rx1, n, min_area, ox, oy)
    want_info, want_crop, points, hull = fit_runs(ry, rx0, rx1, n, min_area, ox, oy)
    assert info == want_info and np.array_equal(crop, want_crop)
    if want_info[0] == 0:
        assert box == (0.0,) * 5 and not corners.any()
        return
    want_corners = np.zeros((4, 2))
    want_box = grown_box_of(points, hull, want_corners)
    assert np.array_equal(np.array(box).view(np.int64), np.array(want_box).view(np.int64))
    assert np.array_equal(corners.view(np.int64), want_corners.view(np.int64))
