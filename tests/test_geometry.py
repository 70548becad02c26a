"""Algorithm 1: min_area_box (OpenCV convention), drawn rectangles, invariances, specks."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mistool.geometry import (
    bounding_boxes,
    box_points,
    fit_part,
    min_area_box,
    range_mask,
    remove_specks,
)
from mistool.model import RotatedBox

H, W = 576, 720
PARTS = {"shaft": (160, 160)}


def draw(box: RotatedBox, shape=(H, W), value=160) -> np.ndarray:
    """Light exactly the pixels whose centres lie inside ``box`` (no OpenCV raster)."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    t = math.radians(box.angle_deg)
    u = (xx - box.cx) * math.cos(t) + (yy - box.cy) * math.sin(t)
    v = -(xx - box.cx) * math.sin(t) + (yy - box.cy) * math.cos(t)
    img = np.zeros(shape, np.uint8)
    img[(np.abs(u) <= box.length / 2) & (np.abs(v) <= box.width / 2)] = value
    return img


def angle_err(a: float, b: float) -> float:
    return (a - b + 90.0) % 180.0 - 90.0


def same_corner_set(a: np.ndarray, b: np.ndarray, tol: float) -> bool:
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)
    return bool((d.min(axis=1) < tol).all() and (d.min(axis=0) < tol).all())


# min_area_box: OpenCV's convention converted -----------------------------------------


@pytest.mark.parametrize(
    "angle", [0.0, 10.0, 30.0, 45.0, 60.0, 80.0, 90.0, 100.0, 135.0, 170.0, 179.5]
)
@pytest.mark.parametrize("length, width", [(40.0, 6.0), (25.0, 24.0)])
def test_min_area_box_of_exact_corners(angle, length, width):
    ref = RotatedBox(100.0, 80.0, length, width, angle)
    box, corners = min_area_box(ref.corners())
    assert box.cx == pytest.approx(100.0, abs=1e-3)
    assert box.cy == pytest.approx(80.0, abs=1e-3)
    assert box.length == pytest.approx(length, abs=1e-3)
    assert box.width == pytest.approx(width, abs=1e-3)
    assert abs(angle_err(box.angle_deg, angle)) < 1e-3
    assert 0.0 <= box.angle_deg < 180.0
    assert corners.shape == (4, 2) and corners.dtype == np.float64
    assert same_corner_set(corners, ref.corners(), 1e-3)


@pytest.mark.parametrize("angle", [0.0, 25.0, 90.0, 120.0, 179.0])
def test_corners_are_opencv_boxpoints_order(angle):
    pts = RotatedBox(50.0, 40.0, 30.0, 8.0, angle).corners().astype(np.float32)
    _, corners = min_area_box(pts)
    expected = cv2.boxPoints(cv2.minAreaRect(pts))
    np.testing.assert_allclose(corners, expected, atol=1e-4)


@pytest.mark.parametrize(
    "rect",
    [
        ((3.0, 4.0), (10.0, 2.0), -90.0),
        ((100.5, 20.25), (7.0, 33.0), -12.5),
        ((0.0, 0.0), (5.0, 5.0), 45.0),
        ((10.0, 10.0), (4.0, 1.0), 30.0),
    ],
)
def test_box_points_is_opencv_boxpoints(rect):
    np.testing.assert_allclose(box_points(rect), cv2.boxPoints(rect), atol=1e-4)


@pytest.mark.parametrize(
    "points, expected",
    [
        ([[5, 5]], (5.0, 5.0, 0.0, 0.0, 0.0)),  # one point
        ([[5, 5], [9, 5]], (7.0, 5.0, 4.0, 0.0, 0.0)),  # horizontal segment
        ([[5, 5], [5, 9]], (5.0, 7.0, 4.0, 0.0, 90.0)),  # vertical segment
        ([[0, 0], [3, 3]], (1.5, 1.5, math.sqrt(18), 0.0, 45.0)),  # diagonal, y down
        ([[3, 0], [0, 3]], (1.5, 1.5, math.sqrt(18), 0.0, 135.0)),
    ],
)
def test_min_area_box_degenerate(points, expected):
    box, corners = min_area_box(np.array(points))
    got = (box.cx, box.cy, box.length, box.width, box.angle_deg)
    assert got == pytest.approx(expected, abs=1e-5)
    assert np.isfinite(corners).all()


def test_min_area_box_rejects_empty():
    with pytest.raises(ValueError):
        min_area_box(np.empty((0, 2)))


# Algorithm 1 on drawn rectangles -----------------------------------------------------
# A drawn rectangle lights the pixels whose centres it covers. From those, each side can
# be located to within half the spacing of the pixel-centre rows parallel to it (<= 0.5
# px; see geometry.grow_to_pixel_edges). The cases below place the sides off the pixel
# centre rows, where that half-spacing bound is what the test asserts (0.5 px, 0.5 deg).

GENERIC_CENTRE = (351.3, 287.9)


@pytest.mark.parametrize(
    "angle",
    [0.0, 1.0, 2.0, 30.0, 45.0, 60.0, 88.0, 89.0, 90.0, 91.0, 120.0, 135.0, 150.0, 178.0, 179.0],
)
@pytest.mark.parametrize("length, width", [(120.0, 16.0), (200.0, 24.0), (300.0, 41.0)])
def test_drawn_rectangle_recovered(angle, length, width):
    ref = RotatedBox(*GENERIC_CENTRE, length, width, angle)
    box, corners = bounding_boxes(draw(ref), PARTS)["shaft"]
    assert box.cx == pytest.approx(ref.cx, abs=0.5)
    assert box.cy == pytest.approx(ref.cy, abs=0.5)
    assert box.length == pytest.approx(length, abs=0.5)
    assert box.width == pytest.approx(width, abs=0.5)
    assert abs(angle_err(box.angle_deg, angle)) <= 0.5
    assert same_corner_set(corners, box.corners(), 1e-6)


@pytest.mark.parametrize("angle", [0.0, 90.0])
@pytest.mark.parametrize("length, width", [(60.0, 8.0), (121.0, 15.0)])
def test_axis_aligned_rectangle_on_pixel_edges_is_exact(angle, length, width):
    # sides on pixel edges (x.5): exactly `length` x `width` pixels are lit
    cx = 300.5 if length % 2 == 0 else 300.0
    cy = 250.5 if width % 2 == 0 else 250.0
    ref = (
        RotatedBox(cx, cy, length, width, angle)
        if angle == 0
        else RotatedBox(cy, cx, length, width, angle)
    )
    img = draw(ref)
    assert (img > 0).sum() == length * width
    box, _ = bounding_boxes(img, PARTS)["shaft"]
    got = (box.cx, box.cy, box.length, box.width, box.angle_deg)
    assert got == pytest.approx((ref.cx, ref.cy, length, width, angle), abs=1e-6)
    # the paper's own box (pixel centres) is one pixel shorter in each direction
    raw, _ = bounding_boxes(img, PARTS, pixel_edges=False)["shaft"]
    assert (raw.length, raw.width) == pytest.approx((length - 1, width - 1), abs=1e-4)


def test_random_placements_within_quantisation_bound():
    rng = np.random.default_rng(7)
    errs = []
    for _ in range(40):
        ref = RotatedBox(
            rng.uniform(250, 450),
            rng.uniform(200, 350),
            rng.uniform(60, 250),
            rng.uniform(8, 30),
            rng.uniform(0, 180),
        )
        box, _ = bounding_boxes(draw(ref), PARTS)["shaft"]
        errs.append(
            [box.cx - ref.cx, box.cy - ref.cy, box.length - ref.length, box.width - ref.width]
        )
    e = np.abs(np.array(errs))
    assert e[:, :2].max() <= 0.5  # centre
    assert e[:, 2:].max() <= 1.0  # size: half a row spacing per side, two sides
    assert e[:, 2:].mean() < 0.3  # and unbiased on average


# invariances -----------------------------------------------------------------------

TRANSFORMS = {
    # name: (image op, (cx, cy, angle) -> expected)
    "flip_x": (lambda im: im[:, ::-1], lambda cx, cy, a: (W - 1 - cx, cy, 180.0 - a)),
    "flip_y": (lambda im: im[::-1, :], lambda cx, cy, a: (cx, H - 1 - cy, 180.0 - a)),
    "transpose": (lambda im: im.T, lambda cx, cy, a: (cy, cx, 90.0 - a)),
    "rot180": (lambda im: im[::-1, ::-1], lambda cx, cy, a: (W - 1 - cx, H - 1 - cy, a)),
}


@pytest.mark.parametrize("name", list(TRANSFORMS))
@pytest.mark.parametrize("angle", [0.0, 17.0, 45.0, 72.0, 90.0, 133.0, 179.0])
def test_invariances(name, angle):
    op, expect = TRANSFORMS[name]
    img = draw(RotatedBox(351.3, 270.2, 150.0, 20.0, angle))
    box, _ = bounding_boxes(img, PARTS)["shaft"]
    moved, _ = bounding_boxes(np.ascontiguousarray(op(img)), PARTS)["shaft"]
    cx, cy, a = expect(box.cx, box.cy, box.angle_deg)
    assert moved.cx == pytest.approx(cx, abs=1e-3)
    assert moved.cy == pytest.approx(cy, abs=1e-3)
    assert moved.length == pytest.approx(box.length, abs=1e-3)
    assert moved.width == pytest.approx(box.width, abs=1e-3)
    assert abs(angle_err(moved.angle_deg, a % 180.0)) < 1e-3


# masks and specks ------------------------------------------------------------------


def test_range_mask_inclusive_and_dtypes():
    img = np.array([[0, 59, 60, 70, 80, 81]], np.uint8)
    assert range_mask(img, (60, 80)).tolist() == [[0, 0, 255, 255, 255, 0]]
    assert range_mask(img.astype(np.uint16), (60, 80)).tolist() == [[0, 0, 255, 255, 255, 0]]
    assert range_mask(img, (300, 400)).max() == 0  # outside uint8: nothing
    packed = np.array([[0x102030, 0x102031]], np.uint32)
    assert range_mask(packed, (0x102030, 0x102030)).tolist() == [[255, 0]]


def reference_clean(mask: np.ndarray, min_area: int) -> np.ndarray:
    n, cc, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    keep = np.zeros(n, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= min_area
    return keep[cc]


@pytest.mark.parametrize(
    "case", ["big+specks", "thin diagonal", "ring with speck", "all small", "two big"]
)
def test_remove_specks_matches_pixel_counts(case):
    m = np.zeros((60, 80), np.uint8)
    if case in ("big+specks", "ring with speck", "two big"):
        m[10:40, 10:50] = 255
    if case == "big+specks":
        m[50, 5] = m[55:57, 60:62] = 255
    if case == "thin diagonal":  # bounding box 15x15 >= 20 px but only 15 pixels
        m[np.arange(15) + 40, np.arange(15) + 60] = 255
        m[5:15, 5:15] = 255
    if case == "ring with speck":
        m[15:35, 15:45] = 0
        m[25, 30] = 255  # inside the hole, 8-separate from the ring
    if case == "all small":
        m[5, 5] = m[20:22, 20:23] = 255
    if case == "two big":
        m[45:58, 55:78] = 255
    kept, area = remove_specks(m, 20)
    ref = reference_clean(m, 20)
    assert np.array_equal(kept > 0, ref)
    assert area == int(ref.sum())


def test_fit_part_one_pixel_and_offset():
    m = np.zeros((10, 10), np.uint8)
    m[3, 4] = 255
    fit = fit_part(m, 0, offset=(100, 200))
    assert (fit.box.cx, fit.box.cy, fit.box.length, fit.box.width) == (104.0, 203.0, 1.0, 1.0)
    assert fit.offset == (104, 203) and fit.mask.shape == (1, 1) and fit.area_px == 1
    raw = fit_part(m, 0, pixel_edges=False)
    assert (raw.box.length, raw.box.width) == (0.0, 0.0)
    assert fit_part(m, 2) is None
    assert fit_part(np.zeros((5, 5), np.uint8)) is None


def test_box_covers_all_pixels_of_a_split_part():
    """The paper fits one box to all of the part's pixels, also when they are split."""
    img = np.zeros((100, 200), np.uint8)
    img[40:50, 10:60] = 160
    img[40:50, 120:190] = 160  # the same shaft seen on both sides of an occluder
    box, _ = bounding_boxes(img, PARTS)["shaft"]
    assert (box.cx, box.cy, box.length, box.width) == pytest.approx((99.5, 44.5, 180, 10))


# --- the compiled Algorithm 1 (mistool.kernels.boxes) against the definitions it replaced ---


def _random_mask(rng: np.random.Generator) -> np.ndarray:
    """A part mask: lines of any width, filled and hollow circles (holes, components in
    holes), specks, sometimes noise; non-zero values 255, 1 or 7."""
    h, w = int(rng.integers(1, 110)), int(rng.integers(1, 110))
    if rng.random() < 0.2:
        return (rng.random((h, w)) < rng.uniform(0.05, 0.9)).astype(np.uint8) * np.uint8(255)
    m = np.zeros((h, w), np.uint8)
    for _ in range(int(rng.integers(1, 5))):
        a, b = rng.integers(-10, 120, 2), rng.integers(-10, 120, 2)
        cv2.line(m, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), 255, int(rng.integers(1, 20)))
    for _ in range(int(rng.integers(0, 4))):
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        colour = int(rng.choice([0, 255]))
        cv2.circle(m, c, int(rng.integers(1, 25)), colour, int(rng.choice([-1, 1, 2])))
    for _ in range(int(rng.integers(0, 6))):
        m[int(rng.integers(0, h)), int(rng.integers(0, w))] = 255
    return (m > 0).astype(np.uint8) * np.uint8(rng.choice([1, 7, 255]))


def _outer_contours_before(mask: np.ndarray, min_area: int) -> np.ndarray:
    """Points of the outer contours OpenCV gives, of the components with at least
    ``min_area`` pixels, in OpenCV's order (what ``fit_part`` fitted before)."""
    contours, hierarchy = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return np.zeros((0, 2), np.int32)
    _, cc, stats, _ = cv2.connectedComponentsWithStats((mask > 0).astype(np.uint8), None, 8)
    keep = []
    for c, h in zip(contours, hierarchy[0], strict=True):
        x, y = c[0, 0]
        if h[3] < 0 and stats[cc[y, x], cv2.CC_STAT_AREA] >= min_area:
            keep.append(c.reshape(-1, 2))
    return np.concatenate(keep) if keep else np.zeros((0, 2), np.int32)


@settings(max_examples=400, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0, 1, 2, 5, 30, 400]))
def test_runs_components_crop_and_contours_equal_opencvs(seed, min_area):
    """fit_mask: the kept pixels (8-connected components of at least min_area pixels),
    their crop, pixel sums, and every outer contour point in cv2.findContours' order."""
    from mistool.kernels.boxes import fit_mask, mask_runs

    rng = np.random.default_rng(seed)
    mask = _random_mask(rng)
    ry, rx0, rx1, n = mask_runs(mask)
    runs = np.zeros_like(mask, bool)
    for y, a, b in zip(ry[:n], rx0[:n], rx1[:n], strict=True):
        assert not runs[y, a:b].any()
        runs[y, a:b] = True
    assert np.array_equal(runs, mask > 0)
    assert np.all(np.diff(ry[:n].astype(np.int64) * 10**6 + rx0[:n]) > 0)  # raster order

    info, crop, pts, hull = fit_mask(mask, min_area, 30, 40)
    n_cc, cc, stats, _ = cv2.connectedComponentsWithStats((mask > 0).astype(np.uint8), None, 8)
    big = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] >= max(min_area, 1))
    kept = np.isin(cc, big[big > 0])
    assert info[0] == kept.sum()
    if not kept.any():
        assert len(pts) == 0 and len(hull) == 0
        return
    x, y, w, h = cv2.boundingRect(kept.astype(np.uint8))
    assert (info[1], info[2]) == (x, y) and np.array_equal(crop, kept[y : y + h, x : x + w])
    ys, xs = np.nonzero(crop)
    assert (info[3], info[4]) == (xs.sum(), ys.sum())
    want = _outer_contours_before(mask, min_area)
    assert np.array_equal(pts, want + np.array([30, 40], np.int32))
    # the points minAreaRect sees: the same rectangle, the same hull
    assert cv2.minAreaRect(hull) == cv2.minAreaRect(pts)
    assert np.array_equal(cv2.convexHull(hull), cv2.convexHull(pts))


@settings(max_examples=400, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 40), st.integers(1, 14))
def test_hull_points_give_the_rectangle_of_all_points(seed, n, spread):
    """Small clouds (duplicates, collinear points): the rectangle of the points kept for
    minAreaRect is that of all of them; the contours of a few pixels too."""
    from mistool.kernels.boxes import fit_runs

    rng = np.random.default_rng(seed)
    pts = rng.integers(0, spread, (n, 2)).astype(np.int32)
    # a mask of those pixels, as runs: its contours and their hull points
    mask = np.zeros((spread, spread), np.uint8)
    mask[pts[:, 1], pts[:, 0]] = 1
    ys, xs = np.nonzero(mask)
    idx = np.arange(len(xs), dtype=np.int32)
    ry, rx0, rx1 = ys.astype(np.int32), xs.astype(np.int32), (xs + 1).astype(np.int32)
    info, _, contour, hull = fit_runs(ry, rx0, rx1, len(idx), 0, 0, 0)
    assert info[0] == len(xs)
    assert cv2.minAreaRect(hull) == cv2.minAreaRect(contour)
    assert np.array_equal(cv2.convexHull(hull), cv2.convexHull(contour))


def _lattice_gaps_numpy(normals, h, t_lo, t_hi) -> np.ndarray:
    """``geometry._lattice_gaps`` before the kernel (commit 3fc5814): numpy rows."""
    eps, walk = 1e-4, 64
    index = np.arange(walk)
    sides = []
    for (nx, ny), hs, lo, hi in zip(normals, h, t_lo, t_hi, strict=True):
        horiz = abs(ny) >= abs(nx)
        a, b, tangent = (nx, abs(ny), -ny) if horiz else (ny, abs(nx), nx)
        w0, w1 = hs * a + lo * tangent, hs * a + hi * tangent
        start = float(math.ceil(min(w0, w1) - eps))
        full = int(max(math.floor(max(w0, w1) + eps) - start + 1, 1))
        count = min(full, walk)
        sides.append((start, full - count, hs + eps, a, b, count))
    start_, skipped, he, a_, b_, count_ = np.array(sides, np.float64).T[:, :, None]
    p = start_ + index + np.where(index >= walk // 2, skipped, 0.0)
    r = (he - a_ * p) / b_
    frac = r - np.floor(r)
    frac[index >= count_] = -1.0
    return b_[:, 0] * (1.0 - frac.max(1)) + eps


def _grow_numpy(pts: np.ndarray) -> tuple[tuple, np.ndarray]:
    """``grow_to_pixel_edges`` before the kernel (commit 3fc5814): numpy's projections
    (``@``), ``cv2.minMaxLoc``, the numpy lattice walk; OpenCV's rectangle and corners."""
    (_, _), (_, _), angle = cv2.minAreaRect(pts)
    t = math.radians(float(angle))
    c, s = math.cos(t), math.sin(t)
    pf = pts.astype(np.float64)
    p1, p2 = pf @ np.array([c, s]), pf @ np.array([-s, c])
    a_lo, a_hi = cv2.minMaxLoc(p1)[:2]
    b_lo, b_hi = cv2.minMaxLoc(p2)[:2]
    normals = [(-s, c), (s, -c), (c, s), (-c, -s)]
    h = [b_hi, -b_lo, a_hi, -a_lo]
    t_lo = [-a_hi, a_lo, b_lo, -b_hi]
    t_hi = [-a_lo, a_hi, b_hi, -b_lo]
    g0, g1, g2, g3 = (_lattice_gaps_numpy(normals, h, t_lo, t_hi) / 2.0).tolist()
    b_hi, b_lo, a_hi, a_lo = b_hi + g0, b_lo - g1, a_hi + g2, a_lo - g3
    ca, cb = (a_lo + a_hi) / 2.0, (b_lo + b_hi) / 2.0
    rect = ((ca * c - cb * s, ca * s + cb * c), (a_hi - a_lo, b_hi - b_lo), float(angle))
    return rect, box_points(rect)


@settings(max_examples=400, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([1, 2, 3, 8, 50, 400]), st.booleans())
def test_grown_box_equals_the_numpy_definition_bit_for_bit(seed, n, line):
    """grow_to_pixel_edges: the projections as numpy's ``@`` rounds them (a single
    point too), the lattice walk, the rectangle and its corners, to the last bit."""
    from mistool.geometry import _canonical, grow_to_pixel_edges

    rng = np.random.default_rng(seed)
    if line:  # points on a few lines at any angle: many exactly on the box's sides
        t = rng.uniform(0, math.pi)
        k = np.arange(n)[:, None] * np.array([math.cos(t), math.sin(t)]) * rng.uniform(1, 5)
        pts = np.round(k + rng.integers(0, 700, 2) + rng.integers(0, 3, (n, 2)))
        pts = np.clip(pts, 0, 2000).astype(np.int32)
    else:
        pts = rng.integers(0, int(rng.choice([3, 50, 1500])), (n, 2)).astype(np.int32)
    rect, corners = _grow_numpy(pts)
    box, got = grow_to_pixel_edges(pts)
    assert box == _canonical(rect)
    assert got.dtype == np.float64 and np.array_equal(got.view(np.int64), corners.view(np.int64))


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0, 1, 2, 30, 400]))
def test_fit_part_equals_the_opencv_definition(seed, min_area):
    """fit_part against its definition before the kernels (commit 3fc5814): OpenCV's
    speck removal and contours, numpy's projections; any window and offset, masks that
    are views, values other than 255."""
    from mistool.geometry import _canonical, _clean, mask_points

    rng = np.random.default_rng(seed)
    mask = _random_mask(rng)
    if rng.random() < 0.3:  # a view of a larger array (not contiguous)
        big = np.zeros((mask.shape[0] + 7, mask.shape[1] + 9), np.uint8)
        big[3 : 3 + mask.shape[0], 5 : 5 + mask.shape[1]] = mask
        mask = big[2:-1, 4:-2]
    offset = (int(rng.integers(0, 600)), int(rng.integers(0, 400)))
    got = fit_part(mask, min_area, offset)
    kept, area, contours = _clean(np.ascontiguousarray(mask), min_area)
    if area == 0:
        assert got is None
        return
    pts = mask_points(kept) if contours is None else np.concatenate(contours).reshape(-1, 2)
    x, y, bw, bh = cv2.boundingRect(pts)
    rect, corners = _grow_numpy(pts + np.asarray(offset, np.int32))
    assert got is not None
    assert got.box == _canonical(rect) and np.array_equal(got.corners, corners)
    assert got.area_px == area and got.offset == (offset[0] + x, offset[1] + y)
    assert np.array_equal(got.kept, kept[y : y + bh, x : x + bw] > 0)
    assert got.kept.dtype == np.bool_ and got.kept.flags.c_contiguous


def _mask_runs_before(mask: np.ndarray) -> list[tuple[int, int, int]]:
    """The row runs of a mask's non-zero pixels in raster order, from numpy's edges."""
    out = []
    for y, row in enumerate(mask != 0):
        edges = np.flatnonzero(np.diff(np.concatenate([[0], row.astype(np.int8), [0]])))
        out.extend((y, int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True))
    return out


@settings(max_examples=400, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.integers(1, 40),
    st.integers(1, 300),
    st.sampled_from([1, 2, 8, 33, 200]),
)
def test_mask_runs_passing_over_long_stretches_are_numpys_runs(seed, h, w, scale):
    """kernels.boxes.mask_runs (32, then 8 pixels at a time where the row does not
    change) gives the row runs of numpy's edges: runs and gaps of every length (around
    the 8- and 32-pixel strides, at the row's end), any non-zero byte values."""
    from mistool.kernels.boxes import mask_runs

    rng = np.random.default_rng(seed)
    mask = np.zeros((h, w), np.uint8)
    for y in range(h):
        x = int(rng.integers(0, scale + 1))
        while x < w:
            n = int(rng.integers(1, 2 * scale + 2))
            mask[y, x : x + n] = rng.integers(1, 256, min(n, w - x))
            x += n + int(rng.integers(1, 2 * scale + 2))
    if rng.random() < 0.2:
        mask[int(rng.integers(0, h))] = 0xFF  # a row set from end to end
    ry, rx0, rx1, n = mask_runs(mask)
    got = list(zip(ry[:n].tolist(), rx0[:n].tolist(), rx1[:n].tolist(), strict=True))
    assert got == _mask_runs_before(mask)


# cv2.minAreaRect compiled (mistool.kernels.boxes.min_area_rect) ----------------------------


def _point_set(rng: np.random.Generator, kind: str) -> np.ndarray:
    """(N, 2) int32 points of one kind: where OpenCV's hull order, start point and ties
    decide the result."""
    m = int(rng.integers(1, 30))
    if kind == "random":
        pts = rng.integers(0, int(rng.choice([2, 5, 60, 700])), (m, 2))
    elif kind == "collinear":
        step = rng.integers(-5, 6, 2)
        pts = rng.integers(-3, 800, 2) + np.outer(rng.integers(-20, 20, m), step)
    elif kind == "duplicates":
        few = rng.integers(0, int(rng.choice([3, 40])), (int(rng.integers(1, 6)), 2))
        pts = few[rng.integers(0, len(few), m)]
    elif kind == "one or two":
        pts = rng.integers(0, 50, (int(rng.integers(1, 3)), 2))
    elif kind == "rectangle":  # corners of an axis-aligned rectangle or square, and inside
        a, b = (int(v) for v in rng.integers(1, 30, 2))
        b = a if rng.random() < 0.5 else b
        corners = np.array([[0, 0], [a, 0], [a, b], [0, b]])
        pts = np.vstack([corners, rng.integers(0, min(a, b) + 1, (m, 2))])
    elif kind == "diamond":  # a square at 45 deg: four rectangles of equal area
        a = int(rng.integers(1, 30))
        pts = np.vstack(
            [[[a, 0], [0, a], [-a, 0], [0, -a]], rng.integers(-a // 2, a // 2 + 1, (m, 2))]
        )
    else:  # "contour": a drawn part's outer contour points, in OpenCV's order
        mask = np.zeros((60, 60), np.uint8)
        for _ in range(int(rng.integers(1, 4))):
            p, q = rng.integers(0, 60, 2), rng.integers(0, 60, 2)
            cv2.line(
                mask, (int(p[0]), int(p[1])), (int(q[0]), int(q[1])), 255, int(rng.integers(1, 9))
            )
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        pts = np.concatenate(contours).reshape(-1, 2)
    pts = pts[rng.permutation(len(pts))] if kind in ("rectangle", "diamond") else pts
    return np.ascontiguousarray(pts + rng.integers(-1000, 1000, 2) * (rng.random() < 0.3), np.int32)


KINDS = ["random", "collinear", "duplicates", "one or two", "rectangle", "diamond", "contour"]


@settings(max_examples=1500, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from(KINDS))
def test_min_area_rect_is_opencvs_bit_for_bit(seed, kind):
    """min_area_rect: cv2.minAreaRect's five float32 values to the last bit (signs of
    zeros too), and convex_hull_ccw: cv2.convexHull(clockwise=False)'s vertices in its
    order from its start point (which decides between rectangles of equal area)."""
    from mistool.kernels.boxes import convex_hull_ccw, min_area_rect

    pts = _point_set(np.random.default_rng(seed), kind)
    (cx, cy), (w, h), angle = cv2.minAreaRect(pts)
    want = np.array([cx, cy, w, h, angle], np.float64)
    got = np.array(min_area_rect(pts), np.float64)
    assert np.array_equal(got.view(np.int64), want.view(np.int64)), (got, want)
    hull = cv2.convexHull(pts, clockwise=False).reshape(-1, 2)
    assert np.array_equal(pts[convex_hull_ccw(pts)], hull)


def test_min_area_rect_degenerate_and_tied_cases():
    """Known cases: one point, two, a square (four tied rectangles), a 45 deg square."""
    from mistool.kernels.boxes import min_area_rect

    for pts in (
        [[2, 3]],
        [[2, 3], [2, 3]],
        [[0, 0], [3, 3]],
        [[0, 0], [10, 0], [10, 5], [0, 5]],
        [[0, 0], [5, 0], [5, 5], [0, 5]],
        [[5, 0], [0, 5], [-5, 0], [0, -5]],
    ):
        p = np.array(pts, np.int32)
        (cx, cy), (w, h), angle = cv2.minAreaRect(p)
        assert min_area_rect(p) == (cx, cy, w, h, angle)
    assert min_area_rect(np.array([[0, 0], [3, 3]], np.int32))[2:] == (
        0.0,
        pytest.approx(math.sqrt(18)),
        -45.0,
    )
